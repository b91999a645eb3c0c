"""Tests of the latent-force scenarios of ``experiments.benchmark.timing``."""

from __future__ import annotations

import numpy as np

from experiments.benchmark import timing as solver_timing


def test_latent_force_scenarios_start_and_walk() -> None:
    rng = np.random.default_rng(0)
    W = solver_timing.latent_force_scenarios(rng, 5, 7, mean=1.5, spread=0.0, walk_std=0.0)
    assert W.shape == (5, 7)
    np.testing.assert_array_equal(W, 1.5)  # no spread and no walk: the mean throughout
    W = solver_timing.latent_force_scenarios(
        np.random.default_rng(1), 4000, 3, mean=[1.0, -2.0], spread=0.5, walk_std=0.2, n_forces=2
    )
    assert W.shape == (4000, 3, 2)
    np.testing.assert_allclose(W[:, 0].mean(axis=0), [1.0, -2.0], atol=0.05)
    np.testing.assert_allclose(W[:, 0].std(axis=0), 0.5, rtol=0.05)
    np.testing.assert_allclose(np.diff(W, axis=1).std(axis=(0, 1)), 0.2, rtol=0.05)
