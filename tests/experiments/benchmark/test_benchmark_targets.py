"""The benchmark's targets (``experiments.benchmark.targets``), judged on given numbers."""

from __future__ import annotations

import math

import pytest

from experiments.benchmark import report as benchmark_report
from experiments.benchmark import targets as benchmark_targets


def _verdicts(targets: list[dict]) -> list[bool | None]:
    return [t["passed"] for t in targets]


def test_speed_targets_are_judged_from_the_given_figures() -> None:
    worse = [{"seed": 1, "step": 7, "rel_gap": 3e-4}]
    # fast 1.2 ms (p95 4), sqpmethod 15x, textbook 400x, 1 of 50 problems (2%).
    medians = {"fast": 1.2, "sqpmethod": 18.0, "ipopt_multiple_shooting": 480.0}
    targets = benchmark_report.speed_targets(medians, 4.0, worse, 50)
    assert [t["key"] for t in targets] == [
        "fast_median_ms",
        "fast_p95_ms",
        "anchor_over_fast",
        "textbook_over_fast",
        "worse_share_pct",
    ]
    assert [t["value"] for t in targets] == pytest.approx([1.2, 4.0, 15.0, 400.0, 2.0])
    assert _verdicts(targets) == [True] * 5
    assert "seed 1 step 7 (+3.0e-04)" in targets[4]["note"]
    # The limits themselves pass; just past them fails.
    at_limits = {"fast": 1.5, "sqpmethod": 15.0, "ipopt_multiple_shooting": 450.0}
    assert _verdicts(benchmark_report.speed_targets(at_limits, 5.0, [], 10)) == [True] * 5
    past = {"fast": 1.6, "sqpmethod": 15.9, "ipopt_multiple_shooting": 479.0}
    failing = benchmark_report.speed_targets(past, 5.1, worse * 2, 50)
    assert _verdicts(failing) == [False] * 5
    # Other thresholds, by key.
    relaxed = benchmark_report.speed_targets(past, 5.1, worse * 2, 50, {"fast_median_ms": 2.0})
    assert _verdicts(relaxed)[0] is True and relaxed[0]["threshold"] == 2.0


def test_speed_targets_skip_what_was_not_measured() -> None:
    targets = benchmark_report.speed_targets({"fast": 6.0, "sqpmethod": math.nan}, None, None, None)
    assert _verdicts(targets) == [False, None, None, None, None]
    assert "not run" in targets[4]["note"]
    # No problem compared: no share, even with an empty list.
    assert benchmark_report.speed_targets({"fast": 1.0}, 1.0, [], 0)[4]["passed"] is None


def test_thresholds_are_checked_by_key() -> None:
    th = benchmark_targets.check_thresholds({"pf_step_ms": "0.5"})
    assert th["pf_step_ms"] == 0.5 and th["fast_median_ms"] == 1.5
    with pytest.raises(ValueError, match="'pf_step'"):
        benchmark_targets.check_thresholds({"pf_step": 1.0})
    with pytest.raises(ValueError, match="pf_step_ms"):
        benchmark_targets.check_thresholds({"pf_step_ms": math.inf})


def test_target_rejects_an_unknown_comparison() -> None:
    assert benchmark_targets.target("x", 1.0, 1.0, ">")["passed"] is False
    with pytest.raises(ValueError, match="op="):
        benchmark_targets.target("x", 1.0, 1.0, "<")
