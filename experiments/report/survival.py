"""Metrics that do not reward failing (``docs/evidence.md``), and the report's headline section.

An episode that fails stops counting violations, so raw counts favour early failure. The
unbiased forms, from ``episodes.csv``: violations per step survived (:class:`PerStepRate`,
:func:`step_rate`; pooled with a bootstrap over episodes), violation or failure
(:class:`ViolationOrFailure`) and paired differences on the survivor seeds
(:func:`survivors`). A group's headline count is its smallest tolerance's
(:func:`headline_counts`); paired differences are against the report's baseline.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from experiments.evaluation.columns import tolerance_columns
from experiments.report.document import Document
from experiments.report.format import agent_label, fmt, fmt_estimate
from experiments.report.results import Results
from experiments.report.stats import (
    Estimate,
    Metric,
    PairedDifference,
    _beyond,
    bootstrap_ci,
    paired_rows_difference,
    pooled_ratio_ci,
)

#: Violation rates are shown per this many steps survived.
PER_STEPS = 100


@dataclass(frozen=True)
class HeadlineCount:
    """The count a constraint group is judged by: steps with its excess above ``tolerance``."""

    group: str
    tolerance: float  # [group unit]; 0 for the raw count
    column: str  # the episodes.csv column
    label: str  # e.g. "track steps > 0.01 m"


def headline_counts(system: Any) -> tuple[HeadlineCount, ...]:
    """Per constraint group of ``system``: its smallest tolerance's count, else the raw one."""
    smallest: dict[str, tuple[float, str]] = {}
    for g, t, column in tolerance_columns(system):
        if g not in smallest or t < smallest[g][0]:
            smallest[g] = (t, column)
    out = []
    for g in system.constraint_groups:
        if g in smallest:
            t, column = smallest[g]
            out.append(HeadlineCount(g, t, column, f"{g} steps {_beyond(system, g, t)}"))
        else:
            out.append(HeadlineCount(g, 0.0, f"{g}_violation_steps", f"{g} violation steps"))
    return tuple(out)


def _number(row: dict[str, Any], column: str) -> float:
    v = row.get(column, math.nan)
    try:
        return math.nan if v is None else float(v)
    except (TypeError, ValueError):
        return math.nan


@dataclass(frozen=True)
class PerStepRate(Metric):
    """A count column over the episode's steps: violations per step survived (NaN for an
    episode of no step)."""

    def value(self, row: dict[str, Any]) -> float:
        count, steps = _number(row, self.column), _number(row, "steps")
        if not (np.isfinite(count) and np.isfinite(steps)) or steps <= 0:
            return math.nan
        return count / steps


@dataclass(frozen=True)
class ViolationOrFailure(Metric):
    """1 when the count column is above 0 or the episode ended in failure, else 0."""

    def value(self, row: dict[str, Any]) -> float:
        count, failure = _number(row, self.column), _number(row, "failure")
        if not (np.isfinite(count) and np.isfinite(failure)):
            return math.nan
        return float(count > 0 or failure > 0)


def step_rate(rows: Iterable[dict[str, Any]], column: str) -> Estimate:
    """Violations of ``column`` per step survived, pooled over the (error-free) episodes:
    ``sum(count) / sum(steps)``, with a bootstrap over whole episodes (their steps are
    correlated); ``n`` the episodes with at least one step."""
    pairs = [
        (_number(r, column), _number(r, "steps"))
        for r in rows
        if not r.get("error") and np.isfinite(_number(r, column))
    ]
    return pooled_ratio_ci([c for c, _ in pairs], [s for _, s in pairs])


def violation_or_failure(rows: Iterable[dict[str, Any]], column: str) -> Estimate:
    """The fraction of (error-free) episodes with a violation of ``column`` or a failure."""
    metric = ViolationOrFailure(column, column)
    return bootstrap_ci([metric.value(r) for r in rows if not r.get("error")])


@dataclass(frozen=True)
class Survivors:
    """The seeds on which every one of ``agents`` ran without error and did not fail."""

    agents: tuple[str, ...]
    seeds: tuple[int, ...]
    # seed -> ((agent, why), ...): "failure" (the env ended it as one), "error" (it raised),
    # "missing" (no episode of the agent on the seed)
    dropped: dict[int, tuple[tuple[str, str], ...]]

    def describe(self) -> str:
        """The dropped seeds and why, one clause per seed (``""`` when none was dropped)."""
        parts = []
        for seed, why in sorted(self.dropped.items()):
            by_reason: dict[str, list[str]] = {}
            for agent, reason in why:
                by_reason.setdefault(reason, []).append(f"`{agent}`")
            text = "; ".join(f"{_REASONS[r]} of {', '.join(a)}" for r, a in by_reason.items())
            parts.append(f"seed {seed} ({text})")
        return ", ".join(parts)


_REASONS = {"failure": "failure", "error": "error", "missing": "no episode"}


def survivors(results: Results, agents: Sequence[str] | None = None) -> Survivors:
    """The seeds every one of ``agents`` (default: all) survived; :attr:`Survivors.dropped` names
    the others (failure, error or missing) and why.
    """
    agents = tuple(results.agents if agents is None else agents)
    rows = {(r["agent"], r["seed"]): r for r in results.rows if r["agent"] in agents}
    all_seeds = sorted({s for _, s in rows})
    kept, dropped = [], {}
    for seed in all_seeds:
        why = []
        for agent in agents:
            row = rows.get((agent, seed))
            if row is None:
                why.append((agent, "missing"))
            elif row.get("error"):
                why.append((agent, "error"))
            elif _number(row, "failure") > 0:
                why.append((agent, "failure"))
        if why:
            dropped[seed] = tuple(why)
        else:
            kept.append(seed)
    return Survivors(agents, tuple(kept), dropped)


def survivor_difference(
    results: Results, kept: Survivors, metric: str | Metric, agent: str, reference: str
) -> PairedDifference:
    """``agent - reference`` of ``metric`` on the survivor seeds of ``kept`` only."""
    seeds = set(kept.seeds)
    rows = [r for r in results.rows_of(agent) if r["seed"] in seeds]
    ref = [r for r in results.rows_of(reference) if r["seed"] in seeds]
    return paired_rows_difference(rows, ref, metric, agent, reference)


def _rate(e: Estimate) -> str:
    """A per-step rate as "per 100 steps survived"."""
    if e.n == 0:
        return "n/a"
    return fmt_estimate(Estimate(PER_STEPS * e.mean, PER_STEPS * e.low, PER_STEPS * e.high, e.n))


def _difference(d: PairedDifference, scale: float = 1.0, unit_n: bool = True) -> str:
    if not d.seeds:
        return "n/a"
    e = d.estimate
    text = fmt_estimate(Estimate(scale * e.mean, scale * e.low, scale * e.high, e.n))
    return text + (f" (n={len(d.seeds)})" if unit_n else "")


def _median_solve_ms(rows: Sequence[dict[str, Any]], column: str = "solve_time_median") -> str:
    values = np.array([_number(r, column) for r in rows])
    values = values[np.isfinite(values)]
    return fmt(1e3 * float(np.median(values))) if len(values) else "n/a"


def _deadline_misses(rows: Sequence[dict[str, Any]]) -> str:
    """``misses of steps`` over the episodes that counted them (``n/a`` for rows written
    before the column existed)."""
    pairs = [(_number(r, "deadline_misses"), _number(r, "steps")) for r in rows]
    pairs = [(m, s) for m, s in pairs if np.isfinite(m) and np.isfinite(s)]
    if not pairs:
        return "n/a"
    return f"{int(sum(m for m, _ in pairs))} of {int(sum(s for _, s in pairs))}"


def _overview_table(doc: Document, results: Results, reference: str, kept: Survivors) -> None:
    """Per agent: episodes, failure rate, success rate, time to goal and cost against the
    reference, the median solve time."""
    rows = []
    for agent in results.agents:
        mine = results.rows_of(agent)
        failure = bootstrap_ci([_number(r, "failure") for r in mine])
        success = bootstrap_ci([_number(r, "success") for r in mine])
        if agent == reference:
            time_diff = cost_diff = "0 (reference)"
        else:
            t = paired_rows_difference(mine, results.rows_of(reference), "time_to_goal")
            c = survivor_difference(results, kept, "cost", agent, reference)
            time_diff, cost_diff = _difference(t), _difference(c)
        rows.append(
            [
                agent_label(agent),
                str(len(mine)),
                fmt_estimate(failure),
                fmt_estimate(success),
                time_diff,
                cost_diff,
                _median_solve_ms(mine),
                _median_solve_ms(mine, "step_time_median"),
                _deadline_misses(mine),
            ]
        )
    doc.table(
        [
            "agent",
            "episodes",
            "failure rate",
            "success rate",
            f"time to goal vs `{reference}` [s] (seeds both reach it)",
            f"cost vs `{reference}` (survivor seeds)",
            "median solve [ms]",
            "median step [ms]",
            f"steps over dt = {results.config.dt:g} s",
        ],
        rows,
    )


def _group_table(
    doc: Document, results: Results, count: HeadlineCount, reference: str, kept: Survivors
) -> None:
    """One constraint group's headline count: unbiased forms, the biased one beside them,
    and paired differences against the reference."""
    rate_metric = PerStepRate(count.column, count.label)
    vof_metric = ViolationOrFailure(count.column, count.label)
    survivor_seeds = set(kept.seeds)
    rows = []
    for agent in results.agents:
        mine = results.rows_of(agent)
        raw_all = bootstrap_ci([_number(r, count.column) for r in mine])
        raw_kept = bootstrap_ci(
            [_number(r, count.column) for r in mine if r["seed"] in survivor_seeds]
        )
        if agent == reference:
            d_rate = d_vof = d_kept = "0 (reference)"
        else:
            ref_rows = results.rows_of(reference)
            d_rate = _difference(
                paired_rows_difference(mine, ref_rows, rate_metric), PER_STEPS, unit_n=False
            )
            d_vof = _difference(paired_rows_difference(mine, ref_rows, vof_metric), unit_n=False)
            d_kept = _difference(
                survivor_difference(results, kept, count.column, agent, reference), unit_n=False
            )
        rows.append(
            [
                agent_label(agent),
                fmt_estimate(violation_or_failure(mine, count.column)),
                _rate(step_rate(mine, count.column)),
                fmt_estimate(raw_kept),
                fmt_estimate(raw_all),
                d_vof,
                d_rate,
                d_kept,
            ]
        )
    n_kept = len(kept.seeds)
    doc.table(
        [
            "agent",
            "violation-or-failure episodes",
            f"per {PER_STEPS} steps survived",
            f"per episode, {n_kept} survivor seeds",
            "per episode, all seeds (biased)",
            f"violation-or-failure vs `{reference}`",
            f"per {PER_STEPS} steps vs `{reference}`",
            f"per episode vs `{reference}`, survivor seeds",
        ],
        rows,
    )


def headline_section(doc: Document, results: Results, baseline: str) -> Survivors:
    """The report's headline: every agent's constraint metrics in forms that do not reward
    failing, paired against ``baseline``; returns the survivor seeds used.
    """
    reference = baseline
    kept = survivors(results)
    n_seeds = len(kept.seeds) + len(kept.dropped)
    doc.heading("Headline: metrics that do not reward failing")
    doc.paragraph(
        "An episode that ends in failure (the env ends it, e.g. the vehicle left the safety "
        "box) stops counting violations, so raw violation counts favour an agent that fails "
        "early. Here each constraint group is judged by its headline count (the steps whose "
        "excess over the group's bounds is above its smallest tolerance) in forms free of "
        f"that bias: the **violation-or-failure** rate (the fraction of episodes with at "
        "least one such step or a failure), the violations **per "
        f"{PER_STEPS} steps survived** (all violation steps over all steps, pooled over "
        "episodes), and the count per episode on the **survivor seeds** (the seeds on which "
        "every agent ran without error and did not fail). The raw count on all seeds is "
        "shown beside them, marked biased. Failures are a column of their own. Means with "
        "95% bootstrap intervals over episodes; paired differences `agent - "
        f"{reference}` on the same seeds (per-step rates per episode), n the seeds used."
    )
    if kept.dropped:
        doc.paragraph(
            f"Survivor seeds: {len(kept.seeds)} of {n_seeds}; dropped: {kept.describe()}."
        )
    else:
        doc.paragraph(f"Survivor seeds: all {n_seeds}; no agent failed or raised an error.")
    _overview_table(doc, results, reference, kept)
    for count in headline_counts(results.system):
        doc.paragraph(f"**{count.label}** (group `{count.group}`):")
        _group_table(doc, results, count, reference, kept)
    return kept
