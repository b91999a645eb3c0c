"""Learning the latent force's hyperparameters on any world (``experiments.calibration``):
the data the world's model gives the filter, and the fit on both presets."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.config import load_config
from experiments.calibration import (
    CalibrationRecord,
    fit_latent_force,
    force_observations,
    forced_states,
    record_calibration_episodes,
)
from lfm_env.gp import driven_log_likelihood, matern
from lfm_env.worlds.sine_track.config import SineTrackConfig


def simulate(cfg: SineTrackConfig, n_steps: int, rng: np.random.Generator) -> CalibrationRecord:
    """The car's model under random accelerations, every state measured with noise."""
    model = cfg.make_model()
    z = np.linalg.cholesky(model.stationary_latent_covariance()) @ rng.standard_normal(
        model.latent_dim
    )
    x = cfg.initial_state_rad.copy()
    u = np.column_stack([rng.uniform(-2, 2, n_steps), rng.uniform(-0.1, 0.1, n_steps)])
    meas = cfg.measurement_std_rad
    measured, ws = [x + meas * rng.standard_normal(4)], []
    for k in range(n_steps):
        w = model.H @ z
        ws.append(w)
        x = model.physical_step(x, u[k], w) + model.process_std * rng.standard_normal(4)
        z = model.A @ z + model.Q_factor @ rng.standard_normal(model.latent_dim)
        measured.append(x + meas * rng.standard_normal(4))
    return CalibrationRecord(np.array(measured), u, np.array(ws))


def test_the_sine_tracks_data_is_the_speed_exactly():
    """dv/dt = a + w: the speed alone, stepped by a dt, pushed by dt w, no linearisation."""
    cfg = SineTrackConfig()
    model = cfg.make_model()
    rec = simulate(cfg, 30, np.random.default_rng(1))
    states = forced_states(model, [rec])
    assert states.tolist() == [2]
    data = force_observations(model, rec, cfg.measurement_std_rad, states)
    np.testing.assert_array_equal(data["measured"][:, 0], rec.measured[:, 2])
    np.testing.assert_allclose(data["offset"][:, 0], cfg.dt * rec.inputs[:, 0], rtol=1e-15)
    np.testing.assert_allclose(data["gain"], cfg.dt)
    np.testing.assert_allclose(data["transition"], 1.0)
    np.testing.assert_allclose(data["process_covariance"], model.process_std[2] ** 2)
    kernel = matern(2.5, 4.0, 4.0)
    assert np.isfinite(driven_log_likelihood(kernel, cfg.dt, **data))


def test_the_quadrotors_data_carries_the_pitch_noise():
    """dv_x/dt = T sin(theta) / m + w: the pitch's measurement noise adds process noise."""
    cfg = load_config("quadrotor").env
    model = cfg.make_model()
    rec = record_calibration_episodes(load_config("quadrotor"), [1000])[0]
    states = forced_states(model, [rec])
    assert [model.system.state_names[i] for i in states] == ["v_x [m/s]"]
    data = force_observations(model, rec, cfg.measurement_std_rad, states)
    thrust, theta = rec.inputs[:, 0], rec.measured[:-1, 2]
    spread = (cfg.dt * thrust * np.cos(theta) / cfg.mass * cfg.measurement_std_rad[2]) ** 2
    np.testing.assert_allclose(
        data["process_covariance"][:, 0, 0], model.process_std[3] ** 2 + spread, rtol=1e-9
    )


def test_fit_recovers_the_hyperparameters_within_their_standard_errors():
    cfg = SineTrackConfig()
    rng = np.random.default_rng(7)
    records = [simulate(cfg, 150, rng) for _ in range(12)]
    result = fit_latent_force(records, cfg)
    assert result.success and result.states == ("v [m/s]",)
    for name, true in (("variance", 4.0), ("lengthscale", 4.0)):
        learned = getattr(result.latent_force, name)
        se = result.std_errors[name]
        assert np.isfinite(se) and se > 0
        assert abs(np.log(learned / true)) < 3.5 * se, (name, learned, se)


def test_fit_needs_records():
    with pytest.raises(ValueError, match="records"):
        fit_latent_force([], SineTrackConfig())


def test_a_force_that_enters_non_affinely_is_refused_naming_it():
    from lfm_env.model import LatentForceModel
    from lfm_env.system import ControlSystem
    from lfm_env.xp import xp

    def rhs(x, u, w):  # the force's square: no gain df/dw independent of w
        (v,) = xp.unstack(x)
        (a,) = xp.unstack(u)
        (f,) = xp.unstack(w)
        return xp.stack([a + f * f])

    system = ControlSystem(
        name="odd",
        state_names=("v [m/s]",),
        input_names=("a [m/s^2]",),
        rhs=rhs,
        input_lower=[-1.0],
        input_upper=[1.0],
    )
    model = LatentForceModel(system, matern(1.5, 1.0, 1.0), dt=0.1)
    with pytest.raises(ValueError, match="'odd': lfm-calibrate needs a force that enters"):
        forced_states(model, [])
