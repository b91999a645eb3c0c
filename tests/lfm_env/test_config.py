"""Tests of the validated configuration (``lfm_env.config``)."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controllers.config import load_config
from lfm_env.config import ConfigError, LatentForceConfig, from_dict, to_dict
from lfm_env.worlds.registry import load_env_config
from lfm_env.worlds.sine_track.config import SineTrackConfig
from lfm_env.worlds.sine_track.system import track_of


def assert_names_key(exc: pytest.ExceptionInfo, key: str) -> None:
    """The error message names the dotted ``key`` (e.g. ``env.latent_force.nu``)."""
    msg = str(exc.value)
    assert re.search(rf"(?<![\w.]){re.escape(key)}(?![\w])", msg), f"{key!r} not in {msg!r}"


def write(tmp_path, text: str):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------- defaults


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


@pytest.mark.parametrize("source", [None, {}, {"env": {}}, {"env": None}, {"agents": {}}])
def test_defaults_are_the_papers_case_study(source):
    # A world reads its env section; a whole config's other sections are read above it.
    cfg = load_env_config(source) if "agents" not in (source or {}) else load_config(source).env
    assert cfg == SineTrackConfig()
    # REFERENCE.md: vehicle, track, start, goal, bounds, noise, latent force, MPC weights.
    assert cfg.dt == 0.2
    assert cfg.vehicle_length == 0.5
    assert (cfg.track_amplitude, cfg.track_pulsation, cfg.track_half_width) == (3.0, 0.2, 1.0)
    assert (cfg.x_min, cfg.x_max) == (-1.0, 70.0)
    assert (cfg.speed_min, cfg.speed_max) == (0.0, 8.0)
    assert cfg.accel_max == 5.0
    assert cfg.steer_max_deg == 25.0
    assert cfg.steer_max == pytest.approx(math.radians(25.0))
    assert cfg.initial_state == (0.0, 0.0, 1.0, 45.0)
    assert cfg.initial_state_rad == pytest.approx([0.0, 0.0, 1.0, math.pi / 4])
    assert cfg.goal == (62.83, 0.0)
    assert cfg.goal_state == (62.83, 0.0, 4.0, 0.0)
    assert cfg.Q == (2.0, 2.0, 1.0, 0.0)
    assert cfg.R == (0.5, 10.0)
    assert cfg.measurement_noise_std == (0.15, 0.15, 0.15, 0.5)
    assert cfg.measurement_std_rad == pytest.approx([0.15, 0.15, 0.15, math.radians(0.5)])
    assert cfg.process_noise_diffusion == (0.01, 0.01, 0.01, 0.5)
    assert cfg.process_noise_std_rad == pytest.approx(
        [0.01 * math.sqrt(0.2)] * 3 + [math.radians(0.5) * math.sqrt(0.2)]
    )
    assert cfg.max_steps == 150  # 30 s at 0.2 s
    d = cfg.latent_force
    assert (d.kernel, d.nu, d.variance, d.lengthscale) == ("matern", 2.5, 4.0, 4.0)
    track = cfg.track
    assert (track.amplitude, track.pulsation, track.half_width) == (3.0, 0.2, 1.0)
    assert (track.x_min, track.x_max) == (-1.0, 70.0)


# ----------------------------------------------------------------------------- YAML


def test_yaml_round_trip(tmp_path):
    cfg = load_env_config(
        {
            "env": {
                "dt": 0.1,
                "max_steps": 42,
                "Q": [0.5, 2.0, 12.0, 0.0],
                "R": [0.5, 0.75],
                "goal_radius": 0.5,
                "measurement_noise_std": [0.1, 0.2, 0.3, 1.0e-3],
                "latent_force": {"discretization": "euler_maruyama", "start": "zero", "nu": 1.5},
            }
        }
    )
    assert cfg != SineTrackConfig()
    path = tmp_path / "round_trip.yaml"
    path.write_text(yaml.safe_dump({"env": to_dict(cfg)}))
    loaded = load_env_config(path)
    assert loaded == cfg
    assert isinstance(loaded.max_steps, int) and isinstance(loaded.Q, tuple)
    assert load_env_config(str(path)) == cfg


def test_yaml_with_agents_section_and_float_with_dot(tmp_path):
    path = write(tmp_path, "env:\n  dt: 1.0e-1\n  goal: [62.83, 0.5]\nagents:\n  mpc: {}\n")
    cfg = load_env_config(path)
    assert cfg.dt == pytest.approx(0.1)
    assert cfg.goal == (62.83, 0.5)


def test_float_without_dot_gives_helpful_message(tmp_path):
    path = write(tmp_path, "env:\n  dt: 1e-3\n")
    with pytest.raises(ConfigError, match=r"with a dot") as exc:
        load_env_config(path)
    assert_names_key(exc, "env.dt")


def test_malformed_yaml_is_a_config_error(tmp_path):
    path = write(tmp_path, "env:\n  dt: [0.2,\n  goal: {\n")
    with pytest.raises(ConfigError, match="not valid YAML") as exc:
        load_env_config(path)
    assert str(path) in str(exc.value)


def test_yaml_python_tag_is_refused_and_not_executed(tmp_path):
    marker = tmp_path / "executed"
    path = write(tmp_path, f'env:\n  dt: !!python/object/apply:os.system ["touch {marker}"]\n')
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_env_config(path)
    assert not marker.exists()
    path = write(tmp_path, 'env:\n  dt: !!python/object/apply:os.system ["echo hi"]\n')
    with pytest.raises(ConfigError):
        load_env_config(path)


def test_missing_file_and_non_mapping_top_level(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_env_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="mapping"):
        load_env_config(write(tmp_path, "- 1\n- 2\n"))
    with pytest.raises(ConfigError, match="mapping"):
        load_env_config({"env": [1, 2]})


# ----------------------------------------------------------------------------- rejected values


@pytest.mark.parametrize(
    "source, key",
    [
        ({"env": {}, "envv": {}}, "envv"),  # a whole config's top level: read above the world
        ({"env": {"dtt": 0.2}}, "env.dtt"),
        ({"dtt": 0.2}, "env.dtt"),
        ({"env": {"latent_force": {"foo": 1.0}}}, "env.latent_force.foo"),
    ],
)
def test_unknown_keys(source, key):
    read = load_config if key == "envv" else load_env_config
    with pytest.raises(ConfigError, match="unknown") as exc:
        read(source)
    assert_names_key(exc, key)


@pytest.mark.parametrize(
    "env, key",
    [
        # wrong types
        ({"dt": "0.2"}, "env.dt"),
        ({"dt": True}, "env.dt"),
        ({"dt": None}, "env.dt"),
        ({"dt": [0.2]}, "env.dt"),
        ({"max_steps": 1.5}, "env.max_steps"),
        ({"max_steps": "150"}, "env.max_steps"),
        ({"max_steps": True}, "env.max_steps"),
        ({"Q": [1.0, 2.0, 3.0]}, "env.Q"),
        ({"Q": 2.0}, "env.Q"),
        ({"R": [0.5, "x"]}, "env.R[1]"),
        ({"initial_state": {"x": 0.0}}, "env.initial_state"),
        ({"latent_force": 3}, "env.latent_force"),
        ({"latent_force": {"discretization": 1}}, "env.latent_force.discretization"),
        # non-finite
        ({"dt": math.nan}, "env.dt"),
        ({"accel_max": math.inf}, "env.accel_max"),
        ({"x_min": -math.inf}, "env.x_min"),
        ({"goal": [62.83, math.nan]}, "env.goal[1]"),
        ({"latent_force": {"variance": math.inf}}, "env.latent_force.variance"),
        # out of range
        ({"dt": -0.2}, "env.dt"),
        ({"dt": 0.0}, "env.dt"),
        ({"dt": 11.0}, "env.dt"),
        ({"max_steps": 0}, "env.max_steps"),
        ({"vehicle_length": -0.5}, "env.vehicle_length"),
        ({"track_half_width": 0.0}, "env.track_half_width"),
        ({"steer_max_deg": 90.0}, "env.steer_max_deg"),
        ({"Q": [2.0, -2.0, 1.0, 0.0]}, "env.Q"),
        ({"measurement_noise_std": [0.15, 0.15, -0.15, 0.5]}, "env.measurement_noise_std"),
        ({"latent_force": {"nu": 2.0}}, "env.latent_force.nu"),
        ({"latent_force": {"lengthscale": -4.0}}, "env.latent_force.lengthscale"),
        ({"latent_force": {"kernel": "rbf"}}, "env.latent_force.kernel"),
        ({"latent_force": {"start": "random"}}, "env.latent_force.start"),
        # inverted bounds
        ({"x_max": -5.0}, "env.x_max"),
        ({"x_max": -1.0}, "env.x_max"),
        ({"speed_min": 8.0}, "env.speed_max"),
        ({"speed_max": -1.0}, "env.speed_max"),
        # goal and start off the track
        ({"goal": [80.0, 0.0]}, "env.goal"),
        ({"goal": [30.0, 5.0]}, "env.goal"),
        ({"initial_state": [0.0, 2.0, 1.0, 45.0]}, "env.initial_state"),
    ],
)
def test_invalid_values_name_the_key(env, key):
    with pytest.raises(ConfigError) as exc:
        load_env_config({"env": env})
    assert_names_key(exc, key)


def test_invalid_value_in_yaml_names_the_key(tmp_path):
    path = write(tmp_path, "env:\n  latent_force:\n    lengthscale: .nan\n")
    with pytest.raises(ConfigError, match="finite") as exc:
        load_env_config(path)
    assert_names_key(exc, "env.latent_force.lengthscale")


def test_replace_validates():
    cfg = SineTrackConfig().replace(dt=0.1)
    assert cfg.dt == 0.1
    with pytest.raises(ConfigError) as exc:
        SineTrackConfig().replace(dt=-1.0)
    assert_names_key(exc, "env.dt")


def test_huge_integer_for_a_float_field_is_a_config_error(tmp_path):
    path = write(tmp_path, "env:\n  dt: 1" + "0" * 400 + "\n")
    with pytest.raises(ConfigError) as exc:
        load_env_config(path)
    assert_names_key(exc, "env.dt")


@pytest.mark.parametrize("source", [{"env": {1: 2.0, "foo": 3.0}}, {"env": {}, 1: 2, "x": 3}])
def test_unknown_keys_of_mixed_types_are_a_config_error(source):
    with pytest.raises(ConfigError, match="unknown"):
        load_config(source)


# ----------------------------------------------------------------------------- properties

finite = st.floats(allow_nan=False, allow_infinity=False)


def pos(lo: float, hi: float):
    return st.floats(lo, hi) | st.integers(math.ceil(lo), math.floor(hi)).filter(lambda v: v > 0)


def nonneg_vec(n: int):
    return st.lists(st.floats(0.0, 100.0) | st.integers(0, 100), min_size=n, max_size=n)


VALID_ENV = {
    "dt": pos(0.01, 10.0),
    "vehicle_length": pos(0.1, 5.0),
    # The goal [62.83, 0] stays on the track: |A sin(0.2 * 62.83)| < 2e-4 m.
    "track_amplitude": st.floats(0.0, 5.0),
    "track_half_width": pos(0.05, 5.0),
    "speed_min": st.floats(-10.0, 0.0),
    "speed_max": pos(1.0, 20.0),
    "accel_max": pos(0.1, 20.0),
    "steer_max_deg": st.floats(0.5, 89.5),
    "goal_radius": pos(0.01, 5.0),
    "safety_margin": pos(0.1, 100.0),
    "Q": nonneg_vec(4),
    "R": nonneg_vec(2),
    "measurement_noise_std": nonneg_vec(4),
    "process_noise_diffusion": nonneg_vec(4),
    "goal_state": st.lists(finite, min_size=4, max_size=4),
    "max_steps": st.integers(1, 100_000),
}
VALID_DISTURBANCE = {
    "nu": st.sampled_from([0.5, 1.5, 2.5, 3.5]),
    "variance": pos(0.01, 100.0),
    "lengthscale": pos(0.01, 100.0),
    "discretization": st.sampled_from(["exact", "euler_maruyama"]),
    "start": st.sampled_from(["stationary", "zero"]),
}


@st.composite
def valid_env_sections(draw):
    env = draw(st.fixed_dictionaries({}, optional=VALID_ENV))
    dist = draw(st.fixed_dictionaries({}, optional=VALID_DISTURBANCE))
    if dist:
        env["latent_force"] = dist
    return env


def expected_value(value):
    if isinstance(value, list):
        return tuple(float(v) for v in value)
    return value


def same_type_and_value(got, value) -> bool:
    want = expected_value(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        # Integers written for float fields are stored as floats (max_steps stays an int).
        return got == want and isinstance(got, float if isinstance(value, float) else (int, float))
    return got == want


@settings(max_examples=150, deadline=None, database=None)
@given(env=valid_env_sections(), via_yaml=st.booleans())
def test_random_valid_configs_load(env, via_yaml):
    source = {"env": env}
    if via_yaml:
        source = yaml.safe_load(yaml.safe_dump(source))
    cfg = load_env_config(source)
    for name, value in env.items():
        if name == "latent_force":
            for dname, dvalue in value.items():
                assert same_type_and_value(getattr(cfg.latent_force, dname), dvalue)
        else:
            assert same_type_and_value(getattr(cfg, name), value)
    for name in set(env) - {"max_steps", "latent_force"}:
        value = getattr(cfg, name)
        assert all(type(v) is float for v in (value if isinstance(value, tuple) else (value,)))
    untouched = set(f.name for f in dataclasses.fields(SineTrackConfig)) - set(env)
    for name in untouched:
        assert getattr(cfg, name) == getattr(SineTrackConfig(), name)


# Any value that is not a number: a string (with or without a float look), bool, None, list, dict.
not_a_number = (
    st.text(max_size=5)
    | st.sampled_from(["1e-3", "0.2", "nan"])
    | st.booleans()
    | st.none()
    | st.lists(st.floats(), max_size=2)
    | st.dictionaries(st.text(max_size=2), st.integers(), max_size=1)
)
non_finite = st.sampled_from([math.nan, math.inf, -math.inf])
bad_float = not_a_number | non_finite
bad_positive = bad_float | st.floats(max_value=0.0, allow_nan=False) | st.integers(-100, 0)


def bad_vector(n: int, non_negative: bool):
    bad_element = bad_float | (
        st.floats(max_value=-1e-9, allow_nan=False) if non_negative else bad_float
    )
    good = st.floats(0.0, 1.0)
    wrong_length = st.lists(good, max_size=8).filter(lambda v: len(v) != n)
    with_bad_element = st.tuples(
        st.lists(good, min_size=n - 1, max_size=n - 1), bad_element, st.integers(0, n - 1)
    ).map(lambda t: t[0][: t[2]] + [t[1]] + t[0][t[2] :])
    scalar = st.floats(allow_nan=False) | st.text(max_size=3) | st.none()
    return wrong_length | with_bad_element | scalar


INVALID_ENV = {
    "dt": bad_positive | st.floats(10.001, 1e6),
    "vehicle_length": bad_positive,
    "track_half_width": bad_positive,
    "accel_max": bad_positive,
    "goal_radius": bad_positive,
    "safety_margin": bad_positive,
    "track_amplitude": bad_float | st.floats(max_value=-1e-9, allow_nan=False),
    "track_pulsation": bad_float | st.floats(max_value=-1e-9, allow_nan=False),
    "x_min": bad_float | st.floats(70.0, 1e6),  # >= x_max
    "x_max": bad_float | st.floats(-1e6, -1.0),  # <= x_min
    "speed_min": bad_float | st.floats(8.0, 1e6),  # >= speed_max
    "speed_max": bad_float | st.floats(-1e6, 0.0),  # <= speed_min
    "steer_max_deg": bad_float
    | st.floats(max_value=0.0, allow_nan=False)
    | st.floats(min_value=90.0, allow_infinity=False),
    "max_steps": st.integers(max_value=0)
    | st.floats(allow_nan=True)
    | st.booleans()
    | st.text(max_size=4)
    | st.none(),
    "Q": bad_vector(4, non_negative=True),
    "R": bad_vector(2, non_negative=True),
    "measurement_noise_std": bad_vector(4, non_negative=True),
    "process_noise_diffusion": bad_vector(4, non_negative=True),
    "initial_state": bad_vector(4, non_negative=False),
    "goal_state": bad_vector(4, non_negative=False),
    "goal": bad_vector(2, non_negative=False)
    | st.tuples(st.floats(-1e6, -1.001) | st.floats(70.001, 1e6), st.just(0.0)).map(list)
    | st.tuples(st.floats(0.0, 70.0), st.floats(4.01, 1e6)).map(list),
}
INVALID_DISTURBANCE = {
    "kernel": st.text(max_size=8).filter(lambda s: s != "matern") | st.floats() | st.none(),
    "nu": bad_float | st.floats(allow_nan=False).filter(lambda v: v not in (0.5, 1.5, 2.5, 3.5)),
    "variance": bad_positive,
    "lengthscale": bad_positive,
    "discretization": st.text(max_size=8).filter(lambda s: s not in ("exact", "euler_maruyama"))
    | st.integers(),
    "start": st.text(max_size=8).filter(lambda s: s not in ("stationary", "zero")) | st.booleans(),
}


@st.composite
def invalid_env_sections(draw):
    """A valid section with one field replaced by an invalid value; returns (section, key)."""
    env = draw(valid_env_sections())
    if draw(st.booleans()):
        name = draw(st.sampled_from(sorted(INVALID_ENV)))
        env[name] = draw(INVALID_ENV[name])
        return env, f"env.{name}"
    name = draw(st.sampled_from(sorted(INVALID_DISTURBANCE)))
    env["latent_force"] = {**env.get("latent_force", {}), name: draw(INVALID_DISTURBANCE[name])}
    return env, f"env.latent_force.{name}"


BOUND_PARTNERS = {"env.x_min": "env.x_max", "env.speed_min": "env.speed_max"}


@settings(
    max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(case=invalid_env_sections())
def test_random_invalid_values_are_rejected_naming_the_key(case):
    env, key = case
    # Bounds that move with other fields (x_min < x_max, speed_min < speed_max, goal on the
    # track) are checked against the defaults, so keep the related fields at their defaults.
    for partner in ("speed_min", "speed_max", "track_amplitude", "track_half_width"):
        if key != f"env.{partner}" and partner in env:
            del env[partner]
    with pytest.raises(ConfigError) as exc:
        load_env_config({"env": env})
    msg = str(exc.value)
    if key in BOUND_PARTNERS and key not in msg:
        # An inverted bound is reported on the upper key, quoting the lower one.
        partner = BOUND_PARTNERS[key]
        assert partner in msg and key.removeprefix("env.") in msg, msg
    else:
        assert key in msg, f"{key!r} not in {msg!r}"


def test_from_dict_builds_a_latent_force_section_alone():
    d = from_dict(LatentForceConfig, {"nu": 1.5, "variance": 2}, prefix="env.latent_force")
    assert d == LatentForceConfig(nu=1.5, variance=2.0)
    with pytest.raises(ConfigError) as exc:
        from_dict(LatentForceConfig, {"nu": 3.0}, prefix="env.latent_force")
    assert_names_key(exc, "env.latent_force.nu")


# ----------------------------------------------------------------------------- built objects


def test_make_system_model_and_cost_read_the_config():
    cfg = load_env_config(
        {
            "env": {
                "dt": 0.1,
                "vehicle_length": 0.8,
                "track_amplitude": 2.0,
                "speed_min": -1.0,
                "speed_max": 6.0,
                "accel_max": 3.0,
                "steer_max_deg": 30.0,
                "Q": [1.0, 2.0, 3.0, 4.0],
                "R": [0.25, 5.0],
                "goal_state": [60.0, 0.0, 2.0, 90.0],
                "latent_force": {"nu": 1.5, "discretization": "euler_maruyama"},
            }
        }
    )
    system = cfg.make_system()
    assert track_of(system) == cfg.track
    np.testing.assert_allclose(system.input_upper, [3.0, math.radians(30.0)])
    # The speed bounds are the last two constraints: v_min - v, v - v_max.
    g = system.constraint_values(np.array([10.0, 0.0, 7.0, 0.0]))
    assert g[4:] == pytest.approx([-8.0, 1.0])
    # The length enters the yaw rate: v sin(alpha) / (l / 2).
    dx = system.rhs(np.array([0.0, 0.0, 2.0, 0.0]), np.array([0.0, 0.3]), np.zeros(1))
    assert dx[3] == pytest.approx(2.0 * math.sin(math.atan(0.5 * math.tan(0.3))) / 0.4)

    model = cfg.make_model()
    assert model.dt == 0.1 and model.discretization == "euler_maruyama"
    assert model.latent_dim == 2  # Matern 3/2
    np.testing.assert_allclose(model.process_std, cfg.process_noise_std_rad)
    belief = cfg.make_model(LatentForceConfig(nu=0.5), system=system)
    assert belief.system is system and belief.latent_dim == 1

    cost = cfg.make_cost()
    np.testing.assert_array_equal(cost.Q, np.diag([1.0, 2.0, 3.0, 4.0]))
    np.testing.assert_array_equal(cost.Qf, cost.Q)  # the reward has no terminal weight
    np.testing.assert_array_equal(cost.R, np.diag([0.25, 5.0]))
    np.testing.assert_allclose(cost.x_goal, [60.0, 0.0, 2.0, math.pi / 2])
    cost.check_system(system)


def test_state_from_config_converts_the_heading_only():
    cfg = SineTrackConfig()
    np.testing.assert_allclose(cfg.state_from_config([1.0, 2.0, 3.0, 180.0]), [1, 2, 3, math.pi])
    np.testing.assert_array_equal(cfg.state_from_config(cfg.initial_state), cfg.initial_state_rad)


# --------------------------------------------------------------------------- worlds by env id


def test_the_world_is_chosen_by_the_top_level_env_id():
    from lfm_env.worlds.registry import DEFAULT_ENV_ID, WORLDS, world_config_class

    assert load_env_config({"env_id": "lfm_env/SineTrack-v0", "env": {"dt": 0.1}}).dt == 0.1
    assert type(load_env_config({"env": {"dt": 0.1}})).ENV_ID == DEFAULT_ENV_ID
    for env_id in WORLDS:
        assert world_config_class(env_id).ENV_ID == env_id


@pytest.mark.parametrize("env_id", ["lfm_env/Nope-v0", 3, ""])
def test_an_unknown_env_id_is_refused_naming_it(env_id):
    with pytest.raises(ConfigError, match="env_id=.*must be one of"):
        load_env_config({"env_id": env_id, "env": {}})


def test_an_env_refuses_the_config_of_another_world():
    with pytest.raises(ConfigError, match="for another env than 'lfm_env/Other-v0'"):
        load_env_config({"env_id": "lfm_env/SineTrack-v0"}, env_id="lfm_env/Other-v0")


def test_the_resolved_experiment_config_round_trips_through_yaml(tmp_path):
    import yaml

    from controllers.config import load_config

    cfg = load_config({"env": {"dt": 0.1}, "agents": {"horizon": 5}})
    path = tmp_path / "resolved.yaml"
    path.write_text(yaml.safe_dump(cfg.to_dict()))
    again = load_config(path)
    assert again == cfg and again.env_id == "lfm_env/SineTrack-v0"


def test_the_old_name_of_the_latent_force_section_still_reads_with_a_warning():
    old = {"env": {"disturbance": {"variance": 2.0}}, "agents": {"disturbance": {"nu": 1.5}}}
    with pytest.warns(FutureWarning, match=r"env\.disturbance is now env\.latent_force"):
        cfg = load_env_config(old)
    assert cfg.latent_force.variance == 2.0

    from controllers.config import load_config

    with pytest.warns(FutureWarning, match=r"agents\.disturbance is now agents\.latent_force"):
        full = load_config(old)
    assert full.agents.latent_force.nu == 1.5 and full.env.latent_force.variance == 2.0
    both = {"env": {"disturbance": {}, "latent_force": {}}}
    with pytest.raises(ConfigError, match="env.disturbance and env.latent_force are one setting"):
        load_env_config(both)
