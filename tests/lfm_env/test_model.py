"""The latent-force model (``lfm_env.model``): its matrices, forecasts and the particle
transition (the filter's proposal), on the paper's model and on a two-component force."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from lfm_env.gp import matern
from lfm_env.model import LatentForceModel
from tests.point_mass import point_mass_system

PLANAR = point_mass_system("planar")
PLANAR_KERNELS = (matern(2.5, 1.0, 2.0), matern(0.5, 0.5, 1.0))


@pytest.fixture(scope="module")
def planar_model() -> LatentForceModel:
    return LatentForceModel(PLANAR, list(PLANAR_KERNELS), dt=0.1, process_noise_std=[0.01] * 4)


@pytest.fixture(params=["paper", "planar"])
def model(request, paper_model, planar_model) -> LatentForceModel:
    return {"paper": paper_model, "planar": planar_model}[request.param]


def _particles(model: LatentForceModel, n: int, rng: np.random.Generator) -> np.ndarray:
    nx = model.nx
    x = rng.standard_normal((n, nx)) * np.linspace(0.4, 2.0, nx) + np.linspace(0.0, 8.0, nx)
    pinf = model.stationary_latent_covariance()
    z = rng.standard_normal((n, model.latent_dim)) @ np.linalg.cholesky(pinf).T
    return np.concatenate([x, z], axis=1)


def _input(model: LatentForceModel) -> np.ndarray:
    return 0.3 * model.system.input_upper


# ----------------------------------------------------------------------------- matrices


def test_paper_model_matrices(paper_model, paper_config):
    kernel = matern(2.5, 4.0, 4.0)
    A, Q = kernel.discretize(0.2, method="exact")
    np.testing.assert_array_equal(paper_model.A, A)
    np.testing.assert_array_equal(paper_model.Q, Q)
    np.testing.assert_array_equal(paper_model.H, np.asarray(kernel.H).reshape(1, -1))
    np.testing.assert_array_equal(paper_model.process_std, paper_config.process_noise_std_rad)
    np.testing.assert_allclose(paper_model.Q_factor @ paper_model.Q_factor.T, Q, atol=1e-14)
    assert (paper_model.nx, paper_model.nw, paper_model.latent_dim) == (4, 1, 3)
    assert paper_model.state_dim == 7 and paper_model.dt == 0.2


def test_a_two_component_force_stacks_its_kernels_block_diagonally(planar_model):
    blocks = [k.discretize(0.1, method="exact") for k in PLANAR_KERNELS]
    np.testing.assert_array_equal(planar_model.A, scipy.linalg.block_diag(*[a for a, _ in blocks]))
    np.testing.assert_array_equal(planar_model.Q, scipy.linalg.block_diag(*[q for _, q in blocks]))
    np.testing.assert_array_equal(planar_model.H, [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(
        planar_model.stationary_latent_covariance(),
        scipy.linalg.block_diag(*[k.Pinf for k in PLANAR_KERNELS]),
    )
    assert (planar_model.nw, planar_model.latent_dim) == (2, 4)


def test_stationary_covariance_is_invariant_under_the_step(model):
    P = model.stationary_latent_covariance()
    np.testing.assert_allclose(model.A @ P @ model.A.T + model.Q, P, atol=1e-10)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"kernel": [matern(1.5, 1.0, 1.0)]}, "1 kernel.*2 force component"),
        ({"kernel": "matern"}, "lfm_env.gp kernels"),
        ({"dt": 0.0}, "dt"),
        ({"dt": float("nan")}, "dt"),
        ({"process_noise_std": [0.1, 0.1, 0.1]}, "process_noise_std.*p_x"),
        ({"process_noise_std": [0.1, 0.1, -0.1, 0.1]}, "process_noise_std"),
        ({"discretization": "rk4"}, "discretization"),
        ({"system": "planar"}, "ControlSystem"),
    ],
)
def test_bad_arguments_name_the_field(kwargs, match):
    args = {"system": PLANAR, "kernel": list(PLANAR_KERNELS), "dt": 0.1, **kwargs}
    with pytest.raises(ValueError, match=match):
        LatentForceModel(**args)


# ----------------------------------------------------------------------------- forces


def test_latent_force_and_forecasts_have_a_force_axis(model):
    rng = np.random.default_rng(3)
    z = _particles(model, 6, rng)[:, model.nx :]
    w = model.latent_force(z)
    assert w.shape == (6, model.nw)
    np.testing.assert_allclose(w, z @ model.H.T, rtol=1e-15)
    assert model.latent_force(z[0]).shape == (model.nw,)

    mean = model.mean_latent_forecast(z, 5)
    assert mean.shape == (6, 5, model.nw)
    for k in range(5):
        expected = z @ np.linalg.matrix_power(model.A, k).T @ model.H.T
        np.testing.assert_allclose(mean[:, k], expected, rtol=1e-12, atol=1e-12)

    draws = model.sample_latent_forecasts(z, 5, np.random.default_rng(0))
    assert draws.shape == (6, 5, model.nw)
    np.testing.assert_array_equal(draws[:, 0], w)  # step 0 acts with the given z
    again = model.sample_latent_forecasts(z, 5, np.random.default_rng(0))
    np.testing.assert_array_equal(draws, again)


def test_sampled_forecasts_average_to_the_mean_forecast(model):
    z0 = np.tile(_particles(model, 1, np.random.default_rng(4))[:, model.nx :], (4000, 1))
    draws = model.sample_latent_forecasts(z0, 4, np.random.default_rng(5))
    mean = model.mean_latent_forecast(z0[0], 4)
    spread = draws.std(axis=0)
    assert np.all(np.abs(draws.mean(axis=0) - mean) <= 5.0 * spread / np.sqrt(4000) + 1e-12)


# ----------------------------------------------------------------------------- transition


def test_physical_step_is_the_systems_euler_step(model):
    rng = np.random.default_rng(6)
    x = _particles(model, 10, rng)
    w = model.latent_force(x[:, model.nx :])
    u = _input(model)
    np.testing.assert_array_equal(
        model.physical_step(x[:, : model.nx], u, w),
        model.system.euler_step(x[:, : model.nx], u, w, model.dt),
    )


def test_transition_shape_layout_and_input_untouched(model):
    rng = np.random.default_rng(0)
    particles = _particles(model, 500, rng)
    before = particles.copy()
    out = model.transition(particles, _input(model), rng)
    assert out.shape == particles.shape and out.dtype == np.float64
    # Column-major (a component-major buffer): the next transition needs no transposed copy.
    assert out.flags.f_contiguous
    np.testing.assert_array_equal(particles, before)
    # Fed back in that layout, the same step with the same draws gives the same particles.
    again = model.transition(out, _input(model), np.random.default_rng(3))
    row_major = model.transition(np.ascontiguousarray(out), _input(model), np.random.default_rng(3))
    np.testing.assert_array_equal(again, row_major)


def test_transition_mean_and_noise_covariance_match_the_model(model):
    """Over many draws: mean = the noise-free step, spread = the model's process noise."""
    rng = np.random.default_rng(1)
    n, draws, nx = 300, 400, model.nx
    particles = _particles(model, n, rng)
    u = -_input(model)
    mean_x = model.physical_step(particles[:, :nx], u, model.latent_force(particles[:, nx:]))
    mean_z = particles[:, nx:] @ model.A.T
    out = np.stack([model.transition(particles, u, rng) for _ in range(draws)])
    noise = out - np.concatenate([mean_x, mean_z], axis=1)
    flat = noise.reshape(-1, model.state_dim)
    m = flat.shape[0]
    std = np.sqrt(np.concatenate([model.process_std**2, np.diag(model.Q)]))
    # Sample means within 5 standard errors; covariances within 3 %.
    assert np.all(np.abs(flat.mean(axis=0)) < 5.0 * std / np.sqrt(m))
    cov = np.cov(flat.T)
    expected = scipy.linalg.block_diag(np.diag(model.process_std**2), model.Q)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.all(np.abs(cov - expected) <= 0.03 * scale)
    # Physical and latent noise are independent, and so are particles.
    corr = np.corrcoef(noise[:, 0, 2], noise[:, 1, 2])[0, 1]
    assert abs(corr) < 5.0 / np.sqrt(draws)


def test_transition_is_reproducible_from_the_generator_state(model):
    particles = _particles(model, 100, np.random.default_rng(2))
    u = -0.5 * _input(model)
    a = model.transition(particles, u, np.random.default_rng(7))
    b = model.transition(particles, u, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    c = model.transition(particles, u, np.random.default_rng(8))
    assert not np.array_equal(a, c)


def test_single_precision_drift_is_the_double_precision_step_up_to_float32_rounding(model):
    """The same draws through both drift precisions: the states differ by float32 rounding
    of f dt (far below the process noise), the latent states not at all."""
    import dataclasses

    double = dataclasses.replace(model, drift_precision="double")
    particles = _particles(model, 2000, np.random.default_rng(3))
    u = _input(model)
    a = model.transition(particles, u, np.random.default_rng(11))
    b = double.transition(particles, u, np.random.default_rng(11))
    nx = model.nx
    np.testing.assert_array_equal(a[:, nx:], b[:, nx:])
    # float32 rounds the states and f by ~6e-8 relative: errors scale with |x| and |f dt|,
    # here below 1e-6 of them, while the process noise is >= 1e-3 of them.
    scale = np.abs(particles[:, :nx]) + np.abs(b[:, :nx] - particles[:, :nx]) + 1.0
    assert np.all(np.abs(a[:, :nx] - b[:, :nx]) <= 1e-6 * scale)
    assert not np.array_equal(a[:, :nx], b[:, :nx])  # single precision was used


def test_an_unknown_drift_precision_names_the_field_and_the_choices():
    with pytest.raises(ValueError, match=r"drift_precision='half': one of \('single', 'double'\)"):
        LatentForceModel(PLANAR, PLANAR_KERNELS, 0.1, drift_precision="half")
