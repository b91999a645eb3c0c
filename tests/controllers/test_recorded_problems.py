"""The fast solver against the full (textbook) problem on recorded closed-loop problems.

``data/recorded_problems.npz`` holds scenario problems (``x0``, 150 latent-force scenarios,
the warm start the closed loop gave) met by the scenario agent in paper episodes, several of
which need slack (a latent force beyond the braking authority). See
``data/make_recorded_problems.py`` for how they were chosen.

The problem is not convex, so "the same solution" is checked both ways: started at the
textbook's solution, the fast SQP stays there (and its extra starts only ever go lower);
and the fast solver's own plan is a local optimum of the full problem (no nearby point is
lower). Which local optimum each solver finds from a warm start is a quality figure of the
benchmark (``lfm-benchmark``), not asserted here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controllers import problem as mpc_problem
from controllers.solvers.fast import FastScenarioSolver
from controllers.solvers.ipopt import IpoptScenarioSolver
from experiments import benchmark

DATA = dict(np.load(Path(__file__).resolve().parents[1] / "data" / "recorded_problems.npz"))
IDS = [f"seed{s}-step{k}" for s, k in zip(DATA["seed"], DATA["step"], strict=True)]
RTOL = 1e-4  # objective agreement (the benchmark's target)
VIOLATION_TOL = 1e-6  # [m or m/s] where the solution needs no slack


@pytest.fixture(scope="module")
def problem() -> mpc_problem.ScenarioProblem:
    return benchmark.problem_from_config(benchmark.DEFAULT_CONFIG, n_scenarios=150)


@pytest.fixture(scope="module")
def textbook(problem: mpc_problem.ScenarioProblem) -> IpoptScenarioSolver:
    return IpoptScenarioSolver(problem, formulation="multiple_shooting")


def _slack_and_violation(problem, x0, W, u) -> tuple[float, float]:
    X = mpc_problem.rollout(problem, x0, W, u)
    slack = float(np.sum(mpc_problem.minimal_slack(problem, X)))
    return slack, mpc_problem.constraint_violation(problem, X)


def test_the_recorded_set_covers_slack_and_the_goal() -> None:
    assert DATA["W"].shape[1:] == (150, 7)
    assert np.sum(DATA["slack"] > 0.1) >= 3  # problems that need slack
    assert np.sum(DATA["slack"] <= 1e-6) >= 8  # and problems that do not


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_fast_solver_stays_at_the_textbook_solution(i, problem, textbook) -> None:
    x0, W, guess = DATA["x0"][i], DATA["W"][i], DATA["u_guess"][i]
    textbook.reset()
    ref = textbook.solve(x0, W, u_guess=guess)
    assert ref.success, ref.status
    ref_objective = mpc_problem.objective(problem, x0, W, ref.u)
    ref_slack, _ = _slack_and_violation(problem, x0, W, ref.u)
    # Plain SQP (no extra starts) from the full problem's solution: the same point.
    plain = FastScenarioSolver(problem, restarts=()).solve(x0, W, u_guess=ref.u)
    assert plain.success, plain.status
    assert plain.objective == pytest.approx(ref_objective, rel=RTOL)
    _, violation = _slack_and_violation(problem, x0, W, plain.u)
    if ref_slack <= VIOLATION_TOL:
        assert violation <= VIOLATION_TOL
    # With its extra starts it may move to a lower optimum, never to a higher one.
    best = FastScenarioSolver(problem).solve(x0, W, u_guess=ref.u)
    assert best.objective <= ref_objective * (1 + RTOL)


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_fast_plan_is_a_local_optimum_of_the_full_problem(i, problem) -> None:
    """No point next to the fast plan has a lower full-problem objective.

    The full problem's objective (``mpc_problem.objective``: every scenario, every
    constraint, the exact slack penalty) is probed along every input coordinate in both
    directions and along random directions, at two radii, clipped to the input box. This
    certificate is independent of the solver's own derivatives. (IPOPT is no such check:
    its barrier first pushes a warm start off the active input bounds, and from there it
    may settle in another local optimum, higher or lower.)
    """
    x0, W, guess = DATA["x0"][i], DATA["W"][i], DATA["u_guess"][i]
    fast = FastScenarioSolver(problem).solve(x0, W, u_guess=guess)
    assert fast.success, fast.status
    J = mpc_problem.objective(problem, x0, W, fast.u)
    assert fast.objective == pytest.approx(J, rel=1e-9)
    worst = mpc_problem.largest_local_descent(problem, x0, W, fast.u, seed=i)
    assert worst >= -1e-9 * abs(J), worst
    slack, violation = _slack_and_violation(problem, x0, W, fast.u)
    if slack <= VIOLATION_TOL:
        assert violation <= VIOLATION_TOL


def test_extra_starts_only_ever_lower_the_objective(problem) -> None:
    kept = 0
    for i in range(len(IDS)):
        x0, W, guess = DATA["x0"][i], DATA["W"][i], DATA["u_guess"][i]
        plain = FastScenarioSolver(problem, restarts=()).solve(x0, W, u_guess=guess)
        best = FastScenarioSolver(problem).solve(x0, W, u_guess=guess)
        assert best.objective <= plain.objective * (1 + 1e-12), IDS[i]
        if "kept" in best.extra["restarts"].values():
            kept += best.objective < plain.objective * (1 - 1e-3)
    # On this set the extra starts matter: some problem ends clearly lower with them.
    assert kept >= 1
