"""Paired closed-loop comparison of two lfm-evaluate folders: open-loop and feedback agents.

Both folders ran the same world and seeds (the env seed fixes the latent force and the
noise, so episodes of one seed are paired), one with ``agents.prediction: open_loop``, the
other with ``feedback``. Prints per agent the episode figures and, for every agent of the
feedback folder, its paired differences (mean, 95% BCa interval) against ``--reference``
of the open-loop folder, and its time to goal against ``pf``'s.

    python scripts/compare_predictions.py OPEN_DIR FEEDBACK_DIR --group track
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import numpy as np

from experiments.report.stats import Metric, paired_rows_difference


def load(folder: Path) -> dict[str, list[dict]]:
    """Rows of ``folder/episodes.csv`` by agent (numbers as floats, seeds as ints)."""
    out: dict[str, list[dict]] = {}
    with (folder / "episodes.csv").open() as fh:
        for row in csv.DictReader(fh):
            r: dict = {}
            for k, v in row.items():
                if k in ("agent", "error"):
                    r[k] = v
                elif v in ("True", "False"):
                    r[k] = float(v == "True")
                else:
                    r[k] = float(v) if v not in ("", None) else math.nan
            r["seed"] = int(r["seed"])
            out.setdefault(r["agent"], []).append(r)
    return out


def _mean(rows: list[dict], key: str) -> float:
    x = np.array([r[key] for r in rows], dtype=float)
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if x.size else math.nan


def figures_table(sides: dict[str, dict[str, list[dict]]], group: str) -> str:
    over = f"{group}_violation_steps_over_0.01"
    lines = [
        f"| agent | prediction | episodes | reached goal | zero-violation episodes (1 cm) | "
        f"{group} steps > 1 cm (mean) | time to goal [s] (mean) | solver failures | "
        "unconverged (usable) | fallback steps | solve median [ms] (median) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for side, agents in sides.items():
        for agent, rows in agents.items():
            n = len(rows)
            zero = sum(r[over] == 0 for r in rows)
            solve = np.nanmedian([r["solve_time_median"] for r in rows]) * 1e3
            lines.append(
                f"| {agent} | {side} | {n} | {int(sum(r['success'] for r in rows))} | "
                f"{zero / n:.2f} | {_mean(rows, over):.2f} | {_mean(rows, 'time_to_goal'):.2f} | "
                f"{int(sum(r['solver_failures'] for r in rows))} | "
                f"{int(sum(r['unconverged_solves'] for r in rows))} | "
                f"{int(sum(r['fallback_steps'] for r in rows))} | {solve:.1f} |"
            )
    return "\n".join(lines)


def paired_table(
    open_rows: dict[str, list[dict]], fb_rows: dict[str, list[dict]], group: str, reference: str
) -> str:
    metrics = [
        Metric(f"{group}_violation_steps_over_0.01", f"{group} steps > 1 cm"),
        Metric(
            f"{group}_violation_steps_over_0.01", "zero-violation episodes (1 cm)", zero_count=True
        ),
        Metric("time_to_goal", "time to goal [s]"),
        Metric("cost", "cost"),
    ]
    lines = [
        "| feedback agent | metric | vs | seeds | mean difference [95% CI] | lower / higher |",
        "|---|---|---|---|---|---|",
    ]
    for agent, rows in fb_rows.items():
        pairs = [(m, reference) for m in metrics] + [(metrics[2], "pf")]
        for m, ref in pairs:
            if ref not in open_rows:
                continue
            d = paired_rows_difference(rows, open_rows[ref], m, agent, ref)
            e = d.estimate
            lines.append(
                f"| {agent} | {m.label} | {ref} (open loop) | {e.n} | "
                f"{e.mean:+.3f} [{e.low:+.3f}, {e.high:+.3f}] | "
                f"{d.agent_lower} / {d.reference_lower} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("open_dir", type=Path)
    parser.add_argument("feedback_dir", type=Path)
    parser.add_argument("--group", default="track", help="constraint group (track, corridor)")
    parser.add_argument("--reference", default="robust", help="open-loop agent to pair against")
    args = parser.parse_args()
    open_rows, fb_rows = load(args.open_dir), load(args.feedback_dir)
    print(figures_table({"open_loop": open_rows, "feedback": fb_rows}, args.group))
    print()
    print(paired_table(open_rows, fb_rows, args.group, args.reference))


if __name__ == "__main__":
    main()
