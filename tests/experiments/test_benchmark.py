"""Smoke tests of the benchmark: it runs, its JSON is complete, its comparisons are computed.

No timing is asserted here (speed is a printed figure, see ``lfm-benchmark``); these tests
only check that the figures exist, are finite and are consistent.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from controllers.solvers.ipopt import IpoptScenarioSolver
from experiments import benchmark
from lfm_env.config import load_env_config
from lfm_env.model import LatentForceModel

TIMING_KEYS = ("solve_ms_median", "solve_ms_p95", "solve_ms_max", "wall_ms_median")


def _finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str]:
    out = tmp_path_factory.mktemp("bench") / "b.json"
    code = benchmark.main(
        ["--quick", "--out", str(out), "--skip-textbook", "--skip-csnlp", "--no-progress"]
    )
    assert code == 0
    return json.loads(out.read_text()), str(out)


def test_quick_run_writes_complete_json(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    for key in ("meta", "closed_loop", "sweep", "particle_filter", "episode", "targets"):
        assert key in data
    closed = data["closed_loop"]
    assert set(closed["solvers"]) == {"fast", "ipopt_condensed"}
    assert closed["n_problems"] == len(closed["problems"]) > 0
    # Without the textbook solver the condensed IPOPT is the objective reference.
    assert closed["reference"] == "ipopt_condensed"
    for name, info in closed["solvers"].items():
        if not info["available"]:
            assert info["reason"]
            continue
        summary = closed["summary"][name]
        for key in TIMING_KEYS:
            assert _finite(summary[key]) and summary[key] > 0, (name, key)
        assert summary["n_problems"] == closed["n_problems"]
        assert len(closed["records"][name]) == closed["n_problems"]
        # Objective gaps are computed wherever both solvers succeed.
        if summary["n_success"] and closed["summary"]["ipopt_condensed"]["n_success"]:
            assert summary["n_compared"] > 0
            assert _finite(summary["rel_gap_abs_max"])
            assert summary["rel_gap_abs_max"] >= summary["rel_gap_abs_median"] >= 0
    assert closed["summary"]["ipopt_condensed"]["rel_gap_abs_max"] == 0.0
    # Times are of warm-started solves; each closed loop's first (cold) solve is apart.
    n_loops = len({p["seed"] for p in closed["problems"]})
    for name in closed["summary"]:
        assert closed["summary"][name]["n_cold"] == n_loops
        assert _finite(closed["summary"][name]["cold_solve_ms_max"])
    # The fast solver's closed loop again, alone: same problems, the same plans.
    alone = closed["fast_alone"]
    assert alone["n_problems"] == closed["n_problems"]
    assert alone["plan_difference_max"] <= 1e-6
    assert _finite(alone["solve_ms_p95"]) and alone["solve_ms_p95"] > 0
    if closed["solvers"]["fast"]["available"]:
        assert _finite(closed["speedup"]["ipopt_condensed"]["median_ratio"])

    for row in data["sweep"]["results"]:
        for name, summary in row["summary"].items():
            assert _finite(summary["solve_ms_median"]), (row["n_scenarios"], name)
    for row in data["particle_filter"]["results"]:
        assert _finite(row["step_ms_median"]) and _finite(row["update_ms_median"])
        assert row["step_ms_median"] >= row["update_ms_median"] > 0
    episode = data["episode"]
    assert episode["steps"] > 0 and _finite(episode["episode_s"])


def test_targets_are_judged_from_measurements(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    targets = data["targets"]
    assert len(targets) >= 9
    for t in targets:
        assert t["passed"] in (True, False, None)
        if t["passed"] is not None:
            op = {"<=": np.less_equal, ">=": np.greater_equal, ">": np.greater}[t["op"]]
            assert bool(op(t["value"], t["threshold"])) == t["passed"], t["target"]
    # Textbook and csnlp were skipped, and the quick sweep has no Ns = 1000.
    skipped = [t for t in targets if t["passed"] is None]
    assert any("textbook" in t["target"] for t in skipped)
    assert any("csnlp" in t["target"] for t in skipped)
    assert any("1000" in t["target"] for t in skipped)


def test_json_is_strict(quick_run: tuple[dict, str]) -> None:
    _, path = quick_run
    text = open(path).read()
    # NaN and Infinity are not JSON; the writer must have turned them into null.
    assert "NaN" not in text and "Infinity" not in text


def test_report_names_every_target(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    report = benchmark.format_report(data)
    for t in data["targets"]:
        assert t["target"] in report
    assert report.count("PASS") + report.count("FAIL") + report.count("SKIP") >= len(
        data["targets"]
    )


def test_parse_seeds() -> None:
    assert benchmark.parse_seeds("0:3") == [0, 1, 2]
    assert benchmark.parse_seeds("5") == [5]
    assert benchmark.parse_seeds("1,4,1,0:2") == [1, 4, 0]
    for bad in ("", "3:1", "-1", "a"):
        with pytest.raises(ValueError, match="seeds="):
            benchmark.parse_seeds(bad)


def test_unknown_solver_is_rejected() -> None:
    problem = benchmark.problem_from_config(n_scenarios=2)
    with pytest.raises(ValueError, match="unknown solver"):
        benchmark.build_solver("gurobi", problem)


def _small_problem(n_scenarios: int = 5, seed: int = 0):
    problem = benchmark.problem_from_config(n_scenarios=n_scenarios)
    env_config = load_env_config(benchmark._config_path(benchmark.DEFAULT_CONFIG))
    model = LatentForceModel(env_config)
    rng = np.random.default_rng(seed)
    z0 = np.tile(rng.standard_normal(model.latent_dim), (n_scenarios, 1))
    W = model.sample_latent_forecasts(z0, problem.horizon, rng)
    return problem, env_config.initial_state_rad, W


def test_csnlp_adapter_matches_ipopt_condensed() -> None:
    pytest.importorskip("csnlp")
    problem, x0, W = _small_problem()
    reference = IpoptScenarioSolver(problem, formulation="condensed").solve(x0, W)
    solver = benchmark.CsnlpScenarioSolver(problem)
    sol = solver.solve(x0, W)
    assert reference.success and sol.success
    assert sol.u.shape == (problem.horizon, 2)
    assert sol.objective == pytest.approx(reference.objective, rel=1e-5)
    # csnlp's own objective is the same exact-penalty function at its optimum.
    assert sol.extra["csnlp_objective"] == pytest.approx(sol.objective, rel=1e-6)
    # A warm-started second solve of the same problem stays at the optimum.
    again = solver.solve(x0, W)
    assert again.objective == pytest.approx(reference.objective, rel=1e-5)


def test_csnlp_adapter_rejects_per_scenario_initial_states() -> None:
    pytest.importorskip("csnlp")
    problem, x0, W = _small_problem(n_scenarios=2)
    x0s = np.stack([x0, x0 + 0.1])
    with pytest.raises(ValueError, match="one initial state"):
        benchmark.CsnlpScenarioSolver(problem).solve(x0s, W)


def test_restart_check_resolves_from_the_reference_solution() -> None:
    problem, x0, W = _small_problem()
    solver = IpoptScenarioSolver(problem, formulation="condensed")
    reference = benchmark._solve_record(solver, problem, x0, W)
    assert reference["success"]
    # A record as if the solver had settled in a worse point: the gap exceeds GAP_TOL.
    worse = {**reference, "objective": reference["objective"] * 1.01}
    records = {"ipopt_condensed": [worse], "reference": [reference]}
    summary: dict = {"ipopt_condensed": {}, "reference": {}}
    benchmark._restart_check(
        {"ipopt_condensed": solver}, problem, [(0, 0, x0, W)], records, "reference", summary
    )
    assert summary["ipopt_condensed"]["n_restarted"] == 1
    assert summary["ipopt_condensed"]["restart_rel_gap_abs_max"] < 1e-6
    assert records["ipopt_condensed"][0]["restart_from_reference"]["success"]
