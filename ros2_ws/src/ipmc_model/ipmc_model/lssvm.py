"""Least-squares support vector machine (LSSVM) regression with an RBF kernel (paper Eq. 9-15).

Model: f(x) = sum_j coef_j K(x, c_j) + b,  K(x, z) = exp(-||x - z||^2 / (2 sigma^2)).

* :class:`LSSVMRegressor` is the exact LSSVM: the dual system (Eq. 13)

      [0   1^T        ] [b]   [0]
      [1   K + I / C  ] [a] = [y]

  is solved with one Cholesky factorisation of the SPD block A = K + I/C and two SPD solves,
  A eta = 1 and A nu = y; the Schur complement gives b = 1^T nu / 1^T eta and a = nu - b eta.
  Memory and time grow as N^2 and N^3, fine up to a few thousand samples.

* :class:`FixedSizeLSSVMRegressor` is the fixed-size (Nystroem) variant for long records
  (60 000 samples): M prototypes c_j are chosen from the training rows by k-means++ seeding
  (D^2 sampling: each next prototype is drawn with probability proportional to its squared
  distance to the nearest prototype already chosen, so they cover the occupied regressor space
  instead of following the sample density) or uniformly at random. The weights solve, in the
  primal on the Nystroem features phi(x) = K(x, P) U Lambda^{-1/2} (eigenpairs of K_MM),

      min_{w, b}  1/2 ||w||^2 + C/2 sum_k (y_k - phi(x_k)^T w - b)^2,

  which is the LSSVM objective restricted to the span of the prototypes' feature vectors.
  With b eliminated this is one M x M SPD system (Cholesky), accumulated over chunks of rows:
  memory O(M^2 + chunk M), time O(N M^2). The result is again a kernel expansion over the
  prototypes, coef = U Lambda^{-1/2} w.

Both keep C and sigma as given; both expose ``predict`` (batch) and ``predict_one`` (a single
row, one kernel row of cost O(M d), for 100 Hz control loops).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, eigh

from .errors import check_fitted

#: Largest N accepted by the exact solver (an N x N matrix of 8-byte floats: 20000 -> 3.2 GB).
MAX_EXACT_SAMPLES = 15000

#: Rows per block of :meth:`_KernelExpansion.predict` (a 1500-centre kernel block: 3 MB).
_BLOCK_ROWS = 256


def _check_hyper(C, sigma) -> tuple[float, float]:
    try:
        C, sigma = float(C), float(sigma)
    except (TypeError, ValueError):
        raise ValueError(f"C and sigma must be numbers, got C={C!r}, sigma={sigma!r}") from None
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a finite number > 0, got {sigma}")
    if not (np.isfinite(C) and C > 0):
        raise ValueError(f"C must be a finite number > 0, got {C}")
    return C, sigma


def _check_xy(X, y=None):
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    if X.ndim != 2 or X.shape[0] < 2:
        raise ValueError(f"X must be 2-D with at least 2 rows, got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ValueError("X must be finite (no NaN or inf)")
    if y is None:
        return X
    y = np.asarray(y, dtype=float).reshape(-1)
    if y.size != X.shape[0]:
        raise ValueError(f"X and y must have the same length: X has {X.shape[0]}, y has {y.size}")
    if not np.all(np.isfinite(y)):
        raise ValueError("y must be finite (no NaN or inf)")
    return X, y


def rbf_kernel(X, Z, sigma: float) -> np.ndarray:
    """RBF kernel matrix exp(-||x_i - z_j||^2 / (2 sigma^2)), shape (len(X), len(Z))."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    Z = np.atleast_2d(np.asarray(Z, dtype=float))
    d2 = (X * X).sum(1)[:, None] + (Z * Z).sum(1)[None, :] - 2.0 * (X @ Z.T)
    np.maximum(d2, 0.0, out=d2)
    d2 *= -1.0 / (2.0 * sigma * sigma)
    return np.exp(d2, out=d2)


def _cholesky_jittered(A: np.ndarray):
    """cho_factor of A, adding a growing diagonal jitter if A is only positive semidefinite."""
    jitter = 0.0
    scale = float(np.mean(np.diag(A))) or 1.0
    for _ in range(8):
        try:
            if jitter:
                A = A + jitter * np.eye(A.shape[0])
            return cho_factor(A, lower=True, overwrite_a=False, check_finite=False)
        except LinAlgError:
            jitter = scale * (1e-12 if jitter == 0.0 else 100.0)
    raise ValueError("the LSSVM system is not positive definite; try a smaller C or larger sigma")


class _KernelExpansion:
    """f(x) = sum_j coef_j K(x, c_j) + b with fast single-row evaluation."""

    centers_ = None

    def _set_expansion(self, centers, coef, intercept):
        self.centers_ = np.ascontiguousarray(centers)
        self.coef_ = np.ascontiguousarray(coef)
        self.intercept_ = float(intercept)
        self._gamma = 1.0 / (2.0 * self.sigma_ * self.sigma_)
        self._center_sq = (self.centers_ * self.centers_).sum(1)
        # predict_one's exponent 2 g c.x - g |c|^2 - g |x|^2, the product Fortran-ordered: a
        # 1500 x 13 kernel row in 5.7 us instead of 8.0 (every free run; docs/models.md)
        self._row_a = np.asfortranarray(2.0 * self._gamma * self.centers_)
        self._row_c = -self._gamma * self._center_sq

    def predict(self, X, chunk_size: int | None = None) -> np.ndarray:
        """Regression output for rows of ``X`` (n, d) -> (n,), in blocks of ``chunk_size``
        rows (default ``_BLOCK_ROWS``)."""
        check_fitted(self, "centers_")
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if X.shape[1] != self.centers_.shape[1]:
            raise ValueError(
                f"X must have {self.centers_.shape[1]} columns, got {X.shape[1]}"
            )
        # predict_one's exponent, a block of rows at a time: a block that stays in cache runs
        # 30 000 rows of a 1500-centre model in 0.08 s, against 0.19 s for 8192-row blocks of
        # rbf_kernel and 0.17 s for 30 000 predict_one calls (one BLAS thread)
        rows = int(chunk_size or _BLOCK_ROWS)
        n = X.shape[0]
        out = np.empty(n)
        for s in range(0, n, rows):
            xb = X[s : s + rows]
            if xb.shape[0] < rows:
                # every block the same shape, so BLAS takes the same path for each: a row's
                # output does not depend on how many rows follow it (a free run's prefix is
                # the prefix of its run, to the bit, which the diagnosis's cache relies on)
                xb = np.concatenate([xb, np.zeros((rows - xb.shape[0], X.shape[1]))])
            t = xb @ self._row_a.T
            t += self._row_c
            t -= self._gamma * (xb * xb).sum(1)[:, None]
            np.exp(t, out=t)
            out[s : s + rows] = (t @ self.coef_)[: n - s] + self.intercept_
        return out

    def predict_one(self, x: np.ndarray) -> float:
        """Output for one row ``x`` (d,): one kernel row, no validation (hot path)."""
        t = self._row_a @ x
        t += self._row_c
        t -= self._gamma * (x @ x)
        np.exp(t, out=t)
        return float(t @ self.coef_) + self.intercept_

    @property
    def n_centers_(self) -> int:
        check_fitted(self, "centers_")
        return int(self.centers_.shape[0])


class LSSVMRegressor(_KernelExpansion):
    """Exact LSSVM regression, solved by Cholesky (two SPD solves and a Schur complement).

    Parameters
    ----------
    C : float
        Regularisation factor (> 0), paper Eq. 10.
    sigma : float
        RBF bandwidth (> 0), paper Eq. 14, in the units of the regressor rows.

    Attributes
    ----------
    centers_ : ndarray (N, d)
        Training rows (support vectors; every LSSVM row is one).
    coef_ : ndarray (N,)
        Dual weights alpha.
    intercept_ : float
        Bias b.
    """

    def __init__(self, C: float = 998.0867, sigma: float = 0.2):
        self.C = C
        self.sigma = sigma

    def fit(self, X, y) -> LSSVMRegressor:
        """Fit to rows ``X`` (N, d) and targets ``y`` (N,); returns self."""
        C, sigma = _check_hyper(self.C, self.sigma)
        X, y = _check_xy(X, y)
        n = X.shape[0]
        if n > MAX_EXACT_SAMPLES:
            raise ValueError(
                f"the exact LSSVM needs an N x N matrix; N = {n} > {MAX_EXACT_SAMPLES}: "
                "use FixedSizeLSSVMRegressor"
            )
        A = rbf_kernel(X, X, sigma)
        A[np.diag_indices_from(A)] += 1.0 / C
        factor = _cholesky_jittered(A)
        del A
        rhs = np.column_stack([np.ones(n), y])
        sol = cho_solve(factor, rhs, overwrite_b=True, check_finite=False)
        eta, nu = sol[:, 0], sol[:, 1]
        b = nu.sum() / eta.sum()
        self.sigma_, self.C_ = sigma, C
        self._set_expansion(X, nu - b * eta, b)
        return self

    def get_params(self) -> dict:
        return {"C": self.C, "sigma": self.sigma}


def select_prototypes(X, n_prototypes: int, method: str = "kmeans++", seed=None) -> np.ndarray:
    """Indices of ``n_prototypes`` distinct rows of ``X`` chosen as fixed-size prototypes.

    ``"kmeans++"``: D^2 sampling (Arthur and Vassilvitskii 2007); ``"random"``: uniform.
    """
    X = np.asarray(X, dtype=float)
    n = X.shape[0]
    m = min(int(n_prototypes), n)
    rng = np.random.default_rng(seed)
    if method == "random":
        return np.sort(rng.choice(n, size=m, replace=False))
    if method != "kmeans++":
        raise ValueError(f"prototypes must be 'kmeans++' or 'random', got {method!r}")
    idx = np.empty(m, dtype=int)
    idx[0] = rng.integers(n)
    d2 = ((X - X[idx[0]]) ** 2).sum(1)
    for j in range(1, m):
        total = d2.sum()
        if total <= 0:  # fewer distinct rows than prototypes: fill with unused rows
            rest = np.setdiff1d(np.arange(n), idx[:j])
            idx[j:] = rng.choice(rest, size=m - j, replace=False)
            break
        idx[j] = rng.choice(n, p=d2 / total)
        np.minimum(d2, ((X - X[idx[j]]) ** 2).sum(1), out=d2)
    return np.sort(idx)


class FixedSizeLSSVMRegressor(_KernelExpansion):
    """Fixed-size (Nystroem) LSSVM for long records; see the module docstring.

    Parameters
    ----------
    C, sigma : float
        As :class:`LSSVMRegressor`.
    n_prototypes : int
        Number M of prototypes (kernel centres); M >= N gives M = N.
    prototypes : {"kmeans++", "random"}
        Prototype selection method.
    seed : int or None
        Seed of the prototype selection.
    chunk_size : int
        Rows per block when accumulating K_NM^T K_NM (bounds memory).
    eig_floor : float
        Eigenvalues of K_MM below ``eig_floor`` times the largest are dropped (numerical rank).
    """

    def __init__(
        self,
        C: float = 998.0867,
        sigma: float = 0.2,
        n_prototypes: int = 1000,
        prototypes: str = "kmeans++",
        seed: int | None = 0,
        chunk_size: int = 8192,
        eig_floor: float = 1e-10,
    ):
        self.C = C
        self.sigma = sigma
        self.n_prototypes = n_prototypes
        self.prototypes = prototypes
        self.seed = seed
        self.chunk_size = chunk_size
        self.eig_floor = eig_floor

    def fit(self, X, y) -> FixedSizeLSSVMRegressor:
        """Fit to rows ``X`` (N, d) and targets ``y`` (N,); returns self."""
        C, sigma = _check_hyper(self.C, self.sigma)
        X, y = _check_xy(X, y)
        if int(self.n_prototypes) < 1:
            raise ValueError(f"n_prototypes must be >= 1, got {self.n_prototypes}")
        idx = select_prototypes(X, self.n_prototypes, self.prototypes, self.seed)
        stats = FixedSizeStatistics(X, y, idx, sigma, self.chunk_size, self.eig_floor)
        return stats.solve(C, self)

    def get_params(self) -> dict:
        return {
            "C": self.C,
            "sigma": self.sigma,
            "n_prototypes": self.n_prototypes,
            "prototypes": self.prototypes,
            "seed": self.seed,
            "chunk_size": self.chunk_size,
            "eig_floor": self.eig_floor,
        }


class FixedSizeStatistics:
    """What a fixed-size LSSVM fit needs from the data for one sigma, reusable across C.

    Building the Nystroem features and their Gram matrix costs O(N M^2) and depends on the
    rows, the prototypes and sigma only; the regularisation C enters in one M x M Cholesky
    solve. Hyperparameter tuning keeps these per sigma and scores many C values cheaply with
    exactly the regressor the final fit uses.

    Parameters
    ----------
    X : ndarray (N, d)
        Training rows.
    y : ndarray (N,)
        Targets.
    prototype_indices : ndarray of int
        Rows of ``X`` used as prototypes (see :func:`select_prototypes`).
    sigma : float
        RBF bandwidth.
    chunk_size : int
        Rows per block when accumulating the Gram matrix.
    eig_floor : float
        Relative eigenvalue floor of K_MM (numerical rank).
    """

    def __init__(self, X, y, prototype_indices, sigma: float, chunk_size: int = 8192,
                 eig_floor: float = 1e-10):
        idx = np.asarray(prototype_indices, dtype=int)
        P = X[idx]
        n = X.shape[0]
        # Nystroem features phi(x) = K(x, P) T with T = U_r diag(lambda_r)^(-1/2) from the
        # eigenpairs of K_MM above a relative floor: an eigen-basis instead of a Cholesky of
        # K_MM, because K_MM is numerically singular for wide kernels (large sigma). The
        # features are formed chunk by chunk before the Gram matrix, not as T^T (K^T K) T,
        # which would square the conditioning of the small eigen-directions.
        lam, U = eigh(rbf_kernel(P, P, sigma))
        keep = lam > eig_floor * lam[-1]
        T = U[:, keep] / np.sqrt(lam[keep])
        r = T.shape[1]
        A = np.zeros((r, r))
        f1 = np.zeros(r)
        fy = np.zeros(r)
        chunk = int(chunk_size)
        for s in range(0, n, chunk):
            F = rbf_kernel(X[s : s + chunk], P, sigma) @ T
            A += F.T @ F
            f1 += F.sum(0)
            fy += F.T @ y[s : s + chunk]
        y_mean = float(y.mean())
        mu = f1 / n  # mean feature
        A -= np.outer(f1, mu)  # centred Gram: the bias is not regularised
        self.sigma, self.indices, self.prototypes = float(sigma), idx, P
        self._T, self._A, self._rhs, self._mu, self._y_mean = T, A, fy - f1 * y_mean, mu, y_mean

    def solve(self, C: float, regressor: FixedSizeLSSVMRegressor | None = None
              ) -> FixedSizeLSSVMRegressor:
        """Fitted regressor for this sigma and ``C`` (a copy of ``regressor``'s settings).

        Solves the primal ridge with an unregularised bias,
        (Phi_c^T Phi_c + I/C) w = Phi_c^T (y - mean y), by Cholesky.
        """
        if regressor is None:
            regressor = FixedSizeLSSVMRegressor(C=C, sigma=self.sigma,
                                                n_prototypes=self.indices.size)
        C, sigma = _check_hyper(C, self.sigma)
        A = self._A.copy()
        A[np.diag_indices_from(A)] += 1.0 / C
        factor = _cholesky_jittered(A)
        w = cho_solve(factor, self._rhs, check_finite=False)
        regressor.n_features_kept_ = int(self._T.shape[1])
        regressor.sigma_, regressor.C_ = sigma, C
        regressor.prototype_indices_ = self.indices
        regressor._set_expansion(self.prototypes, self._T @ w, self._y_mean - self._mu @ w)
        return regressor

    @property
    def nbytes(self) -> int:
        """Memory held (bytes)."""
        return int(self._T.nbytes + self._A.nbytes + self.prototypes.nbytes)
