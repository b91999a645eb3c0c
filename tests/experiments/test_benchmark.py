"""Tests of the benchmark (``experiments.benchmark`` and its ``bench_*`` modules).

A quick run (``--quick``) checks that every part runs and that its JSON and Markdown are
complete; the verdicts are checked on given numbers. No timing is asserted (speed is a
printed figure, see ``lfm-benchmark``).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from controllers.solvers import SOLVERS, make_solver
from experiments import bench_problems, bench_report, bench_solvers, benchmark

TIMING_KEYS = ("solve_ms_median", "solve_ms_p95", "solve_ms_max", "wall_ms_median")
QUICK_SOLVERS = ("fast", "fast_bicycle", "ipopt")  # the textbook and csnlp are slow


def _finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str]:
    out = tmp_path_factory.mktemp("bench") / "b.json"
    skips = [a for s in SOLVERS if s not in QUICK_SOLVERS for a in ("--skip", s)]
    code = benchmark.main(["--quick", "--out", str(out), "--no-progress", *skips])
    assert code == 0
    return json.loads(out.read_text()), str(out)


# --------------------------------------------------------------------------- the quick run


def test_quick_run_writes_complete_json(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    for key in ("meta", "closed_loop", "sweep", "particle_filter", "episode", "targets"):
        assert key in data
    closed = data["closed_loop"]
    assert set(closed["solvers"]) == set(QUICK_SOLVERS)
    assert closed["n_problems"] == len(closed["problems"]) > 0
    # Without the textbook, IPOPT on the condensed NLP is the objective reference.
    assert closed["reference"] == "ipopt"
    for name, info in closed["solvers"].items():
        assert info["available"], (name, info["reason"])
        summary = closed["summary"][name]
        for key in TIMING_KEYS:
            assert _finite(summary[key]) and summary[key] > 0, (name, key)
        assert summary["n_problems"] == closed["n_problems"]
        assert len(closed["records"][name]) == closed["n_problems"]
        # Objective gaps are computed wherever both solvers succeed.
        if summary["n_success"] and closed["summary"]["ipopt"]["n_success"]:
            assert summary["n_compared"] > 0
            assert summary["rel_gap_abs_max"] >= summary["rel_gap_abs_median"] >= 0
        assert summary["n_reference_ok"] == closed["summary"]["ipopt"]["n_success"]
    assert closed["summary"]["ipopt"]["rel_gap_abs_max"] == 0.0
    assert closed["summary"]["ipopt"]["worse_than_reference"] == []
    # Times are of warm-started solves; each closed loop's first (cold) solve is apart.
    n_loops = len({p["seed"] for p in closed["problems"]})
    for name in closed["summary"]:
        assert closed["summary"][name]["n_cold"] == n_loops
        assert _finite(closed["summary"][name]["cold_solve_ms_max"])
    # The fast solvers' closed loop again, alone: same problems, the same plans.
    assert set(closed["alone"]) == {"fast", "fast_bicycle"}
    for alone in closed["alone"].values():
        assert alone["n_problems"] == closed["n_problems"]
        assert alone["plan_difference_max"] <= 1e-6
        assert _finite(alone["solve_ms_p95"]) and alone["solve_ms_p95"] > 0
    assert _finite(closed["speedup"]["ipopt"]["median_ratio"])
    assert _finite(closed["speedup"]["fast_bicycle"]["median_ratio"])

    for row in data["sweep"]["results"]:
        assert set(row["summary"]) == {"fast", "fast_bicycle", "ipopt"}
        for name, summary in row["summary"].items():
            assert _finite(summary["solve_ms_median"]), (row["n_scenarios"], name)
    for row in data["particle_filter"]["results"]:
        assert _finite(row["step_ms_median"]) and _finite(row["update_ms_median"])
        assert row["step_ms_median"] >= row["update_ms_median"] > 0
    episode = data["episode"]
    assert episode["steps"] > 0 and _finite(episode["episode_s"])


def test_targets_of_the_run_follow_from_its_figures(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    targets = data["targets"]
    assert len(targets) >= 11
    for t in targets:
        assert t["passed"] in (True, False, None)
        if t["passed"] is not None:
            op = {"<=": np.less_equal, ">=": np.greater_equal, ">": np.greater}[t["op"]]
            assert bool(op(t["value"], t["threshold"])) == t["passed"], t["target"]
    # The generic / hand-written ratio is the run's two medians.
    summary = data["closed_loop"]["summary"]
    generic = next(t for t in targets if t["target"].startswith("generic fast / fast_bicycle"))
    ratio = summary["fast"]["solve_ms_median"] / summary["fast_bicycle"]["solve_ms_median"]
    assert generic["value"] == pytest.approx(ratio)
    # The textbook and csnlp were skipped, and the quick sweep has no Ns = 1000.
    skipped = [t["target"] for t in targets if t["passed"] is None]
    assert any(t.startswith("textbook") for t in skipped)
    assert any(t.startswith("problems where fast ends") for t in skipped)
    assert any("csnlp" in t for t in skipped)
    assert any("1000" in t for t in skipped)


def test_json_is_strict_and_the_markdown_has_the_speed_table(quick_run) -> None:
    data, path = quick_run
    text = open(path).read()
    # NaN and Infinity are not JSON; the writer must have turned them into null.
    assert "NaN" not in text and "Infinity" not in text
    markdown = open(path.removesuffix(".json") + ".md").read()
    for name in QUICK_SOLVERS:
        assert f"| {name} |" in markdown
    assert "generic fast / fast_bicycle:" in markdown
    assert markdown.count("- PASS") + markdown.count("- FAIL") + markdown.count("- SKIP") == len(
        data["targets"]
    )


def test_report_shows_the_speed_table_and_every_target(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    report = benchmark.format_report(data)
    assert report.startswith("Speed (N = 7, Ns = 150")
    for name in QUICK_SOLVERS:
        assert f"\n{name} " in report
    for t in data["targets"]:
        assert t["target"] in report


# --------------------------------------------------------------------------- verdicts


def _verdicts(targets: list[dict]) -> list[bool | None]:
    return [t["passed"] for t in targets]


def test_speed_targets_are_judged_from_the_given_figures() -> None:
    worse = [{"seed": 1, "step": 7, "rel_gap": 3e-4}]
    # generic 1.2x hand-written, textbook 40x fast, 30 ms at Ns=1000, 1 of 50 problems (2%).
    targets = bench_report.speed_targets(6.0, 5.0, 240.0, 30.0, worse, 50)
    assert [t["value"] for t in targets] == pytest.approx([1.2, 40.0, 30.0, 2.0])
    assert _verdicts(targets) == [True, True, True, True]
    assert "seed 1 step 7 (+3.0e-04)" in targets[3]["note"]
    # The limits themselves pass; just past them fails.
    at_limits = bench_report.speed_targets(7.5, 5.0, 225.0, 50.0, [], 10)
    assert _verdicts(at_limits) == [True, True, True, True]
    failing = bench_report.speed_targets(8.0, 5.0, 200.0, 50.5, worse * 2, 50)
    assert _verdicts(failing) == [False, False, False, False]
    assert [t["value"] for t in failing] == pytest.approx([1.6, 25.0, 50.5, 4.0])


def test_speed_targets_skip_what_was_not_measured() -> None:
    targets = bench_report.speed_targets(6.0, None, math.nan, None, None, None)
    assert _verdicts(targets) == [None, None, None, None]
    assert "not run" in targets[3]["note"]
    # No problem compared: no share, even with an empty list.
    assert bench_report.speed_targets(6.0, 5.0, 240.0, 30.0, [], 0)[3]["passed"] is None


def test_target_rejects_an_unknown_comparison() -> None:
    assert bench_report.target("x", 1.0, 1.0, ">")["passed"] is False
    with pytest.raises(ValueError, match="op="):
        bench_report.target("x", 1.0, 1.0, "<")


def test_worse_problems_lists_gaps_above_the_tolerance_and_crashes() -> None:
    def rec(step: int, objective: float, success: bool = True) -> dict:
        return {"seed": 0, "step": step, "objective": objective, "success": success}

    reference = [rec(0, 100.0), rec(1, 100.0), rec(2, 100.0), rec(3, 100.0, success=False)]
    records = [rec(0, 100.005), rec(1, 100.02, success=False), rec(2, math.nan), rec(3, 200.0)]
    worse = bench_solvers.worse_problems(records, reference)
    # 5e-5 is within 1e-4; a failed solve still counts; a crash (NaN) is listed; the
    # problem the reference did not solve is not compared.
    assert [w["step"] for w in worse] == [1, 2]
    assert worse[0]["rel_gap"] == pytest.approx(2e-4)
    assert math.isnan(worse[1]["rel_gap"])


# --------------------------------------------------------------------------- parts


def test_parse_seeds() -> None:
    assert benchmark.parse_seeds("0:3") == [0, 1, 2]
    assert benchmark.parse_seeds("5") == [5]
    assert benchmark.parse_seeds("1,4,1,0:2") == [1, 4, 0]
    for bad in ("", "3:1", "-1", "a"):
        with pytest.raises(ValueError, match="seeds="):
            benchmark.parse_seeds(bad)


@pytest.mark.parametrize("name", ["gurobi", "textbook", "ipopt_condensed"])
def test_only_the_registry_names_are_accepted(name: str) -> None:
    problem = bench_problems.problem_from_config(n_scenarios=2)
    with pytest.raises(ValueError, match="unknown solver"):
        bench_solvers.build_solver(name, problem)
    with pytest.raises(ValueError, match="unknown solver"):
        bench_solvers.time_solvers([], [name], problem=problem)
    with pytest.raises(SystemExit):
        benchmark.build_parser().parse_args(["--skip", name])


def test_an_unavailable_solver_is_reported_with_its_reason() -> None:
    problem = bench_problems.problem_from_config(n_scenarios=2)
    solver, build_time, reason = bench_solvers.build_solver("fast", problem, no_such_option=1)
    assert solver is None and math.isnan(build_time)
    assert "no_such_option" in reason


def test_recording_keeps_the_agents_problems_and_estimates() -> None:
    cfg = bench_problems.experiment_config()
    problem = cfg.make_problem()
    problems, anchors = bench_problems.record_closed_loop(cfg, seeds=[3], max_steps=2)
    assert [(p.seed, p.step) for p in problems] == [(3, 0), (3, 1)]
    assert [(a.seed, a.step) for a in anchors] == [(3, 0), (3, 1)]
    for p, a in zip(problems, anchors, strict=True):
        x0, W = problem.check_data(p.x0, p.W)  # the agent's problem size
        assert np.array_equal(x0[0], a.x0)  # the scenarios start from the estimate
        assert a.z.shape == (problem.model.latent_dim,)
    # Draws of another size around the anchors, as the agent draws them.
    small = cfg.make_problem(n_scenarios=5)
    draws = bench_problems.scenario_draws(small, anchors, np.random.default_rng(0))
    assert [d.W.shape for d in draws] == [(5, small.horizon, small.nw)] * 2
    assert np.allclose(draws[0].W[:, 0], small.model.latent_force(anchors[0].z))


def _small_problem(n_scenarios: int = 5, seed: int = 0):
    cfg = bench_problems.experiment_config()
    problem = cfg.make_problem(n_scenarios=n_scenarios)
    model = problem.model
    rng = np.random.default_rng(seed)
    z0 = np.tile(rng.standard_normal(model.latent_dim), (n_scenarios, 1))
    W = model.sample_latent_forecasts(z0, problem.horizon, rng)
    x0, _ = bench_problems.env_start(cfg, seed=0)
    return problem, x0, W


def test_restart_check_resolves_from_the_reference_solution() -> None:
    problem, x0, W = _small_problem()
    solver = make_solver(problem, "ipopt")
    reference = bench_solvers.solve_record(solver, problem, x0, W)
    assert reference["success"]
    # A record as if the solver had settled in a worse point: the gap exceeds GAP_TOL.
    worse = {**reference, "objective": reference["objective"] * 1.01}
    records = {"ipopt": [worse], "reference": [reference]}
    summary: dict = {"ipopt": {}, "reference": {}}
    bench_solvers.restart_check(
        {"ipopt": solver}, problem, [(0, 0, x0, W)], records, "reference", summary
    )
    assert summary["ipopt"]["n_restarted"] == 1
    assert summary["ipopt"]["restart_rel_gap_abs_max"] < 1e-6
    assert records["ipopt"][0]["restart_from_reference"]["success"]


def test_solve_record_recomputes_the_figures_from_the_plan() -> None:
    problem, x0, W = _small_problem(seed=1)
    rec = bench_solvers.solve_record(make_solver(problem, "fast"), problem, x0, W)
    u = np.asarray(rec["u"])
    assert u.shape == (problem.horizon, problem.nu)
    assert rec["objective"] == problem.objective(x0, W, u)
    X = problem.rollout(x0, W, u)
    assert rec["slack"] == pytest.approx(float(np.sum(problem.minimal_slack(X))))
    assert rec["max_violation"] == problem.constraint_violation(X)
