"""Checks of user-supplied arrays, shared by the env and the agents."""

from __future__ import annotations

from typing import Any

import numpy as np


def real_vector(value: Any, size: int, name: str, layout: str) -> np.ndarray:
    """``value`` as a finite float vector of ``size`` entries, or a ``ValueError``.

    Args:
        value: what the user passed (list, array, ...).
        size: required number of entries.
        name: the argument's name in messages (e.g. ``"action"``).
        layout: what the entries are, e.g. ``"[a m/s^2, delta rad]"``.

    Raises:
        ValueError: naming ``name``, for text, objects or complex numbers (which NumPy would
            convert or truncate silently), a wrong shape, or NaN/inf entries.
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r}: must be {size} numbers {layout}") from exc
    if arr.dtype.kind not in "biuf":
        raise ValueError(
            f"{name}={value!r}: must be {size} real numbers {layout}, not dtype {arr.dtype}"
        )
    arr = arr.astype(float)
    if arr.shape != (size,):
        raise ValueError(f"{name} has shape {arr.shape}: must be ({size},) = {layout}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}={arr.tolist()}: must be finite (no NaN or inf)")
    return arr


def frozen_vector(value: Any, n: int, name: str) -> np.ndarray:
    """``value`` as a read-only float vector of ``n`` entries; a ``ValueError`` names ``name``."""
    arr = np.asarray(value, dtype=float).reshape(-1) if value is not None else None
    if arr is None or arr.shape != (n,):
        raise ValueError(f"{name}={value!r}: must be {n} numbers")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr
