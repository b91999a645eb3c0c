"""Checks of user-supplied vectors, and errors on one line: shared by every layer."""

from __future__ import annotations

from typing import Any

import numpy as np


def real_vector(
    value: Any, size: int | None, name: str, layout: str = "", finite: bool = True
) -> np.ndarray:
    """``value`` as a new float vector of ``size`` entries, or a ``ValueError``.

    Args:
        value: what the user passed (list, array, ...).
        size: required number of entries; ``None`` for any.
        name: the argument's name in messages (e.g. ``"action"``).
        layout: what the entries are, e.g. ``"[a m/s^2, delta rad]"``.
        finite: refuse NaN and inf entries (``False``: bounds may be infinite, an estimate
            may be NaN).

    Raises:
        ValueError: naming ``name``, for text, objects or complex numbers (which NumPy would
            convert or truncate silently), a wrong shape, or NaN/inf entries.
    """
    count = "" if size is None else f"{size} "
    layout = f" {layout}" if layout else ""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r}: must be {count}numbers{layout}") from exc
    if arr.dtype.kind not in "biuf":
        raise ValueError(
            f"{name}={value!r}: must be {count}real numbers{layout}, not dtype {arr.dtype}"
        )
    arr = arr.astype(float)
    if arr.ndim != 1 or (size is not None and arr.shape != (size,)):
        shape = "(n,)" if size is None else f"({size},)"
        raise ValueError(f"{name} has shape {arr.shape}: must be {shape}{layout and ' =' + layout}")
    if finite and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}={arr.tolist()}: must be finite (no NaN or inf)")
    return arr


def frozen_vector(value: Any, n: int, name: str) -> np.ndarray:
    """:func:`real_vector` of ``n`` entries (a column flattened; infinite entries allowed, as
    for unbounded inputs), read-only."""
    arr = real_vector(np.ravel(value), n, name, finite=False)
    arr.flags.writeable = False
    return arr


def one_line(exc: BaseException) -> str:
    """``"Type: message"`` on one line, so an error fits a CSV cell, a log line and a
    message that names it."""
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


__all__ = ["frozen_vector", "one_line", "real_vector"]
