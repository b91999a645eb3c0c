"""The fast SQP at long horizons, its QP solvers, and no state carried between solves.

``data/long_horizon_problems.npz`` holds closed-loop-like problems at N = 15 and 30 (see
``data/make_long_horizon_problems.py``) with IPOPT's solution from the same warm start.
The fast solver must converge on them within a bounded iteration count and reach at least
IPOPT's objective (the problem is not convex: a lower objective is another, better local
optimum, never an error). At N = 30 IPOPT on the condensed NLP stopped at its iteration
limit on all three problems, so its objective there is only an upper bound.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.qp.slot_qp import QP_SOLVERS
from controllers.solvers.fast.solver import FastScenarioSolver
from experiments.benchmark.problems import problem_from_config
from tests.controllers.solvers.recorded import load_problems

LONG = load_problems("long_horizon_problems.npz")
RECORDED = load_problems()
RTOL = 1e-4  # objective no more than this above IPOPT's (the benchmark's target)
MAX_ITERATIONS = {15: 60, 30: 80}  # SQP iterations of all starts together
# Open (issue 16): problem 0 at N = 30 is strongly infeasible (its best plan keeps slack)
# and its merit falls through a long flat valley: it converges, but its first start takes
# ~40 SQP iterations and the extra starts as many again, over the bound. (Before the trust
# region, N = 15 problem 1 crawled to max_iter and problem 2 stopped 7% above IPOPT.)
KNOWN = {
    (30, 0): "converges, but needs ~90 SQP iterations over all starts (flat, infeasible valley)",
}
CASES = [
    pytest.param(n, i, id=f"N{n}-{i}", marks=[pytest.mark.xfail(reason=KNOWN[n, i], strict=True)])
    if (n, i) in KNOWN
    else pytest.param(n, i, id=f"N{n}-{i}")
    for n in (15, 30)
    for i in range(LONG[f"seed_{n}"].size)
]


def _problem(n: int) -> ScenarioProblem:
    ns = LONG[f"W_{n}"].shape[1]
    return problem_from_config(n_scenarios=ns, horizon=n)


@pytest.mark.parametrize(("n", "i"), CASES)
def test_long_horizon_problem_converges_to_ipopts_objective(n: int, i: int) -> None:
    problem = _problem(n)
    x0, W, guess = LONG[f"x0_{n}"][i], LONG[f"W_{n}"][i], LONG[f"u_guess_{n}"][i]
    sol = FastScenarioSolver(problem).solve(x0, W, u_guess=guess)
    assert sol.success, sol.status
    assert sol.iterations <= MAX_ITERATIONS[n]
    reference = float(LONG[f"reference_objective_{n}"][i])
    assert sol.objective <= reference + RTOL * abs(reference)
    assert sol.objective == pytest.approx(problem.objective(x0, W, sol.u), rel=1e-10)


def test_the_long_horizon_set_has_the_stored_shapes() -> None:
    for n in (15, 30):
        k = LONG[f"seed_{n}"].size
        assert k >= 2
        assert LONG[f"W_{n}"].shape[:3] == (k, LONG[f"W_{n}"].shape[1], n)
        assert LONG[f"reference_u_{n}"].shape == LONG[f"u_guess_{n}"].shape == (k, n, 2)


@pytest.mark.parametrize("qp_solver", QP_SOLVERS)
def test_every_qp_solver_matches_the_recorded_references(qp_solver: str) -> None:
    """Each QP solver kept reaches the textbook's objective on recorded closed-loop problems."""
    problem = problem_from_config(n_scenarios=150)
    solver = FastScenarioSolver(problem, qp_solver=qp_solver)
    for i in range(0, RECORDED["seed"].size, 4):
        x0, W = RECORDED["x0"][i], RECORDED["W"][i]
        sol = solver.solve(x0, W, u_guess=RECORDED["reference_u"][i])
        assert sol.success, (i, sol.status)
        assert sol.extra["qp_solver"] == qp_solver
        reference = float(RECORDED["reference_objective"][i])
        assert sol.objective <= reference + RTOL * abs(reference)


@pytest.mark.parametrize("qp_solver", QP_SOLVERS)
def test_solving_in_sequence_equals_solving_each_fresh(qp_solver: str) -> None:
    """No state (QP hot starts, buffers) leaks from one problem into the next."""
    problem = problem_from_config(n_scenarios=150)
    picks = range(0, RECORDED["seed"].size, 3)
    shared = FastScenarioSolver(problem, qp_solver=qp_solver)
    for i in picks:
        x0, W, guess = RECORDED["x0"][i], RECORDED["W"][i], RECORDED["u_guess"][i]
        in_sequence = shared.solve(x0, W, u_guess=guess)
        fresh = FastScenarioSolver(problem, qp_solver=qp_solver).solve(x0, W, u_guess=guess)
        assert in_sequence.status == fresh.status
        assert in_sequence.iterations == fresh.iterations
        np.testing.assert_array_equal(in_sequence.u, fresh.u)
        assert in_sequence.objective == fresh.objective


def test_the_strongly_infeasible_n30_problem_converges() -> None:
    """The one known case above is slow, not stuck: it converges to an objective below
    IPOPT's (which stopped at its own iteration limit)."""
    problem = _problem(30)
    x0, W, guess = LONG["x0_30"][0], LONG["W_30"][0], LONG["u_guess_30"][0]
    sol = FastScenarioSolver(problem).solve(x0, W, u_guess=guess)
    assert sol.success, sol.status
    assert sol.extra["first_start"]["iterations"] <= 60
    assert sol.objective <= float(LONG["reference_objective_30"][0])


def test_a_creeping_start_ends_at_the_acceptable_level() -> None:
    """On the strongly infeasible N = 30 problem the mirrored start creeps along a flat
    valley, lowering the merit by ~1e-9 of itself per iteration. The stagnation stop ends it
    as "Solved_To_Acceptable_Level" with the objective of the start left to run (to 1e-8)
    in fewer iterations, and the last acceptable_iter steps each lowered the merit by at
    most acceptable_tol of it."""
    problem = _problem(30)
    x0, W, guess = LONG["x0_30"][0], LONG["W_30"][0], LONG["u_guess_30"][0]
    solver = FastScenarioSolver(problem)
    solver.trace = []
    stopped = solver.solve(x0, W, u_guess=guess)
    left = FastScenarioSolver(problem, acceptable_iter=10**9).solve(x0, W, u_guess=guess)
    assert stopped.success and left.success, (stopped.status, left.status)
    assert "Solved_To_Acceptable_Level" in (stopped.status, *stopped.extra["restarts"].values())
    assert "Solved_To_Acceptable_Level" not in (left.status, *left.extra["restarts"].values())
    assert stopped.iterations < left.iterations
    assert stopped.objective == pytest.approx(left.objective, rel=1e-8)
    # The trace's rows by start (each start counts its QP solves from zero); the kept start
    # is the stagnating one, and its last merit is the solution's objective.
    starts: list[list[float]] = []
    last = 0
    for row in solver.trace:
        if not starts or row["qp_solves"] < last:
            starts.append([])
        starts[-1].append(row["merit"])
        last = row["qp_solves"]
    names = ["first", *stopped.extra["restarts"]]
    kept = [k for k, name in enumerate(names) if stopped.extra["restarts"].get(name) == "kept"]
    assert len(kept) == 1 and stopped.extra["restarts"][names[kept[0]]] == "kept"
    options = solver.options
    merits = starts[kept[0]] + [stopped.objective]
    falls = -np.diff(merits[-options.acceptable_iter - 1 :])
    assert np.all(falls <= options.acceptable_tol * (1.0 + stopped.objective))
    # ... and the step before that run did not count (else the start had ended earlier).
    assert -np.diff(merits)[-options.acceptable_iter - 1] > options.acceptable_tol * (
        1.0 + stopped.objective
    )


@pytest.mark.parametrize("n", [15])
def test_levenberg_marquardt_damping_is_still_selectable(n: int) -> None:
    """trust_radius=0 is the solver before the trust region (damping after backtracking):
    it converges on the first long-horizon problem and reaches IPOPT's objective."""
    problem = _problem(n)
    x0, W, guess = LONG[f"x0_{n}"][0], LONG[f"W_{n}"][0], LONG[f"u_guess_{n}"][0]
    sol = FastScenarioSolver(problem, trust_radius=0.0).solve(x0, W, u_guess=guess)
    assert sol.success, sol.status
    reference = float(LONG[f"reference_objective_{n}"][0])
    assert sol.objective <= reference + RTOL * abs(reference)
