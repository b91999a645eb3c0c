"""The estimators behind one face: the Rao-Blackwellised particle filter and the UKF against
the exact Kalman filter of a linear-Gaussian latent-force model, and all of them in an agent."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.agents import make_agent
from controllers.estimators.estimator import ESTIMATORS, make_estimator
from controllers.estimators.rbpf import RaoBlackwellisedParticleFilter
from controllers.estimators.ukf import UnscentedKalmanFilter
from lfm_env import gp
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem
from lfm_env.xp import xp

DT = 0.1
DAMPING = 0.3  # [1/s]
R_STD = np.array([0.05, 0.05])


def damped_mass(force_gain: float = 1.0) -> LatentForceModel:
    """A mass with viscous damping pushed by a Matern 3/2 force: linear-Gaussian."""

    def rhs(x, u, w):
        _, v = xp.unstack(x)
        (a,) = xp.unstack(u)
        (f,) = xp.unstack(w)
        return xp.stack([v, a + force_gain * f - DAMPING * v])

    system = ControlSystem("damped_mass", ("p [m]", "v [m/s]"), ("a [m/s^2]",), rhs, [-5], [5])
    return LatentForceModel(system, gp.matern(1.5, 1.0, 1.0), DT, process_noise_std=[0.01, 0.02])


class KalmanFilter:
    """The exact filter of the damped mass's augmented linear model [p, v, z]."""

    def __init__(self, model: LatentForceModel, y0: np.ndarray) -> None:
        nx, p = 2, model.latent_dim
        Fx = np.array([[1.0, DT], [0.0, 1.0 - DAMPING * DT]])
        Gz = DT * np.outer([0.0, 1.0], model.H[0])
        self.A = np.block([[Fx, Gz], [np.zeros((p, nx)), model.A]])
        self.B = np.concatenate([[0.0, DT], np.zeros(p)])
        self.Q = np.zeros((nx + p, nx + p))
        self.Q[:nx, :nx] = np.diag(model.process_std**2)
        self.Q[nx:, nx:] = model.Q
        self.C = np.hstack([np.eye(nx), np.zeros((nx, p))])
        self.R = np.diag(R_STD**2)
        self.mean = np.concatenate([y0, np.zeros(p)])
        self.cov = np.zeros((nx + p, nx + p))
        self.cov[:nx, :nx] = self.R
        self.cov[nx:, nx:] = model.stationary_latent_covariance()

    def step(self, u: float, y: np.ndarray) -> None:
        m = self.A @ self.mean + self.B * u
        P = self.A @ self.cov @ self.A.T + self.Q
        S = self.C @ P @ self.C.T + self.R
        K = P @ self.C.T @ np.linalg.inv(S)
        self.mean = m + K @ (y - self.C @ m)
        self.cov = P - K @ S @ K.T


def simulate(model: LatentForceModel, n_steps: int, seed: int):
    """True states, measurements and inputs of the damped mass."""
    rng = np.random.default_rng(seed)
    p = model.latent_dim
    x = np.zeros(2)
    z = np.linalg.cholesky(model.stationary_latent_covariance()) @ rng.standard_normal(p)
    ys, us = [x + R_STD * rng.standard_normal(2)], []
    for k in range(n_steps):
        u = np.array([np.sin(0.3 * k)])
        x = model.physical_step(
            x, u, model.latent_force(z)
        ) + model.process_std * rng.standard_normal(2)
        z = model.A @ z + model.Q_factor @ rng.standard_normal(p)
        ys.append(x + R_STD * rng.standard_normal(2))
        us.append(u)
    return ys, us


def run_bootstrap_and_rbpf(model: LatentForceModel, std, ys, us, n_rbpf: int) -> tuple:
    """A 40000-particle bootstrap estimator (the reference) and a Rao-Blackwellised one of
    ``n_rbpf`` particles, run over the same inputs and measurements."""
    big = make_estimator("bootstrap", model, std, n_particles=40000)
    rb = make_estimator("rbpf", model, std, n_particles=n_rbpf)
    big.start(ys[0], np.random.default_rng(1))
    rb.start(ys[0], np.random.default_rng(2))
    for u, y in zip(us, ys[1:], strict=True):
        big.step(u, y)
        rb.step(u, y)
    return big, rb


@pytest.mark.parametrize("seed", [0, 1])
def test_rbpf_matches_the_exact_kalman_filter_on_a_linear_model(seed):
    model = damped_mass()
    ys, us = simulate(model, 60, seed)
    kf = KalmanFilter(model, ys[0])
    rng = np.random.default_rng(10 + seed)
    n = 4000
    rbpf = RaoBlackwellisedParticleFilter(
        model,
        R_STD,
        ys[0] + R_STD * rng.standard_normal((n, 2)),
        np.zeros(model.latent_dim),
        model.stationary_latent_covariance(),
        rng,
    )
    worst_mean, worst_std = 0.0, 0.0
    for u, y in zip(us, ys[1:], strict=True):
        kf.step(float(u[0]), y)
        rbpf.step(u, y)
        kf_std = np.sqrt(np.diag(kf.cov))
        worst_mean = max(worst_mean, np.max(np.abs(rbpf.mean - kf.mean) / kf_std))
        worst_std = max(worst_std, np.max(np.abs(rbpf.std / kf_std - 1.0)))
    # Monte-Carlo error only (4000 particles): measured 0.07 and 0.04.
    assert worst_mean < 0.2, worst_mean
    assert worst_std < 0.1, worst_std


def test_rbpf_with_a_wrong_latent_model_would_fail_the_comparison():
    """The comparison above can fail: a filter that believes the force twice as strong does."""
    truth, believed = damped_mass(), damped_mass(force_gain=2.0)
    ys, us = simulate(truth, 60, 0)
    kf = KalmanFilter(truth, ys[0])
    rng = np.random.default_rng(3)
    rbpf = RaoBlackwellisedParticleFilter(
        believed,
        R_STD,
        ys[0] + R_STD * rng.standard_normal((4000, 2)),
        np.zeros(truth.latent_dim),
        truth.stationary_latent_covariance(),
        rng,
    )
    worst = 0.0
    for u, y in zip(us, ys[1:], strict=True):
        kf.step(float(u[0]), y)
        rbpf.step(u, y)
        worst = max(worst, np.max(np.abs(rbpf.mean - kf.mean) / np.sqrt(np.diag(kf.cov))))
    assert worst > 0.5


def test_ukf_equals_the_kalman_filter_on_a_linear_model():
    model = damped_mass()
    ys, us = simulate(model, 40, 2)
    kf = KalmanFilter(model, ys[0])
    ukf = UnscentedKalmanFilter(model, R_STD, kf.mean, kf.cov)
    for u, y in zip(us, ys[1:], strict=True):
        kf.step(float(u[0]), y)
        ukf.step(u, y)
        np.testing.assert_allclose(ukf.mean, kf.mean, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ukf.covariance, kf.cov, rtol=1e-9, atol=1e-14)


def test_rbpf_refuses_a_force_that_does_not_enter_affinely():
    def rhs(x, u, w):
        _, v = xp.unstack(x)
        (a,) = xp.unstack(u)
        (f,) = xp.unstack(w)
        return xp.stack([v, a + xp.sin(f)])

    system = ControlSystem("nonaffine", ("p [m]", "v [m/s]"), ("a [m/s^2]",), rhs, [-1], [1])
    model = LatentForceModel(system, gp.matern(0.5, 1.0, 1.0), DT)
    assert not model.force_enters_affinely and damped_mass().force_enters_affinely
    with pytest.raises(ValueError, match="affinely"):
        make_estimator("rbpf", model, R_STD)
    with pytest.raises(ValueError, match="unknown estimator 'kf'"):
        make_estimator("kf", model, R_STD)


@pytest.mark.parametrize("name", ESTIMATORS)
def test_every_estimator_tracks_the_state_and_samples_its_distribution(name):
    model = damped_mass()
    ys, us = simulate(model, 50, 4)
    kf = KalmanFilter(model, ys[0])
    est = make_estimator(name, model, R_STD, n_particles=3000)
    rng = np.random.default_rng(0)
    est.start(ys[0], rng)
    for u, y in zip(us, ys[1:], strict=True):
        kf.step(float(u[0]), y)
        info = est.step(u, y)
        assert not info.degenerate and np.isfinite(info.nis)
    kf_std = np.sqrt(np.diag(kf.cov))
    assert np.all(np.abs(est.mean - kf.mean) < 0.5 * kf_std + 1e-9)
    draws = est.sample(20000, rng)
    np.testing.assert_allclose(draws.mean(axis=0), est.mean, atol=0.05 * kf_std.max())
    np.testing.assert_allclose(np.cov(draws.T), est.covariance, atol=0.1 * kf_std.max() ** 2)


@pytest.mark.parametrize("name", ESTIMATORS)
def test_agents_run_with_each_estimator(name):
    cfg = {
        "env": {"max_steps": 5},
        "agents": {"estimator": name, "n_particles": 500, "n_scenarios": 5},
    }
    agent = make_agent("scenario_particles", cfg)
    agent.reset(seed=0)
    obs = np.array([0.0, 0.0, 1.0, np.pi / 4])
    for _ in range(3):
        agent.act(obs)
        obs = obs + np.array([0.1, 0.1, 0.0, 0.0])
    info = agent.last_info
    assert info["estimate"].shape == (4 + agent.model.latent_dim,)
    assert info["x0"].shape == (5, 4) and np.unique(info["x0"][:, 0]).size > 1


def test_rbpf_agrees_with_a_large_bootstrap_filter_on_the_paper_model():
    from controllers.config import load_config

    cfg = load_config("configs/paper.yaml")
    model, std = cfg.make_model(), cfg.measurement_std
    rng = np.random.default_rng(5)
    x = cfg.env.initial_state_rad
    z = np.linalg.cholesky(model.stationary_latent_covariance()) @ rng.standard_normal(3)
    ys, us = [x + std * rng.standard_normal(4)], []
    for k in range(30):
        u = np.array([1.0, 0.2 * np.sin(0.2 * k)])
        x = model.physical_step(
            x, u, model.latent_force(z)
        ) + model.process_std * rng.standard_normal(4)
        z = model.A @ z + model.Q_factor @ rng.standard_normal(3)
        ys.append(x + std * rng.standard_normal(4))
        us.append(u)
    big, rb = run_bootstrap_and_rbpf(model, std, ys, us, n_rbpf=1000)
    # The latent force's mean and spread agree within a fifth of its spread.
    H = model.H[0]
    w_big, w_rb = H @ big.mean[4:], H @ rb.mean[4:]
    s_big = np.sqrt(H @ big.covariance[4:, 4:] @ H)
    s_rb = np.sqrt(H @ rb.covariance[4:, 4:] @ H)
    assert abs(w_rb - w_big) < 0.2 * s_big, (w_rb, w_big, s_big)
    assert abs(s_rb / s_big - 1.0) < 0.2, (s_rb, s_big)


def test_rbpf_with_a_state_dependent_gain_agrees_with_a_large_bootstrap_filter():
    """Each particle keeps its own latent covariance when G(x, u) varies with the state."""

    def rhs(x, u, w):
        p, v = xp.unstack(x)
        (a,) = xp.unstack(u)
        (f,) = xp.unstack(w)
        return xp.stack([v, a + (1.0 + 0.5 * xp.cos(p)) * f - DAMPING * v])

    system = ControlSystem("gain", ("p [m]", "v [m/s]"), ("a [m/s^2]",), rhs, [-5], [5])
    model = LatentForceModel(system, gp.matern(1.5, 1.0, 1.0), DT, process_noise_std=[0.01, 0.02])
    assert model.force_enters_affinely and not model.force_gain_is_constant
    ys, us = simulate(model, 40, 6)
    big, rb = run_bootstrap_and_rbpf(model, R_STD, ys, us, n_rbpf=2000)
    std = big.std
    assert np.all(np.abs(rb.mean - big.mean) < 0.25 * std), (rb.mean, big.mean, std)
    assert np.all(np.abs(rb.std / std - 1.0) < 0.25), (rb.std, std)
