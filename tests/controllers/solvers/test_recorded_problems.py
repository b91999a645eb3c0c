"""The fast solver and IPOPT against recorded reference solutions of closed-loop problems.

``data/recorded_problems.npz`` holds scenario problems (``x0``, 150 latent-force scenarios,
the warm start the closed loop gave) met by the scenario agent in paper episodes, several of
which need slack (a latent force beyond the braking authority), and the textbook IPOPT
formulation's solution of each (``reference_u``, ``reference_objective``). See
``data/make_recorded_problems.py`` for how they were chosen and solved.

The problem is not convex, so "the same solution" is checked both ways: started at the
reference solution, the fast SQP stays there (and its extra starts only ever go lower), and
IPOPT on the condensed NLP (another formulation than the reference's) reaches the same
objective from the closed loop's warm start; and the fast solver's own plan is a local
optimum of the full problem (no nearby point is lower). Which local optimum each solver
finds from a warm start is a quality figure of the benchmark (``lfm-benchmark``), not
asserted here.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers.problem import ScenarioProblem
from controllers.solvers import make_solver
from experiments.benchmark.problems import problem_from_config
from tests.controllers.solvers.recorded import load_problems

DATA = load_problems()
IDS = [f"seed{s}-step{k}" for s, k in zip(DATA["seed"], DATA["step"], strict=True)]
RTOL = 1e-4  # objective agreement (the benchmark's target)
IPOPT_RTOL = 1e-6  # IPOPT at tol 1e-10 against the reference (measured: <= 1.1e-8)
VIOLATION_TOL = 1e-6  # [m or m/s] where the solution needs no slack


@pytest.fixture(scope="module")
def problem() -> ScenarioProblem:
    return problem_from_config(n_scenarios=150)


@pytest.fixture(scope="module")
def ipopt(problem: ScenarioProblem):
    return make_solver(problem, "ipopt", ipopt_options={"tol": 1e-10})


def _problem(i: int) -> tuple[np.ndarray, ...]:
    return DATA["x0"][i], DATA["W"][i], DATA["u_guess"][i], DATA["reference_u"][i]


def _slack_and_violation(problem, x0, W, u) -> tuple[float, float]:
    X = problem.rollout(x0, W, u)
    return float(np.sum(problem.minimal_slack(X))), problem.constraint_violation(X)


def test_the_recorded_set_covers_slack_and_the_goal(problem: ScenarioProblem) -> None:
    n = len(IDS)
    assert DATA["W"].shape == (n, 150, problem.horizon, problem.nw)
    assert DATA["reference_u"].shape == DATA["u_guess"].shape == (n, problem.horizon, problem.nu)
    assert np.sum(DATA["slack"] > 0.1) >= 3  # problems that need slack
    assert np.sum(DATA["slack"] <= 1e-6) >= 8  # and problems that do not


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_the_reference_objective_is_the_problems_objective(i, problem) -> None:
    x0, W, _, ref_u = _problem(i)
    assert problem.objective(x0, W, ref_u) == pytest.approx(
        DATA["reference_objective"][i], rel=1e-12
    )


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_ipopt_reaches_the_reference_objective(i, problem, ipopt) -> None:
    x0, W, guess, _ = _problem(i)
    ipopt.reset()
    sol = ipopt.solve(x0, W, u_guess=guess)
    assert sol.success, sol.status
    J = problem.objective(x0, W, sol.u)
    assert J == pytest.approx(DATA["reference_objective"][i], rel=IPOPT_RTOL)


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_fast_solver_stays_at_the_reference_solution(i, problem) -> None:
    x0, W, _, ref_u = _problem(i)
    ref_objective = DATA["reference_objective"][i]
    ref_slack, _ = _slack_and_violation(problem, x0, W, ref_u)
    # Plain SQP (no extra starts) from the reference solution: the same point.
    plain = make_solver(problem, "fast", restarts=()).solve(x0, W, u_guess=ref_u)
    assert plain.success, plain.status
    assert plain.objective == pytest.approx(ref_objective, rel=RTOL)
    _, violation = _slack_and_violation(problem, x0, W, plain.u)
    if ref_slack <= VIOLATION_TOL:
        assert violation <= VIOLATION_TOL
    # With its extra starts it may move to a lower optimum, never to a higher one.
    best = make_solver(problem, "fast").solve(x0, W, u_guess=ref_u)
    assert best.objective <= ref_objective * (1 + RTOL)


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_fast_plan_is_a_local_optimum_of_the_full_problem(i, problem) -> None:
    """No point next to the fast plan has a lower full-problem objective.

    The full problem's objective (every scenario, every constraint, the exact slack
    penalty) is probed along every input coordinate in both directions and along random
    directions, at two radii, clipped to the input box
    (:func:`controllers.problem.largest_local_descent`). This certificate is independent
    of the solver's own derivatives.
    """
    from controllers.problem import largest_local_descent

    x0, W, guess, _ = _problem(i)
    fast = make_solver(problem, "fast").solve(x0, W, u_guess=guess)
    assert fast.success, fast.status
    J = problem.objective(x0, W, fast.u)
    assert fast.objective == pytest.approx(J, rel=1e-9)
    worst = largest_local_descent(problem, x0, W, fast.u, seed=i)
    assert worst >= -1e-9 * abs(J), worst
    slack, violation = _slack_and_violation(problem, x0, W, fast.u)
    if slack <= VIOLATION_TOL:
        assert violation <= VIOLATION_TOL


@pytest.mark.parametrize("trust_radius", [0.25, 0.0])
def test_extra_starts_only_ever_lower_the_objective(problem, trust_radius: float) -> None:
    kept = 0
    plain_solver = make_solver(problem, "fast", restarts=(), trust_radius=trust_radius)
    best_solver = make_solver(problem, "fast", trust_radius=trust_radius)
    for i in range(len(IDS)):
        x0, W, guess, _ = _problem(i)
        plain = plain_solver.solve(x0, W, u_guess=guess)
        best = best_solver.solve(x0, W, u_guess=guess)
        assert best.objective <= plain.objective * (1 + 1e-12), IDS[i]
        if "kept" in best.extra["restarts"].values():
            kept += best.objective < plain.objective * (1 - 1e-3)
    if trust_radius == 0.0:
        # Without the trust region the extra starts matter on this set: some problem ends
        # clearly lower with them (with it, the first start already reaches those plans
        # here; on closed-loop problems the extra starts still lower some objectives).
        assert kept >= 1


def test_an_extra_start_heading_back_to_the_best_plan_stops_early(problem) -> None:
    """``restart_near_tol``: an extra start that draws near the best plan while still worse
    than it is the same plan; stopped there, the solve ends with the same plan in fewer
    iterations (the mirrored starts of two recorded problems take two iterations less)."""
    saved = 0
    for i in range(len(IDS)):
        x0, W, guess, _ = _problem(i)
        late = make_solver(problem, "fast", restart_near_tol=0.05).solve(x0, W, u_guess=guess)
        early = make_solver(problem, "fast").solve(x0, W, u_guess=guess)
        np.testing.assert_array_equal(early.u, late.u, err_msg=IDS[i])
        assert early.iterations <= late.iterations, IDS[i]
        if early.iterations < late.iterations:
            assert "duplicate" in early.extra["restarts"].values(), IDS[i]
            saved += 1
    assert saved >= 1
