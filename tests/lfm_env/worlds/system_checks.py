"""Checks every world's system passes, shared by the worlds' test modules."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lfm_env.system import ControlSystem

Draw = Callable[[np.random.Generator, int], np.ndarray]


def assert_batched_step_equals_row_by_row(
    system: ControlSystem, dt: float, random_states: Draw, random_actions: Draw, force_std: float
) -> tuple[np.ndarray, np.ndarray]:
    """One Euler step of a batch of 50 random states (the world's own draws, seed 0), actions
    and forces ``N(0, force_std^2)`` has the batch's shape and equals the steps taken row by
    row, bit for bit. Returns the states and actions drawn."""
    rng = np.random.default_rng(0)
    n = 50
    states, actions = random_states(rng, n), random_actions(rng, n)
    w = rng.normal(0.0, force_std, size=(n, 1))
    batch = system.euler_step(states, actions, w, dt)
    assert batch.shape == states.shape
    for i in range(n):
        np.testing.assert_array_equal(batch[i], system.euler_step(states[i], actions[i], w[i], dt))
    return states, actions
