"""Tests of the kinematic bicycle (``lfm_env.vehicle``) and the track (``lfm_env.track``)."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from highway_env.vehicle.kinematics import Vehicle

from lfm_env.track import SineTrack
from lfm_env.vehicle import bicycle_rhs, euler_step, slip_angle

DT = 0.2  # [s] the paper's sampling time
LENGTH = 0.5  # [m] the paper's car length


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
        state = euler_step(state, [0.0, 0.0], DT)
        assert state == pytest.approx([1.0 + 3.0 * DT * k, 2.0, 3.0, 0.0], rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("psi", [-2.5, -0.3, 0.0, 0.7, math.pi / 2, 3.0])
def test_zero_steering_keeps_heading_and_moves_along_it(psi):
    v = 2.5
    state = np.array([4.0, -1.0, v, psi])
    nxt = euler_step(state, [1.5, 0.0], DT)
    assert nxt[3] == psi
    assert nxt[0] == pytest.approx(4.0 + v * DT * math.cos(psi), rel=1e-12, abs=1e-12)
    assert nxt[1] == pytest.approx(-1.0 + v * DT * math.sin(psi), rel=1e-12, abs=1e-12)
    assert nxt[2] == pytest.approx(v + 1.5 * DT, rel=1e-12)


@pytest.mark.parametrize("a, w", [(0.0, 1.3), (2.0, -0.7), (-5.0, 4.0)])
def test_disturbance_adds_to_acceleration(a, w):
    state = np.array([0.0, 0.0, 1.0, 0.4])
    action = np.array([a, 0.2])
    with_w = bicycle_rhs(state, action, disturbance=w)
    without = bicycle_rhs(state, action)
    assert with_w[2] == pytest.approx(a + w, rel=1e-14)
    # The force acts on the speed only.
    np.testing.assert_array_equal(with_w[[0, 1, 3]], without[[0, 1, 3]])
    assert euler_step(state, action, DT, w)[2] == pytest.approx(1.0 + (a + w) * DT, rel=1e-14)


def test_steering_turns_with_the_slip_angle_formula():
    delta = math.radians(20.0)
    v, psi = 3.0, 0.25
    alpha = math.atan(0.5 * math.tan(delta))
    assert slip_angle(delta) == pytest.approx(alpha, rel=1e-14)
    rhs = bicycle_rhs([0.0, 0.0, v, psi], [0.0, delta], length=LENGTH)
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
    rng = np.random.default_rng(0)
    n = 50
    states, actions = random_states(rng, n), random_actions(rng, n)
    w = rng.normal(0.0, 2.0, size=n)
    batch = euler_step(states, actions, DT, w, LENGTH)
    assert batch.shape == (n, 4)
    for i in range(n):
        np.testing.assert_array_equal(batch[i], euler_step(states[i], actions[i], DT, w[i], LENGTH))
    # One action broadcast over all particles.
    shared = euler_step(states, actions[0], DT, 0.0, LENGTH)
    for i in range(n):
        np.testing.assert_array_equal(shared[i], euler_step(states[i], actions[0], DT, 0.0, LENGTH))


def test_component_major_layout_equals_row_major_bit_for_bit():
    rng = np.random.default_rng(1)
    n = 40
    states, actions = random_states(rng, n), random_actions(rng, n)
    w = rng.normal(0.0, 2.0, size=n)
    rows = euler_step(states, actions, DT, w, LENGTH)
    cols = euler_step(states.T.copy(), actions.T.copy(), DT, w, LENGTH, axis=0)
    assert cols.shape == (4, n)
    np.testing.assert_array_equal(cols.T, rows)
    # A single action (2,) is shared by every column, as in the particle filter.
    shared = euler_step(states.T.copy(), actions[0], DT, w, LENGTH, axis=0)
    np.testing.assert_array_equal(shared.T, euler_step(states, actions[0], DT, w, LENGTH))
    np.testing.assert_array_equal(
        bicycle_rhs(states.T.copy(), actions.T.copy(), w, LENGTH, axis=0).T,
        bicycle_rhs(states, actions, w, LENGTH),
    )


def test_casadi_equals_numpy():
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    w = ca.SX.sym("w")
    step = ca.Function("step", [x, u, w], [euler_step(x, u, DT, w, LENGTH)])
    rhs = ca.Function("rhs", [x, u, w], [bicycle_rhs(x, u, w, LENGTH)])
    rng = np.random.default_rng(1)
    states, actions = random_states(rng, 40), random_actions(rng, 40)
    ws = rng.normal(0.0, 2.0, size=40)
    for s, a, wi in zip(states, actions, ws, strict=True):
        sym_step = np.asarray(step(s, a, wi)).ravel()
        sym_rhs = np.asarray(rhs(s, a, wi)).ravel()
        np.testing.assert_allclose(
            sym_step, euler_step(s, a, DT, wi, LENGTH), rtol=1e-13, atol=1e-13
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
        ours = euler_step(s, a, DT, 0.0, LENGTH)
        theirs = highway_env_step(s, a, DT)
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-12)


def test_highway_env_cross_check_detects_a_wrong_length():
    # Guards the cross-check itself: with another length the headings must differ.
    s = np.array([0.0, 0.0, 4.0, 0.3])
    a = np.array([0.0, math.radians(20.0)])
    assert euler_step(s, a, DT, 0.0, 2.0 * LENGTH)[3] != pytest.approx(
        highway_env_step(s, a, DT)[3], rel=1e-6
    )


# ----------------------------------------------------------------------------- track


def test_track_constraints_sign_convention():
    track = SineTrack()
    x = 10.0
    c = track.centre_y(x)
    assert c == pytest.approx(3.0 * math.sin(0.2 * x))
    on_centre = track.constraints([x, c, 1.0, 0.0])
    assert on_centre == pytest.approx([-1.0, -1.0, -11.0, -60.0])
    assert np.all(track.constraints([x, c + 0.99, 1.0, 0.0]) <= 0.0)
    assert np.all(track.constraints([x, c - 0.99, 1.0, 0.0]) <= 0.0)
    above = track.constraints([x, c + 1.5, 1.0, 0.0])
    assert above[0] == pytest.approx(0.5) and np.all(above[1:] <= 0.0)
    below = track.constraints([x, c - 1.5, 1.0, 0.0])
    assert below[1] == pytest.approx(0.5) and below[0] < 0.0 and np.all(below[2:] <= 0.0)
    behind = track.constraints([-2.0, track.centre_y(-2.0), 1.0, 0.0])
    assert behind[2] == pytest.approx(1.0) and behind[3] < 0.0
    beyond = track.constraints([71.5, track.centre_y(71.5), 1.0, 0.0])
    assert beyond[3] == pytest.approx(1.5) and beyond[2] < 0.0
    # The excess helpers agree: zero inside, the distance outside.
    assert track.track_excess(x, c + 0.5) == 0.0
    assert track.track_excess(x, c - 1.5) == pytest.approx(0.5)
    assert track.x_excess(71.5) == pytest.approx(1.5)
    assert track.x_excess(30.0) == 0.0


def test_track_constraints_batched_shape():
    rng = np.random.default_rng(3)
    states = random_states(rng, 7)
    g = SineTrack().constraints(states)
    assert g.shape == (7, 4)
    for i in range(7):
        np.testing.assert_array_equal(g[i], SineTrack().constraints(states[i]))


@pytest.mark.parametrize(
    "track", [SineTrack(), SineTrack(amplitude=1.5, pulsation=0.5, phase=0.3, half_width=0.4)]
)
def test_track_constraints_casadi_equals_numpy(track):
    x = ca.SX.sym("x", 4)
    g = ca.Function("g", [x], [track.constraints(x)])
    rng = np.random.default_rng(4)
    for s in random_states(rng, 30):
        np.testing.assert_allclose(
            np.asarray(g(s)).ravel(), track.constraints(s), rtol=1e-13, atol=1e-13
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
