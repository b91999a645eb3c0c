"""The benchmark end to end (``experiments.benchmark.run``): a ``--quick`` run's JSON,
Markdown and printed report are complete, and its verdicts follow from its figures. No
timing is asserted (speed is a printed figure, see ``lfm-benchmark``)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from experiments.benchmark import checks as benchmark_checks
from experiments.benchmark import compiled as benchmark_compiled
from experiments.benchmark import failures as benchmark_failures
from experiments.benchmark import report as benchmark_report
from experiments.cli import benchmark as benchmark_cli

TIMING_KEYS = ("solve_ms_median", "solve_ms_p95", "solve_ms_max", "wall_ms_median")
# --quick's solvers: the compiled loop (fast_c) beside the Python loop (fast) and IPOPT, the
# objective reference (the textbook, sqpmethod's JIT build and csnlp are slow; sqpmethod's
# JIT is tested in tests/controllers/solvers/casadi/test_ipopt_solver.py).
QUICK_SOLVERS = ("fast", "fast_c", "ipopt")
# A threshold no run can meet: the quick run must still exit 0 (no --check) and say FAIL.
IMPOSSIBLE = "fast_median_ms=1e-9"


def _finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str]:
    out = tmp_path_factory.mktemp("bench") / "b.json"
    solvers = ",".join(QUICK_SOLVERS)
    argv = ["--quick", "--out", str(out), "--no-progress", "--solvers", solvers]
    code = benchmark_cli.benchmark_main([*argv, "--threshold", IMPOSSIBLE])
    assert code == 0  # a failing check without --check: exit 0, the verdict in the report
    return json.loads(out.read_text()), str(out)


def test_quick_run_writes_complete_json(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    for key in (
        "meta",
        "closed_loop",
        "horizons",
        "sweep",
        "first_solve",
        "particle_filter",
        "episode",
        "compiled",
        "failures",
        "checks",
    ):
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
    # The C library's build time of each solver, its solves timed like the others'.
    assert closed["solvers"]["fast_c"]["build_time_s"] > 0
    # The fast solver's closed loop again, alone: same problems, the same plans.
    assert set(closed["alone"]) == {"fast", "fast_c"}
    for alone in closed["alone"].values():
        assert alone["n_problems"] == closed["n_problems"]
        assert alone["plan_difference_max"] <= 1e-6
        assert _finite(alone["solve_ms_p95"]) and alone["solve_ms_p95"] > 0
    assert _finite(closed["speedup"]["ipopt"]["median_ratio"])

    rows = data["sweep"]["results"]
    for row in rows:
        # The C library on two threads at the sweep's largest Ns (here 50; from 500 on in full).
        extra = {"fast_2threads"} if row is rows[-1] else set()
        assert set(row["summary"]) == {"fast", "fast_c", "ipopt"} | extra
        for name, summary in row["summary"].items():
            assert _finite(summary["solve_ms_median"]), (row["n_scenarios"], name)
    threaded, fast = rows[-1]["summary"]["fast_2threads"], rows[-1]["summary"]["fast"]
    assert threaded["n_success"] == threaded["n_problems"] > 0
    # The same plans as fast to rounding, so the same largest gap to IPOPT's objectives.
    assert threaded["rel_gap_abs_max"] == pytest.approx(fast["rel_gap_abs_max"], abs=1e-9)
    for row in data["particle_filter"]["results"]:
        assert _finite(row["step_ms_median"]) and _finite(row["update_ms_median"])
        assert row["step_ms_median"] >= row["update_ms_median"] > 0
        assert _finite(row["numpy_normals_step_ms_median"])
    episode = data["episode"]
    assert episode["steps"] > 0 and _finite(episode["episode_s"])
    first = data["first_solve"]["results"]
    assert len(first) == 2
    for row in first:
        assert row["build_s"] > 0 and row["first_solve_ms"] > 0 and row["success"]
        assert row["backend"]
    # The first build compiles its C library in an empty cache, the second finds it.
    assert [row["codegen_cache"] for row in first] == ["fresh", "as found"]
    if first[0]["backend"] == "compiled-c":
        assert not first[0]["cache_hit"] and first[0]["codegen_compile_time_s"] > 0
        assert first[1]["cache_hit"]


def test_quick_run_sweeps_the_horizons(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    rows = {row["horizon"]: row for row in data["horizons"]["results"]}
    assert sorted(rows) == [7, 15, 30]
    # N = 7 is the main comparison's problems, the others recorded at their own horizon.
    assert rows[7]["source"] == "closed_loop"
    assert rows[7]["n_problems"] == data["closed_loop"]["n_problems"]
    for n in (15, 30):
        assert rows[n]["source"] == "recorded"
        assert rows[n]["n_problems"] == 2  # quick: 2 steps of seed 0
    for row in rows.values():
        assert row["n_scenarios"] == 150
        # quick: the fast solver alone (IPOPT takes seconds per problem at N = 15, 30)
        assert set(row["summary"]) == {"fast"} and row["agreement"] is None
        s = row["summary"]["fast"]
        assert s["n_problems"] == row["n_problems"]
        assert _finite(s["solve_ms_median"]) and s["solve_ms_median"] > 0
    assert data["meta"]["horizon_solvers"] == ["fast"]


def test_the_objective_agreement_with_ipopt() -> None:
    """The horizon sweep's agreement (the quick run leaves IPOPT out of it): a problem is
    within when fast ends at most GAP_TOL above IPOPT; a failed solve never is."""
    from experiments.benchmark.suites import objective_agreement

    ref = [{"seed": 0, "step": k, "success": True, "objective": 100.0} for k in range(4)]
    ref[3]["success"] = False
    recs = [
        {"seed": 0, "step": 0, "success": True, "objective": 100.0},
        {"seed": 0, "step": 1, "success": True, "objective": 100.5},
        {"seed": 0, "step": 2, "success": False, "objective": 90.0},
        {"seed": 0, "step": 3, "success": True, "objective": 100.0},
    ]
    agreement = objective_agreement(recs, ref)
    assert agreement["n_compared"] == 3 and agreement["n_within"] == 1
    assert agreement["share_within_pct"] == pytest.approx(100.0 / 3)


def test_quick_run_says_which_problems_no_input_can_satisfy(quick_run) -> None:
    """At N = 30 the scenarios' speeds spread wider than the 8 m/s band (measured: the
    least slack of seed 0's first two problems is about 100 m/s); the fast solver's plans
    keep at least that much slack (the bound is a lower bound), and the report says so."""
    data, path = quick_run
    rows = {row["horizon"]: row for row in data["horizons"]["results"]}
    for row in rows.values():
        f = row["feasibility"]
        assert f["n_problems"] == row["n_problems"]
        assert 0 <= f["n_infeasible"] <= f["n_problems"]
    f30 = rows[30]["feasibility"]
    assert f30["n_infeasible"] == 2 and f30["seeds_infeasible"] == [0]
    assert f30["bound_median"] > 10.0
    assert f30["slack_over_bound_median"] >= 1.0 - 1e-9
    assert rows[15]["feasibility"]["n_infeasible"] == 0
    report = benchmark_report.format_report(data)
    assert "Infeasible for every input" in report
    assert "N = 30: 2/2 problems (seeds 0)" in report
    least = {(f["seed"], f["step"]): f["least_slack"] for f in f30["infeasible"]}
    assert sorted(least) == [(0, 0), (0, 1)]
    for f in data["failures"]:  # a failed N = 30 solve carries its problem's least slack
        if f["part"] == "horizon_sweep" and f["N"] == 30:
            assert f["least_slack"] == least[(f["seed"], f["step"])]


def test_every_failed_solve_is_listed_with_its_problem(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    failures = data["failures"]
    keys = {"part", "solver", "seed", "step", "N", "Ns", "kind", "status"}
    for f in failures:
        # horizon-sweep failures also give the problem's least slack over every input
        assert set(f) - keys <= {"least_slack"} and keys <= set(f)
        assert f["kind"] == benchmark_failures.classify_failure(f["status"])
    # The list matches the success counts of every part, solver by solver.
    closed = data["closed_loop"]
    for name, s in closed["summary"].items():
        listed = [f for f in failures if f["part"] == "closed_loop" and f["solver"] == name]
        assert len(listed) == s["n_problems"] - s["n_success"]
        assert all(f["N"] == 7 and f["Ns"] == 150 for f in listed)
    for row in data["horizons"]["results"]:
        if row["source"] == "recorded":
            for name, s in row["summary"].items():
                listed = [
                    f
                    for f in failures
                    if f["part"] == "horizon_sweep"
                    and f["solver"] == name
                    and f["N"] == row["horizon"]
                ]
                assert len(listed) == s["n_problems"] - s["n_success"]
    for row in data["sweep"]["results"]:
        for name, s in row["summary"].items():
            listed = [
                f
                for f in failures
                if f["part"] == "ns_sweep" and f["solver"] == name and f["Ns"] == row["n_scenarios"]
            ]
            assert len(listed) == s["n_problems"] - s["n_success"]
    report = benchmark_report.format_report(data)
    assert "Failed solves: " in report
    for f in failures:
        assert f"{f['part']:<20}{f['solver']:<25}{f['seed']:>5}{f['step']:>6}" in report


def test_checks_of_the_run_follow_from_its_figures(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    checks = data["checks"]
    assert [c["key"] for c in checks] == list(benchmark_checks.DEFAULT_THRESHOLDS)
    for c in checks:
        assert c["passed"] in (True, False, None)
        assert c["threshold"] == data["meta"]["thresholds"][c["key"]]
        if c["passed"] is not None:
            op = {"<=": np.less_equal, ">=": np.greater_equal}[c["op"]]
            assert bool(op(c["value"], c["threshold"])) == c["passed"], c["key"]
    by_key = {c["key"]: c for c in checks}
    summary = data["closed_loop"]["summary"]
    # The impossible threshold given on the command line: the measured median, FAIL.
    assert by_key["fast_median_ms"]["threshold"] == 1e-9
    assert by_key["fast_median_ms"]["value"] == summary["fast"]["solve_ms_median"]
    assert by_key["fast_median_ms"]["passed"] is False
    rows = {r["horizon"]: r for r in data["horizons"]["results"]}
    assert by_key["horizon_30_median_ms"]["value"] == rows[30]["summary"]["fast"]["solve_ms_median"]
    fast_failed = [
        f
        for f in data["failures"]
        if f["solver"] == "fast"
        and f["part"] in ("closed_loop", "closed_loop_alone", "horizon_sweep")
    ]
    assert by_key["fast_failures"]["value"] == len(fast_failed)
    qp = [
        f for f in data["failures"] if f["kind"] == "QP_Failed" and f["solver"].startswith("fast")
    ]
    assert by_key["qp_failed"]["value"] == len(qp)
    pf = next(r for r in data["particle_filter"]["results"] if r["n_particles"] == 7000)
    assert by_key["pf_step_ms"]["value"] == pf["step_ms_median"]
    cold = data["first_solve"]["results"][0]
    assert cold["codegen_cache"] == "fresh"
    assert by_key["cold_build_s"]["value"] == cold["total_s"] > 0
    # The textbook was skipped, and the quick sweep has no Ns = 5000.
    skipped = {c["key"] for c in checks if c["passed"] is None}
    assert {"textbook_over_fast_c", "worse_share_pct", "fast_c_ns5000_median_ms"} <= skipped


def test_json_is_strict_and_the_markdown_has_the_speed_table(quick_run) -> None:
    data, path = quick_run
    text = open(path).read()
    # NaN and Infinity are not JSON; the writer must have turned them into null.
    assert "NaN" not in text and "Infinity" not in text
    markdown = open(path.removesuffix(".json") + ".md").read()
    for name in QUICK_SOLVERS:
        assert f"| {name} |" in markdown
    assert "sqpmethod / fast:" in markdown
    # The checks, then the compiled part as printed, each in a text block.
    checks, compiled = (b.split("\n```\n")[0] for b in markdown.split("\n```text\n")[1:3])
    assert checks == "\n".join(benchmark_checks.check_lines(data["checks"]))
    assert compiled == "\n".join(benchmark_compiled.compiled_lines(data))


def test_report_shows_the_speed_table_and_every_check(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    report = benchmark_report.format_report(data)
    assert report.startswith("Speed (N = 7, Ns = 150")
    for name in QUICK_SOLVERS:
        assert f"\n{name} " in report
    for line in benchmark_checks.check_lines(data["checks"]):
        assert f"\n  {line}" in report


@pytest.mark.skipif(
    shutil.which("make") is None or shutil.which("cc") is None, reason="needs make and cc"
)
def test_quick_run_compares_the_compiled_loop_and_times_the_export(quick_run) -> None:
    """The compiled loop's plans against the Python loop's on the closed-loop problems, the
    exported scenario controller's example on them, the exported robust agent's step on an
    episode's measurements, and the checks taken from those figures."""
    data, _ = quick_run
    closed, compiled = data["closed_loop"], data["compiled"]
    (row,) = compiled["agreement"]  # the quick sweep has no Ns = 1000 or 5000
    assert row["n_problems"] == closed["n_problems"] and row["loop"] == "c"
    assert row["max_abs_diff"] <= benchmark_compiled.PLAN_TOL and row["n_above_tol"] == 0
    export = compiled["export"]
    assert export["available"], export["reason"]
    assert export["n_problems"] == closed["n_problems"] and export["n_failed"] == 0
    assert export["plan_diff_max"] <= benchmark_compiled.EXPORT_PLAN_TOL
    assert export["dependencies"]["ok"] and export["dependencies"]["other_libraries"] == []
    robust = export["robust"]
    assert robust["example_returncode"] == 0 and robust["steps"] > 0
    assert robust["input_diff_max"] <= benchmark_compiled.EXPORT_PLAN_TOL
    assert _finite(robust["c_step_us_median"]) and _finite(export["solve_us"]["median"])
    by_key = {c["key"]: c for c in data["checks"]}
    summary = closed["summary"]
    assert by_key["fast_c_median_ms"]["value"] == summary["fast_c"]["solve_ms_median"]
    assert by_key["fast_c_p95_ms"]["value"] == summary["fast_c"]["solve_ms_p95"]
    assert by_key["anchor_over_fast_c"]["passed"] is None  # sqpmethod not run: SKIP
    assert by_key["robust_step_ms"]["value"] == pytest.approx(robust["c_step_us_median"] / 1e3)
    assert by_key["export_plan_diff"]["value"] == export["plan_diff_max"]
    assert by_key["export_dependencies"]["value"] == 0 and by_key["export_dependencies"]["passed"]
    report = benchmark_report.format_report(data)
    assert "\nCompiled loop (fast_c) against the Python loop" in report
    assert "\nExported controllers (make: scenario " in report
