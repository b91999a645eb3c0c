"""Learning the latent force's hyperparameters from measured speeds
(``experiments.calibration``)."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.calibration import (
    SpeedRecord,
    fit_latent_force,
    speed_log_likelihood,
)
from lfm_env.config import SineTrackConfig
from lfm_env.gp import matern
from lfm_env.model import LatentForceModel


def dense_speed_log_likelihood(kernel, rec, dt, r_std, q_std):
    """Independent check: the joint Gaussian of y_1..y_T written out densely."""
    T = len(rec.accel)
    times = dt * np.arange(T)
    K = kernel.covariance(times[:, None] - times[None, :])
    C = np.tril(np.ones((T, T)))  # v_k - v_0 sums the steps j < k, k = 1..T
    r, q = r_std**2, q_std**2
    mean = rec.speed[0] + dt * np.cumsum(rec.accel)
    cov = r * np.ones((T, T)) + dt**2 * C @ K @ C.T + q * C @ C.T + r * np.eye(T)
    resid = rec.speed[1:] - mean
    sign, logdet = np.linalg.slogdet(cov)
    assert sign > 0
    return -0.5 * (T * np.log(2 * np.pi) + logdet + resid @ np.linalg.solve(cov, resid))


def simulate(model: LatentForceModel, n_steps: int, rng: np.random.Generator) -> SpeedRecord:
    """Speeds of the augmented model under random accelerations, measured with noise."""
    cfg = SineTrackConfig()
    z = np.linalg.cholesky(model.stationary_latent_covariance()) @ rng.standard_normal(
        model.latent_dim
    )
    v = 4.0
    a = rng.uniform(-2, 2, n_steps)
    meas = cfg.measurement_std_rad[2]
    speeds, ws = [v + meas * rng.standard_normal()], []
    for k in range(n_steps):
        w = float((model.H @ z)[0])
        ws.append(w)
        v = v + (a[k] + w) * cfg.dt + model.process_std[2] * rng.standard_normal()
        z = model.A @ z + model.Q_factor @ rng.standard_normal(model.latent_dim)
        speeds.append(v + meas * rng.standard_normal())
    return SpeedRecord(np.array(speeds), a, np.array(ws))


@pytest.mark.parametrize("nu, variance, lengthscale", [(2.5, 4.0, 4.0), (1.5, 0.7, 1.3)])
def test_kalman_likelihood_equals_the_dense_gaussian(nu, variance, lengthscale):
    cfg = SineTrackConfig()
    model = cfg.make_model()
    rec = simulate(model, 40, np.random.default_rng(1))
    kernel = matern(nu, variance, lengthscale)
    r, q = cfg.measurement_std_rad[2], cfg.process_noise_std_rad[2]
    kf = speed_log_likelihood(kernel, [rec], cfg.dt, r, q)
    dense = dense_speed_log_likelihood(kernel, rec, cfg.dt, r, q)
    assert kf == pytest.approx(dense, rel=1e-8)


def test_fit_recovers_the_hyperparameters_within_their_standard_errors():
    cfg = SineTrackConfig()
    model = cfg.make_model()
    rng = np.random.default_rng(7)
    records = [simulate(model, 150, rng) for _ in range(12)]
    result = fit_latent_force(records, cfg)
    assert result.success
    for name, true in (("variance", 4.0), ("lengthscale", 4.0)):
        learned = getattr(result.latent_force, name)
        se = result.std_errors[name]
        assert np.isfinite(se) and se > 0
        assert abs(np.log(learned / true)) < 3.5 * se, (name, learned, se)


def test_fit_needs_records():
    with pytest.raises(ValueError, match="records"):
        fit_latent_force([], SineTrackConfig())
