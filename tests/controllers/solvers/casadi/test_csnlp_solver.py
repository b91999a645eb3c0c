"""Tests of the csnlp formulation of the scenario problem (the optional ``bench`` extra).

Its generic use on a second system is covered by ``test_second_system.py``; here it is
checked on the paper's problem against IPOPT's textbook formulation.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from controllers.config import load_config
from controllers.problem import ScenarioProblem
from controllers.solvers import make_solver

pytest.importorskip("csnlp")

from controllers.solvers.casadi.csnlp import SHOOTINGS, CsnlpScenarioSolver  # noqa: E402

N, NS = 5, 15
MID_TRACK = np.array([20.0, 3.0 * np.sin(4.0), 5.0, 0.1])  # [m, m, m/s, rad]


@pytest.fixture(scope="module")
def problem() -> ScenarioProblem:
    return load_config().make_problem(n_scenarios=NS, horizon=N)


@pytest.fixture(scope="module")
def reference(problem: ScenarioProblem):
    return make_solver(problem, "ipopt_multiple_shooting", ipopt_options={"tol": 1e-10})


@pytest.fixture(scope="module")
def solvers(problem: ScenarioProblem) -> dict[str, CsnlpScenarioSolver]:
    return {
        shooting: make_solver(problem, "csnlp", shooting=shooting, ipopt_options={"tol": 1e-10})
        for shooting in SHOOTINGS
    }


@pytest.mark.parametrize("shooting", SHOOTINGS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_ipopt_multiple_shooting(
    problem: ScenarioProblem, reference, solvers: dict, shooting: str, seed: int
) -> None:
    # Spread 3 m/s^2: large enough that some scenarios need slack.
    W = np.random.default_rng(seed).normal(0.0, 3.0, size=(NS, N))
    reference.reset()
    ref = reference.solve(MID_TRACK, W)
    solver = solvers[shooting]
    solver.reset()
    sol = solver.solve(MID_TRACK, W)
    assert sol.success and ref.success, (sol.status, ref.status)
    assert sol.objective == pytest.approx(ref.objective, rel=1e-6)
    assert sol.objective == problem.objective(MID_TRACK, W, sol.u)
    # csnlp's own objective is the same exact-penalty function at its optimum.
    assert sol.extra["csnlp_objective"] == pytest.approx(sol.objective, rel=1e-6)
    np.testing.assert_allclose(sol.predicted, problem.rollout(MID_TRACK, W, sol.u))
    assert np.all(sol.u >= problem.input_lower) and np.all(sol.u <= problem.input_upper)


def test_warm_start_from_the_previous_plan(problem: ScenarioProblem, solvers: dict) -> None:
    solver = solvers["multi"]
    W = np.random.default_rng(2).normal(0.0, 1.0, size=(NS, N))
    solver.reset()
    cold = solver.solve(MID_TRACK, W)
    assert cold.success
    # Started at its own optimum, IPOPT needs fewer iterations (primal warm start only).
    again = solver.solve(MID_TRACK, W, u_guess=cold.u)
    assert again.success and again.iterations < cold.iterations
    assert again.objective == pytest.approx(cold.objective, rel=1e-8)
    solver.reset()
    fresh = solver.solve(MID_TRACK, W)
    assert fresh.iterations == cold.iterations
    np.testing.assert_array_equal(fresh.u, cold.u)


def test_rejects_bad_arguments(problem: ScenarioProblem, solvers: dict) -> None:
    solver = solvers["multi"]
    W = np.zeros((NS, N))
    x0s = np.tile(MID_TRACK, (NS, 1))
    x0s[3, 1] += 0.1
    with pytest.raises(ValueError, match="shares one initial state"):
        solver.solve(x0s, W)
    with pytest.raises(ValueError, match="W has shape"):
        solver.solve(MID_TRACK, np.zeros((NS, N + 1)))
    with pytest.raises(ValueError, match="u_guess"):
        solver.solve(MID_TRACK, W, u_guess=np.zeros((N + 1, 2)))
    with pytest.raises(ValueError, match="shooting"):
        CsnlpScenarioSolver(problem, shooting="collocation")


def test_equal_per_scenario_initial_states_are_accepted(
    problem: ScenarioProblem, solvers: dict
) -> None:
    solver = solvers["multi"]
    W = np.random.default_rng(3).normal(0.0, 1.0, size=(NS, N))
    solver.reset()
    shared = solver.solve(MID_TRACK, W)
    solver.reset()
    tiled = solver.solve(np.tile(MID_TRACK, (NS, 1)), W)
    np.testing.assert_array_equal(tiled.u, shared.u)


def test_missing_csnlp_says_how_to_install(
    problem: ScenarioProblem, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A None entry in sys.modules makes the import fail as if csnlp were not installed.
    monkeypatch.setitem(sys.modules, "csnlp", None)
    with pytest.raises(ImportError, match=r"pip install -e \.\[bench\]"):
        CsnlpScenarioSolver(problem)
