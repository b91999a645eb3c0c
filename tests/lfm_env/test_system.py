"""Tests of the generic system definition (``lfm_env.system``): ``ControlSystem``,
``QuadraticCost`` and the array namespace ``xp``, on the sine track and on a double
integrator with the latent force on one axis, defined here."""

from __future__ import annotations

import math
import pickle

import casadi as ca
import numpy as np
import pytest

from lfm_env.cost import QuadraticCost
from lfm_env.system import ControlSystem, split_unit
from lfm_env.worlds.sine_track.system import sine_track_system
from lfm_env.xp import is_symbolic, xp

# ----------------------------------------------------------------------------- a second system


def double_integrator_rhs(x, u, w):
    """A planar double integrator ``[p_x, p_y, v_x, v_y]``; the force pushes along x only."""
    _, _, vx, vy = xp.unstack(x)
    ax, ay = xp.unstack(u)
    (force,) = xp.unstack(w)
    return xp.stack([vx, vy, ax + force, ay])


def double_integrator_constraints(x):
    """``|v_x| <= 1.5 m/s`` and ``p_y <= 2 m``."""
    _, py, vx, _ = xp.unstack(x)
    return xp.stack([vx - 1.5, -vx - 1.5, py - 2.0])


DOUBLE_INTEGRATOR = dict(
    name="double_integrator",
    state_names=("p_x [m]", "p_y [m]", "v_x [m/s]", "v_y [m/s]"),
    input_names=("a_x [m/s^2]", "a_y [m/s^2]"),
    force_names=("w [m/s^2]",),
    rhs=double_integrator_rhs,
    input_lower=(-2.0, -1.0),
    input_upper=(2.0, 1.0),
    constraints=double_integrator_constraints,
    constraint_names=("vx_max [m/s]", "vx_min [m/s]", "y_max [m]"),
)


def double_integrator(**changes) -> ControlSystem:
    return ControlSystem(**{**DOUBLE_INTEGRATOR, **changes})


SYSTEMS = {"sine_track": sine_track_system(), "double_integrator": double_integrator()}


@pytest.fixture(params=sorted(SYSTEMS))
def system(request) -> ControlSystem:
    return SYSTEMS[request.param]


def random_points(system: ControlSystem, n: int, seed: int = 0):
    """States ``(n, nx)``, inputs ``(n, nu)`` inside the bounds and forces ``(n, nw)``."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.0, 1.0, size=(n, system.nx)) * np.linspace(3.0, 10.0, system.nx)
    u = rng.uniform(system.input_lower, system.input_upper, size=(n, system.nu))
    w = rng.normal(0.0, 2.0, size=(n, system.nw))
    return x, u, w


# ----------------------------------------------------------------------------- NumPy and CasADi


def test_numpy_batched_equals_casadi(system):
    n, dt = 200, 0.2
    x, u, w = random_points(system, n)
    f = system.casadi_rhs().map(n)
    step = system.casadi_step(dt).map(n)
    g = system.casadi_constraints().map(n)
    np.testing.assert_allclose(
        np.asarray(f(x.T, u.T, w.T)).T, system.rhs(x, u, w), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(step(x.T, u.T, w.T)).T, system.euler_step(x, u, w, dt), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(g(x.T)).T, system.constraint_values(x), rtol=1e-12, atol=1e-12
    )


def test_batched_equals_one_by_one_and_broadcasts(system):
    x, u, w = random_points(system, 30, seed=1)
    batch = system.rhs(x, u, w)
    assert batch.shape == (30, system.nx)
    for i in range(30):
        np.testing.assert_array_equal(batch[i], system.rhs(x[i], u[i], w[i]))
    # One input and one force shared by a (3, 10) batch of states.
    grid = x.reshape(3, 10, system.nx)
    shared = system.rhs(grid, u[0], w[0])
    assert shared.shape == (3, 10, system.nx)
    np.testing.assert_array_equal(shared[1, 2], system.rhs(grid[1, 2], u[0], w[0]))
    assert system.constraint_values(grid).shape == (3, 10, system.ng)


def test_casadi_functions_on_symbols_and_expressions(system):
    x = ca.SX.sym("x", system.nx)
    u = ca.SX.sym("u", system.nu)
    w = ca.SX.sym("w", system.nw)
    dx = system.rhs(x, u, w)
    assert is_symbolic(dx) and dx.shape == (system.nx, 1)
    assert system.euler_step(x, u, w, 0.1).shape == (system.nx, 1)
    assert system.constraint_values(x).shape == (system.ng, 1)
    # MX works too (the multiple-shooting formulation's symbols).
    xm = ca.MX.sym("x", system.nx)
    assert system.casadi_rhs()(xm, ca.MX.zeros(system.nu), ca.MX.zeros(system.nw)).shape == (
        system.nx,
        1,
    )


@pytest.mark.parametrize(
    "name, values",
    [
        ("sin", [-2.0, 0.3, 4.0]),
        ("cos", [-2.0, 0.3, 4.0]),
        ("tan", [-1.2, 0.3, 1.0]),
        ("arctan", [-5.0, 0.3, 4.0]),
        ("arcsin", [-0.9, 0.3, 0.7]),
        ("arccos", [-0.9, 0.3, 0.7]),
        ("tanh", [-2.0, 0.3, 4.0]),
        ("sqrt", [0.0, 0.3, 4.0]),
        ("exp", [-2.0, 0.3, 4.0]),
        ("log", [0.1, 0.3, 4.0]),
        ("abs", [-2.0, 0.0, 4.0]),
    ],
)
def test_namespace_functions_agree_on_both_backends(name, values):
    fun = getattr(xp, name)
    s = ca.SX.sym("s", 3)
    symbolic = ca.Function("f", [s], [fun(s)])
    np.testing.assert_allclose(
        np.asarray(symbolic(values)).ravel(), fun(np.array(values)), rtol=1e-14, atol=1e-15
    )
    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    atan2 = ca.Function("atan2", [a, b], [xp.arctan2(a, b)])
    assert float(atan2(-1.0, -2.0)) == pytest.approx(math.atan2(-1.0, -2.0), rel=1e-15)


def test_the_piecewise_functions_agree_on_both_backends():
    """Issue 35, item 8: xp lacked minimum, maximum, where and clip."""
    x = np.array([-2.0, -0.5, 0.0, 0.7, 3.0])
    s = ca.SX.sym("s", 5)
    cases = {
        "minimum": (lambda v: xp.minimum(v, 0.5), np.minimum(x, 0.5)),
        "maximum": (lambda v: xp.maximum(v, 0.0), np.maximum(x, 0.0)),
        "where": (lambda v: xp.where(v > 0.0, v * v, -v), np.where(x > 0.0, x * x, -x)),
        "clip": (lambda v: xp.clip(v, -1.0, 1.0), np.clip(x, -1.0, 1.0)),
    }
    for name, (fun, expected) in cases.items():
        symbolic = ca.Function(name, [s], [fun(s)])
        np.testing.assert_array_equal(np.asarray(symbolic(x)).ravel(), expected, err_msg=name)
        np.testing.assert_array_equal(fun(x), expected, err_msg=name)
    # Single precision stays single (the particle transition's drift).
    assert xp.clip(x.astype(np.float32), -1.0, 1.0).dtype == np.float32
    assert xp.where(x.astype(np.float32) > 0, x.astype(np.float32), 0.0).dtype == np.float32


def test_stack_and_unstack_keep_components_on_the_last_axis():
    x = np.arange(24.0).reshape(2, 3, 4)
    parts = xp.unstack(x)
    assert len(parts) == 4 and parts[1].shape == (2, 3)
    np.testing.assert_array_equal(xp.stack(parts), x)
    np.testing.assert_array_equal(xp.stack([1.0, np.array([2.0, 3.0])]), [[1.0, 2.0], [1.0, 3.0]])
    s = ca.SX.sym("s", 3)
    assert [str(p) for p in xp.unstack(s)] == ["s_0", "s_1", "s_2"]
    assert xp.stack(xp.unstack(s)).shape == (3, 1)


# ----------------------------------------------------------------------------- double integrator


def test_double_integrator_moves_as_expected():
    system = SYSTEMS["double_integrator"]
    x = np.array([1.0, -1.0, 0.5, 0.25])
    nxt = system.euler_step(x, [1.0, -0.5], [0.5], 0.1)
    np.testing.assert_allclose(nxt, [1.05, -0.975, 0.65, 0.2], rtol=1e-15)
    # The force acts on the x axis only.
    without = system.euler_step(x, [1.0, -0.5], [0.0], 0.1)
    assert nxt[2] - without[2] == pytest.approx(0.05) and nxt[3] == without[3]


def test_double_integrator_constraints_excess_and_default_groups():
    system = SYSTEMS["double_integrator"]
    assert system.constraint_groups == {"vx_max": (0,), "vx_min": (1,), "y_max": (2,)}
    x = np.array([[0.0, 2.5, -2.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    np.testing.assert_allclose(system.constraint_values(x)[0], [-3.5, 0.5, 0.5])
    np.testing.assert_allclose(system.constraint_excess(x), [[0.0, 0.5, 0.5], [0.0, 0.0, 0.0]])
    excess = system.group_excess(x)
    np.testing.assert_allclose(excess["vx_min"], [0.5, 0.0])
    np.testing.assert_allclose(excess["y_max"], [0.5, 0.0])
    np.testing.assert_array_equal(system.clip_input([5.0, -0.5]), [2.0, -0.5])
    np.testing.assert_array_equal(system.fallback_input, [0.0, 0.0])


def test_system_without_constraints():
    system = double_integrator(constraints=None, constraint_names=())
    assert system.ng == 0 and system.constraint_groups == {}
    assert system.constraint_values(np.zeros((5, 4))).shape == (5, 0)
    assert system.casadi_constraints().size_out(0) == (0, 1)
    assert system.group_excess(np.zeros(4)) == {}


def test_default_fallback_is_the_input_nearest_zero():
    system = double_integrator(input_lower=(0.5, -1.0), input_upper=(2.0, -0.25))
    np.testing.assert_array_equal(system.fallback_input, [0.5, -0.25])


def test_labels_and_units():
    system = SYSTEMS["double_integrator"]
    assert system.state_labels == ("p_x", "p_y", "v_x", "v_y")
    assert system.constraint_labels == ("vx_max", "vx_min", "y_max")
    assert split_unit("a_x [m/s^2]") == ("a_x", "m/s^2")
    assert split_unit("count") == ("count", "")


def test_a_system_pickles_and_rebuilds_its_casadi_functions(system):
    system.casadi_rhs()
    clone = pickle.loads(pickle.dumps(system))
    x, u, w = random_points(system, 5, seed=3)
    np.testing.assert_array_equal(clone.rhs(x, u, w), system.rhs(x, u, w))
    np.testing.assert_allclose(
        np.asarray(clone.casadi_rhs()(x[0], u[0], w[0])).ravel(), system.rhs(x[0], u[0], w[0])
    )


# ----------------------------------------------------------------------------- system errors


def _rhs_one_short(x, u, w):
    return xp.stack(xp.unstack(x)[:3])


def _constraints_wrong(x):
    return xp.stack(xp.unstack(x)[:2])


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"name": ""}, "ControlSystem.name"),
        ({"rhs": "f"}, "ControlSystem.rhs"),
        ({"rhs": _rhs_one_short}, r"ControlSystem.rhs .*returned shape \(3, 3\).*\(3, 4\)"),
        ({"constraints": _constraints_wrong}, r"ControlSystem.constraints .*shape \(3, 2\)"),
        ({"input_lower": (2.0, -1.0)}, "input_lower < input_upper"),
        ({"input_upper": (2.0, -1.0)}, "input_lower < input_upper"),
        ({"input_upper": (2.0, math.inf)}, "finite"),
        ({"input_lower": (-2.0,)}, "ControlSystem.input_lower"),
        ({"state_names": ("p_x [m]", "p_x [km]", "v_x", "v_y")}, "state_names.*unique"),
        ({"state_names": "p_x p_y v_x v_y"}, "state_names.*sequence of strings"),
        ({"input_names": ("a_x", "")}, "input_names.*non-empty"),
        ({"force_names": (1,)}, "force_names"),
        ({"constraint_names": ("vx_max", "vx_min")}, "ControlSystem.constraints"),
        ({"constraints": None}, "constraint_names given without constraints"),
        ({"mirror_inputs": (2,)}, "mirror_inputs"),
        ({"fallback_input": (3.0, 0.0)}, "fallback_input"),
        ({"fallback_input": (0.0,)}, "fallback_input"),
        ({"constraint_groups": {"speed": (0, 3)}}, "constraint_groups"),
        ({"constraint_groups": {"speed": ()}}, "constraint_groups"),
        ({"constraint_groups": [1, 2]}, "constraint_groups"),
    ],
)
def test_a_bad_system_is_refused_naming_the_field(changes, match):
    with pytest.raises(ValueError, match=match):
        double_integrator(**changes)


# ----------------------------------------------------------------------------- the cost


def test_cost_from_diagonals_equals_cost_from_matrices():
    diag = QuadraticCost(Q=[2.0, 2.0, 1.0, 0.0], R=[0.5, 10.0], x_goal=[62.83, 0.0, 4.0, 0.0])
    full = QuadraticCost(
        Q=np.diag([2.0, 2.0, 1.0, 0.0]), R=np.diag([0.5, 10.0]), x_goal=[62.83, 0.0, 4.0, 0.0]
    )
    assert diag.diagonal and full.diagonal
    np.testing.assert_array_equal(diag.Qf, diag.Q)
    x, u, _ = random_points(SYSTEMS["sine_track"], 20, seed=4)
    np.testing.assert_allclose(diag.stage_cost(x, u), full.stage_cost(x, u), rtol=1e-14)
    e = x[0] - diag.x_goal
    assert diag.stage_cost(x[0], u[0]) == pytest.approx(
        2 * e[0] ** 2 + 2 * e[1] ** 2 + e[2] ** 2 + 0.5 * u[0, 0] ** 2 + 10 * u[0, 1] ** 2,
        rel=1e-14,
    )


def test_full_weight_matrices_and_the_terminal_weight():
    Q = np.array([[2.0, 0.5], [0.5, 1.0]])
    cost = QuadraticCost(Q=Q, R=[1.0], Qf=10.0 * Q, x_goal=[1.0, -1.0])
    assert not cost.diagonal and (cost.nx, cost.nu) == (2, 1)
    x = np.array([[0.0, 0.0], [2.0, 1.0]])
    e = x - [1.0, -1.0]
    np.testing.assert_allclose(cost.state_cost(x), np.einsum("ni,ij,nj->n", e, Q, e))
    np.testing.assert_allclose(cost.terminal_cost(x), 10.0 * cost.state_cost(x))
    np.testing.assert_allclose(cost.input_cost(np.array([[2.0]])), [4.0])


def test_cost_numpy_equals_casadi(system):
    n = system.nx
    Q = np.diag(np.linspace(0.5, 2.0, n)) + 0.1 * (np.eye(n, k=1) + np.eye(n, k=-1))
    for cost in (
        QuadraticCost(Q=np.linspace(0.0, 2.0, n), R=np.ones(system.nu), x_goal=np.arange(n)),
        QuadraticCost(Q=Q, R=np.eye(system.nu), Qf=2.0 * Q, x_goal=-np.arange(n)),
    ):
        xs, us = ca.SX.sym("x", n), ca.SX.sym("u", system.nu)
        f = ca.Function(
            "c", [xs, us], [cost.stage_cost(xs, us), cost.terminal_cost(xs), cost.input_cost(us)]
        )
        x, u, _ = random_points(system, 10, seed=5)
        for i in range(10):
            stage, terminal, inputs = (float(v) for v in f(x[i], u[i]))
            assert stage == pytest.approx(cost.stage_cost(x[i], u[i]), rel=1e-12)
            assert terminal == pytest.approx(cost.terminal_cost(x[i]), rel=1e-12)
            assert inputs == pytest.approx(cost.input_cost(u[i]), rel=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"Q": [[1.0, 2.0], [2.0, 1.0]]}, r"QuadraticCost.Q: must be positive semi-definite"),
        ({"Q": [1.0, -1.0]}, r"QuadraticCost.Q: must be positive semi-definite"),
        ({"Q": [[1.0, 0.5], [0.0, 1.0]]}, r"QuadraticCost.Q: must be symmetric"),
        ({"Q": [1.0, math.nan]}, r"QuadraticCost.Q: must be 2 finite numbers"),
        ({"R": [-1.0]}, r"QuadraticCost.R: must be positive semi-definite"),
        ({"R": 1.0}, "Q and R must be vectors or square matrices"),
        ({"Qf": [1.0, 1.0, 1.0]}, r"QuadraticCost.Qf: must be 2 finite numbers"),
        ({"x_goal": [0.0, 0.0, 0.0]}, r"QuadraticCost.x_goal"),
        ({"x_goal": [0.0, math.inf]}, r"QuadraticCost.x_goal must be finite"),
    ],
)
def test_a_bad_cost_is_refused_naming_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        QuadraticCost(**{"Q": [1.0, 1.0], "R": [1.0], **kwargs})


def test_check_system_refuses_other_dimensions():
    cost = QuadraticCost(Q=[1.0, 1.0, 1.0, 1.0], R=[1.0])
    with pytest.raises(ValueError, match=r"nx=4, nu=1; system 'double_integrator' has.*nu=2"):
        cost.check_system(SYSTEMS["double_integrator"])
    QuadraticCost(Q=[1.0] * 4, R=[1.0, 1.0]).check_system(SYSTEMS["double_integrator"])
