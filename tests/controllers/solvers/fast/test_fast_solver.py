"""Tests of the fast condensed SQP solver against an IPOPT reference of the same problem."""

from __future__ import annotations

import functools
import pickle
import sys

import casadi as ca
import numpy as np
import pytest

from controllers.problem import MPCSolution, ScenarioProblem
from controllers.solvers import make_solver
from controllers.solvers.fast.condensed import CondensedModel
from controllers.solvers.fast.solver import FastScenarioSolver
from lfm_env.worlds.sine_track.config import SineTrackConfig
from tests.random_walk_scenarios import latent_force_scenarios

RTOL = 1e-4  # objective agreement with the reference
VIOLATION_TOL = 1e-6  # [m or m/s] allowed constraint violation where the reference has none

STARTS = {
    "start": np.array([0.0, 0.0, 1.0, np.pi / 4]),
    "mid_track": np.array([20.0, 3.0 * np.sin(4.0), 5.0, 0.1]),
    "fast": np.array([40.0, 3.0 * np.sin(8.0), 7.8, -0.3]),
}


# --------------------------------------------------------------------------- reference


def paper_problem(**changes) -> ScenarioProblem:
    """The paper's problem (sine-track model and cost) with some fields changed."""
    config = SineTrackConfig()
    return ScenarioProblem(config.make_model(), config.make_cost(), **changes)


@functools.cache
def reference_solver(problem: ScenarioProblem):
    """IPOPT on the textbook multiple-shooting NLP of the same problem."""
    return make_solver(problem, "ipopt_multiple_shooting", ipopt_options={"tol": 1e-10})


def reference_solve(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray) -> MPCSolution:
    solver = reference_solver(problem)
    solver.reset()  # every reference solve starts from zero inputs, like the fast one
    return solver.solve(x0, W)


@functools.cache
def fast_solver(problem: ScenarioProblem, name: str = "fast"):
    return make_solver(problem, name)


def fast_solve(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, name: str = "fast"):
    solver = fast_solver(problem, name)
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
    assert sol.objective == pytest.approx(problem.objective(x0, W, sol.u), rel=1e-12)
    assert np.all(sol.u >= problem.input_lower) and np.all(sol.u <= problem.input_upper)
    X = problem.rollout(x0, W, sol.u)
    np.testing.assert_allclose(sol.predicted, X, rtol=0, atol=1e-12)
    assert sol.slack == pytest.approx(np.sum(problem.minimal_slack(X)), abs=1e-9)
    if ref.slack <= VIOLATION_TOL:
        assert problem.constraint_violation(X) <= VIOLATION_TOL


# --------------------------------------------------------------------------- agreement


PROBLEM_30 = paper_problem(n_scenarios=30)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("start", sorted(STARTS))
def test_matches_reference_on_random_problems(seed: int, start: str) -> None:
    problem = PROBLEM_30
    x0, W = STARTS[start], draw_W(seed, 30)
    assert_matches_reference(
        problem, x0, W, fast_solve(problem, x0, W), reference_solve(problem, x0, W)
    )


@pytest.mark.parametrize("seed", [3, 4])
def test_matches_reference_narrow_scenarios_without_slack(seed: int) -> None:
    """Scenarios as a particle filter would give them: feasible, no slack needed."""
    problem = PROBLEM_30
    rng = np.random.default_rng(seed)
    W = latent_force_scenarios(rng, 30, 7, mean=0.5, spread=0.3, walk_std=0.1)
    x0 = STARTS["mid_track"]
    ref = reference_solve(problem, x0, W)
    assert ref.slack <= VIOLATION_TOL  # the point of this test: a feasible hard problem
    assert_matches_reference(problem, x0, W, fast_solve(problem, x0, W), ref)


@pytest.mark.parametrize("start", ["start", "fast"])
def test_matches_reference_at_paper_size(start: str) -> None:
    problem = paper_problem(n_scenarios=150)
    x0, W = STARTS[start], draw_W(11, 150)
    assert_matches_reference(
        problem, x0, W, fast_solve(problem, x0, W), reference_solve(problem, x0, W)
    )


def test_problem_that_needs_slack() -> None:
    """Near the speed bound with a push stronger than full braking: slack is unavoidable."""
    problem = PROBLEM_30
    x0 = np.array([40.0, 3.0 * np.sin(8.0), 7.9, 0.0])
    W = np.full((30, 7), 6.0)
    sol, ref = fast_solve(problem, x0, W), reference_solve(problem, x0, W)
    assert sol.slack > 0.1 and ref.slack > 0.1
    assert_matches_reference(problem, x0, W, sol, ref)
    # Full braking from the start is the only way to limit the excess speed.
    assert sol.u[0, 0] == pytest.approx(problem.input_lower[0])


def test_per_scenario_initial_states() -> None:
    problem = PROBLEM_30
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
    problem = PROBLEM_30
    x0 = np.array([0.0, 0.0, 0.5, -0.6])
    sol = fast_solve(problem, x0, draw_W(6, 30))
    assert sol.success
    lower = np.broadcast_to(problem.input_lower, sol.u.shape)
    upper = np.broadcast_to(problem.input_upper, sol.u.shape)
    assert np.all(sol.u >= lower) and np.all(sol.u <= upper)
    assert np.any(sol.u == upper) or np.any(sol.u == lower)  # some bound is active


def test_warm_resolve_converges_in_at_most_two_iterations() -> None:
    problem = paper_problem(n_scenarios=150)
    x0, W = STARTS["mid_track"], draw_W(7, 150)
    solver = FastScenarioSolver(problem)
    first = solver.solve(x0, W)
    again = solver.solve(x0, W, u_guess=first.u)
    assert first.success and again.success
    assert again.iterations <= 2
    assert again.objective == pytest.approx(first.objective, rel=1e-10)
    np.testing.assert_allclose(again.u, first.u, atol=1e-6)


def test_shifted_warm_start_is_the_default() -> None:
    problem = PROBLEM_30
    x0, W = STARTS["mid_track"], draw_W(8, 30)
    solver = FastScenarioSolver(problem)
    first = solver.solve(x0, W)
    x1 = problem.model.physical_step(x0, first.u[0], W[0, :1])
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
    problem = PROBLEM_30
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
    problem = PROBLEM_30
    x0, W = STARTS["start"], draw_W(9, 30)
    screened = FastScenarioSolver(problem, screen_rows=1, screen_margin=1e-3).solve(x0, W)
    full = FastScenarioSolver(problem, screen_rows=30, screen_margin=1e3).solve(x0, W)
    assert screened.success and full.success
    assert screened.objective == pytest.approx(full.objective, rel=1e-9)
    np.testing.assert_allclose(screened.u, full.u, atol=1e-6)


@pytest.mark.parametrize("case", ["feasible", "needs_slack", "low_penalty"])
def test_qps_without_slacks_give_the_same_solution(case: str) -> None:
    """``elastic_qp="on_demand"`` (QPs without slacks first) solves like ``"always"``: on a
    feasible problem with QPs without slacks only, where slack is unavoidable (the hard QP
    is infeasible) and where the slack penalty is so low that slack beats meeting the rows
    (the hard QP is feasible, but its multipliers exceed the penalty: accepting its steps
    anyway ends 0.5% higher, at the hard problem's optimum)."""
    rng = np.random.default_rng(3)
    narrow = latent_force_scenarios(rng, 30, 7, mean=0.5, spread=0.3, walk_std=0.1)
    x0, W, problem = STARTS["mid_track"], narrow, PROBLEM_30
    if case == "low_penalty":
        problem = paper_problem(n_scenarios=30, slack_penalty=1.0)
    elif case == "needs_slack":
        x0, W = np.array([40.0, 3.0 * np.sin(8.0), 7.9, 0.0]), np.full((30, 7), 6.0)
    hard = FastScenarioSolver(problem).solve(x0, W)
    elastic = FastScenarioSolver(problem, elastic_qp="always").solve(x0, W)
    assert hard.success and elastic.success
    assert hard.objective == pytest.approx(elastic.objective, rel=1e-9)
    np.testing.assert_allclose(hard.u, elastic.u, atol=1e-6)
    assert elastic.extra["qp_hard"] == 0 and hard.extra["qp_hard"] > 0
    if case == "feasible":
        assert hard.slack <= VIOLATION_TOL
        assert hard.extra["qp_hard_rejected"] == 0
        assert hard.extra["qp_hard"] == hard.extra["qp_solves"]
    else:
        assert hard.extra["qp_hard_rejected"] >= 1 and hard.slack > 1.0


def test_without_daqp_the_qps_without_slacks_go_to_qpoases(monkeypatch) -> None:
    """The default's QPs without slacks are DAQP's; without the package, qpOASES's, with
    the same plan."""
    rng = np.random.default_rng(4)
    W = latent_force_scenarios(rng, 30, 7, mean=0.5, spread=0.3, walk_std=0.1)
    x0 = STARTS["mid_track"]
    with_daqp = FastScenarioSolver(PROBLEM_30).solve(x0, W)
    assert with_daqp.extra["qp_calls"].get("daqp", 0) == with_daqp.extra["qp_hard"] > 0
    monkeypatch.setitem(sys.modules, "daqp", None)  # the package is not installed
    without = FastScenarioSolver(PROBLEM_30).solve(x0, W)
    assert "daqp" not in without.extra["qp_calls"] and without.extra["qp_hard"] > 0
    assert without.objective == pytest.approx(with_daqp.objective, rel=1e-9)
    np.testing.assert_allclose(without.u, with_daqp.u, atol=1e-6)


def test_a_bad_elastic_mode_names_the_field_and_the_choices() -> None:
    with pytest.raises(ValueError, match=r"elastic_qp='never': must be one of \('on_demand'"):
        FastScenarioSolver(paper_problem(n_scenarios=5), elastic_qp="never")


def test_the_stagnation_stop_counts_accepted_steps_in_a_row() -> None:
    """With a stagnation threshold every decrease meets, the start ends as acceptable after
    exactly acceptable_iter accepted steps; with the default one it runs on to convergence."""
    problem = PROBLEM_30
    x0, W = STARTS["start"], draw_W(10, 30)
    full = FastScenarioSolver(problem, restarts=()).solve(x0, W)
    assert full.status == "Solve_Succeeded" and full.iterations > 3
    for count in (1, 2):
        sol = FastScenarioSolver(
            problem, restarts=(), acceptable_tol=1.0, acceptable_iter=count
        ).solve(x0, W)
        assert sol.success
        assert sol.status == "Solved_To_Acceptable_Level"
        assert sol.iterations == count
        assert sol.objective < problem.objective(x0, W, np.zeros((7, 2)))


# One closed-loop problem of the paper evaluation's certainty-equivalent agent ("pf", env seed
# 0, step 41, near the goal; one scenario: the estimated force), with its warm start.
CREEPING_X0 = [57.77821232013492, -1.5702984472042978, 7.453441270459591, 0.3481842597733405]
CREEPING_W = [
    2.5423411385032457, 2.600331412906511, 2.639652715893501, 2.6612736765473826,
    2.6664135849261608, 2.6564524290691316, 2.6328599201276264,
]  # fmt: skip
CREEPING_GUESS = [
    [-5.0, 0.004289226959010901], [-5.0, -0.12075060944105738],
    [-4.566141109947966, -0.1204691834042342], [-3.458349196589167, 0.38476033284438294],
    [-2.3360084932596132, 0.4363323129985824], [-1.1103095554667035, 0.1143932978605367],
    [-1.1103095554667035, 0.1143932978605367],
]  # fmt: skip


def test_a_poor_accepted_step_gets_the_second_order_correction() -> None:
    """Along a curved constraint, full steps that the line search accepts but that fall far
    short of the model (the slack grows with the constraint's curvature) held the trust
    region at its minimum: 108 first-start iterations. Correcting those steps too lets it
    grow again: far fewer iterations, the same objective."""
    problem = paper_problem(n_scenarios=1)
    x0, W = np.array(CREEPING_X0), np.array(CREEPING_W).reshape(1, 7, 1)
    guess = np.array(CREEPING_GUESS)
    before = FastScenarioSolver(problem, soc_below_ratio=0.0).solve(x0, W, u_guess=guess)
    after = FastScenarioSolver(problem).solve(x0, W, u_guess=guess)
    assert before.success and after.success, (before.status, after.status)
    assert before.extra["first_start"]["iterations"] > 100
    assert after.extra["first_start"]["iterations"] <= 80
    assert after.extra["soc_steps"] > before.extra["soc_steps"]
    assert after.objective == pytest.approx(before.objective, rel=1e-7)


def test_iteration_limit_returns_best_iterate_without_raising() -> None:
    problem = PROBLEM_30
    x0, W = STARTS["start"], draw_W(10, 30)
    start_objective = problem.objective(x0, W, np.zeros((7, 2)))
    sol = FastScenarioSolver(problem, max_iter=1, restarts=()).solve(x0, W)
    assert not sol.success
    assert sol.status == "Maximum_Iterations_Exceeded"
    assert sol.iterations == 1
    assert np.all(np.isfinite(sol.u))
    assert sol.objective < start_objective


@pytest.mark.parametrize("cost_kind", ["diagonal", "full"])
def test_derivatives_match_casadi(cost_kind: str) -> None:
    """Gradient, exact Lagrangian Hessian and row Jacobians against CasADi's AD of the
    whole condensed problem (the model's own CasADi step, unrolled)."""
    config = SineTrackConfig()
    cost = config.make_cost()
    if cost_kind == "full":  # a coupled, non-diagonal weight exercises the general path
        Q = np.diag([2.0, 2.0, 1.0, 0.1]) + 0.3 * (np.eye(4, k=1) + np.eye(4, k=-1))
        cost = type(cost)(Q=Q, R=[[0.5, 0.1], [0.1, 10.0]], x_goal=cost.x_goal)
    problem = ScenarioProblem(config.make_model(), cost, n_scenarios=4)
    system = problem.system
    rng = np.random.default_rng(12)
    n, ns, ng = problem.horizon, problem.n_scenarios, problem.ng
    x0 = STARTS["mid_track"] + rng.normal(0.0, 0.1, size=(ns, 4))
    W = draw_W(12, ns)
    u = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-0.4, 0.4, n)]).ravel()
    model = CondensedModel(problem)
    mu = np.zeros((ng, n, ns))
    mu[model.screened] = rng.uniform(0.0, 5.0, size=(model.screened.size, n, ns))

    U = ca.SX.sym("u", 2 * n)
    step, cons = system.casadi_step(problem.dt), system.casadi_constraints()
    total, lagrangian_terms, rows = 0, 0, []
    for i in range(ns):
        x = ca.DM(x0[i])
        for k in range(n):
            x = step(x, U[2 * k : 2 * k + 2], W[i, k])
            total += (cost.terminal_cost(x) if k == n - 1 else cost.state_cost(x)) / ns
            g = cons(x)
            rows.append(g)
            lagrangian_terms += ca.dot(ca.DM(mu[:, k, i]), g)
    for k in range(n):
        total += cost.input_cost(U[2 * k : 2 * k + 2])
    f = ca.Function(
        "f",
        [U],
        [
            ca.gradient(total, U),
            ca.hessian(total + lagrangian_terms, U)[0],
            ca.jacobian(ca.vertcat(*rows), U),
        ],
    )
    grad_ref, hess_ref, jac_ref = (m.full() for m in f(u))

    _, Wc = problem.check_data(x0, W)
    W_steps = np.ascontiguousarray(Wc.transpose(1, 0, 2))
    W_lanes = np.ascontiguousarray(Wc.transpose(2, 1, 0))
    ro = model.evaluate(np.ascontiguousarray(x0.T), W_steps, u, model.state_cost0(x0))
    assert ro.merit == pytest.approx(problem.objective(x0, W, u.reshape(n, 2)), rel=1e-12)
    lin = model.linearise(ro, W_lanes)
    hess = model.hessian(lin, mu, W_lanes)
    np.testing.assert_allclose(lin.grad, grad_ref.ravel(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(hess, hess_ref, rtol=1e-9, atol=1e-8 * np.abs(hess_ref).max())
    # Reference row (scenario i, step k, constraint j) is (i * N + k) * ng + j.
    pos = np.array([(j, k, i) for i in range(ns) for k in range(n) for j in range(ng)])
    jac, values = model.rows(lin, pos)
    np.testing.assert_allclose(jac, jac_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(values, problem.constraint_values(problem.rollout(x0, W, u)).ravel())


def test_speed_bounds_are_found_to_be_shared_linear_rows() -> None:
    """The structure the solver exploits is read from the model, not hard-coded."""
    problem = PROBLEM_30
    model = CondensedModel(problem)
    labels = [problem.system.constraint_labels[j] for j in model.shared]
    assert labels == ["speed_min", "speed_max"]
    assert model.screened.tolist() == [0, 1, 2, 3]
    # v_k = v_0 + dt sum_{j<k} (a_j + w_j): the rows are dt on earlier accelerations.
    dt, n = problem.dt, problem.horizon
    expected = np.zeros((n, 2 * n))
    for k in range(n):
        expected[k, 0 : 2 * (k + 1) : 2] = dt
    np.testing.assert_allclose(model.shared_rows[1], expected, atol=1e-15)
    np.testing.assert_allclose(model.shared_rows[0], -expected, atol=1e-15)


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
    solver = fast_solver(PROBLEM_30)
    with pytest.raises(ValueError):
        solver.solve(x0, W, u_guess=u_guess)


@pytest.mark.parametrize(
    "options",
    [
        {"max_iter": 0},
        {"tol": -1.0},
        {"acceptable_tol": 0.0},
        {"acceptable_iter": 0},
        {"acceptable_iter": 1.5},
        {"soc_below_ratio": -0.1},
        {"soc_below_ratio": 1.5},
        {"armijo": 0.7},
        {"qp_solver": "nope"},
        {"foo": 1},
        {"restarts": ("mirror", "random")},
        {"restarts": "mirror"},
        {"restart_threshold": 0.0},
        {"restart_optimism": -1.0},
        {"restart_margin": float("nan")},
        {"restart_probe": 0},
        {"restart_near_tol": 0.01},  # below restart_same_tol
        {"restart_near_tol": float("inf")},
        {"hessian_modification": "clip"},
        {"elastic_qp": "never"},
        {"threads": 0},
        {"threads": 1.5},
        {"threads": True},
        {"threads": 1000},
        {"max_expand": -1},
        {"expand_ratio": 0.0},
        {"damping_decrease": 1.0},
        {"trust_radius": -0.1},
        {"trust_radius": 1.5},
        {"trust_radius": float("nan")},
    ],
)
def test_bad_options_raise_value_error(options: dict) -> None:
    with pytest.raises(ValueError):
        FastScenarioSolver(paper_problem(n_scenarios=5), **options)


def test_an_extra_start_is_the_best_plan_only_when_near_worse_and_closing_in() -> None:
    from controllers.solvers.fast.iterate import Rollout

    solver = FastScenarioSolver(paper_problem(n_scenarios=5))
    n_u = solver._n_u
    rival, bar = np.zeros(n_u), 10.0  # the best plan and its merit

    def at(gap: float, merit: float) -> Rollout:
        return Rollout(u=np.full(n_u, gap), X=np.empty(0), G=np.empty(0), slack=0.0, merit=merit)

    before = np.full(n_u, 0.4)
    assert solver._bound_for(rival, before, at(0.04, 9.0), bar)  # within restart_same_tol
    assert solver._bound_for(rival, before, at(0.2, 11.0), bar)  # near, worse, closer
    assert not solver._bound_for(rival, before, at(0.2, 9.0), bar)  # near but better: go on
    assert not solver._bound_for(rival, np.full(n_u, 0.1), at(0.2, 11.0), bar)  # moving away
    assert not solver._bound_for(rival, before, at(0.3, 11.0), bar)  # beyond restart_near_tol
    strict = FastScenarioSolver(paper_problem(n_scenarios=5), restart_near_tol=0.05)
    assert not strict._bound_for(rival, before, at(0.2, 11.0), bar)


def test_a_bad_trust_radius_names_the_field_and_the_range() -> None:
    with pytest.raises(ValueError, match=r"trust_radius=1\.5: must be in \[0, 1\]"):
        FastScenarioSolver(paper_problem(n_scenarios=5), trust_radius=1.5)


@pytest.mark.parametrize(
    "options",
    [{"min_trust_radius": 0.5, "trust_radius": 0.25}, {"min_trust_radius": -1e-3}],
)
def test_a_bad_minimum_trust_radius_raises_value_error(options: dict) -> None:
    with pytest.raises(ValueError, match="min_trust_radius"):
        FastScenarioSolver(paper_problem(n_scenarios=5), **options)


def test_the_trust_region_bounds_every_qp_step() -> None:
    """With a tiny trust region the first SQP step moves no input by more than its share
    of the input's range (step expansion, which may go beyond it, switched off)."""
    problem = paper_problem(n_scenarios=20)
    x0, W = STARTS["mid_track"], draw_W(3, 20)
    solver = FastScenarioSolver(
        problem, trust_radius=0.01, min_trust_radius=0.01, max_iter=1, max_expand=0
    )
    solver.trace = []
    sol = solver.solve(x0, W)
    span = problem.system.input_upper - problem.system.input_lower
    assert np.all(np.abs(sol.u) <= 0.01 * span + 1e-12)
    assert solver.trace and solver.trace[0]["d"] <= 0.01 * float(np.max(span)) + 1e-12


@pytest.mark.parametrize("mode", ["floor", "abs", "augmented"])
def test_the_convexified_hessian_keeps_the_step_on_the_active_set_when_it_can(mode) -> None:
    """Negative curvature only along an active bound's direction: sigma e_0 e_0' fixes it
    (the QP step on that active set is unchanged). Negative curvature in a free direction
    too: the augmentation cannot fix it, and the mode decides (eigenvalues raised to the
    floor, their absolute values, or the floor on the augmented matrix)."""
    solver = FastScenarioSolver(paper_problem(n_scenarios=5), hessian_modification=mode)
    n_u, floor = solver._n_u, solver.options.hessian_floor
    none_pos, none_shared = np.empty((0, 3), dtype=int), np.empty(0, dtype=int)
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(n_u - 1, n_u - 1)))
    free = Q @ np.diag(np.linspace(1.0, 3.0, n_u - 1)) @ Q.T  # positive definite
    H = np.zeros((n_u, n_u))
    H[0, 0], H[1:, 1:] = -2.0, free
    H_qp, sigma, _ = solver._convexify(H, None, none_pos, none_shared, np.array([0]))
    assert sigma > 0.0
    np.testing.assert_array_equal(H_qp - H, sigma * np.eye(n_u)[:, :1] @ np.eye(n_u)[:1])
    assert np.linalg.eigvalsh(H_qp)[0] >= floor
    # Negative curvature also in a free direction (input 1): no sigma helps.
    H[1, 1] -= 10.0
    H_qp, sigma, _ = solver._convexify(H, None, none_pos, none_shared, np.array([0]))
    w = np.linalg.eigvalsh(H_qp)
    assert w[0] >= floor * (1 - 1e-6)
    if mode != "abs":
        assert w[0] == pytest.approx(floor, rel=1e-6)  # negative curvature raised to it
    if mode == "augmented":
        assert sigma > 0.0  # the constraint's own curvature is kept
    else:
        assert sigma == 0.0
        expected = np.abs(np.linalg.eigvalsh(H)) if mode == "abs" else np.linalg.eigvalsh(H)
        np.testing.assert_allclose(w, np.sort(np.maximum(expected, floor)), atol=1e-9)


@pytest.mark.parametrize("traced", [False, True])
def test_a_hessian_above_the_floor_is_the_qp_hessian_itself(traced: bool) -> None:
    """Positive definite above the floor: returned as it is, whether the check is the quick
    Cholesky one (no trace) or the eigen-decomposition (traced); just below the floor: not."""
    solver = FastScenarioSolver(paper_problem(n_scenarios=5))
    solver.trace = [] if traced else None
    n_u, floor = solver._n_u, solver.options.hessian_floor
    none_pos, none_shared = np.empty((0, 3), dtype=int), np.empty(0, dtype=int)
    Q, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(n_u, n_u)))
    eig = np.linspace(floor * (1 + 1e-6), 5.0, n_u)
    H = Q @ np.diag(eig) @ Q.T
    H = 0.5 * (H + H.T)
    H_qp, sigma, _ = solver._convexify(H, None, none_pos, none_shared, np.empty(0, dtype=int))
    assert H_qp is H and sigma == 0.0
    eig[0] = floor * (1 - 1e-3)
    H = Q @ np.diag(eig) @ Q.T
    H = 0.5 * (H + H.T)
    H_qp, sigma, _ = solver._convexify(H, None, none_pos, none_shared, np.empty(0, dtype=int))
    assert H_qp is not H
    assert np.linalg.eigvalsh(H_qp)[0] == pytest.approx(floor, rel=1e-6)


def test_the_augmentation_is_tried_when_as_many_rows_as_negative_eigenvalues() -> None:
    """Two active bounds, negative curvature along both: sigma J'J can fix it (and must be
    used); one active bound for the same two negative eigenvalues: it cannot, the floor."""
    solver = FastScenarioSolver(paper_problem(n_scenarios=5))
    n_u, floor = solver._n_u, solver.options.hessian_floor
    none_pos, none_shared = np.empty((0, 3), dtype=int), np.empty(0, dtype=int)
    H = np.diag(np.linspace(1.0, 2.0, n_u))
    H[0, 0], H[1, 1] = -2.0, -3.0
    H_qp, sigma, _ = solver._convexify(H, None, none_pos, none_shared, np.array([0, 1]))
    assert sigma > 0.0
    np.testing.assert_array_equal(H_qp - H, sigma * np.diag((np.arange(n_u) < 2).astype(float)))
    H_qp, sigma, _ = solver._convexify(H, None, none_pos, none_shared, np.array([0]))
    assert sigma == 0.0
    np.testing.assert_allclose(np.diag(H_qp), np.maximum(np.diag(H), floor), atol=1e-12)


def test_latent_force_scenarios_start_and_walk() -> None:
    rng = np.random.default_rng(0)
    W = latent_force_scenarios(rng, 5, 7, mean=1.5, spread=0.0, walk_std=0.0)
    assert W.shape == (5, 7)
    np.testing.assert_array_equal(W, 1.5)  # no spread and no walk: the mean throughout
    W = latent_force_scenarios(
        np.random.default_rng(1), 4000, 3, mean=[1.0, -2.0], spread=0.5, walk_std=0.2, n_forces=2
    )
    assert W.shape == (4000, 3, 2)
    np.testing.assert_allclose(W[:, 0].mean(axis=0), [1.0, -2.0], atol=0.05)
    np.testing.assert_allclose(W[:, 0].std(axis=0), 0.5, rtol=0.05)
    np.testing.assert_allclose(np.diff(W, axis=1).std(axis=(0, 1)), 0.2, rtol=0.05)
