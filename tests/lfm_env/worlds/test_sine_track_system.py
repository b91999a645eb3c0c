"""Tests of the paper's case study as a system (``lfm_env.worlds.sine_track.system``): the
kinematic bicycle, the sine track and their :class:`~lfm_env.system.ControlSystem`."""

from __future__ import annotations

import math
import pickle

import casadi as ca
import numpy as np
import pytest
from highway_env.vehicle.kinematics import Vehicle

from lfm_env.system import ControlSystem
from lfm_env.worlds.sine_track.system import (
    CONSTRAINT_NAMES,
    SineTrack,
    bicycle_rhs,
    sine_track_system,
    slip_angle,
    track_constraints,
    track_of,
)
from tests.lfm_env.worlds.system_checks import assert_batched_step_equals_row_by_row

DT = 0.2  # [s] the paper's sampling time
LENGTH = 0.5  # [m] the paper's car length
SYSTEM = sine_track_system()


def euler_step(x, u, w: float = 0.0, length: float = LENGTH) -> np.ndarray:
    """One Euler step of the bicycle of length ``length`` [m] under a scalar force ``w``."""
    system = SYSTEM if length == LENGTH else sine_track_system(vehicle_length=length)
    return system.euler_step(np.asarray(x, dtype=float), u, [w], DT)


def random_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """States ``(n, 4)`` spread over the region the car visits, with negative speeds too."""
    low = np.array([-5.0, -5.0, -3.0, -math.pi])
    high = np.array([75.0, 5.0, 10.0, math.pi])
    return rng.uniform(low, high, size=(n, 4))


def random_actions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Actions ``(n, 2)`` within the paper's bounds ``|a| <= 5``, ``|delta| <= 25 deg``."""
    high = np.array([5.0, math.radians(25.0)])
    return rng.uniform(-high, high, size=(n, 2))


# ----------------------------------------------------------------------------- analytic cases


def test_straight_line_at_constant_speed():
    state = np.array([1.0, 2.0, 3.0, 0.0])
    for k in range(1, 11):
        state = SYSTEM.euler_step(state, [0.0, 0.0], [0.0], DT)
        assert state == pytest.approx([1.0 + 3.0 * DT * k, 2.0, 3.0, 0.0], rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("psi", [-2.5, -0.3, 0.0, 0.7, math.pi / 2, 3.0])
def test_zero_steering_keeps_heading_and_moves_along_it(psi):
    v = 2.5
    state = np.array([4.0, -1.0, v, psi])
    nxt = SYSTEM.euler_step(state, [1.5, 0.0], [0.0], DT)
    assert nxt[3] == psi
    assert nxt[0] == pytest.approx(4.0 + v * DT * math.cos(psi), rel=1e-12, abs=1e-12)
    assert nxt[1] == pytest.approx(-1.0 + v * DT * math.sin(psi), rel=1e-12, abs=1e-12)
    assert nxt[2] == pytest.approx(v + 1.5 * DT, rel=1e-12)


@pytest.mark.parametrize("a, w", [(0.0, 1.3), (2.0, -0.7), (-5.0, 4.0)])
def test_disturbance_adds_to_acceleration(a, w):
    state = np.array([0.0, 0.0, 1.0, 0.4])
    action = np.array([a, 0.2])
    with_w = bicycle_rhs(state, action, [w])
    without = bicycle_rhs(state, action, [0.0])
    assert with_w[2] == pytest.approx(a + w, rel=1e-14)
    # The force acts on the speed only.
    np.testing.assert_array_equal(with_w[[0, 1, 3]], without[[0, 1, 3]])
    assert SYSTEM.euler_step(state, action, [w], DT)[2] == pytest.approx(1.0 + (a + w) * DT)


def test_steering_turns_with_the_slip_angle_formula():
    delta = math.radians(20.0)
    v, psi = 3.0, 0.25
    alpha = math.atan(0.5 * math.tan(delta))
    assert slip_angle(delta) == pytest.approx(alpha, rel=1e-14)
    rhs = bicycle_rhs(np.array([0.0, 0.0, v, psi]), np.array([0.0, delta]), [0.0], LENGTH)
    expected = [
        v * math.cos(psi + alpha),
        v * math.sin(psi + alpha),
        0.0,
        v / (LENGTH / 2.0) * math.sin(alpha),
    ]
    assert rhs == pytest.approx(expected, rel=1e-13, abs=1e-14)
    assert rhs[3] > 0.0  # positive steering turns left (counter-clockwise)


# ----------------------------------------------------------------------------- batched and CasADi


def test_batched_step_equals_row_by_row():
    states, actions = assert_batched_step_equals_row_by_row(
        SYSTEM, DT, random_states, random_actions, force_std=2.0
    )
    # One action and one force broadcast over all particles.
    shared = SYSTEM.euler_step(states, actions[0], [0.0], DT)
    for i in range(len(states)):
        row = SYSTEM.euler_step(states[i], actions[0], [0.0], DT)
        np.testing.assert_array_equal(shared[i], row)


def test_transposed_component_major_data_equals_row_major_bit_for_bit():
    # The particle transition keeps its particles component-major, (4, n), and hands the
    # system transposed views; the result must not depend on the memory layout.
    rng = np.random.default_rng(1)
    n = 40
    states, actions = random_states(rng, n), random_actions(rng, n)
    w = rng.normal(0.0, 2.0, size=(n, 1))
    rows = bicycle_rhs(states, actions, w, LENGTH)
    cols = np.ascontiguousarray(states.T)
    np.testing.assert_array_equal(bicycle_rhs(cols.T, actions, w, LENGTH), rows)
    np.testing.assert_array_equal(
        bicycle_rhs(cols.T, actions[0], w, LENGTH), bicycle_rhs(states, actions[0], w, LENGTH)
    )


def test_casadi_equals_numpy():
    x, u, w = ca.SX.sym("x", 4), ca.SX.sym("u", 2), ca.SX.sym("w", 1)
    rhs = ca.Function("rhs", [x, u, w], [bicycle_rhs(x, u, w, LENGTH)])
    step = SYSTEM.casadi_step(DT)
    rng = np.random.default_rng(1)
    states, actions = random_states(rng, 40), random_actions(rng, 40)
    ws = rng.normal(0.0, 2.0, size=(40, 1))
    for s, a, wi in zip(states, actions, ws, strict=True):
        sym_step = np.asarray(step(s, a, wi)).ravel()
        sym_rhs = np.asarray(rhs(s, a, wi)).ravel()
        np.testing.assert_allclose(
            sym_step, SYSTEM.euler_step(s, a, wi, DT), rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(sym_rhs, bicycle_rhs(s, a, wi, LENGTH), rtol=1e-13, atol=1e-13)


# ----------------------------------------------------------------------------- highway-env


class _PaperCar(Vehicle):
    """highway-env's vehicle with the paper's length and no speed limits."""

    LENGTH = LENGTH
    MIN_SPEED = -1e9  # lifted so ``clip_actions`` never overrides the acceleration
    MAX_SPEED = 1e9


def highway_env_step(state: np.ndarray, action: np.ndarray, dt: float) -> np.ndarray:
    """One ``Vehicle.step`` of highway-env from ``state`` (no road: no lane bookkeeping)."""
    car = _PaperCar(None, position=state[:2], heading=float(state[3]), speed=float(state[2]))
    car.act({"acceleration": float(action[0]), "steering": float(action[1])})
    car.step(dt)
    assert not car.crashed
    return np.array([car.position[0], car.position[1], car.speed, car.heading])


def test_euler_step_equals_highway_env_vehicle_step():
    rng = np.random.default_rng(2)
    states, actions = random_states(rng, 100), random_actions(rng, 100)
    for s, a in zip(states, actions, strict=True):
        ours = euler_step(s, a)
        theirs = highway_env_step(s, a, DT)
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-12)


def test_highway_env_cross_check_detects_a_wrong_length():
    # Guards the cross-check itself: with another length the headings must differ.
    s = np.array([0.0, 0.0, 4.0, 0.3])
    a = np.array([0.0, math.radians(20.0)])
    assert euler_step(s, a, 0.0, 2.0 * LENGTH)[3] != pytest.approx(
        highway_env_step(s, a, DT)[3], rel=1e-6
    )


# ----------------------------------------------------------------------------- track


def test_track_constraints_sign_convention():
    track = SineTrack()

    def g(px, py, v=1.0):
        return track_constraints(np.array([px, py, v, 0.0]), track, 0.0, 8.0)

    x = 10.0
    c = track.centre_y(x)
    assert c == pytest.approx(3.0 * math.sin(0.2 * x))
    assert g(x, c) == pytest.approx([-1.0, -1.0, -11.0, -60.0, -1.0, -7.0])
    assert np.all(g(x, c + 0.99) <= 0.0) and np.all(g(x, c - 0.99) <= 0.0)
    above = g(x, c + 1.5)
    assert above[0] == pytest.approx(0.5) and np.all(above[1:] <= 0.0)
    below = g(x, c - 1.5)
    assert below[1] == pytest.approx(0.5) and below[0] < 0.0 and np.all(below[2:] <= 0.0)
    behind = g(-2.0, track.centre_y(-2.0))
    assert behind[2] == pytest.approx(1.0) and behind[3] < 0.0
    beyond = g(71.5, track.centre_y(71.5))
    assert beyond[3] == pytest.approx(1.5) and beyond[2] < 0.0
    assert g(x, c, v=-0.5)[4] == pytest.approx(0.5)
    assert g(x, c, v=9.0)[5] == pytest.approx(1.0)
    # The excess helpers agree: zero inside, the distance outside.
    assert track.track_excess(x, c + 0.5) == 0.0
    assert track.track_excess(x, c - 1.5) == pytest.approx(0.5)
    assert track.x_excess(71.5) == pytest.approx(1.5)
    assert track.x_excess(30.0) == 0.0


def test_group_excess_equals_the_track_helpers_bit_for_bit():
    # The env reports the groups' excesses; they must equal the track's own formulas.
    rng = np.random.default_rng(5)
    track = track_of(SYSTEM)
    for s in random_states(rng, 200):
        excess = SYSTEM.group_excess(s)
        assert excess["track"] == track.track_excess(s[0], s[1])
        assert excess["x"] == track.x_excess(s[0])
        assert excess["speed"] == max(0.0 - s[2], s[2] - 8.0, 0.0)


def test_track_constraints_batched_shape():
    rng = np.random.default_rng(3)
    states = random_states(rng, 7)
    g = SYSTEM.constraint_values(states)
    assert g.shape == (7, 6)
    for i in range(7):
        np.testing.assert_array_equal(g[i], SYSTEM.constraint_values(states[i]))


@pytest.mark.parametrize(
    "track", [SineTrack(), SineTrack(amplitude=1.5, pulsation=0.5, phase=0.3, half_width=0.4)]
)
def test_track_constraints_casadi_equals_numpy(track):
    x = ca.SX.sym("x", 4)
    g = ca.Function("g", [x], [track_constraints(x, track, -1.0, 6.0)])
    rng = np.random.default_rng(4)
    for s in random_states(rng, 30):
        np.testing.assert_allclose(
            np.asarray(g(s)).ravel(), track_constraints(s, track, -1.0, 6.0), rtol=1e-13, atol=1e-13
        )


@pytest.mark.parametrize(
    "track", [SineTrack(), SineTrack(amplitude=2.0, pulsation=0.35, phase=0.4, x_min=-5.0)]
)
def test_make_lane_centre_line_is_the_track_centre(track):
    lane = track.make_lane()
    for s in np.linspace(0.0, track.x_max - track.x_min, 57):
        px, py = lane.position(s, 0.0)
        assert px == pytest.approx(track.x_min + s, abs=1e-9)
        assert py == pytest.approx(track.centre_y(px), abs=1e-9)
    assert lane.width == pytest.approx(2.0 * track.half_width)


# ----------------------------------------------------------------------------- the system


def test_the_system_has_the_papers_names_bounds_and_groups():
    assert isinstance(SYSTEM, ControlSystem)
    assert (SYSTEM.nx, SYSTEM.nu, SYSTEM.nw, SYSTEM.ng) == (4, 2, 1, 6)
    assert SYSTEM.state_labels == ("p_x", "p_y", "v", "psi")
    assert SYSTEM.constraint_names == CONSTRAINT_NAMES
    assert SYSTEM.constraint_groups == {"track": (0, 1), "x": (2, 3), "speed": (4, 5)}
    np.testing.assert_allclose(SYSTEM.input_upper, [5.0, math.radians(25.0)])
    np.testing.assert_allclose(SYSTEM.input_lower, [-5.0, -math.radians(25.0)])
    np.testing.assert_array_equal(SYSTEM.fallback_input, [-5.0, 0.0])  # full braking
    assert SYSTEM.mirror_inputs == (1,)
    assert track_of(SYSTEM) == SineTrack()


def test_the_config_builds_the_same_system(paper_config, sine_track_system):
    assert track_of(sine_track_system) == paper_config.track
    rng = np.random.default_rng(6)
    x, u, w = random_states(rng, 20), random_actions(rng, 20), rng.normal(size=(20, 1))
    np.testing.assert_array_equal(
        sine_track_system.euler_step(x, u, w, DT), SYSTEM.euler_step(x, u, w, DT)
    )
    np.testing.assert_array_equal(
        sine_track_system.constraint_values(x), SYSTEM.constraint_values(x)
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"steer_max": math.pi / 2}, "steer_max"),
        ({"steer_max": 0.0}, "steer_max"),
        ({"vehicle_length": 0.0}, "vehicle_length"),
        ({"accel_max": -1.0}, "input_lower"),
    ],
)
def test_bad_parameters_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sine_track_system(**kwargs)


def test_track_of_another_system_raises():
    other = ControlSystem(
        name="other",
        state_names=("p [m]",),
        input_names=("v [m/s]",),
        rhs=lambda x, u, w: u,
        input_lower=(-1.0,),
        input_upper=(1.0,),
    )
    with pytest.raises(ValueError, match="not a sine-track system"):
        track_of(other)


def test_the_system_pickles_and_rebuilds_its_casadi_functions():
    SYSTEM.casadi_rhs()  # fill the cache; pickling must drop it
    clone = pickle.loads(pickle.dumps(SYSTEM))
    s, a = np.array([1.0, 0.5, 3.0, 0.2]), np.array([0.5, 0.1])
    np.testing.assert_array_equal(
        clone.euler_step(s, a, [0.3], DT), SYSTEM.euler_step(s, a, [0.3], DT)
    )
    np.testing.assert_allclose(
        np.asarray(clone.casadi_step(DT)(s, a, 0.3)).ravel(), SYSTEM.euler_step(s, a, [0.3], DT)
    )


def test_the_fallback_brakes_to_a_standstill_not_backwards():
    dt = 0.2
    np.testing.assert_allclose(SYSTEM.fallback(np.array([0.0, 0.0, 8.0, 0.0]), dt), [-5.0, 0.0])
    np.testing.assert_allclose(SYSTEM.fallback(np.array([0.0, 0.0, 0.5, 0.0]), dt), [-2.5, 0.0])
    # At a negative speed it accelerates forwards (full braking would drive backwards).
    np.testing.assert_allclose(SYSTEM.fallback(np.array([0.0, 0.0, -0.2, 0.0]), dt), [1.0, 0.0])
    v = 3.0
    for _ in range(5):
        v += dt * SYSTEM.fallback(np.array([0.0, 0.0, v, 0.0]), dt)[0]
    assert v == pytest.approx(0.0, abs=1e-12)
