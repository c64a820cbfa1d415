"""The one validation helper of ipmc-ros: turns inputs into finite float arrays or says why not."""

from __future__ import annotations

import numpy as np


def as_signal(name: str, x, *, min_length: int = 1, allow_nan: bool = False) -> np.ndarray:
    """Return ``x`` as a 1-D float64 array, or raise ``ValueError`` naming ``name``.

    Parameters
    ----------
    name : str
        Name of the argument, used in the error message (e.g. ``"u"``).
    x : array_like, shape (N,)
        The signal.
    min_length : int
        Smallest accepted N.
    allow_nan : bool
        Accept NaN/inf entries (default: refuse them).
    """
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric, got {type(x).__name__}: {exc}") from None
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.size < min_length:
        raise ValueError(f"{name} needs at least {min_length} samples, got {arr.size}")
    if not allow_nan and not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise ValueError(f"{name} must be finite; first non-finite value at index {bad}")
    return arr


def same_length(**signals: np.ndarray) -> int:
    """Check that all named signals have one length and return it (``ValueError`` otherwise)."""
    lengths = {k: len(v) for k, v in signals.items()}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"{k} has {n}" for k, n in lengths.items())
        raise ValueError(f"signals must have the same length: {desc}")
    return next(iter(lengths.values()))
