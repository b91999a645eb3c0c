"""The solvers side by side (``experiments.benchmark.solvers``): registry names only, failures
classified, worse problems listed, a record's figures recomputed from its plan."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.solvers import SOLVERS, make_solver
from experiments.benchmark import failures as benchmark_failures
from experiments.benchmark import problems as benchmark_problems
from experiments.benchmark import solvers as benchmark_solvers
from experiments.cli import benchmark as benchmark_cli


def test_failures_are_classified_by_kind() -> None:
    kinds = {
        "QP_Failed": "QP_Failed",
        "Maximum_Iterations_Exceeded": "Maximum_Iterations_Exceeded",
        "Maximum_WallTime_Exceeded": "wall_time",
        "Infeasible_Problem_Detected": "infeasible",
        "raised RuntimeError: boom": "exception",
        "Line_Search_Failed": "other",
    }
    for status, kind in kinds.items():
        assert benchmark_failures.classify_failure(status) == kind
    records = {
        "a": [
            {"seed": 2, "step": 0, "success": True, "status": "Solve_Succeeded"},
            {"seed": 2, "step": 1, "success": False, "status": "QP_Failed"},
        ]
    }
    assert benchmark_failures.failures_of(records, "part", 15, 150) == [
        {
            "part": "part",
            "solver": "a",
            "seed": 2,
            "step": 1,
            "N": 15,
            "Ns": 150,
            "kind": "QP_Failed",
            "status": "QP_Failed",
        }
    ]


def test_worse_problems_lists_gaps_above_the_tolerance_and_crashes() -> None:
    def rec(step: int, objective: float, success: bool = True) -> dict:
        return {"seed": 0, "step": step, "objective": objective, "success": success}

    reference = [rec(0, 100.0), rec(1, 100.0), rec(2, 100.0), rec(3, 100.0, success=False)]
    records = [rec(0, 100.005), rec(1, 100.02, success=False), rec(2, math.nan), rec(3, 200.0)]
    worse = benchmark_solvers.worse_problems(records, reference)
    # 5e-5 is within 1e-4; a failed solve still counts; a crash (NaN) is listed; the
    # problem the reference did not solve is not compared.
    assert [w["step"] for w in worse] == [1, 2]
    assert worse[0]["rel_gap"] == pytest.approx(2e-4)
    assert math.isnan(worse[1]["rel_gap"])


@pytest.mark.parametrize("name", ["gurobi", "textbook", "ipopt_condensed"])
def test_only_the_registry_names_are_accepted(name: str) -> None:
    problem = benchmark_problems.problem_from_config(n_scenarios=2)
    with pytest.raises(ValueError, match="unknown solver"):
        benchmark_solvers.build_solver(name, problem)
    with pytest.raises(ValueError, match="unknown solver"):
        benchmark_solvers.time_solvers([], [name], problem=problem)
    with pytest.raises(SystemExit):
        benchmark_cli.build_parser().parse_args(["--skip", name])
    assert name not in SOLVERS


def test_an_unavailable_solver_is_reported_with_its_reason() -> None:
    problem = benchmark_problems.problem_from_config(n_scenarios=2)
    solver, build_time, reason = benchmark_solvers.build_solver("fast", problem, no_such_option=1)
    assert solver is None and math.isnan(build_time)
    assert "no_such_option" in reason


def _small_problem(n_scenarios: int = 5, seed: int = 0):
    cfg = benchmark_problems.experiment_config()
    problem = cfg.make_problem(n_scenarios=n_scenarios)
    model = problem.model
    rng = np.random.default_rng(seed)
    z0 = np.tile(rng.standard_normal(model.latent_dim), (n_scenarios, 1))
    W = model.sample_latent_forecasts(z0, problem.horizon, rng)
    x0, _ = benchmark_problems.env_start(cfg, seed=0)
    return problem, x0, W


def test_restart_check_resolves_from_the_reference_solution() -> None:
    problem, x0, W = _small_problem()
    solver = make_solver(problem, "ipopt")
    reference = benchmark_solvers.solve_record(solver, problem, x0, W)
    assert reference["success"]
    # A record as if the solver had settled in a worse point: the gap exceeds GAP_TOL.
    worse = {**reference, "objective": reference["objective"] * 1.01}
    records = {"ipopt": [worse], "reference": [reference]}
    summary: dict = {"ipopt": {}, "reference": {}}
    benchmark_solvers.restart_check(
        {"ipopt": solver}, problem, [(0, 0, x0, W)], records, "reference", summary
    )
    assert summary["ipopt"]["n_restarted"] == 1
    assert summary["ipopt"]["restart_rel_gap_abs_max"] < 1e-6
    assert records["ipopt"][0]["restart_from_reference"]["success"]


def test_solve_record_recomputes_the_figures_from_the_plan() -> None:
    problem, x0, W = _small_problem(seed=1)
    rec = benchmark_solvers.solve_record(make_solver(problem, "fast"), problem, x0, W)
    u = np.asarray(rec["u"])
    assert u.shape == (problem.horizon, problem.nu)
    assert rec["objective"] == problem.objective(x0, W, u)
    X = problem.rollout(x0, W, u)
    assert rec["slack"] == pytest.approx(float(np.sum(problem.minimal_slack(X))))
    assert rec["max_violation"] == problem.constraint_violation(X)
