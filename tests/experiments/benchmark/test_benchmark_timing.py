"""Tests of the solver timing harness (``experiments.benchmark.timing``); no timing is asserted."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.solvers import make_solver
from experiments.benchmark import timing as solver_timing
from experiments.benchmark.problems import env_start, experiment_config


@pytest.fixture(scope="module")
def small_problem():
    return experiment_config().make_problem(n_scenarios=8)


def test_latent_force_scenarios_start_and_walk() -> None:
    rng = np.random.default_rng(0)
    W = solver_timing.latent_force_scenarios(rng, 5, 7, mean=1.5, spread=0.0, walk_std=0.0)
    assert W.shape == (5, 7)
    np.testing.assert_array_equal(W, 1.5)  # no spread and no walk: the mean throughout
    W = solver_timing.latent_force_scenarios(
        np.random.default_rng(1), 4000, 3, mean=[1.0, -2.0], spread=0.5, walk_std=0.2, n_forces=2
    )
    assert W.shape == (4000, 3, 2)
    np.testing.assert_allclose(W[:, 0].mean(axis=0), [1.0, -2.0], atol=0.05)
    np.testing.assert_allclose(W[:, 0].std(axis=0), 0.5, rtol=0.05)
    np.testing.assert_allclose(np.diff(W, axis=1).std(axis=(0, 1)), 0.2, rtol=0.05)


def test_force_std_is_the_stationary_std_of_the_force(small_problem) -> None:
    # The paper's force: a Matern 5/2 GP of variance 4 (m/s^2)^2.
    np.testing.assert_allclose(solver_timing.force_std(small_problem), [2.0], rtol=1e-9)


@pytest.mark.parametrize("redraw", [False, True])
def test_closed_loop_problems_follow_the_plant(small_problem, redraw: bool) -> None:
    problem = small_problem
    x_start, _ = env_start(seed=0)
    solver = make_solver(problem, "fast")
    problems = solver_timing.closed_loop_problems(
        problem, solver, x_start, n_steps=3, seed=2, spread=0.5, walk_std=0.1, redraw=redraw
    )
    assert len(problems) == 3
    np.testing.assert_array_equal(problems[0][0], x_start)
    # Replaying the loop: every next state is the model's step under the plan's first input.
    replay = make_solver(problem, "fast")
    for (x0, W), (x1, W1) in zip(problems[:-1], problems[1:], strict=True):
        assert W.shape == (problem.n_scenarios, problem.horizon, problem.nw)
        u0 = replay.solve(x0, W).u[0]
        if not redraw:  # the plant feels scenario 0, and W moves on by one step
            np.testing.assert_allclose(x1, problem.model.physical_step(x0, u0, W[0, 0]))
            np.testing.assert_array_equal(W1[:, :-1], W[:, 1:])
        else:
            assert not np.allclose(x1, x0)
    with pytest.raises(ValueError, match="x_start"):
        solver_timing.closed_loop_problems(problem, solver, [0.0, 1.0], n_steps=1)


def test_time_solvers_records_every_solve(small_problem) -> None:
    problem = small_problem
    x_start, _ = env_start(seed=0)
    sequences = [
        solver_timing.closed_loop_problems(
            problem, make_solver(problem, "fast"), x_start, n_steps=2, seed=s, spread=0.5
        )
        for s in (0, 1)
    ]
    results = solver_timing.time_solvers(
        {name: (lambda name=name: make_solver(problem, name)) for name in ("fast", "ipopt")},
        sequences,
    )
    assert list(results) == ["fast", "ipopt"]
    for timing in results.values():
        s = timing.summary()
        assert s["solves"] == 4 and s["failures"] == 0
        assert s["max_ms"] >= s["p95_ms"] >= s["median_ms"] > 0
    agreement = solver_timing.objective_agreement(results["fast"], results["ipopt"])
    assert agreement["compared"] == 4
    assert agreement["within_rtol"] + agreement["better"] + agreement["worse"] == 4
    table = solver_timing.format_timing_table(results, baseline="fast")
    assert "fast" in table and "ipopt" in table


def test_objective_agreement_on_given_records() -> None:
    a = solver_timing.SolverTiming(
        "a", objective=[1.0, 2.0, 3.0, 4.0], success=[True, True, True, False]
    )
    b = solver_timing.SolverTiming("b", objective=[1.0, 2.1, 2.9, 1.0], success=[True] * 4)
    agreement = solver_timing.objective_agreement(a, b)
    assert agreement == {"compared": 3.0, "within_rtol": 1.0, "better": 1.0, "worse": 1.0}


def test_default_benchmark_uses_registry_names() -> None:
    with pytest.raises(ValueError, match="recipe="):
        solver_timing.default_benchmark(recipe="textbook")
    out = solver_timing.default_benchmark(
        n_scenarios=(4,), seeds=(0,), solvers=("fast", "ipopt"), recipe="shift"
    )
    assert list(out) == [4]
    assert list(out[4]) == ["fast", "ipopt"]
    assert out[4]["fast"].summary()["solves"] == solver_timing.RECIPES["shift"]["n_steps"]
