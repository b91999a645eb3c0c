"""Tests of the fast condensed SQP solver against an IPOPT reference of the same problem."""

from __future__ import annotations

import functools
import pickle

import casadi as ca
import numpy as np
import pytest

from controllers import problem as mpc_problem
from controllers.problem import MPCSolution, ScenarioProblem
from controllers.solvers.fast import FastScenarioSolver
from experiments.solver_timing import (
    closed_loop_problems,
    default_benchmark,
    format_timing_table,
    latent_force_scenarios,
    objective_agreement,
    time_solvers,
)
from lfm_env.vehicle import euler_step

RTOL = 1e-4  # objective agreement with the reference
VIOLATION_TOL = 1e-6  # [m or m/s] allowed constraint violation where the reference has none

STARTS = {
    "start": np.array([0.0, 0.0, 1.0, np.pi / 4]),
    "mid_track": np.array([20.0, 3.0 * np.sin(4.0), 5.0, 0.1]),
    "fast": np.array([40.0, 3.0 * np.sin(8.0), 7.8, -0.3]),
}


# --------------------------------------------------------------------------- reference


class _CondensedIpopt:
    """Independent reference: condensed single-shooting NLP in (u, s) solved by IPOPT.

    Built from :func:`lfm_env.vehicle.euler_step` and the track's CasADi constraints, with
    the ``6 N`` shared slacks and the exact L1 penalty of :mod:`controllers.problem`.
    """

    def __init__(self, problem: ScenarioProblem) -> None:
        n, ns = problem.horizon, problem.n_scenarios
        u = ca.SX.sym("u", 2 * n)
        s = ca.SX.sym("s", 6 * n)
        x0 = ca.SX.sym("x0", 4, ns)
        w = ca.SX.sym("w", n, ns)
        goal = ca.DM(problem.x_goal)
        q, qf, r = ca.DM(problem.Q), ca.DM(problem.Qf), ca.DM(problem.R)
        cost, g = 0, []
        for i in range(ns):
            x = x0[:, i]
            cost += ca.sum1(q * (x - goal) ** 2)
            for k in range(n):
                x = euler_step(x, u[2 * k : 2 * k + 2], problem.dt, w[k, i], problem.vehicle_length)
                cost += ca.sum1((q if k < n - 1 else qf) * (x - goal) ** 2)
                kinds = ca.vertcat(
                    problem.track.constraints(x), problem.speed_min - x[2], x[2] - problem.speed_max
                )
                g.append(kinds - s[6 * k : 6 * k + 6])
        cost = cost / ns + ca.sum1(ca.repmat(r, n, 1) * u**2) + problem.slack_penalty * ca.sum1(s)
        nlp = {"x": ca.vertcat(u, s), "p": ca.vertcat(ca.vec(x0), ca.vec(w)), "f": cost}
        nlp["g"] = ca.vertcat(*g)
        opts = {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-10}}
        self._solver = ca.nlpsol("reference", "ipopt", nlp, opts)
        self._problem = problem
        self._lbx = np.concatenate([np.tile(problem.input_lower, n), np.zeros(6 * n)])
        self._ubx = np.concatenate([np.tile(problem.input_upper, n), np.full(6 * n, np.inf)])
        self._ng = 6 * n * ns

    def solve(self, x0: np.ndarray, W: np.ndarray) -> MPCSolution:
        problem, n = self._problem, self._problem.horizon
        x0, W = problem.check_data(x0, W)
        u0 = np.zeros((n, 2))
        s0 = mpc_problem.minimal_slack(problem, mpc_problem.rollout(problem, x0, W, u0))
        res = self._solver(
            x0=np.concatenate([u0.ravel(), s0.ravel()]),
            p=np.concatenate([x0.T.ravel(order="F"), W.T.ravel(order="F")]),
            lbx=self._lbx,
            ubx=self._ubx,
            lbg=-np.inf * np.ones(self._ng),
            ubg=np.zeros(self._ng),
        )
        stats = self._solver.stats()
        u = np.clip(
            res["x"].full().ravel()[: 2 * n].reshape(n, 2), problem.input_lower, problem.input_upper
        )
        X = mpc_problem.rollout(problem, x0, W, u)
        return MPCSolution(
            u=u,
            objective=mpc_problem.objective(problem, x0, W, u),
            slack=float(np.sum(mpc_problem.minimal_slack(problem, X))),
            status=stats["return_status"],
            success=bool(stats["success"]),
            solve_time=0.0,
            iterations=int(stats["iter_count"]),
            predicted=X,
        )


@functools.cache
def reference_solver(problem: ScenarioProblem):
    """IPOPT reference: the multiple-shooting IpoptScenarioSolver when the repository has
    it, else the condensed NLP above (same problem, same exact penalty)."""
    try:
        from controllers.solvers.ipopt import IpoptScenarioSolver
    except ImportError:
        return _CondensedIpopt(problem)
    return IpoptScenarioSolver(problem, formulation="multiple_shooting")


def reference_solve(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray) -> MPCSolution:
    solver = reference_solver(problem)
    if hasattr(solver, "reset"):
        solver.reset()  # every reference solve starts from zero inputs, like the fast one
    return solver.solve(x0, W)


@functools.cache
def fast_solver(problem: ScenarioProblem) -> FastScenarioSolver:
    return FastScenarioSolver(problem)


def fast_solve(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray) -> MPCSolution:
    solver = fast_solver(problem)
    solver.reset()
    return solver.solve(x0, W)


def draw_W(seed: int, ns: int, n: int = 7) -> np.ndarray:
    """Latent forces of the case study's prior: w0 ~ N(0, 4) plus a 0.3/step random walk."""
    return latent_force_scenarios(np.random.default_rng(seed), ns, n, spread=2.0, walk_std=0.3)


def assert_matches_reference(
    problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, sol: MPCSolution, ref: MPCSolution
) -> None:
    assert sol.success, sol.status
    assert ref.success, ref.status
    assert sol.objective == pytest.approx(ref.objective, rel=RTOL)
    assert sol.objective == pytest.approx(mpc_problem.objective(problem, x0, W, sol.u), rel=1e-12)
    assert np.all(sol.u >= problem.input_lower) and np.all(sol.u <= problem.input_upper)
    X = mpc_problem.rollout(problem, x0, W, sol.u)
    np.testing.assert_allclose(sol.predicted, X, rtol=0, atol=1e-12)
    assert sol.slack == pytest.approx(np.sum(mpc_problem.minimal_slack(problem, X)), abs=1e-9)
    if ref.slack <= VIOLATION_TOL:
        assert mpc_problem.constraint_violation(problem, X) <= VIOLATION_TOL


# --------------------------------------------------------------------------- agreement


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("start", sorted(STARTS))
def test_matches_reference_on_random_problems(seed: int, start: str) -> None:
    problem = ScenarioProblem(n_scenarios=30)
    x0, W = STARTS[start], draw_W(seed, 30)
    assert_matches_reference(
        problem, x0, W, fast_solve(problem, x0, W), reference_solve(problem, x0, W)
    )


@pytest.mark.parametrize("seed", [3, 4])
def test_matches_reference_narrow_scenarios_without_slack(seed: int) -> None:
    """Scenarios as a particle filter would give them: feasible, no slack needed."""
    problem = ScenarioProblem(n_scenarios=30)
    rng = np.random.default_rng(seed)
    W = latent_force_scenarios(rng, 30, 7, mean=0.5, spread=0.3, walk_std=0.1)
    x0 = STARTS["mid_track"]
    ref = reference_solve(problem, x0, W)
    assert ref.slack <= VIOLATION_TOL  # the point of this test: a feasible hard problem
    assert_matches_reference(problem, x0, W, fast_solve(problem, x0, W), ref)


@pytest.mark.parametrize("start", ["start", "fast"])
def test_matches_reference_at_paper_size(start: str) -> None:
    problem = ScenarioProblem(n_scenarios=150)
    x0, W = STARTS[start], draw_W(11, 150)
    assert_matches_reference(
        problem, x0, W, fast_solve(problem, x0, W), reference_solve(problem, x0, W)
    )


def test_problem_that_needs_slack() -> None:
    """Near the speed bound with a push stronger than full braking: slack is unavoidable."""
    problem = ScenarioProblem(n_scenarios=30)
    x0 = np.array([40.0, 3.0 * np.sin(8.0), 7.9, 0.0])
    W = np.full((30, 7), 6.0)
    sol, ref = fast_solve(problem, x0, W), reference_solve(problem, x0, W)
    assert sol.slack > 0.1 and ref.slack > 0.1
    assert_matches_reference(problem, x0, W, sol, ref)
    # Full braking from the start is the only way to limit the excess speed.
    assert sol.u[0, 0] == pytest.approx(-problem.accel_max)


def test_per_scenario_initial_states() -> None:
    problem = ScenarioProblem(n_scenarios=30)
    rng = np.random.default_rng(5)
    x0 = STARTS["mid_track"] + rng.normal(0.0, [0.15, 0.15, 0.15, 0.01], size=(30, 4))
    W = draw_W(5, 30)
    sol = fast_solve(problem, x0, W)
    assert_matches_reference(problem, x0, W, sol, reference_solve(problem, x0, W))
    # A shared x0 is a different problem: the per-scenario states must be used.
    shared = fast_solve(problem, x0.mean(axis=0), W)
    assert abs(shared.objective - sol.objective) > 1e-6 * sol.objective


# --------------------------------------------------------------------------- properties


def test_input_bounds_are_respected_exactly() -> None:
    """Far from the goal and slow: full acceleration is optimal, steering near its bound."""
    problem = ScenarioProblem(n_scenarios=30)
    x0 = np.array([0.0, 0.0, 0.5, -0.6])
    sol = fast_solve(problem, x0, draw_W(6, 30))
    assert sol.success
    lower = np.broadcast_to(problem.input_lower, sol.u.shape)
    upper = np.broadcast_to(problem.input_upper, sol.u.shape)
    assert np.all(sol.u >= lower) and np.all(sol.u <= upper)
    assert np.any(sol.u == upper) or np.any(sol.u == lower)  # some bound is active


def test_warm_resolve_converges_in_at_most_two_iterations() -> None:
    problem = ScenarioProblem(n_scenarios=150)
    x0, W = STARTS["mid_track"], draw_W(7, 150)
    solver = FastScenarioSolver(problem)
    first = solver.solve(x0, W)
    again = solver.solve(x0, W, u_guess=first.u)
    assert first.success and again.success
    assert again.iterations <= 2
    assert again.objective == pytest.approx(first.objective, rel=1e-10)
    np.testing.assert_allclose(again.u, first.u, atol=1e-6)


def test_shifted_warm_start_is_the_default() -> None:
    problem = ScenarioProblem(n_scenarios=30)
    x0, W = STARTS["mid_track"], draw_W(8, 30)
    solver = FastScenarioSolver(problem)
    first = solver.solve(x0, W)
    x1 = euler_step(x0, first.u[0], problem.dt, W[0, 0])
    W1 = np.column_stack([W[:, 1:], W[:, -1]])
    warm = solver.solve(x1, W1)
    shifted = np.vstack([first.u[1:], first.u[-1:]])
    explicit = FastScenarioSolver(problem).solve(x1, W1, u_guess=shifted)
    np.testing.assert_allclose(warm.u, explicit.u, atol=1e-12)
    assert warm.iterations == explicit.iterations
    solver.reset()
    cold = solver.solve(x1, W1)
    assert cold.objective == pytest.approx(warm.objective, rel=RTOL)


def test_pickle_round_trip_keeps_warm_start_and_result() -> None:
    problem = ScenarioProblem(n_scenarios=30)
    x0, W = STARTS["mid_track"], draw_W(13, 30)
    solver = FastScenarioSolver(problem, max_iter=40)
    solver.solve(x0, W)  # builds the QP objects and a warm start
    clone = pickle.loads(pickle.dumps(solver))
    assert clone.options == solver.options
    a, b = solver.solve(x0, W), clone.solve(x0, W)  # same shifted warm start
    assert a.success and b.success
    # Only qpOASES' hot-start history differs: same solution up to QP round-off.
    np.testing.assert_allclose(a.u, b.u, atol=1e-7)
    assert a.objective == pytest.approx(b.objective, rel=1e-10)


def test_screening_gives_the_unscreened_solution() -> None:
    """Check-and-add makes the screened QP rows exact: same result as all rows at once."""
    problem = ScenarioProblem(n_scenarios=30)
    x0, W = STARTS["start"], draw_W(9, 30)
    screened = FastScenarioSolver(problem, screen_rows=1, screen_margin=1e-3).solve(x0, W)
    full = FastScenarioSolver(problem, screen_rows=30, screen_margin=1e3).solve(x0, W)
    assert screened.success and full.success
    assert screened.objective == pytest.approx(full.objective, rel=1e-9)
    np.testing.assert_allclose(screened.u, full.u, atol=1e-6)


def test_iteration_limit_returns_best_iterate_without_raising() -> None:
    problem = ScenarioProblem(n_scenarios=30)
    x0, W = STARTS["start"], draw_W(10, 30)
    start_objective = mpc_problem.objective(problem, x0, W, np.zeros((7, 2)))
    sol = FastScenarioSolver(problem, max_iter=1, restarts=()).solve(x0, W)
    assert not sol.success
    assert sol.status == "Maximum_Iterations_Exceeded"
    assert sol.iterations == 1
    assert np.all(np.isfinite(sol.u))
    assert sol.objective < start_objective


def test_derivatives_match_casadi() -> None:
    """Gradient of the cost and exact Lagrangian Hessian against CasADi's AD."""
    problem = ScenarioProblem(n_scenarios=4)
    rng = np.random.default_rng(12)
    n, ns = problem.horizon, problem.n_scenarios
    x0 = STARTS["mid_track"] + rng.normal(0.0, 0.1, size=(ns, 4))
    W = draw_W(12, ns)
    u = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-0.4, 0.4, n)]).ravel()
    mu = rng.uniform(0.0, 5.0, size=(4, n, ns))

    U = ca.SX.sym("u", 2 * n)
    goal = ca.DM(problem.x_goal)
    cost, lagrangian_terms, track_upper = 0, 0, []
    for i in range(ns):
        x = ca.DM(x0[i])
        for k in range(n):
            x = euler_step(x, U[2 * k : 2 * k + 2], problem.dt, W[i, k], problem.vehicle_length)
            weight = ca.DM(problem.Q if k < n - 1 else problem.Qf)
            cost += ca.sum1(weight * (x - goal) ** 2) / ns
            g = problem.track.constraints(x)
            track_upper.append(g[0])
            lagrangian_terms += ca.dot(ca.DM(mu[:, k, i]), g)
    cost += ca.sum1(ca.repmat(ca.DM(problem.R), n, 1) * U**2)
    f = ca.Function(
        "f",
        [U],
        [
            ca.gradient(cost, U),
            ca.hessian(cost + lagrangian_terms, U)[0],
            ca.jacobian(ca.vertcat(*track_upper), U),
        ],
    )
    grad_ref, hess_ref, jac_ref = (m.full() for m in f(u))

    solver = FastScenarioSolver(problem)
    lin = solver._linearise(solver._evaluate(x0, W, u, cost0=0.0))
    hess = solver._hessian(lin, mu)
    np.testing.assert_allclose(lin.grad, grad_ref.ravel(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(hess, hess_ref, rtol=1e-9, atol=1e-8 * np.abs(hess_ref).max())
    # Row (scenario i, step k) of the reference is i * N + k.
    j_track = lin.S[1] - lin.slope[:, :, None] * lin.S[0]
    jac = j_track.transpose(1, 0, 2).reshape(ns * n, 2 * n)
    np.testing.assert_allclose(jac, jac_ref, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------- input checks


@pytest.mark.parametrize(
    "x0, W, u_guess",
    [
        (np.zeros(3), np.zeros((30, 7)), None),
        (np.zeros((29, 4)), np.zeros((30, 7)), None),
        (np.zeros(4), np.zeros((30, 6)), None),
        (np.zeros(4), np.zeros((7, 30)), None),
        (np.array([0.0, np.nan, 1.0, 0.0]), np.zeros((30, 7)), None),
        (np.zeros(4), np.full((30, 7), np.inf), None),
        (np.zeros(4), np.zeros((30, 7)), np.zeros((6, 2))),
        (np.zeros(4), np.zeros((30, 7)), np.full((7, 2), np.nan)),
    ],
)
def test_bad_input_raises_value_error(x0, W, u_guess) -> None:
    solver = fast_solver(ScenarioProblem(n_scenarios=30))
    with pytest.raises(ValueError):
        solver.solve(x0, W, u_guess=u_guess)


@pytest.mark.parametrize(
    "options",
    [
        {"max_iter": 0},
        {"tol": -1.0},
        {"armijo": 0.7},
        {"qp_solver": "nope"},
        {"foo": 1},
        {"restarts": ("mirror", "random")},
        {"restarts": "mirror"},
        {"restart_threshold": 0.0},
        {"restart_optimism": -1.0},
        {"restart_margin": float("nan")},
        {"restart_probe": 0},
    ],
)
def test_bad_options_raise_value_error(options: dict) -> None:
    with pytest.raises(ValueError):
        FastScenarioSolver(ScenarioProblem(n_scenarios=5), **options)


# --------------------------------------------------------------------------- closed loop


def test_short_closed_loop_and_timing_harness() -> None:
    """Warm-started closed-loop problems solve, and the timing harness reports on them."""
    problem = ScenarioProblem(n_scenarios=20)
    sequence = closed_loop_problems(
        problem, FastScenarioSolver(problem), n_steps=6, seed=3, spread=0.5, redraw=True
    )
    assert len(sequence) == 6
    assert sequence[1][0][0] > sequence[0][0][0]  # the vehicle moves along the track
    results = time_solvers(
        {"fast": lambda: FastScenarioSolver(problem), "fast again": lambda: fast_solver(problem)},
        [sequence],
    )
    fast, again = results["fast"], results["fast again"]
    assert all(fast.success) and len(fast.times) == 6
    assert objective_agreement(fast, again)["within_rtol"] == 6
    summary = fast.summary()
    assert summary["p95_ms"] >= summary["median_ms"] > 0
    table = format_timing_table(results, baseline="fast")
    assert "fast again" in table and "median ms" in table


def test_default_benchmark_without_ipopt() -> None:
    results = default_benchmark(n_scenarios=(10,), recipe="shift", include_ipopt=False)
    fast = results[10]["fast SQP"]
    assert list(results[10]) == ["fast SQP"]
    assert len(fast.times) == 40 and np.all(np.isfinite(fast.objective))
    with pytest.raises(ValueError):
        default_benchmark(n_scenarios=(10,), recipe="nope", include_ipopt=False)
