"""The benchmark's checks (``experiments.benchmark.checks``), judged on given figures."""

from __future__ import annotations

import math

import pytest

from experiments.benchmark import checks as benchmark_checks


def closed_loop(fast_c: float, fast: float, anchor: float, worse: int, compared: int) -> dict:
    """A result with the closed-loop part only: medians [ms], problems fast ends above the
    textbook on, of those compared."""
    summary = {
        "fast_c": {"solve_ms_median": fast_c, "solve_ms_p95": 2 * fast_c},
        "fast": {
            "solve_ms_median": fast,
            "solve_ms_p95": 3 * fast,
            "n_reference_ok": compared,
            "worse_than_reference": [{"seed": 0, "step": k} for k in range(worse)],
            "max_violation_no_slack": 1e-9,
        },
        "sqpmethod": {"solve_ms_median": anchor},
        "ipopt_multiple_shooting": {"solve_ms_median": 400.0},
    }
    return {
        "closed_loop": {"summary": summary, "reference": "ipopt_multiple_shooting"},
        "failures": [],
    }


def by_key(checks: list[dict]) -> dict[str, dict]:
    return {c["key"]: c for c in checks}


def test_the_checks_are_judged_from_the_figures_of_the_run() -> None:
    checks = by_key(benchmark_checks.run_checks(closed_loop(0.8, 2.6, 26.0, 1, 100)))
    assert checks["fast_c_median_ms"]["value"] == 0.8 and checks["fast_c_median_ms"]["passed"]
    assert checks["anchor_over_fast_c"]["value"] == pytest.approx(32.5)
    assert checks["textbook_over_fast_c"]["value"] == pytest.approx(500.0)
    assert checks["worse_share_pct"]["value"] == pytest.approx(1.0)
    assert checks["fast_failures"]["value"] == 0.0 and checks["qp_failed"]["passed"]
    # Not measured here: SKIP, never FAIL.
    for key in ("horizon_15_median_ms", "pf_step_ms", "robust_step_ms", "episode_s"):
        assert checks[key]["value"] is None and checks[key]["passed"] is None
    # Past a bound: FAIL; the bound itself passes.
    slow = by_key(benchmark_checks.run_checks(closed_loop(1.5, 5.1, 22.0, 3, 100)))
    assert slow["fast_c_median_ms"]["passed"] and slow["fast_median_ms"]["passed"] is False
    assert slow["anchor_over_fast_c"]["passed"] is False  # 14.7x < 15x
    assert slow["worse_share_pct"]["passed"] is False
    assert benchmark_checks.failed_checks(list(slow.values()))


def test_bounds_are_changed_by_key_and_checked() -> None:
    relaxed = benchmark_checks.run_checks(
        closed_loop(2.0, 1.0, 26.0, 0, 10), {"fast_c_median_ms": 3}
    )
    assert by_key(relaxed)["fast_c_median_ms"] == {
        **by_key(relaxed)["fast_c_median_ms"],
        "threshold": 3.0,
        "passed": True,
    }
    th = benchmark_checks.check_thresholds({"pf_step_ms": "0.5"})
    assert th["pf_step_ms"] == 0.5 and th["fast_c_median_ms"] == 1.5
    with pytest.raises(ValueError, match="'pf_step'"):
        benchmark_checks.check_thresholds({"pf_step": 1.0})
    with pytest.raises(ValueError, match="pf_step_ms"):
        benchmark_checks.check_thresholds({"pf_step_ms": math.inf})


def test_the_printed_lines_name_verdict_figure_and_bound() -> None:
    checks = benchmark_checks.run_checks(closed_loop(0.8, 6.0, 26.0, 0, 0))
    lines = dict(zip([c["key"] for c in checks], benchmark_checks.check_lines(checks), strict=True))
    assert lines["fast_c_median_ms"].split()[:5] == ["PASS", "fast_c_median_ms", "0.8", "ms", "<="]
    assert lines["fast_median_ms"].startswith("FAIL  fast_median_ms")
    assert lines["worse_share_pct"].split()[:3] == ["SKIP", "worse_share_pct", "-"]
    assert "32.5x" in lines["anchor_over_fast_c"] and ">= 15x" in lines["anchor_over_fast_c"]


def test_every_check_is_documented() -> None:
    """Each check's key, bound and figure are in docs/benchmark.md's table."""
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[3] / "docs" / "benchmark.md").read_text()
    for c in benchmark_checks.CHECKS:
        assert f"| `{c.key}` |" in doc, c.key
