"""The fast SQP's native feedback prediction against its oracle, the exact rewrite.

``make_solver(problem, "fast")`` on a feedback problem runs the condensed SQP on the
closed-loop step (``controllers/solvers/fast/closed_loop.py``); every other solver, and the
tests' oracle, run the exact open-loop rewrite of ``controllers/solvers/feedback.py``. On the
recorded feedback problems (``data/feedback_problems.npz``, with the rewrite's IPOPT optimum)
the native plans must reach that optimum; its derivatives (the sensitivities with
``A + B K``, the input rows, the per-scenario input cost and the exact Hessian) must be those
of its own rollout, by finite differences.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from controllers.config import load_config
from controllers.feedback_law import FeedbackLaw
from controllers.problem import ScenarioProblem
from controllers.solvers import make_solver, solver_spec
from controllers.solvers.fast.closed_loop import applied_inputs
from controllers.solvers.fast.compiled import CompiledScenarioSolver
from controllers.solvers.fast.solver import FastScenarioSolver
from controllers.solvers.feedback import FeedbackScenarioSolver

ROOT = Path(__file__).resolve().parents[4]
DATA = dict(np.load(ROOT / "tests" / "data" / "feedback_problems.npz"))
CASES = [(str(name), i) for name in DATA["sets"] for i in range(len(DATA[f"{name}_seed"]))]
IDS = [f"{n}-{i}" for n, i in CASES]
RTOL = 1e-6  # objective agreement with the rewrite's optimum
PLAN_TOL = 1e-6  # [input units] plans started at that optimum
SLACK_TOL = 1e-6

_PROBLEMS: dict[str, ScenarioProblem] = {}


def get(name: str, key: str) -> np.ndarray:
    return DATA[f"{name}_{key}"]


def problem_of(name: str) -> ScenarioProblem:
    if name not in _PROBLEMS:
        cfg = load_config(ROOT / "configs" / f"{get(name, 'config')}.yaml")
        _PROBLEMS[name] = cfg.make_problem(
            n_scenarios=int(get(name, "n_scenarios")),
            horizon=int(get(name, "horizon")),
            prediction="feedback",
        )
    return _PROBLEMS[name]


def case(name: str, i: int):
    law = FeedbackLaw(get(name, "K")[i], get(name, "r")[i])
    return get(name, "x0")[i], get(name, "W")[i], law


def v_bound_active(name: str, i: int) -> bool:
    """The rewrite's optimum has a nominal input v_k (k >= 1) at its bound."""
    p, u = problem_of(name), get(name, "reference_u")[i][1:]
    lo, hi = p.input_lower, p.input_upper
    return bool(np.any((np.abs(u - lo) < 1e-7) | (np.abs(u - hi) < 1e-7)))


@pytest.mark.parametrize(("name", "i"), CASES, ids=IDS)
def test_with_every_nominal_input_bounded_the_native_plans_are_the_rewrites(name, i) -> None:
    # feedback_bounds="all" is the rewrite's formulation: the same optimum
    problem = problem_of(name)
    x0, W, law = case(name, i)
    ref, ref_u = get(name, "reference_objective")[i], get(name, "reference_u")[i]
    solver = make_solver(problem, "fast", feedback_bounds="all")
    assert isinstance(solver, FastScenarioSolver) and solver.condensed.feedback
    sol = solver.solve(x0, W, u_guess=get(name, "u_guess")[i], law=law)
    assert sol.success, sol.status
    assert sol.objective == pytest.approx(problem.objective(x0, W, sol.u, law=law), rel=1e-9)
    if get(name, "slack")[i] <= SLACK_TOL:
        assert sol.objective == pytest.approx(ref, rel=RTOL)
    else:  # another local optimum of an infeasible problem, never a higher one
        assert sol.objective <= ref * (1 + RTOL)
    assert sol.law is law and sol.extra["reference"] == "u_guess"
    # Started at that optimum (no extra starts) it stays there, at the rewrite's own plan.
    plain = make_solver(problem, "fast", feedback_bounds="all", restarts=())
    stay = plain.solve(x0, W, u_guess=ref_u, law=law)
    assert stay.success, stay.status
    assert stay.objective == pytest.approx(ref, rel=RTOL)
    if get(name, "slack")[i] <= SLACK_TOL:  # (with slack the plans are not unique)
        oracle = FeedbackScenarioSolver(problem, solver_spec("fast"), restarts=())
        again = oracle.solve(x0, W, u_guess=ref_u, law=law)
        np.testing.assert_allclose(stay.u, again.u, atol=PLAN_TOL)
        np.testing.assert_allclose(stay.u, ref_u, atol=10 * PLAN_TOL)


@pytest.mark.parametrize(("name", "i"), CASES, ids=IDS)
def test_free_nominal_inputs_reach_the_rewrites_optimum_or_below(name, i) -> None:
    # the default ("first"): only v_0 is bounded; where the rewrite's bounds on v_k are not
    # active the optimum is the same, elsewhere the larger feasible set gives a lower one
    problem = problem_of(name)
    x0, W, law = case(name, i)
    ref = get(name, "reference_objective")[i]
    sol = make_solver(problem, "fast").solve(x0, W, u_guess=get(name, "u_guess")[i], law=law)
    assert sol.success, sol.status
    assert sol.objective == pytest.approx(problem.objective(x0, W, sol.u, law=law), rel=1e-9)
    assert np.all(sol.u[0] >= problem.input_lower) and np.all(sol.u[0] <= problem.input_upper)
    if v_bound_active(name, i) or get(name, "slack")[i] > SLACK_TOL:
        assert sol.objective <= ref * (1 + RTOL)
    else:
        assert sol.objective == pytest.approx(ref, rel=RTOL)
    # the scenarios' states and inputs are those of the law
    np.testing.assert_allclose(sol.predicted, problem.rollout(x0, W, sol.u, law=law), atol=1e-9)
    np.testing.assert_allclose(
        sol.extra["inputs"], problem.inputs(x0, W, sol.u, law=law), atol=1e-9
    )
    slack = sol.extra["state_slack"] + sol.extra["input_slack"]
    assert slack == pytest.approx(sol.slack, rel=1e-12, abs=1e-12)


def _model_at(name: str, i: int, bounds: str = "first"):
    """The native solver's condensed model of recorded problem ``(name, i)`` with its law,
    and the data in the model's layouts."""
    problem = problem_of(name)
    solver = make_solver(problem, "fast")
    x0, W, law = case(name, i)
    x0, W = problem.check_data(x0, W)
    solver._use_law(law.K, law.r, bounds)
    m = solver.condensed
    data = (
        np.ascontiguousarray(x0.T),
        np.ascontiguousarray(W.transpose(1, 0, 2)),
        m.state_cost0(x0),
    )
    return problem, m, data, np.ascontiguousarray(W.transpose(2, 1, 0)), law


@pytest.mark.parametrize(("name", "i"), [("quadrotor", 0), ("paper_n7", 2)])
def test_the_derivatives_are_those_of_the_rollout(name, i) -> None:
    problem, m, (x0T, Wn, c0), Wl, law = _model_at(name, i)
    u = get(name, "reference_u")[i].ravel() + 0.01
    eps = 1e-6
    basis = np.eye(u.size)

    def rollout(u):
        return m.evaluate(x0T, Wn, u, c0)

    def smooth(u):  # the merit without its slack penalty
        ro = rollout(u)
        return ro.merit - problem.slack_penalty * ro.slack

    def central(f):
        return np.stack([(f(u + eps * e) - f(u - eps * e)) / (2 * eps) for e in basis], -1)

    ro = rollout(u)
    lin = m.linearise(ro, Wl)
    np.testing.assert_allclose(lin.grad, central(smooth), atol=1e-6 * np.abs(lin.grad).max())
    S = lin.sensitivities()  # (N, Ns, nx + nu, N nu): states, then the applied inputs
    dX = central(lambda u: rollout(u).X.copy())  # (N + 1, nx, Ns, N nu)
    np.testing.assert_allclose(S[:, :, : problem.nx], dX[1:].transpose(0, 2, 1, 3), atol=1e-7)
    v = u.reshape(problem.horizon, problem.nu)

    def inputs(u):
        return applied_inputs(rollout(u).X.transpose(2, 0, 1), u.reshape(v.shape), law)

    dU = central(inputs)  # (Ns, N, nu, N nu)
    np.testing.assert_allclose(S[:, :, problem.nx :], dU.transpose(1, 0, 2, 3), atol=1e-7)
    # the rows (state constraints and input rows, every step but the first's inputs)
    rng = np.random.default_rng(0)
    pos = np.array(
        [
            (j, k, s)
            for j in range(m.n_rows)
            for k in range(1, problem.horizon)
            for s in rng.choice(problem.n_scenarios, 3, replace=False)
        ]
    )
    jac, values = m.rows(lin, pos)
    np.testing.assert_array_equal(values, ro.G[pos[:, 0], pos[:, 1], pos[:, 2]])
    dG = central(lambda u: rollout(u).G[pos[:, 0], pos[:, 1], pos[:, 2]].copy())
    np.testing.assert_allclose(jac, dG, atol=1e-7)
    # the exact Hessian of the Lagrangian with multipliers on those rows
    mu = np.zeros((m.n_rows, problem.horizon, problem.n_scenarios))
    weights = rng.uniform(0.1, 2.0, len(pos))
    mu[pos[:, 0], pos[:, 1], pos[:, 2]] = weights

    def lagrangian_gradient(u):
        lin_u = m.linearise(rollout(u), Wl)
        return lin_u.grad + weights @ m.rows(lin_u, pos)[0]

    H = m.hessian(lin, mu, Wl)
    dH = central(lagrangian_gradient)
    np.testing.assert_allclose(H, dH, atol=1e-6 * np.abs(dH).max())


def test_the_first_steps_input_rows_and_a_zero_law_repeat_the_bounds() -> None:
    # u_{s,0} = v_0 is hard-bounded: its rows never enter (-inf); with the zero law and every
    # v_k bounded the problem is the open-loop one (no input row counts)
    problem, m, (x0T, Wn, c0), _, law = _model_at("paper_n7", 0)
    u = get("paper_n7", "reference_u")[0].ravel()
    G = m.evaluate(x0T, Wn, u, c0).G
    assert np.all(G[problem.ng :, 0] == -np.inf) and np.all(np.isfinite(G[problem.ng :, 1:]))
    open_loop = dataclasses.replace(problem, prediction="open_loop")
    zero = FeedbackLaw.zero(problem)
    x0, W = get("paper_n7", "x0")[0], get("paper_n7", "W")[0]
    solver = make_solver(problem, "fast", feedback_bounds="all")
    solver._use_law(zero.K, zero.r, "all")
    ro = solver.condensed.evaluate(x0T, Wn, u, c0)
    assert np.all(ro.G[problem.ng :] == -np.inf)
    assert ro.merit == pytest.approx(open_loop.objective(x0, W, u), rel=1e-12)


def test_the_first_solve_plans_the_open_loop_reference_and_then_follows_the_plan() -> None:
    problem = problem_of("paper_n7")
    open_loop = dataclasses.replace(problem, prediction="open_loop")
    x0, W, _ = case("paper_n7", 0)
    solver = make_solver(problem, "fast")
    first = solver.solve(x0, W)
    assert first.extra["reference"] == "open_loop_solve" and first.usable
    reference = first.extra["open_loop"]
    assert reference["status"] == "Solve_Succeeded"
    # the law is linearised along the open-loop plan, which the open-loop solver finds too
    plan = make_solver(open_loop, "fast").solve(x0, W)
    gains = make_solver(problem, "fast").solve(x0, W, u_guess=plan.u)
    np.testing.assert_allclose(first.law.K, gains.law.K, atol=1e-6)
    assert first.objective == pytest.approx(
        problem.objective(x0, W, first.u, law=first.law), rel=1e-9
    )
    second = solver.solve(x0, W)
    assert second.extra["reference"] == "previous_plan" and second.extra["open_loop"] is None
    solver.reset()
    assert solver.solve(x0, W).extra["reference"] == "open_loop_solve"


def test_an_open_loop_problem_takes_no_law() -> None:
    problem = dataclasses.replace(problem_of("paper_n7"), prediction="open_loop")
    x0, W, law = case("paper_n7", 0)
    with pytest.raises(ValueError, match="law given"):
        make_solver(problem, "fast").solve(x0, W, law=law)


# ----------------------------------------------------------------------------- the C loop


def _compiled_and_python(problem: ScenarioProblem, **options):
    compiled = make_solver(problem, "fast_c", **options)
    assert isinstance(compiled, CompiledScenarioSolver) and compiled.loop == "c"
    python = make_solver(problem, "fast", qp_solver="elastic_ipm", **options)
    return compiled, python


@pytest.mark.parametrize("bounds", ["first", "all"])
def test_the_c_loop_gives_the_python_loops_plans_with_the_recorded_laws(bounds) -> None:
    for name in DATA["sets"]:
        compiled, python = _compiled_and_python(problem_of(str(name)), feedback_bounds=bounds)
        for i in range(len(get(name, "seed"))):
            x0, W, law = case(name, i)
            guess = get(name, "u_guess")[i]
            a = compiled.solve(x0, W, u_guess=guess, law=law)
            b = python.solve(x0, W, u_guess=guess, law=law)
            assert (a.status, a.iterations) == (b.status, b.iterations), (name, i)
            np.testing.assert_allclose(a.u, b.u, atol=1e-9)
            assert a.objective == pytest.approx(b.objective, rel=1e-12)
            assert a.law is law and a.extra["reference"] == "u_guess"
            np.testing.assert_allclose(a.nominal_u, b.nominal_u, atol=1e-9)
            np.testing.assert_allclose(a.extra["inputs"], b.extra["inputs"], atol=1e-9)
            assert a.extra["input_slack"] == pytest.approx(b.extra["input_slack"], abs=1e-9)


def test_the_c_loop_computes_the_law_and_its_reference_as_python() -> None:
    # the first solve plans the open-loop reference and the TV-LQR law in C; the next ones
    # follow the nominal plan: the same laws, plans and references as the Python loop
    for name in ("paper_n7", "quadrotor"):
        compiled, python = _compiled_and_python(problem_of(name))
        for i in range(len(get(name, "seed"))):
            x0, W, _ = case(name, i)
            a, b = compiled.solve(x0, W), python.solve(x0, W)
            assert a.extra["reference"] == b.extra["reference"]
            assert a.extra["reference"] == ("open_loop_solve" if i == 0 else "previous_plan")
            if i == 0:
                assert a.extra["open_loop"]["status"] == b.extra["open_loop"]["status"]
                assert a.extra["open_loop"]["iterations"] == b.extra["open_loop"]["iterations"]
            np.testing.assert_allclose(a.law.K, b.law.K, atol=1e-10)
            np.testing.assert_allclose(a.law.r, b.law.r, atol=1e-10)
            assert a.iterations == b.iterations
            np.testing.assert_allclose(a.u, b.u, atol=1e-9)
            np.testing.assert_allclose(a.nominal_u, b.nominal_u, atol=1e-9)
            assert a.usable and a.plan is a.nominal_u
    compiled.reset()
    assert compiled.solve(x0, W).extra["reference"] == "open_loop_solve"
