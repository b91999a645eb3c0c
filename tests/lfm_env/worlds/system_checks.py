"""Checks every world's system passes, shared by the worlds' test modules."""

from __future__ import annotations

import numpy as np

from lfm_env.system import ControlSystem


def assert_batched_step_equals_row_by_row(
    system: ControlSystem, states: np.ndarray, actions: np.ndarray, w: np.ndarray, dt: float
) -> None:
    """One Euler step of the batch ``states`` ``(n, nx)`` (with ``actions``, forces ``w``) has
    the batch's shape and equals the steps taken row by row, bit for bit."""
    batch = system.euler_step(states, actions, w, dt)
    assert batch.shape == states.shape
    for i in range(len(states)):
        np.testing.assert_array_equal(batch[i], system.euler_step(states[i], actions[i], w[i], dt))
