"""Tests of the benchmark (``experiments.benchmark.run`` and its ``bench_*`` modules).

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
from experiments.benchmark import problems as bench_problems
from experiments.benchmark import report as bench_report
from experiments.benchmark import solvers as bench_solvers
from experiments.benchmark import suites as bench_suites
from experiments.benchmark import targets as bench_targets
from experiments.cli import benchmark as benchmark_cli

TIMING_KEYS = ("solve_ms_median", "solve_ms_p95", "solve_ms_max", "wall_ms_median")
# The textbook and csnlp are slow; sqpmethod (the anchor) is in, JIT compilation included.
QUICK_SOLVERS = ("fast", "fast_bicycle", "ipopt", "sqpmethod")
# A threshold no run can meet: the quick run must still exit 0 (no --check) and say FAIL.
IMPOSSIBLE = "fast_median_ms=1e-9"
# Thresholds every measured figure meets: with --check such a run exits 0.
LOOSE = [
    f"{key}={-1e9 if key.endswith(('_over_fast', '_share_pct')) else 1e9}"
    for key in bench_targets.DEFAULT_THRESHOLDS
    if key != "worse_share_pct"
] + ["worse_share_pct=100"]


def _finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str]:
    out = tmp_path_factory.mktemp("bench") / "b.json"
    solvers = ",".join(QUICK_SOLVERS)
    argv = ["--quick", "--out", str(out), "--no-progress", "--solvers", solvers]
    code = benchmark_cli.benchmark_main([*argv, "--threshold", IMPOSSIBLE])
    assert code == 0  # a failing target without --check: exit 0, the verdict in the report
    return json.loads(out.read_text()), str(out)


# --------------------------------------------------------------------------- the quick run


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
        "failures",
        "targets",
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
    # The anchor: compiled at build, its solves timed like the others'.
    assert closed["solvers"]["sqpmethod"]["build_time_s"] > 0
    assert _finite(closed["speedup"]["sqpmethod"]["median_ratio"])
    # The fast solvers' closed loop again, alone: same problems, the same plans.
    assert set(closed["alone"]) == {"fast", "fast_bicycle"}
    for alone in closed["alone"].values():
        assert alone["n_problems"] == closed["n_problems"]
        assert alone["plan_difference_max"] <= 1e-6
        assert _finite(alone["solve_ms_p95"]) and alone["solve_ms_p95"] > 0
    assert _finite(closed["speedup"]["ipopt"]["median_ratio"])
    assert _finite(closed["speedup"]["fast_bicycle"]["median_ratio"])

    rows = data["sweep"]["results"]
    for row in rows:
        # The kernel on two threads at the sweep's largest Ns (here 50; from 500 on in full).
        extra = {"fast_2threads"} if row is rows[-1] else set()
        assert set(row["summary"]) == {"fast", "fast_bicycle", "ipopt"} | extra
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
    # The first build compiles its kernel in an empty cache, the second finds it.
    assert [row["kernel_cache"] for row in first] == ["fresh", "as found"]
    if first[0]["backend"] == "compiled-c":
        assert not first[0]["cache_hit"] and first[0]["kernel_compile_time_s"] > 0
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
        for name in ("fast", "ipopt"):
            s = row["summary"][name]
            assert s["n_problems"] == row["n_problems"]
            assert _finite(s["solve_ms_median"]) and s["solve_ms_median"] > 0
        agreement = row["agreement"]
        ok = row["summary"]["ipopt"]["n_success"]
        assert agreement["n_compared"] == ok == len(agreement["gaps"])
        gaps = [g["rel_gap"] for g in agreement["gaps"]]
        within = sum(g is not None and g <= bench_solvers.GAP_TOL for g in gaps)
        assert agreement["n_within"] == within
        if ok:
            assert agreement["share_within_pct"] == pytest.approx(100.0 * within / ok)


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
    report = bench_report.format_report(data)
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
        assert f["kind"] == bench_solvers.classify_failure(f["status"])
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
    report = bench_report.format_report(data)
    assert "Failed solves: " in report
    for f in failures:
        assert f"{f['part']:<20}{f['solver']:<25}{f['seed']:>5}{f['step']:>6}" in report


def test_targets_of_the_run_follow_from_its_figures(quick_run: tuple[dict, str]) -> None:
    data, _ = quick_run
    targets = data["targets"]
    keys = [t["key"] for t in targets]
    assert len(keys) == len(set(keys))  # one target per key
    assert {t["key"] for t in targets} == set(bench_targets.DEFAULT_THRESHOLDS)
    for t in targets:
        assert t["passed"] in (True, False, None)
        assert t["threshold"] == data["meta"]["thresholds"][t["key"]]
        if t["passed"] is not None:
            op = {"<=": np.less_equal, ">=": np.greater_equal, ">": np.greater}[t["op"]]
            assert bool(op(t["value"], t["threshold"])) == t["passed"], t["target"]
    by_key = {t["key"]: t for t in targets}
    summary = data["closed_loop"]["summary"]
    # The impossible threshold given on the command line: the measured median, FAIL.
    assert by_key["fast_median_ms"]["threshold"] == 1e-9
    assert by_key["fast_median_ms"]["value"] == summary["fast"]["solve_ms_median"]
    assert by_key["fast_median_ms"]["passed"] is False
    anchor = summary["sqpmethod"]["solve_ms_median"] / summary["fast"]["solve_ms_median"]
    assert by_key["anchor_over_fast"]["value"] == pytest.approx(anchor)
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
    assert cold["kernel_cache"] == "fresh"
    assert by_key["cold_build_s"]["value"] == cold["total_s"] > 0
    # The textbook and csnlp were skipped, and the quick sweep has no Ns = 5000.
    skipped = {t["key"] for t in targets if t["passed"] is None}
    assert {"textbook_over_fast", "worse_share_pct", "csnlp_over_fast"} <= skipped
    assert "large_ns_median_ms" in skipped


def test_check_exits_1_when_a_target_fails_and_0_when_all_pass(tmp_path) -> None:
    """--check on a small real run: an impossible threshold fails it, loose ones pass."""
    small = ["--quick", "--solvers", "fast", "--horizons", "7", "--max-steps", "2"]
    small += ["--no-progress", "--out", str(tmp_path / "c.json")]
    assert benchmark_cli.benchmark_main([*small, "--check", "--threshold", IMPOSSIBLE]) == 1
    data = json.loads((tmp_path / "c.json").read_text())
    assert "fast_median_ms" in [t["key"] for t in data["targets"] if t["passed"] is False]
    loose = [a for kv in LOOSE for a in ("--threshold", kv)]
    assert benchmark_cli.benchmark_main([*small, "--check", *loose]) == 0
    data = json.loads((tmp_path / "c.json").read_text())
    assert not [t for t in data["targets"] if t["passed"] is False]
    assert any(t["passed"] for t in data["targets"])


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--threshold", "no_such_key=1"], "no_such_key"),
        (["--threshold", "pf_step_ms=fast"], "pf_step_ms"),
        (["--threshold", "pf_step_ms"], "KEY=VALUE"),
        (["--horizons", "7,0"], "horizons"),
        (["--solvers", "fast,gurobi"], "gurobi"),
    ],
)
def test_bad_options_name_the_field(argv: list[str], match: str, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        benchmark_cli.benchmark_main([*argv, "--no-progress"])
    assert exc.value.code == 2
    assert match in capsys.readouterr().err


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
    report = bench_report.format_report(data)
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
    # fast 1.2 ms (p95 4), sqpmethod 15x, textbook 400x, generic 1.2x, 1 of 50 problems (2%).
    medians = {"fast": 1.2, "sqpmethod": 18.0, "ipopt_multiple_shooting": 480.0}
    medians["fast_bicycle"] = 1.0
    targets = bench_report.speed_targets(medians, 4.0, worse, 50)
    assert [t["key"] for t in targets] == [
        "fast_median_ms",
        "fast_p95_ms",
        "anchor_over_fast",
        "textbook_over_fast",
        "generic_over_hand",
        "worse_share_pct",
    ]
    assert [t["value"] for t in targets] == pytest.approx([1.2, 4.0, 15.0, 400.0, 1.2, 2.0])
    assert _verdicts(targets) == [True] * 6
    assert "seed 1 step 7 (+3.0e-04)" in targets[5]["note"]
    # The limits themselves pass; just past them fails.
    at_limits = {"fast": 1.5, "sqpmethod": 15.0, "ipopt_multiple_shooting": 450.0}
    at_limits["fast_bicycle"] = 1.0
    assert _verdicts(bench_report.speed_targets(at_limits, 5.0, [], 10)) == [True] * 6
    past = {"fast": 1.6, "sqpmethod": 15.9, "ipopt_multiple_shooting": 479.0}
    past["fast_bicycle"] = 1.0
    failing = bench_report.speed_targets(past, 5.1, worse * 2, 50)
    assert _verdicts(failing) == [False] * 6
    # Other thresholds, by key.
    relaxed = bench_report.speed_targets(past, 5.1, worse * 2, 50, {"fast_median_ms": 2.0})
    assert _verdicts(relaxed)[0] is True and relaxed[0]["threshold"] == 2.0


def test_speed_targets_skip_what_was_not_measured() -> None:
    targets = bench_report.speed_targets({"fast": 6.0, "sqpmethod": math.nan}, None, None, None)
    assert _verdicts(targets) == [False, None, None, None, None, None]
    assert "not run" in targets[5]["note"]
    # No problem compared: no share, even with an empty list.
    assert bench_report.speed_targets({"fast": 1.0}, 1.0, [], 0)[5]["passed"] is None


def test_thresholds_are_checked_by_key() -> None:
    th = bench_targets.check_thresholds({"pf_step_ms": "0.5"})
    assert th["pf_step_ms"] == 0.5 and th["fast_median_ms"] == 1.5
    with pytest.raises(ValueError, match="'pf_step'"):
        bench_targets.check_thresholds({"pf_step": 1.0})
    with pytest.raises(ValueError, match="pf_step_ms"):
        bench_targets.check_thresholds({"pf_step_ms": math.inf})


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
        assert bench_solvers.classify_failure(status) == kind
    records = {
        "a": [
            {"seed": 2, "step": 0, "success": True, "status": "Solve_Succeeded"},
            {"seed": 2, "step": 1, "success": False, "status": "QP_Failed"},
        ]
    }
    assert bench_solvers.failures_of(records, "part", 15, 150) == [
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


def test_objective_agreement_counts_problems_within_the_tolerance() -> None:
    def rec(step: int, objective: float, success: bool = True) -> dict:
        return {"seed": 0, "step": step, "objective": objective, "success": success}

    reference = [rec(0, 100.0), rec(1, 100.0), rec(2, 100.0), rec(3, 100.0, success=False)]
    records = [rec(0, 100.005), rec(1, 90.0), rec(2, 100.0, success=False), rec(3, 50.0)]
    out = bench_suites.objective_agreement(records, reference)
    # within: 5e-5 above, and 10% lower (at least as good); a failed solve never is; the
    # problem the reference did not solve is not compared.
    assert (out["n_compared"], out["n_within"], out["n_within_abs"]) == (3, 2, 1)
    assert out["share_within_pct"] == pytest.approx(200.0 / 3.0)
    assert [g["step"] for g in out["gaps"]] == [0, 1, 2]
    assert math.isnan(out["gaps"][2]["rel_gap"])


def test_target_rejects_an_unknown_comparison() -> None:
    assert bench_targets.target("x", 1.0, 1.0, ">")["passed"] is False
    with pytest.raises(ValueError, match="op="):
        bench_targets.target("x", 1.0, 1.0, "<")


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
    assert benchmark_cli.parse_seeds("0:3") == [0, 1, 2]
    assert benchmark_cli.parse_seeds("5") == [5]
    assert benchmark_cli.parse_seeds("1,4,1,0:2") == [1, 4, 0]
    for bad in ("", "3:1", "-1", "a"):
        with pytest.raises(ValueError, match="seeds="):
            benchmark_cli.parse_seeds(bad)


@pytest.mark.parametrize("name", ["gurobi", "textbook", "ipopt_condensed"])
def test_only_the_registry_names_are_accepted(name: str) -> None:
    problem = bench_problems.problem_from_config(n_scenarios=2)
    with pytest.raises(ValueError, match="unknown solver"):
        bench_solvers.build_solver(name, problem)
    with pytest.raises(ValueError, match="unknown solver"):
        bench_solvers.time_solvers([], [name], problem=problem)
    with pytest.raises(SystemExit):
        benchmark_cli.build_parser().parse_args(["--skip", name])
    assert name not in SOLVERS


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
