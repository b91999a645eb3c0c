"""The augmented latent-force model's particle transition (the filter's proposal)."""

from __future__ import annotations

import numpy as np
import pytest

from lfm_env.config import load_env_config
from lfm_env.model import LatentForceModel
from lfm_env.vehicle import euler_step


@pytest.fixture(scope="module")
def model() -> LatentForceModel:
    return LatentForceModel(load_env_config("configs/paper.yaml"))


def _particles(model: LatentForceModel, n: int, rng: np.random.Generator) -> np.ndarray:
    x = np.array([0.0, 0.0, 8.0, 0.3]) + rng.standard_normal((n, 4)) * [1.0, 0.5, 2.0, 0.4]
    z = rng.standard_normal((n, model.latent_dim)) @ np.linalg.cholesky(model.kernel.Pinf).T
    return np.concatenate([x, z], axis=1)


def test_transition_shape_layout_and_input_untouched(model):
    rng = np.random.default_rng(0)
    particles = _particles(model, 500, rng)
    before = particles.copy()
    out = model.transition(particles, np.array([0.5, 0.05]), rng)
    assert out.shape == particles.shape and out.dtype == np.float64
    assert out.flags.c_contiguous  # row-major, as the filter's resampling gather wants
    np.testing.assert_array_equal(particles, before)


def test_transition_mean_and_noise_covariance_match_the_model(model):
    """Over many draws: mean = the noise-free step, spread = the model's process noise."""
    rng = np.random.default_rng(1)
    n, draws = 300, 400
    particles = _particles(model, n, rng)
    u = np.array([-1.0, 0.2])
    mean_x = euler_step(
        particles[:, :4], u, model.dt, particles[:, 4:] @ model.H, model.config.vehicle_length
    )
    mean_z = particles[:, 4:] @ model.A.T
    out = np.stack([model.transition(particles, u, rng) for _ in range(draws)])
    noise = out - np.concatenate([mean_x, mean_z], axis=1)
    flat = noise.reshape(-1, model.state_dim)
    m = flat.shape[0]
    std = np.sqrt(np.concatenate([model.process_std**2, np.diag(model.Q)]))
    # Sample means within 5 standard errors; covariances within 3 %.
    assert np.all(np.abs(flat.mean(axis=0)) < 5.0 * std / np.sqrt(m))
    cov = np.cov(flat.T)
    expected = np.zeros((model.state_dim, model.state_dim))
    expected[:4, :4] = np.diag(model.process_std**2)
    expected[4:, 4:] = model.Q
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.all(np.abs(cov - expected) <= 0.03 * scale)
    # Physical and latent noise are independent, and so are particles.
    corr = np.corrcoef(noise[:, 0, 2], noise[:, 1, 2])[0, 1]
    assert abs(corr) < 5.0 / np.sqrt(draws)


def test_transition_is_reproducible_from_the_generator_state(model):
    particles = _particles(model, 100, np.random.default_rng(2))
    u = np.array([0.0, -0.1])
    a = model.transition(particles, u, np.random.default_rng(7))
    b = model.transition(particles, u, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    c = model.transition(particles, u, np.random.default_rng(8))
    assert not np.array_equal(a, c)
