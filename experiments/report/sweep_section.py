"""A report's risk-sweep section: which sweep a report includes, whether it ran on the
report's config (refused otherwise, unless allowed; the differing fields listed), and its
table and Pareto figure (:mod:`experiments.report.sweep_summary` reads the sweep)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from experiments import plots
from experiments.report.document import Document
from experiments.report.results import Results
from experiments.report.sweep_summary import (
    FIGURE_CAPTION,
    SWEEP_TABLE,
    SweepSummary,
    load_sweep,
    sweep_description,
    sweep_figure,
    sweep_table,
)


def load_report_sweep(directory: Path, sweep_dir: str | Path | None) -> SweepSummary | None:
    """The risk sweep to include: ``sweep_dir``'s, else the folder's own if it has one."""
    if sweep_dir is None:
        if not (directory / SWEEP_TABLE).is_file():
            return None
        sweep_dir = directory
    return load_sweep(sweep_dir)


def _flat(data: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config mapping as ``{dotted key: value}``."""
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in data.items():
        out.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def config_differences(ours: dict, theirs: dict) -> list[tuple[str, Any, Any]]:
    """``(dotted key, our value, their value)`` of every field two resolved configs (their
    :meth:`~controllers.config.ExperimentConfig.to_dict`) hold differently, sorted."""
    a, b = _flat(ours), _flat(theirs)
    missing = object()
    return [
        (k, a.get(k, "(none)"), b.get(k, "(none)"))
        for k in sorted(set(a) | set(b))
        if a.get(k, missing) != b.get(k, missing)
    ]


def check_sweep_config(
    results: Results, summary: SweepSummary, allow: bool
) -> list[tuple[str, Any, Any]]:
    """The fields where the sweep's base config differs from the report's; refused (a
    ``ValueError`` listing them) unless ``allow``."""
    ours = results.experiment.to_dict()
    diffs = config_differences(ours, summary.config)
    if diffs and not allow:
        shown = "; ".join(f"{k} ({_text(a)} here, {_text(b)} there)" for k, a, b in diffs[:8])
        more = f"; and {len(diffs) - 8} more" if len(diffs) > 8 else ""
        raise ValueError(
            f"the sweep {summary.directory} ran on another config than {results.directory}: "
            f"{shown}{more}. Rerun the sweep on this config, or include it anyway with "
            "lfm-report --allow-other-config (the report then lists these fields)"
        )
    return diffs


def _text(value: Any) -> str:
    return str(value) if not isinstance(value, str) else repr(value)


def sweep_section(
    doc: Document,
    results: Results,
    summary: SweepSummary,
    differences: Sequence[tuple[str, Any, Any]] = (),
) -> None:
    """The risk sweep's table and Pareto figure (see :mod:`experiments.sweep`), with the
    fields its config does not share with the report's, if any."""
    doc.heading(f"Risk trade-off: `{summary.key}` of `{summary.agent}`")
    world = summary.system.name
    doc.paragraph(
        f"From the sweep folder `{summary.directory}` (`lfm-sweep`, on the `{world}` system"
        + ("" if world == results.system.name else ", not this report's world")
        + "). "
        + sweep_description(summary)
    )
    if differences:
        doc.paragraph(
            f"**The sweep ran on another config than this report** ({len(differences)} "
            "fields differ; included with `--allow-other-config`): its numbers are not "
            "comparable with the tables above."
        )
        doc.table(
            ["field", "this report", "the sweep"],
            [[f"`{k}`", _text(a), _text(b)] for k, a, b in differences],
        )
    header, rows = sweep_table(summary)
    doc.table(header, rows)
    rel = "figures/sweep.png"
    plots.save_figure(sweep_figure(summary), results.directory / rel)
    doc.image(rel, FIGURE_CAPTION)
