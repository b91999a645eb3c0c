"""Metrics that do not reward failing (``experiments.report.survival``): on a constructed set
of episodes where one agent fails early, the raw counts favour it and the unbiased forms do
not."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from experiments.report.document import Document
from experiments.report.results import Results
from experiments.report.stats import paired_differences
from experiments.report.survival import (
    PerStepRate,
    ViolationOrFailure,
    headline_counts,
    headline_section,
    step_rate,
    survivor_difference,
    survivors,
    violation_or_failure,
)
from lfm_env.worlds.registry import load_env_config

COUNT = "track_violation_steps_over_0.01"
RATE = 0.2  # every episode is in violation on a fifth of the steps it lasts


def _row(agent: str, seed: int, steps: int, failure: bool = False, error: str = "") -> dict:
    return {
        "agent": agent,
        "seed": seed,
        "steps": float(steps),
        "success": float(not failure),
        "failure": float(failure),
        "time_to_goal": math.nan if failure else 0.2 * steps,
        "cost": 10.0 * steps,
        COUNT: RATE * steps,
        "track_violation_steps": RATE * steps,
        "solve_time_median": 0.002,
        "error": error,
    }


@pytest.fixture
def results() -> Results:
    """``pf`` fails early on seeds 0 and 1 (after 10 and 5 steps); ``robust`` lasts 50 steps
    everywhere; both violate on a fifth of their steps. ``oracle`` raised on seed 3."""
    rows = [_row("robust", s, 50) for s in range(4)]
    rows += [_row("pf", 0, 10, failure=True), _row("pf", 1, 5, failure=True)]
    rows += [_row("pf", s, 50) for s in (2, 3)]
    rows += [_row("oracle", s, 50) for s in range(3)]
    rows += [_row("oracle", 3, 0, error="RuntimeError: boom")]
    return Results(Path("."), rows, load_env_config(None), {})


def test_the_raw_count_rewards_failing_and_the_unbiased_forms_do_not(results):
    pf, robust = results.rows_of("pf"), results.rows_of("robust")
    # Biased: pf's mean count (2 + 1 + 10 + 10) / 4 is below robust's 10, and the paired
    # difference on all seeds says pf violates less.
    raw_pf = np.mean([r[COUNT] for r in pf])
    assert raw_pf == pytest.approx(5.75) and np.mean([r[COUNT] for r in robust]) == 10.0
    assert paired_differences(results, COUNT, "pf", "robust").estimate.mean == pytest.approx(
        (2 - 10 + 1 - 10) / 4
    )
    # Per step survived: the same rate, pooled and paired.
    assert step_rate(pf, COUNT).mean == pytest.approx(RATE)
    assert step_rate(robust, COUNT).mean == pytest.approx(RATE)
    d = paired_differences(results, PerStepRate(COUNT, "rate"), "pf", "robust")
    assert d.estimate.mean == pytest.approx(0.0) and d.estimate.low == pytest.approx(0.0)
    assert len(d.seeds) == 4
    # On the survivor seeds (2: no agent failed or raised): no difference either.
    kept = survivors(results)
    assert kept.seeds == (2,)
    assert kept.dropped == {
        0: (("pf", "failure"),),
        1: (("pf", "failure"),),
        3: (("oracle", "error"),),
    }
    assert survivor_difference(results, kept, COUNT, "pf", "robust").seeds == (2,)
    assert survivor_difference(results, kept, COUNT, "pf", "robust").estimate.mean == 0.0
    # Without the oracle, seed 3 is kept.
    assert survivors(results, ["pf", "robust"]).seeds == (2, 3)


def test_violation_or_failure_counts_a_failure_without_violations():
    metric = ViolationOrFailure(COUNT, COUNT)
    clean_failure = {COUNT: 0.0, "failure": 1.0}
    assert metric.value(clean_failure) == 1.0
    assert metric.value({COUNT: 0.0, "failure": 0.0}) == 0.0
    assert metric.value({COUNT: 3.0, "failure": 0.0}) == 1.0
    assert math.isnan(metric.value({COUNT: math.nan, "failure": 0.0}))
    rows = [clean_failure, {COUNT: 0.0, "failure": 0.0}, {COUNT: 0.0, "failure": 0.0, "error": "x"}]
    assert violation_or_failure(rows, COUNT).mean == 0.5  # the error row is left out
    assert math.isnan(PerStepRate(COUNT, COUNT).value({COUNT: 0.0, "steps": 0.0}))


def test_headline_counts_take_each_groups_smallest_tolerance():
    system = load_env_config(None).make_system()  # the sine track
    counts = {c.group: (c.tolerance, c.column, c.label) for c in headline_counts(system)}
    assert counts["track"] == (0.01, COUNT, "track steps > 0.01 m")
    assert counts["speed"] == (0.05, "speed_violation_steps_over_0.05", "speed steps > 0.05 m/s")
    assert list(counts) == list(system.constraint_groups)


def test_the_section_says_which_seeds_were_dropped_and_why(results):
    doc = Document()
    headline_section(doc, results, baseline="pf")
    md = doc.markdown()
    assert "Survivor seeds: 1 of 4; dropped: seed 0 (failure of `pf`)" in md
    assert "seed 3 (error of `oracle`)" in md
    assert "time to goal vs `pf`" in md  # the report's baseline, robust or not
    track = md.split("**track steps > 0.01 m**")[1]
    line = next(x for x in track.splitlines() if x.startswith("| PF + CE MPC |"))
    cells = [c.strip() for c in line.strip("|").split(" | ")]
    # violation-or-failure, per 100 steps survived, survivor seeds, all seeds (biased)
    assert cells[1].startswith("1 [1, 1]") and cells[2].startswith("20 [20, 20]")
    assert cells[3].startswith("10 ") and cells[4].startswith("5.75 ")
