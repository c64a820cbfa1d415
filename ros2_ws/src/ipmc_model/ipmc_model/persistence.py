"""Model files: a JSON document (kind, format version, hyperparameters, scalings) plus an NPZ
file of its arrays next to it (``model.json`` + ``model.npz``).

``load_model`` fails with a :class:`~ipmc_model.errors.ModelFileError` whose message is one
sentence naming the file and what is wrong (missing, not JSON, not an ipmc-ros model, newer
format version, changed or corrupted after it was written, arrays missing).

Format versions: 1, every model; 2 adds a forward ``lssvm-narx`` model's voltage channels
(``model.params``: ``input_memory_taus_s``, ``include_voltage``, ``dt_s``); 3 adds the kind
``lssvm-narx-committee`` (``model.members``: one ``lssvm-narx`` body each, their arrays named
``m<i>_centers``, ``m<i>_coef``); 4 adds the kinds ``gpi`` and ``gpi-inverse`` (the
rate-dependent generalised Prandtl-Ishlinskii model, and the same model served through its
numerical inverse as a feedforward); 5 adds ``document_sha256``, the checksum of the JSON
document itself (without that field, serialised with sorted keys and no spaces), which holds
the NPZ file's checksum ``arrays_sha256``: an edited number in either file is refused. Every
file is written as version 5; files of versions 1-4 load with their own check (the NPZ file's
checksum only).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np

from ipmc_driver.dataio import write_atomic
from ipmc_driver.validation import check_output_file

from .errors import ModelFileError, NotFittedError
from .hysteresis import GeneralizedPI, GpiInverse
from .lssvm import FixedSizeLSSVMRegressor, LSSVMRegressor
from .narx import InverseNarxModel, NarxCommittee, NarxModel
from .play import PrandtlIshlinskii

FORMAT = "ipmc-ros-model"
FORMAT_VERSION = 5  # the newest this module reads, and the one it writes
#: The field of the JSON document's own checksum (format version 5 on).
DOCUMENT_CHECKSUM = "document_sha256"
#: The first format version whose files carry :data:`DOCUMENT_CHECKSUM`.
DOCUMENT_CHECKSUM_SINCE = 5
#: NarxModel parameters that exist only since format version 2 (voltage channels).
CHANNEL_PARAMS = ("input_memory_taus_s", "include_voltage", "dt_s")
KINDS = ("pi", "lssvm-narx", "lssvm-narx-inverse", "lssvm-narx-committee", "gpi", "gpi-inverse")
#: The learned scalars and arrays of a GeneralizedPI in a file.
GPI_SCALARS = ("charge_tau_s_", "slew_v_per_s_", "train_rmse_")
GPI_ARRAYS = ("thresholds_", "feature_mean_", "feature_scale_", "weights_", "knots_", "map_coef_")


def _arrays_path(path: Path) -> Path:
    return path.with_suffix(".npz")


def _regressor_doc(reg) -> tuple[dict, dict]:
    if isinstance(reg, FixedSizeLSSVMRegressor):
        kind = "fixed-size-lssvm"
    elif isinstance(reg, LSSVMRegressor):
        kind = "lssvm"
    else:
        raise ValueError(f"cannot save a regressor of type {type(reg).__name__}")
    doc = {"type": kind, "params": reg.get_params(), "sigma": reg.sigma_, "C": reg.C_,
           "intercept": reg.intercept_}
    return doc, {"centers": reg.centers_, "coef": reg.coef_}


def _narx_doc(m: NarxModel) -> tuple[dict, dict]:
    reg_doc, arrays = _regressor_doc(m.regressor_)
    params = m.get_params()
    if not m.uses_voltage_channels:  # absent, as in the files before format version 2
        params = {k: v for k, v in params.items() if k not in CHANNEL_PARAMS}
    doc = {
        "params": params,
        "input_lags_": list(m.input_lags_),
        "u_mean": [float(v) for v in np.atleast_1d(m.u_mean_)],
        "u_scale": [float(v) for v in np.atleast_1d(m.u_scale_)],
        "y_mean": m.y_mean_,
        "y_scale": m.y_scale_,
        "regressor": reg_doc,
    }
    return doc, arrays


def model_paths(path) -> tuple[Path, Path]:
    """The JSON file (``.json`` added if missing) and the NPZ file beside it that
    :func:`save_model` writes for ``path``."""
    path = Path(path)
    if path.suffix != ".json":
        path = path.with_name(path.name + ".json")
    return path, _arrays_path(path)


#: Suffixes a model file name may not end in: .json is added to them, which would give
#: ``fwd.npz.json`` or ``day1.csv.json`` - most likely a mistaken argument.
FOREIGN_SUFFIXES = (".npz", ".csv", ".mcap", ".db3", ".yaml", ".yml", ".png")


def check_model_output(path, option: str = "--out") -> Path:
    """The JSON file a model will be written to, checked before any work: ``ValueError`` (one
    sentence naming ``option``) if ``path`` ends in another file kind's suffix, if it or its
    NPZ file is a folder, or if its folder cannot be written."""
    given = Path(path)
    if given.suffix.lower() in FOREIGN_SUFFIXES:
        raise ValueError(f"{option} {given}: a model file is a .json name (its arrays go in a "
                         ".npz file beside it)")
    if given.is_dir():
        raise ValueError(f"{option} {given} is a folder; give a model file name, e.g. "
                         f"{given / 'model.json'}")
    json_path, npz_path = model_paths(given)
    check_output_file(json_path, option=option, suffixes=(".json",))
    check_output_file(npz_path, option=option, suffixes=(".npz",))
    return json_path


def save_model(model, path, *, metadata: dict | None = None) -> Path:
    """Save a fitted model to ``path`` (JSON, ``.json`` added if missing) and ``.npz`` beside it.

    Both files are written in full under temporary names and then renamed into place, the JSON
    last, so that a crash leaves no partly written file under the final names.

    Parameters
    ----------
    model : PrandtlIshlinskii, NarxModel, NarxCommittee, InverseNarxModel, GeneralizedPI or
        GpiInverse (fitted)
    path : str or os.PathLike
    metadata : dict, optional
        JSON-serialisable notes stored under ``"metadata"`` (data file, tuning result, units).

    Returns
    -------
    pathlib.Path
        The JSON file written.
    """
    path, arrays_path = model_paths(path)
    kind, body, arrays = _model_doc(model)
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v, dtype=float) for k, v in arrays.items()})
    blob = buf.getvalue()
    doc = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": kind,
        "units": {"input": "V", "output": "mm"},
        "arrays_file": arrays_path.name,
        "arrays_sha256": hashlib.sha256(blob).hexdigest(),
        "model": body,
        "metadata": metadata or {},
    }
    # the checksum of the document as a reader parses it back (tuples become lists, NumPy
    # scalars numbers), so that reading and checking agree on every value
    parsed = json.loads(json.dumps(doc, default=_json_default))
    doc[DOCUMENT_CHECKSUM] = document_sha256(parsed)
    text = json.dumps(doc, indent=2, default=_json_default) + "\n"
    write_atomic({arrays_path: blob, path: text})
    return path


def document_sha256(doc: dict) -> str:
    """SHA-256 of a model document without its own checksum field, serialised canonically
    (sorted keys, no spaces, ASCII): what :data:`DOCUMENT_CHECKSUM` holds."""
    rest = {k: v for k, v in doc.items() if k != DOCUMENT_CHECKSUM}
    text = json.dumps(rest, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def _model_doc(model) -> tuple[str, dict, dict]:
    """The kind, JSON body and arrays of a fitted model."""
    if isinstance(model, (GeneralizedPI, GpiInverse)):
        return _gpi_doc(model)
    if isinstance(model, PrandtlIshlinskii):
        if model.weights_ is None:
            raise NotFittedError("this PrandtlIshlinskii is not fitted yet; nothing to save")
        body = {"params": model.get_params(), "offset": model.offset_}
        return "pi", body, {"thresholds": model.thresholds_, "weights": model.weights_}
    if isinstance(model, InverseNarxModel):
        if model.narx_ is None:
            raise NotFittedError("this InverseNarxModel is not fitted yet; nothing to save")
        body, arrays = _narx_doc(model.narx_)
        body["params"] = model.get_params()
        return "lssvm-narx-inverse", body, arrays
    if isinstance(model, NarxModel):
        if model.regressor_ is None:
            raise NotFittedError("this NarxModel is not fitted yet; nothing to save")
        return ("lssvm-narx", *_narx_doc(model))
    if isinstance(model, NarxCommittee):
        if model.regressor_ is None:
            raise NotFittedError("this NarxCommittee is not fitted yet; nothing to save")
        body, arrays = {"members": []}, {}
        for i, m in enumerate(model.members):
            b, a = _narx_doc(m)
            body["members"].append(b)
            arrays.update({f"m{i}_{k}": v for k, v in a.items()})
        return "lssvm-narx-committee", body, arrays
    raise ValueError(f"cannot save an object of type {type(model).__name__}")


def _gpi_doc(model) -> tuple[str, dict, dict]:
    """The kind, JSON body and arrays of a GeneralizedPI or of its inverse (the forward model
    and the inverse's voltage limit)."""
    inverse = isinstance(model, GpiInverse)
    m = model.model if inverse else model
    if m.weights_ is None:
        raise NotFittedError("this GeneralizedPI is not fitted yet; nothing to save")
    body = {"params": m.get_params(), "memory_taus_s_": list(m.memory_taus_s_),
            "cv": m.cv_.as_dict()}
    body.update({k: float(getattr(m, k)) for k in GPI_SCALARS})
    body["negative_gain_"] = float(m.negative_gain_)
    body["output_coef_"] = [float(v) for v in m.output_coef_]
    body["drift_gain_per_s_"] = float(m.drift_gain_per_s_)
    body["drift_offset_mm_per_s_"] = float(m.drift_offset_mm_per_s_)
    body["limit_mm_"] = float(m.limit_mm_) if math.isfinite(m.limit_mm_) else None
    body["delay_samples_"] = int(m.delay_samples_)
    body["map_range_"] = [v if math.isfinite(v) else None for v in m.map_range_]
    if m.map_edge_slopes_ is not None:
        body["map_edge_slopes_"] = [float(v) for v in m.map_edge_slopes_]
    if inverse:
        body["u_max_v"] = model.u_max_v
    return ("gpi-inverse" if inverse else "gpi"), body, {k: getattr(m, k) for k in GPI_ARRAYS}


def _build_gpi(body: dict, arrays: dict):
    from .hysteresis import MAP_BASES, CvResult

    # a file written before the path-memory or direction-memory channels has none
    m = GeneralizedPI(**{"path_memory_v": (), "direction_memory_v": (), **body["params"]})
    if m.map_basis not in MAP_BASES:
        raise ValueError(f"its output map is {m.map_basis!r}; this ipmc-ros knows "
                         f"{sorted(MAP_BASES)}")
    m.memory_taus_s_ = tuple(float(t) for t in body["memory_taus_s_"])
    for k in GPI_SCALARS:
        setattr(m, k, float(body[k]))
    m.delay_samples_ = int(body["delay_samples_"])
    m.negative_gain_ = float(body.get("negative_gain_", 1.0))
    m.output_coef_ = np.asarray(body.get("output_coef_", []), dtype=float)
    if m.output_coef_.size != m.n_output_channels:
        raise ValueError("the output channels' coefficients do not match the channels (charging "
                         "current, relaxations) the file's parameters define")
    m.drift_gain_per_s_ = float(body.get("drift_gain_per_s_", 0.0))
    m.drift_offset_mm_per_s_ = float(body.get("drift_offset_mm_per_s_", 0.0))
    limit = body.get("limit_mm_")
    m.limit_mm_ = math.inf if limit is None else float(limit)
    # a file written before the map's range was kept extrapolates with its outer hinges
    lo, hi = body.get("map_range_", [None, None])
    m.map_range_ = (-math.inf if lo is None else float(lo), math.inf if hi is None else float(hi))
    # one written before the determined edge slopes goes on at the slopes at its range's edges
    edge = body.get("map_edge_slopes_")
    m.map_edge_slopes_ = None if edge is None else (float(edge[0]), float(edge[1]))
    for k in GPI_ARRAYS:
        setattr(m, k, np.asarray(arrays[k], dtype=float))
    cv = body["cv"]
    m.cv_ = CvResult(tuple(cv["alphas"]), tuple(cv["rmse"]), float(cv["alpha"]),
                     int(cv["n_folds"]))
    if m.thresholds_.ndim != 2 or m.knots_.ndim != 1 or m.weights_.ndim != 1:
        raise ValueError("the GPI arrays have the wrong dimensions")
    p = m.feature_mean_.size
    if (m.weights_.size != p + 1 or m.feature_scale_.size != p
            or m.map_coef_.size != m.knots_.size + 1
            or p != (1 + len(m.memory_taus_s_) + m.thresholds_.size + len(m.path_memory_v)
                     + m.n_direction_channels * len(m.direction_memory_v)
                     + m.n_extra_channels)
            or m.thresholds_.shape[0] > 1 + len(m.memory_taus_s_)):
        raise ValueError("the GPI arrays do not match its channels")
    if not (m.dt_s > 0 and m.delay_samples_ >= 0 and m.charge_tau_s_ >= 0
            and m.slew_v_per_s_ > 0 and all(t > 0 for t in m.memory_taus_s_)
            and m.negative_gain_ > 0 and m.limit_mm_ > 0 and m.dead_zone_v >= 0):
        raise ValueError("a GPI time constant, rate limit or delay is out of range")
    return GpiInverse(m, float(body["u_max_v"])) if "u_max_v" in body else m


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _fail(path, why: str):
    raise ModelFileError(f"{path}: {why}.")


def read_model_document(path) -> dict:
    """Read and check the JSON document of a model file (no arrays); ``ModelFileError`` if bad."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        _fail(path, "no such model file")
    except (OSError, UnicodeDecodeError) as exc:
        _fail(path, f"cannot read the model file ({exc.__class__.__name__})")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        _fail(path, f"not a model file: not valid JSON (line {exc.lineno})")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        _fail(path, f"not an ipmc-ros model file (no \"format\": \"{FORMAT}\")")
    version = doc.get("format_version")
    if not isinstance(version, int) or version < 1:
        _fail(path, f"bad format_version {version!r}")
    if version > FORMAT_VERSION:
        _fail(path, f"format version {version} is newer than this ipmc_model supports "
                    f"({FORMAT_VERSION}); upgrade ipmc_model")
    if doc.get("kind") not in KINDS:
        _fail(path, f"unknown model kind {doc.get('kind')!r} (known: {', '.join(KINDS)})")
    # a file of an older version has no document checksum; one that has it is checked whatever
    # its version says, so that lowering the version does not skip the check
    if version >= DOCUMENT_CHECKSUM_SINCE or DOCUMENT_CHECKSUM in doc:
        if doc.get(DOCUMENT_CHECKSUM) != document_sha256(doc):
            _fail(path, "the model file was changed or corrupted after it was written (the "
                        "checksum of its JSON document differs)")
    return doc


def load_model(path):
    """Load a model saved by :func:`save_model`.

    Returns
    -------
    PrandtlIshlinskii, NarxModel, NarxCommittee or InverseNarxModel
        Fitted, ready for ``predict`` / ``simulate`` / ``stepper``. The document's
        ``metadata`` is attached as ``model.metadata_``.

    Raises
    ------
    ModelFileError
        One sentence naming the file and the problem.
    """
    path = Path(path)
    doc = read_model_document(path)
    arrays_path = path.parent / str(doc.get("arrays_file", _arrays_path(path).name))
    try:
        blob = arrays_path.read_bytes()
    except OSError:
        _fail(path, f"its arrays file {arrays_path.name} is missing")
    if hashlib.sha256(blob).hexdigest() != doc.get("arrays_sha256"):
        _fail(path, f"its arrays file {arrays_path.name} was changed or corrupted after it was "
                    "written, or belongs to another model (its checksum differs)")
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        model = _build(doc["kind"], doc["model"], arrays)
    except (KeyError, TypeError, ValueError, zipfile.BadZipFile, OSError) as exc:
        _fail(path, f"corrupt model content ({exc.__class__.__name__}: {exc})".rstrip("."))
    model.metadata_ = doc.get("metadata", {})
    return model


def _build_regressor(doc: dict, arrays: dict):
    cls = {"lssvm": LSSVMRegressor, "fixed-size-lssvm": FixedSizeLSSVMRegressor}[doc["type"]]
    reg = cls(**doc["params"])
    reg.sigma_, reg.C_ = float(doc["sigma"]), float(doc["C"])
    reg._set_expansion(arrays["centers"], arrays["coef"], float(doc["intercept"]))
    return reg


def _build_narx(body: dict, arrays: dict, params: dict) -> NarxModel:
    from .narx import _lag_sets

    m = NarxModel(regressor=None, **params)
    in_lags = tuple(int(v) for v in body["input_lags_"])
    m.input_lags_ = in_lags
    m.in_delays_, m.out_delays_ = _lag_sets(in_lags, int(params["output_lags"]),
                                           int(params.get("lag_step", 1)))
    m.max_lag_ = int(max([ds.max() for ds in m.in_delays_]
                         + [m.out_delays_.max() if m.out_delays_.size else 0]))
    m.n_inputs_ = len(in_lags)
    m.n_features_ = sum(k + 1 for k in in_lags) + int(params["output_lags"])
    m.u_mean_ = np.asarray(body["u_mean"], dtype=float)
    m.u_scale_ = np.asarray(body["u_scale"], dtype=float)
    m.y_mean_, m.y_scale_ = float(body["y_mean"]), float(body["y_scale"])
    m.regressor_ = _build_regressor(body["regressor"], arrays)
    if m.regressor_.centers_.shape[1] != m.n_features_:
        raise ValueError("regressor width does not match the lags")
    if m.uses_voltage_channels:
        m.voltage_poles()  # ValueError on bad time constants or sample period
        n = int(bool(m.include_voltage)) + len(m.input_memory_taus_s)
        if n != m.n_inputs_:
            raise ValueError(f"{n} voltage channel(s) but input lags for {m.n_inputs_}")
    if len(m.u_mean_) != m.n_inputs_ or len(m.u_scale_) != m.n_inputs_:
        raise ValueError("input scalings do not match the input channels")
    return m


def _build(kind: str, body: dict, arrays: dict):
    if kind in ("gpi", "gpi-inverse"):
        model = _build_gpi(body, arrays)
        if isinstance(model, GpiInverse) != (kind == "gpi-inverse"):
            raise ValueError(f"a {kind} body {'without' if kind == 'gpi-inverse' else 'with'} "
                             "u_max_v")
        return model
    if kind == "pi":
        m = PrandtlIshlinskii(**body["params"])
        m.thresholds_ = np.asarray(arrays["thresholds"], dtype=float)
        m.weights_ = np.asarray(arrays["weights"], dtype=float)
        m.offset_ = float(body["offset"])
        return m
    if kind == "lssvm-narx":
        return _build_narx(body, arrays, body["params"])
    if kind == "lssvm-narx-committee":
        members = [_build_narx(b, {k: arrays[f"m{i}_{k}"] for k in ("centers", "coef")},
                               b["params"]) for i, b in enumerate(body["members"])]
        c = NarxCommittee(members)
        c._check_members()
        if len({m.n_inputs_ for m in members}) != 1:
            raise ValueError("the members' input channels differ")
        return c._set_fitted()
    p = body["params"]
    inv = InverseNarxModel(**p)
    inv.narx_ = _build_narx(body, arrays, {"input_lags": p["output_lags"],
                                           "output_lags": p["input_lags"],
                                           "lag_step": p.get("lag_step", 1),
                                           "standardize": p["standardize"]})
    return inv
