"""Tests of the second case study as a system and a world config: the attitude-controlled
planar quadrotor in a bending tunnel (``lfm_env.worlds.quadrotor.system``) and
:class:`~lfm_env.worlds.quadrotor.config.QuadrotorGustConfig` (``configs/quadrotor.yaml``)."""

from __future__ import annotations

import math
import pickle
import re
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import yaml

from lfm_env.config import ConfigError, to_dict
from lfm_env.system import ControlSystem
from lfm_env.worlds.quadrotor.config import QuadrotorGustConfig, QuadrotorLatentForceConfig
from lfm_env.worlds.quadrotor.system import (
    CONSTRAINT_NAMES,
    GRAVITY,
    MASS,
    Corridor,
    attitude_euler_radius,
    attitude_frequency_bound,
    corridor_constraints,
    corridor_of,
    hover_thrust,
    quadrotor_gust_system,
    quadrotor_rhs,
)
from lfm_env.worlds.registry import WORLDS, load_env_config, world_config_class
from lfm_env.worlds.sine_track.config import SineTrackConfig
from lfm_env.worlds.sine_track.system import sine_track_system
from tests.lfm_env.worlds.system_checks import assert_batched_step_equals_row_by_row

DT = 0.1  # [s] the default sampling time
SYSTEM = quadrotor_gust_system()
HOVER = MASS * GRAVITY  # [N]
ENV_ID = "lfm_env/QuadrotorGust-v1"
CONFIG_FILE = Path(__file__).resolve().parents[3] / "configs" / "quadrotor.yaml"


def random_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """States ``(n, 6)`` over and beyond the region the vehicle visits."""
    low = np.array([-1.0, -0.5, -1.2, -3.0, -3.0, -6.0])
    high = np.array([10.0, 2.5, 1.2, 3.0, 3.0, 6.0])
    return rng.uniform(low, high, size=(n, 6))


def random_actions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Actions ``(n, 2)`` within the default bounds ``0 <= T <= 2 m g``, ``|theta_cmd| <= 0.4``."""
    return rng.uniform([0.0, -0.4], [2.0 * HOVER, 0.4], size=(n, 2))


def assert_names_key(exc: pytest.ExceptionInfo, key: str) -> None:
    """The error message names the dotted ``key`` (e.g. ``env.thrust_max``)."""
    msg = str(exc.value)
    assert re.search(rf"(?<![\w.]){re.escape(key)}(?![\w])", msg), f"{key!r} not in {msg!r}"


# ----------------------------------------------------------------------------- dynamics


def test_hover_equilibrium_stays_put():
    state = np.array([2.0, 1.3, 0.0, 0.0, 0.0, 0.0])
    for _ in range(100):
        state = SYSTEM.euler_step(state, [HOVER, 0.0], [0.0], DT)
    np.testing.assert_allclose(state, [2.0, 1.3, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert np.array_equal(SYSTEM.fallback_input, [HOVER, 0.0])  # the fallback is hover
    assert hover_thrust(SYSTEM) == pytest.approx(HOVER, rel=1e-15)


def test_free_fall_without_thrust():
    dx = quadrotor_rhs(np.array([0.0, 1.0, 0.3, 0.5, 0.0, 0.0]), np.array([0.0, 0.3]), [0.0])
    np.testing.assert_allclose(dx, [0.5, 0.0, 0.0, 0.0, -GRAVITY, 0.0], atol=1e-15)


@pytest.mark.parametrize("w", [-3.0, -0.4, 0.0, 1.5, 4.0])
def test_the_gust_adds_to_the_horizontal_acceleration_only(w):
    state = np.array([1.0, 1.2, 0.2, 0.5, -0.1, 0.3])
    action = np.array([0.3, -0.1])
    with_w = quadrotor_rhs(state, action, [w])
    without = quadrotor_rhs(state, action, [0.0])
    assert with_w[3] == pytest.approx(without[3] + w, rel=1e-14, abs=1e-14)
    np.testing.assert_array_equal(with_w[[0, 1, 2, 4, 5]], without[[0, 1, 2, 4, 5]])
    assert SYSTEM.euler_step(state, action, [w], DT)[3] == pytest.approx(
        0.5 + DT * (0.3 * math.sin(0.2) / MASS + w), rel=1e-13
    )


def test_positive_pitch_tilts_the_thrust_towards_plus_x():
    theta = 0.25
    dx = quadrotor_rhs(np.array([0.0, 1.0, theta, 0.0, 0.0, 0.0]), np.array([HOVER, theta]), [0.0])
    assert dx[3] == pytest.approx(GRAVITY * math.sin(theta), rel=1e-13) and dx[3] > 0.0
    assert dx[4] == pytest.approx(GRAVITY * (math.cos(theta) - 1.0), rel=1e-12)
    assert dx[5] == 0.0  # the attitude loop is at rest at its command


def test_the_attitude_loop_is_second_order_and_settles_at_the_command():
    wn, zeta = 10.0, 0.8
    dx = quadrotor_rhs(np.array([0.0, 1.0, 0.1, 0.0, 0.0, 0.5]), np.array([HOVER, 0.3]), [0.0])
    assert dx[2] == 0.5
    assert dx[5] == pytest.approx(wn**2 * (0.3 - 0.1) - 2.0 * zeta * wn * 0.5, rel=1e-14)
    state = np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(40):  # 4 s, many time constants of 1 / (zeta wn) = 0.125 s
        state = SYSTEM.euler_step(state, [HOVER, 0.3], [0.0], DT)
    assert state[2] == pytest.approx(0.3, abs=1e-6) and abs(state[5]) < 1e-5


def test_the_attitude_parameters_reach_the_right_hand_side():
    slow = quadrotor_gust_system(attitude_frequency=4.0, attitude_damping=1.5)
    x, u = np.array([0.0, 1.0, 0.1, 0.0, 0.0, 0.2]), np.array([HOVER, -0.2])
    assert slow.rhs(x, u, [0.0])[5] == pytest.approx(16.0 * (-0.3) - 2.0 * 1.5 * 4.0 * 0.2)
    heavy = quadrotor_gust_system(mass=0.5, gravity=9.0)
    assert heavy.rhs(x, np.array([4.5, 0.0]), [0.0])[3] == pytest.approx(9.0 * math.sin(0.1))
    np.testing.assert_allclose(heavy.input_upper, [9.0, 0.4])  # 2 m g by default


# ----------------------------------------------------------------------------- Euler stability


def test_euler_radius_at_the_defaults():
    # lambda = -8 +- 6i: |1 + 0.1 lambda| = |0.2 +- 0.6i| = sqrt(0.4).
    assert attitude_euler_radius(10.0, 0.8, DT) == pytest.approx(math.sqrt(0.4), rel=1e-12)
    assert attitude_frequency_bound(0.8, DT) == pytest.approx(16.0)


@pytest.mark.parametrize("zeta", [0.3, 0.8, 1.0, 1.5, 3.0])
def test_the_frequency_bound_is_where_the_euler_step_turns_unstable(zeta):
    bound = attitude_frequency_bound(zeta, DT)
    assert attitude_euler_radius(bound, zeta, DT) == pytest.approx(1.0, rel=1e-6)
    assert attitude_euler_radius(0.99 * bound, zeta, DT) < 1.0
    assert attitude_euler_radius(1.01 * bound, zeta, DT) > 1.0


def test_an_unstable_attitude_loop_diverges_and_a_stable_one_does_not():
    def swing(frequency: float) -> float:
        system = quadrotor_gust_system(attitude_frequency=frequency)
        state = np.array([0.0, 1.0, 0.1, 0.0, 0.0, 0.0])
        for _ in range(60):
            state = system.euler_step(state, [HOVER, 0.0], [0.0], DT)
        return abs(state[2])

    assert swing(15.0) < 0.1  # below the bound 2 zeta / dt = 16 rad/s
    assert swing(17.0) > 0.1  # above it the pitch grows


# ----------------------------------------------------------------------------- NumPy and CasADi


def test_batched_step_equals_row_by_row():
    assert_batched_step_equals_row_by_row(SYSTEM, DT, random_states, random_actions, force_std=1.5)


def test_casadi_equals_numpy():
    step, rhs, g = SYSTEM.casadi_step(DT), SYSTEM.casadi_rhs(), SYSTEM.casadi_constraints()
    rng = np.random.default_rng(1)
    states, actions = random_states(rng, 40), random_actions(rng, 40)
    ws = rng.normal(0.0, 1.5, size=(40, 1))
    for s, a, wi in zip(states, actions, ws, strict=True):
        np.testing.assert_allclose(
            np.asarray(rhs(s, a, wi)).ravel(), SYSTEM.rhs(s, a, wi), rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(
            np.asarray(step(s, a, wi)).ravel(),
            SYSTEM.euler_step(s, a, wi, DT),
            rtol=1e-13,
            atol=1e-13,
        )
        np.testing.assert_allclose(
            np.asarray(g(s)).ravel(), SYSTEM.constraint_values(s), rtol=1e-13, atol=1e-13
        )


@pytest.mark.parametrize("corridor", [Corridor(), Corridor(0.5, 0.3, 2.5, 0.7, 0.1, -2.0, 3.0)])
def test_corridor_geometry_casadi_equals_numpy(corridor):
    x = ca.SX.sym("x")
    fun = ca.Function("z", [x], [corridor.centre_z(x), corridor.floor_z(x), corridor.ceiling_z(x)])
    for xi in np.linspace(-2.0, 10.0, 25):
        got = [float(v) for v in fun(xi)]
        c = corridor.centre + corridor.amplitude * math.sin(
            2.0 * math.pi * xi / corridor.wavelength + corridor.phase
        )
        assert corridor.centre_z(xi) == pytest.approx(c, rel=1e-14)
        expected = [c, c - corridor.half_height, c + corridor.half_height]
        np.testing.assert_allclose(got, expected, rtol=1e-13)


# ----------------------------------------------------------------------------- constraints


def test_corridor_constraints_sign_convention_and_groups():
    corridor = Corridor()

    def g(px, pz):
        return corridor_constraints(np.array([px, pz, 0.0, 0.0, 0.0, 0.0]), corridor)

    assert SYSTEM.constraint_names == CONSTRAINT_NAMES
    assert SYSTEM.constraint_labels == ("corridor_floor", "corridor_ceiling", "x_min", "x_max")
    assert SYSTEM.constraint_groups == {"corridor": (0, 1), "x": (2, 3)}
    assert SYSTEM.violation_tolerances == {"corridor": (0.01, 0.05), "x": (0.01, 0.05)}
    x = 1.0  # a crest: centre 1.5 m
    c = corridor.centre_z(x)
    assert c == pytest.approx(1.5)
    assert g(x, c) == pytest.approx([-0.35, -0.35, -1.5, -8.0])
    assert np.all(g(x, c + 0.34) <= 0.0) and np.all(g(x, c - 0.34) <= 0.0)
    above = g(x, c + 0.5)
    assert above[1] == pytest.approx(0.15) and np.all(above[[0, 2, 3]] < 0.0)
    below = g(x, c - 0.45)
    assert below[0] == pytest.approx(0.1) and np.all(below[1:] < 0.0)
    behind = g(-0.8, corridor.centre_z(-0.8))
    assert behind[2] == pytest.approx(0.3) and behind[3] < 0.0
    beyond = g(9.5, corridor.centre_z(9.5))
    assert beyond[3] == pytest.approx(0.5) and beyond[2] < 0.0
    # The excess helpers and the system's groups agree.
    state = np.array([x, c - 0.45, 0.0, 0.0, 0.0, 0.0])
    assert SYSTEM.group_excess(state)["corridor"] == pytest.approx(0.1)
    assert corridor.corridor_excess(x, c - 0.45) == pytest.approx(0.1)
    assert corridor.corridor_excess(x, c + 0.3) == 0.0
    assert corridor.x_excess(9.5) == pytest.approx(0.5) and corridor.x_excess(3.0) == 0.0


def test_group_excess_equals_the_corridor_helpers():
    rng = np.random.default_rng(5)
    corridor = corridor_of(SYSTEM)
    for s in random_states(rng, 200):
        excess = SYSTEM.group_excess(s)
        assert excess["corridor"] == pytest.approx(corridor.corridor_excess(s[0], s[1]), abs=1e-15)
        assert excess["x"] == corridor.x_excess(s[0])


def test_a_horizontal_push_on_a_slope_is_an_altitude_error():
    # The tunnel rises at x = 0 (slope 2 pi A / lambda = 0.785): the same altitude 0.2 m
    # further along lies nearer the floor.
    corridor = Corridor()
    slope = 2.0 * math.pi * corridor.amplitude / corridor.wavelength
    off0 = corridor.vertical_offset(0.0, 1.0)
    off1 = corridor.vertical_offset(0.2, 1.0)
    assert off1 - off0 == pytest.approx(-slope * 0.2, rel=0.05)


# ----------------------------------------------------------------------------- construction


def test_the_system_pickles_and_keeps_its_corridor():
    system = quadrotor_gust_system(Corridor(amplitude=0.3), thrust_max=0.6, pitch_max=0.3)
    system.casadi_step(DT)  # a cached CasADi function must not stop pickling
    clone = pickle.loads(pickle.dumps(system))
    assert isinstance(clone, ControlSystem) and clone.name == "quadrotor_gust"
    assert corridor_of(clone) == Corridor(amplitude=0.3)
    np.testing.assert_array_equal(clone.input_upper, [0.6, 0.3])
    rng = np.random.default_rng(3)
    s, a = random_states(rng, 5), random_actions(rng, 5)
    np.testing.assert_array_equal(
        clone.euler_step(s, a, [0.7], DT), system.euler_step(s, a, [0.7], DT)
    )
    np.testing.assert_allclose(
        np.asarray(clone.casadi_step(DT)(s[0], a[0], 0.7)).ravel(),
        system.euler_step(s[0], a[0], [0.7], DT),
        rtol=1e-13,
    )


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"thrust_max": 0.2}, "thrust_max"),  # below the hover thrust 0.265 N
        ({"thrust_max": -1.0}, "thrust_max"),
        ({"pitch_max": 0.0}, "pitch_max"),
        ({"pitch_max": 1.6}, "pitch_max"),
        ({"mass": 0.0}, "mass"),
        ({"mass": math.nan}, "mass"),
        ({"gravity": -9.81}, "gravity"),
        ({"attitude_frequency": 0.0}, "attitude_frequency"),
        ({"attitude_damping": -0.1}, "attitude_damping"),
        ({"corridor": Corridor(half_height=0.0)}, "half_height"),
        ({"corridor": Corridor(wavelength=0.0)}, "wavelength"),
        ({"corridor": Corridor(x_min=5.0, x_max=4.0)}, "x_max"),
    ],
)
def test_bad_parameters_are_refused_naming_the_field(kwargs, name):
    with pytest.raises(ValueError, match=rf"{name}="):
        quadrotor_gust_system(**kwargs)


def test_helpers_refuse_other_systems():
    with pytest.raises(ValueError, match="not a quadrotor-gust system"):
        corridor_of(sine_track_system())
    with pytest.raises(ValueError, match="not a quadrotor-gust system"):
        hover_thrust(sine_track_system())


# ----------------------------------------------------------------------------- the world config


def test_defaults_are_valid_and_describe_the_case_study():
    cfg = QuadrotorGustConfig()
    assert cfg.ENV_ID == ENV_ID and WORLDS[ENV_ID].config_class is QuadrotorGustConfig
    assert world_config_class(ENV_ID) is QuadrotorGustConfig
    assert cfg.thrust_max == pytest.approx(2.0 * cfg.mass * cfg.gravity)
    system = cfg.make_system()
    assert system.nx == 6 and system.nu == 2 and system.nw == 1 and system.ng == 4
    np.testing.assert_allclose(system.input_lower, [0.0, -0.4])
    np.testing.assert_allclose(system.input_upper, [0.52974, 0.4])
    assert corridor_of(system) == cfg.corridor
    model = cfg.make_model()
    assert model.latent_dim == 2  # Matern 3/2: [w, dw/dt]
    d = cfg.latent_force
    assert isinstance(d, QuadrotorLatentForceConfig)
    assert (d.kernel, d.nu, d.discretization) == ("matern", 1.5, "exact")
    assert model.stationary_latent_covariance()[0, 0] == pytest.approx(d.variance)
    cost = cfg.make_cost()
    np.testing.assert_allclose(cost.x_goal, cfg.goal_state_rad)
    assert cfg.goal_state[:2] == cfg.goal


def test_angles_are_given_in_degrees():
    cfg = QuadrotorGustConfig()
    values = [1.0, 2.0, 180.0, 3.0, 4.0, 90.0]
    np.testing.assert_allclose(cfg.state_from_config(values), [1, 2, math.pi, 3, 4, math.pi / 2])
    np.testing.assert_allclose(
        cfg.measurement_std_rad, [0.02, 0.02, math.radians(1.0), 0.05, 0.05, math.radians(5.0)]
    )
    np.testing.assert_allclose(
        cfg.process_noise_std_rad,
        cfg.state_from_config(cfg.process_noise_diffusion) * math.sqrt(DT),
    )


def test_the_config_file_states_the_defaults():
    """``configs/quadrotor.yaml`` is a record of the defaults, and its agents fit the system."""
    from controllers.config import load_config

    data = yaml.safe_load(CONFIG_FILE.read_text())
    assert data["env_id"] == ENV_ID
    assert load_env_config(CONFIG_FILE) == QuadrotorGustConfig()
    experiment = load_config(CONFIG_FILE)
    assert experiment.env_id == ENV_ID
    cost = experiment.make_cost()
    assert (cost.nx, cost.nu) == (6, 2)
    problem = experiment.make_problem()
    assert (problem.nx, problem.nu, problem.nw, problem.ng) == (6, 2, 1, 4)


def test_yaml_round_trip(tmp_path):
    cfg = load_env_config(
        {
            "env_id": ENV_ID,
            "env": {
                "thrust_max": 0.6,
                "pitch_max": 0.3,
                "corridor_amplitude": 0.4,
                "Q": [0.5, 2.0, 0.0, 1.0, 1.0, 0.0],
                "initial_state": [0.0, 1.0, 5.0, 0.0, 0.0, 10.0],
                "latent_force": {"variance": 1.0, "start": "zero"},
            },
        }
    )
    assert isinstance(cfg, QuadrotorGustConfig) and cfg != QuadrotorGustConfig()
    path = tmp_path / "round_trip.yaml"
    path.write_text(yaml.safe_dump({"env_id": ENV_ID, "env": to_dict(cfg)}))
    loaded = load_env_config(path)
    assert loaded == cfg and isinstance(loaded.Q, tuple) and isinstance(loaded.max_steps, int)
    assert loaded.initial_state_rad[2] == pytest.approx(math.radians(5.0))


def test_a_partial_latent_force_keeps_the_gust_defaults():
    cfg = load_env_config({"env_id": ENV_ID, "env": {"latent_force": {"variance": 3.0}}})
    default = QuadrotorLatentForceConfig()
    assert (cfg.latent_force.variance, cfg.latent_force.nu) == (3.0, default.nu)
    assert cfg.latent_force.lengthscale == default.lengthscale


def test_the_world_follows_the_env_id():
    assert isinstance(load_env_config({"env_id": ENV_ID}), QuadrotorGustConfig)
    assert isinstance(load_env_config({"env": {}}), SineTrackConfig)  # the paper's by default
    assert isinstance(load_env_config({"dt": 0.05}, env_id=ENV_ID), QuadrotorGustConfig)
    with pytest.raises(ConfigError, match="for another env"):
        load_env_config(CONFIG_FILE, env_id="lfm_env/SineTrack-v0")
    with pytest.raises(ConfigError, match="given to"):
        load_env_config(QuadrotorGustConfig(), env_id="lfm_env/SineTrack-v0")
    with pytest.raises(ConfigError, match="unknown config key") as exc:
        load_env_config({"env_id": ENV_ID, "env": {"track_amplitude": 2.0}})
    assert_names_key(exc, "env.track_amplitude")


@pytest.mark.parametrize(
    "env, key",
    [
        ({"thrust_max": 0.25}, "env.thrust_max"),  # below m g
        ({"thrust_max": "0.5"}, "env.thrust_max"),
        ({"mass": -0.027}, "env.mass"),
        ({"pitch_max": 2.0}, "env.pitch_max"),
        ({"attitude_damping": 0.0}, "env.attitude_damping"),
        ({"attitude_frequency": 16.0}, "env.attitude_frequency"),  # Euler-unstable at 0.1 s
        ({"corridor_half_height": 0.0}, "env.corridor_half_height"),
        ({"corridor_wavelength": -4.0}, "env.corridor_wavelength"),
        ({"corridor_amplitude": -0.1}, "env.corridor_amplitude"),
        ({"x_max": -1.0}, "env.x_max"),
        ({"goal": [8.0, 2.0]}, "env.goal"),  # above the ceiling
        ({"goal": [12.0, 1.0]}, "env.goal"),  # beyond x_max
        ({"initial_state": [0.0, 0.5, 0.0, 0.0, 0.0, 0.0]}, "env.initial_state"),
        ({"Q": [1.0, 1.0, 1.0, 1.0]}, "env.Q"),
        ({"R": [1.0, -1.0]}, "env.R"),
        (
            {"measurement_noise_std": [0.02, 0.02, -1.0, 0.05, 0.05, 5.0]},
            "env.measurement_noise_std",
        ),
        ({"max_steps": 0}, "env.max_steps"),
        ({"safety_margin": 0.0}, "env.safety_margin"),
        ({"latent_force": {"nu": 2.0}}, "env.latent_force.nu"),
        ({"latent_force": {"lengthscale": 0.0}}, "env.latent_force.lengthscale"),
    ],
)
def test_bad_fields_are_named(env, key):
    with pytest.raises(ConfigError) as exc:
        load_env_config({"env_id": ENV_ID, "env": env})
    assert_names_key(exc, key)


@pytest.mark.parametrize(
    "env, ok",
    [
        ({"attitude_frequency": 15.9}, True),
        ({"attitude_frequency": 16.1}, False),
        ({"dt": 0.05, "attitude_frequency": 30.0}, True),  # bound 2 zeta / dt = 32 rad/s
        ({"dt": 0.2}, False),  # bound 8 rad/s
        ({"attitude_damping": 2.0, "attitude_frequency": 5.0}, True),  # bound 5.36 rad/s
        ({"attitude_damping": 2.0, "attitude_frequency": 6.0}, False),
    ],
)
def test_the_attitude_loop_must_be_euler_stable(env, ok):
    source = {"env_id": ENV_ID, "env": env}
    if ok:
        cfg = load_env_config(source)
        assert attitude_euler_radius(cfg.attitude_frequency, cfg.attitude_damping, cfg.dt) < 1.0
        return
    with pytest.raises(ConfigError, match=r"attitude_frequency=.*rad/s.*Euler") as exc:
        load_env_config(source)
    assert_names_key(exc, "env.attitude_frequency")


def test_replace_validates():
    cfg = QuadrotorGustConfig()
    assert cfg.replace(corridor_half_height=0.3).corridor.half_height == 0.3
    with pytest.raises(ConfigError) as exc:
        cfg.replace(attitude_frequency=20.0)
    assert_names_key(exc, "env.attitude_frequency")
