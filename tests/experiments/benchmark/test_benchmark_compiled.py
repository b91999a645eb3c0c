"""The benchmark's compiled-loop part (``experiments.benchmark.compiled``) at tiny sizes: the
compiled loop's plans against the Python loop's (closed-loop problems and problems drawn at
another scenario count), the checks of the part skipped without its figures, and the printed
rows.
The part with the exports (make, example, ldd) runs in the quick benchmark
(``test_benchmark_run``). No timing is asserted."""

from __future__ import annotations

import math

import pytest

from experiments.benchmark import compiled as benchmark_compiled
from experiments.benchmark.checks import run_checks
from experiments.benchmark.problems import (
    DEFAULT_CONFIG,
    anchors_per_seed,
    experiment_config,
    record_closed_loop,
)

COMPILED_KEYS = (  # the checks of the compiled loop and the export
    "fast_c_median_ms",
    "fast_c_p95_ms",
    "anchor_over_fast_c",
    "textbook_over_fast_c",
    "fast_c_ns5000_median_ms",
    "robust_step_ms",
    "export_plan_diff",
    "export_dependencies",
)
DRAWN_NS = 40  # a scenario count of the drawn problems (the full run: 1000 and 5000)


@pytest.fixture(scope="module")
def tiny() -> tuple[dict, list, list]:
    cfg = experiment_config(DEFAULT_CONFIG)
    problems, anchors = record_closed_loop(cfg, [0, 1], 3)
    out = benchmark_compiled.time_compiled(cfg, problems, anchors, (DRAWN_NS,), export=False)
    return out, problems, anchors


def test_the_compiled_loop_gives_the_python_loops_plans(tiny) -> None:
    out, problems, anchors = tiny
    assert "export" not in out  # export=False
    main, drawn = out["agreement"]
    assert (main["horizon"], main["n_scenarios"]) == (7, 150)
    assert main["n_problems"] == len(problems) == 6
    assert (drawn["horizon"], drawn["n_scenarios"]) == (7, DRAWN_NS)
    chosen = anchors_per_seed(anchors, benchmark_compiled.AGREEMENT_STEPS)
    assert drawn["n_problems"] == len(chosen) == 4  # two per seed
    for row in (main, drawn):
        assert row["loop"] == "c"  # compiled here, not the Python fallback
        assert 0.0 <= row["max_abs_diff"] <= benchmark_compiled.PLAN_TOL
        assert row["n_above_tol"] == 0
        assert row["rel_gap_abs_max"] <= 1e-9
        assert 0 <= row["n_same_iterations"] <= row["n_problems"]
        assert row["worst"]["seed"] in (0, 1)
        assert "_python_u" not in row  # the plans are dropped from the results
        for side in ("python_ms", "c_ms"):
            assert row[side]["median"] > 0 and math.isfinite(row[side]["p95"])


def test_the_checks_without_the_solvers_and_export_are_skipped(tiny) -> None:
    out, _, _ = tiny
    checks = {c["key"]: c for c in run_checks({"compiled": out})}
    for key in COMPILED_KEYS:
        assert checks[key]["passed"] is None and checks[key]["value"] is None, key


def test_the_printed_part_has_a_row_per_agreement(tiny) -> None:
    out, _, _ = tiny
    lines = benchmark_compiled.compiled_lines({"compiled": out})
    assert lines[0].startswith("Compiled loop (fast_c) against the Python loop")
    rows = [line for line in lines if line.startswith("  N=7, Ns=")]
    assert [row.split(",")[1].strip().split()[0] for row in rows] == ["Ns=150", f"Ns={DRAWN_NS}"]
    for row, agreement in zip(rows, out["agreement"], strict=True):
        assert f"{agreement['n_problems']} problems, loop c" in row
        assert f"plans max abs difference {agreement['max_abs_diff']:.2e}" in row
    assert not any(line.startswith("Exported controllers") for line in lines)
    assert benchmark_compiled.compiled_lines({}) == []
