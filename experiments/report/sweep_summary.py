"""A risk sweep's folder read back (:func:`load_sweep`), its table, Pareto figure and
``sweep.md``. Layout: ``sweep.json`` (the manifest), ``baseline/`` and ``<key>=<value>/``
(evaluation folders), ``sweep.md`` and ``sweep.png``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments import plots
from experiments.evaluation import run as evaluation
from experiments.report.document import Document
from experiments.report.format import agent_label, fmt, fmt_estimate
from experiments.report.stats import (
    FEW_SEEDS,
    Estimate,
    Metric,
    PairedDifference,
    bootstrap_ci,
    few_seeds_caveat,
    paired_rows_difference,
    tolerance_metrics,
    zero_violation_metrics,
)
from lfm_env.config import load_yaml

MANIFEST = "sweep.json"
SWEEP_TABLE = "sweep.md"
SWEEP_FIGURE = "sweep.png"
BASELINE_FOLDER = "baseline"
FIGURE_CAPTION = (
    "The risk trade-off: per value, the paired difference to the baseline (same seeds) in "
    "time to goal (x) and in violation steps beyond the tolerance (y), with 95% bootstrap "
    "intervals; the baseline is the star at the origin, lower left is better."
)


def value_folder(key: str, text: str) -> str:
    """The sub-folder of one value: ``<key>=<value>``, spaces and slashes removed."""
    return f"{key}=" + _UNSAFE_IN_NAME.sub("", text)


_UNSAFE_IN_NAME = re.compile(r"[\s/\\]+")


def sweep_metrics(system: Any) -> tuple[Metric, ...]:
    """The rows of the sweep's table: success rate, per group the violation steps beyond
    each tolerance and the zero-violation episodes at it (the raw counts for a group
    without tolerances), then time to goal."""
    groups = []
    for g in system.constraint_groups:
        steps = tolerance_metrics(system, g)
        zero = zero_violation_metrics(system, g)
        if steps:
            groups += [*steps, *zero[1:]]
        else:
            groups += [Metric(f"{g}_violation_steps", f"{g} violation steps", "steps"), zero[0]]
    return (
        Metric("success", "success rate", lower_is_better=False),
        *groups,
        Metric("time_to_goal", "time to goal (successful episodes)", "s"),
    )


def _pareto_metric(metrics: Sequence[Metric]) -> Metric:
    """The y axis of the Pareto picture: the first group's violation steps beyond its
    first tolerance (its raw count without tolerances)."""
    return next(m for m in metrics if m.unit == "steps")


@dataclass(frozen=True)
class SweepValue:
    """One value of the swept setting: its rows, statistics and paired differences."""

    text: str  # the value as given
    folder: Path
    rows: tuple[dict[str, Any], ...]  # the agent's rows on the sweep's seeds
    stats: dict[str, Estimate]  # metric key -> mean over error-free episodes
    differences: dict[str, PairedDifference]  # metric key -> value - baseline, paired


@dataclass(frozen=True)
class SweepSummary:
    """A sweep read from its folder (:func:`load_sweep`)."""

    directory: Path
    agent: str
    key: str
    baseline: str
    seeds: tuple[int, ...]
    system: Any  # the world's ControlSystem
    metrics: tuple[Metric, ...]
    baseline_rows: tuple[dict[str, Any], ...]
    baseline_stats: dict[str, Estimate]
    values: tuple[SweepValue, ...]
    config: dict = dataclasses.field(default_factory=dict)  # the base config, resolved

    @property
    def short_key(self) -> str:
        """The key's last part, for column headers: ``backoff``."""
        return self.key.rsplit(".", 1)[-1]


def metric_key(metric: Metric) -> str:
    """A metric's key in :class:`SweepValue` statistics: its column, ``zero:`` marked."""
    return f"zero:{metric.column}" if metric.zero_count else metric.column


def _rows(
    folder: Path, agent: str, seeds: Iterable[int], system: Any
) -> tuple[dict[str, Any], ...]:
    """The agent's rows of an evaluation folder on ``seeds``; tolerance-aware counts that
    an older row lacks are counted from its saved trajectory when there is one."""
    wanted = set(seeds)
    rows = evaluation.saved_rows(folder) if (folder / "episodes").is_dir() else []
    rows = [r for r in rows if r["agent"] == agent and r["seed"] in wanted]
    columns = [c for _, _, c in evaluation.tolerance_columns(system)]
    for row in rows:
        if row["error"] or all(c in row for c in columns):
            continue
        try:
            traj = evaluation.load_trajectory(folder, agent, row["seed"])
        except (OSError, ValueError, zipfile.BadZipFile):  # none readable: leave them missing
            continue
        counts = evaluation.violation_counts(traj, system)
        row.update((c, v) for c, v in counts.items() if c not in row)
    return tuple(rows)


def _stats(rows: Sequence[dict[str, Any]], metrics: Sequence[Metric]) -> dict[str, Estimate]:
    ok = [r for r in rows if not r["error"]]
    return {metric_key(m): bootstrap_ci([m.value(r) for r in ok]) for m in metrics}


def read_manifest(out: Path) -> dict[str, Any] | None:
    path = out / MANIFEST
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise evaluation.ResultsFolderError(
            f"sweep folder {str(out)!r}: bad {MANIFEST}: {exc}"
        ) from exc
    keys = ("agent", "baseline", "key", "values", "seeds")
    if not isinstance(data, dict) or any(k not in data for k in keys):
        raise evaluation.ResultsFolderError(
            f"sweep folder {str(out)!r}: {MANIFEST} must hold {list(keys)}"
        )
    return data


def load_sweep(directory: str | os.PathLike) -> SweepSummary:
    """Read a sweep folder: its manifest, the baseline's and every value's rows.

    Raises:
        FileNotFoundError: the folder, ``sweep.json`` or the baseline's ``config.yaml`` is
            missing (naming the path).
        ResultsFolderError: the manifest is unreadable.
    """
    out = Path(directory)
    manifest = read_manifest(out) if out.is_dir() else None
    if manifest is None:
        raise FileNotFoundError(f"no risk sweep in {out}: {out / MANIFEST} does not exist")
    base_folder = out / BASELINE_FOLDER
    if not (base_folder / "config.yaml").is_file():
        raise FileNotFoundError(
            f"sweep {out}: the baseline's {base_folder / 'config.yaml'} is missing"
        )
    base_config = evaluation.resolve_config(load_yaml(base_folder / "config.yaml"))
    system = base_config.make_system()
    metrics = sweep_metrics(system)
    seeds = tuple(int(s) for s in manifest["seeds"])
    agent, baseline, key = manifest["agent"], manifest["baseline"], manifest["key"]
    baseline_rows = _rows(base_folder, baseline, seeds, system)
    values = []
    for text in manifest["values"]:
        folder = out / value_folder(key, text)
        rows = _rows(folder, agent, seeds, system)
        diffs = {
            metric_key(m): paired_rows_difference(rows, baseline_rows, m, agent, baseline)
            for m in metrics
        }
        values.append(SweepValue(text, folder, rows, _stats(rows, metrics), diffs))
    return SweepSummary(
        directory=out,
        agent=agent,
        key=key,
        baseline=baseline,
        seeds=seeds,
        system=system,
        metrics=metrics,
        baseline_rows=baseline_rows,
        baseline_stats=_stats(baseline_rows, metrics),
        values=tuple(values),
        config=base_config.to_dict(),
    )


def _episodes_text(rows: Sequence[dict[str, Any]]) -> str:
    errors = sum(1 for r in rows if r["error"])
    return f"{len(rows) - errors}" + (f" ({errors} with errors)" if errors else "")


def sweep_table(summary: SweepSummary) -> tuple[list[str], list[list[str]]]:
    """The sweep's ``(header, rows)``: one row per metric, the baseline's mean [95% CI], then per
    value its mean and ``Δ`` the paired difference on the same seeds [95% CI] (``(n seeds)``
    when fewer pair).
    """
    header = [
        "metric",
        f"{agent_label(summary.baseline)} (baseline)",
        *(f"{summary.short_key}={v.text}" for v in summary.values),
    ]
    n_base = sum(1 for r in summary.baseline_rows if not r["error"])
    rows = [
        ["episodes (error-free)", _episodes_text(summary.baseline_rows)]
        + [_episodes_text(v.rows) for v in summary.values]
    ]
    for m in summary.metrics:
        k = metric_key(m)
        row = [m.title, fmt_estimate(summary.baseline_stats[k], n_base)]
        for v in summary.values:
            d = v.differences[k]
            n_ok = sum(1 for r in v.rows if not r["error"])
            cell = f"{fmt(v.stats[k].mean)}; Δ {fmt_estimate(d.estimate)}"
            if 0 < len(d.seeds) < min(n_ok, n_base):
                cell += f" ({len(d.seeds)} seeds)"
            row.append(cell if v.stats[k].n else "n/a")
        rows.append(row)
    return header, rows


def sweep_description(summary: SweepSummary) -> str:
    """One paragraph saying what the sweep's table holds."""
    seeds = summary.seeds
    span = f"{seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else f"{seeds[0]}"
    return (
        f"The `{summary.agent}` agent with `{summary.key}` set to each of "
        f"{', '.join(v.text for v in summary.values)}, against the `{summary.baseline}` "
        f"agent (baseline, on the base config) on the same {len(seeds)} env seeds ({span}): "
        "the same hidden latent force and noise for every column. A value's cell is its "
        "mean, then Δ the paired difference `value - baseline` with a 95% paired BCa "
        "bootstrap interval over the seeds both ran without error (an interval that "
        "excludes 0 is a difference the seeds support). Violation steps `> t` count the "
        "steps whose excess over the group's bounds is above the tolerance t; "
        "zero-violation episodes are the fraction of episodes with none."
        + (f" **{caveat}**" if (caveat := few_seeds_caveat(len(seeds))) else "")
    )


def sweep_figure(summary: SweepSummary):
    """The Pareto picture: violations beyond the first tolerance against time to goal."""
    y_metric = _pareto_metric(summary.metrics)
    x_metric = next(m for m in summary.metrics if m.column == "time_to_goal")
    points = []
    for v in summary.values:
        dx = v.differences[metric_key(x_metric)].estimate
        dy = v.differences[metric_key(y_metric)].estimate
        label = f"{summary.short_key}={v.text}"
        points.append((label, [dx.mean, dx.low, dx.high], [dy.mean, dy.low, dy.high]))
    base_x = summary.baseline_stats[metric_key(x_metric)].mean
    base_y = summary.baseline_stats[metric_key(y_metric)].mean
    return plots.pareto_figure(
        points,
        baseline=agent_label(summary.baseline),
        xlabel="time to goal: value - baseline [s] (paired)",
        ylabel=f"{y_metric.label}: value - baseline (paired)",
        title=(
            f"{summary.agent}: {summary.key} against {summary.baseline} "
            f"(baseline: {fmt(base_y)} steps, {fmt(base_x)} s)"
        ),
    )


def _reading(summary: SweepSummary) -> list[str]:
    """Plain words per value on the Pareto picture's two axes."""
    out = []
    for m in (_pareto_metric(summary.metrics), summary.metrics[-1]):
        for v in summary.values:
            e = v.differences[metric_key(m)].estimate
            if e.n == 0:
                out.append(f"{summary.short_key}={v.text}: {m.label}: no common seeds.")
                continue
            if e.low > 0 or e.high < 0:
                verdict = "higher than" if e.low > 0 else "lower than"
                verdict += " the baseline's (the interval excludes 0"
                verdict += f"; only {e.n} seeds: a hint, not a finding)" if e.n < FEW_SEEDS else ")"
            else:
                verdict = "not distinguishable from the baseline's (the interval holds 0)"
            unit = f" {m.unit}" if m.unit and m.unit != "steps" else ""
            out.append(
                f"{summary.short_key}={v.text}: {m.label} {verdict}: Δ {fmt(e.mean)}{unit} "
                f"[{fmt(e.low)}, {fmt(e.high)}] over {e.n} seeds."
            )
    return out


def write_sweep(summary: SweepSummary) -> Path:
    """Write ``sweep.md`` and ``sweep.png`` into the folder; returns the path of ``sweep.md``."""
    plots.save_figure(sweep_figure(summary), summary.directory / SWEEP_FIGURE)
    doc = Document()
    doc.heading(f"Risk sweep: `{summary.key}` of `{summary.agent}` against `{summary.baseline}`", 1)
    doc.paragraph(sweep_description(summary))
    header, rows = sweep_table(summary)
    doc.table(header, rows)
    doc.image(SWEEP_FIGURE, FIGURE_CAPTION)
    doc.paragraph("In plain words:")
    doc.bullets(_reading(summary))
    path = summary.directory / SWEEP_TABLE
    path.write_text(doc.markdown())
    return path


def sweep_errors(summary: SweepSummary) -> int:
    """Episodes of the sweep (baseline and values) that ended with an error."""
    rows = list(summary.baseline_rows) + [r for v in summary.values for r in v.rows]
    return sum(1 for r in rows if r["error"])
