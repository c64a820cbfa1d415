"""The validation helpers of ipmc-ros: inputs into finite float arrays, and the output paths of
the commands checked before any work, each refusal one sentence saying why."""

from __future__ import annotations

import os
from pathlib import Path

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


def _check_folder_writable(folder: Path, option: str, target: Path) -> None:
    """``folder`` (created later if missing) can hold ``target``: the nearest part of it that
    exists is a folder this process may write in."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{option} {target}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{option} {target}: the folder {existing} cannot be written")


def check_output_file(path, *, option: str, suffixes: tuple[str, ...]) -> Path:
    """The file ``path`` a command will write, checked before any work is done.

    Parameters
    ----------
    path : str or os.PathLike
        The file to write. Missing folders on the way are allowed (the writer creates them).
    option : str
        The command-line option that gave it (``"--out"``), named in the message.
    suffixes : tuple of str
        Accepted suffixes, lower case with the dot (``(".csv",)``).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ValueError
        One sentence: the path is a folder, its suffix is not one of ``suffixes``, a part of its
        folder is a file, or the folder cannot be written.
    """
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{option} {p} is a folder; give a file name, e.g. "
                         f"{p / ('out' + suffixes[0])}")
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {p}: expected a {' or '.join(suffixes)} file name")
    _check_folder_writable(p.parent, option, p)
    return p


def check_output_dir(path, *, option: str) -> Path:
    """The folder ``path`` a command will write files in, checked before any work is done:
    ``ValueError`` (one sentence naming ``option``) if it is a file or cannot be written. A
    missing folder is allowed (the writer creates it)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{option} {p} is a file; give a folder (it is created if missing)")
    _check_folder_writable(p, option, p)
    return p
