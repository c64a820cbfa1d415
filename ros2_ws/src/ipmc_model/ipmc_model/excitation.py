"""The kind of an input record: its bandwidth and its share in holds, kept with a model so a
later record can be compared with the one the model was identified on."""

from __future__ import annotations

import numpy as np

from .residuals import find_holds, spectrum

#: Two kinds differ when their 95 % bandwidths differ by more than this factor ...
SHIFT_BANDWIDTH_FACTOR = 3.0
#: ... or their shares of samples in input holds by more than this.
SHIFT_HOLD_SHARE = 0.3
#: A hold: the input still for this long (s).
HOLD_S = 3.0


def input_kind(u, rate_hz: float) -> dict:
    """The 95 % power bandwidth (Hz, ``bandwidth_hz``) of an input (V at ``rate_hz``) and the
    share of its samples in holds of >= 3 s (``hold_share``)."""
    u = np.asarray(u, float)
    f, p = spectrum(u, rate_hz, nperseg=min(u.size, 4096))
    c = np.cumsum(p)
    f95 = float(f[np.searchsorted(c, 0.95 * c[-1])]) if c[-1] > 0 else 0.0
    held = sum(e - s for s, e in find_holds(u, 1.0 / rate_hz, HOLD_S))
    return {"bandwidth_hz": max(f95, float(f[1]) if f.size > 1 else 1e-3),
            "hold_share": held / u.size}


def kinds_differ(a: dict, b: dict) -> bool:
    """Whether two :func:`input_kind` results differ (bandwidth factor or hold share)."""
    lo, hi = sorted((a["bandwidth_hz"], b["bandwidth_hz"]))
    return bool(hi / max(lo, 1e-12) > SHIFT_BANDWIDTH_FACTOR
                or abs(a["hold_share"] - b["hold_share"]) > SHIFT_HOLD_SHARE)


def kind_text(kind: dict) -> str:
    """``kind`` (:func:`input_kind`) in words."""
    return (f"95 % bandwidth {kind['bandwidth_hz']:.3g} Hz, {100 * kind['hold_share']:.0f} % "
            "in holds")


def model_input_kind(model) -> dict | None:
    """The :func:`input_kind` a model file keeps (``metadata["input_kind"]``), or None."""
    k = getattr(model, "metadata_", None)
    k = k.get("input_kind") if isinstance(k, dict) else None
    try:
        k = {"bandwidth_hz": float(k["bandwidth_hz"]), "hold_share": float(k["hold_share"])}
    except (TypeError, KeyError, ValueError):
        return None
    return k if k["bandwidth_hz"] > 0 and 0 <= k["hold_share"] <= 1 else None
