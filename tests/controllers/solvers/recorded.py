"""The scenario problems recorded in ``tests/data`` (by ``tests/data/make_*_problems.py``),
shared by the solver tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

DATA_DIR = Path(__file__).resolve().parents[2] / "data"


def load_problems(name: str = "recorded_problems.npz") -> dict[str, np.ndarray]:
    """The arrays of one recorded set (``seed``, ``step``, ``x0``, ``W``, ...) by name."""
    return dict(np.load(DATA_DIR / name))
