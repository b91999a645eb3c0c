"""Two lfm-evaluate folders of the same agents and seeds, one against the other: per agent the
reference's headline means with their BCa intervals, the other's mean, whether it lies
inside, and the paired difference with its interval::

    python -m experiments.report.compare_runs REFERENCE OTHER [--group G] [--tolerance 0.01]
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import numpy as np

from experiments.report.stats import bootstrap_ci, paired_ci


def load(folder: Path) -> dict[str, dict[int, dict]]:
    """Rows of ``folder/episodes.csv`` by agent and seed (numbers as floats)."""
    out: dict[str, dict[int, dict]] = {}
    with (folder / "episodes.csv").open() as fh:
        for row in csv.DictReader(fh):
            r: dict = {}
            for k, v in row.items():
                if k in ("agent", "error"):
                    r[k] = v
                elif v in ("True", "False"):
                    r[k] = float(v == "True")
                else:
                    try:
                        r[k] = float(v)
                    except (TypeError, ValueError):
                        r[k] = math.nan
            out.setdefault(r["agent"], {})[int(r["seed"])] = r
    return out


def metrics(group: str, tolerance: float) -> list[tuple[str, object]]:
    """``(label, value of a row)`` of the judged metrics."""
    over = f"{group}_violation_steps_over_{tolerance:g}"
    return [
        (f"{group} steps > {tolerance:g}", lambda r: r[over]),
        (f"zero-violation episodes ({tolerance:g})", lambda r: float(r[over] == 0)),
        ("time to goal [s]", lambda r: r["time_to_goal"] if r["success"] else math.nan),
        ("success rate", lambda r: r["success"]),
    ]


def _fmt(e) -> str:
    return f"{e.mean:.3g} [{e.low:.3g}, {e.high:.3g}]"


def _groups(runs: dict, tolerance: float) -> list[str]:
    """The constraint groups whose ``<group>_violation_steps_over_<tolerance>`` column every
    episode of ``runs`` has, in column order."""
    suffix = f"_violation_steps_over_{tolerance:g}"
    rows = [row for agent in runs.values() for row in agent.values()]
    if not rows:
        return []
    return [k[: -len(suffix)] for k in rows[0] if k.endswith(suffix) and all(k in r for r in rows)]


def _check_group(group: str | None, ref: dict, other: dict, tolerance: float) -> str:
    """``group``, or the first constraint group of both runs; an unknown one is an error
    naming those the runs have."""
    both = [g for g in _groups(ref, tolerance) if g in _groups(other, tolerance)]
    if group is None and both:
        return both[0]
    if group not in both:
        raise SystemExit(
            f"compare_runs: --group {group!r} with --tolerance {tolerance:g}: the runs' "
            f"constraint groups are {both} (a tolerance of the world's report columns)"
        )
    return group


def compare(ref_dir: Path, other_dir: Path, group: str | None, tolerance: float) -> list[str]:
    """The table's lines (Markdown) and a closing verdict; ``group`` None for the runs'
    first constraint group (``track`` on the sine track, ``corridor`` for the quadrotor)."""
    ref, other = load(ref_dir), load(other_dir)
    group = _check_group(group, ref, other, tolerance)
    lines = [
        f"| agent | metric | {ref_dir.name} mean [95% CI] | {other_dir.name} mean | inside | "
        "paired difference [95% CI] |",
        "|---|---|---|---|---|---|",
    ]
    outside = 0
    for agent in [a for a in ref if a in other]:
        seeds = sorted(set(ref[agent]) & set(other[agent]))
        for label, get in metrics(group, tolerance):
            a = np.array([get(ref[agent][s]) for s in seeds], dtype=float)
            b = np.array([get(other[agent][s]) for s in seeds], dtype=float)
            e = bootstrap_ci(a)
            m = float(np.nanmean(b)) if np.isfinite(b).any() else math.nan
            inside = e.low - 1e-12 <= m <= e.high + 1e-12
            outside += not inside
            both = np.isfinite(a) & np.isfinite(b)
            d = paired_ci(b[both], a[both])
            lines.append(
                f"| {agent} | {label} | {_fmt(e)} | {m:.3g} | {'yes' if inside else 'NO'} | "
                f"{_fmt(d)} |"
            )
        for column, label in (("solve_time_median", "median solve [ms]"),):
            a = np.nanmedian([ref[agent][s][column] for s in seeds]) * 1e3
            b = np.nanmedian([other[agent][s][column] for s in seeds]) * 1e3
            lines.append(f"| {agent} | {label} (median of episodes) | {a:.3g} | {b:.3g} | | |")
        if all("deadline_misses" in ref[agent][s] for s in seeds):
            a = sum(ref[agent][s]["deadline_misses"] for s in seeds)
            b = sum(other[agent][s]["deadline_misses"] for s in seeds)
            lines.append(f"| {agent} | deadline misses (all episodes) | {a:g} | {b:g} | | |")
    lines.append("")
    lines.append(f"metrics outside the reference's interval: {outside}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reference", type=Path)
    parser.add_argument("other", type=Path)
    parser.add_argument(
        "--group", default=None, help="constraint group (default: the world's first, e.g. track)"
    )
    parser.add_argument("--tolerance", type=float, default=0.01, help="[group unit] (0.01)")
    args = parser.parse_args()
    print("\n".join(compare(args.reference, args.other, args.group, args.tolerance)))


if __name__ == "__main__":
    main()
