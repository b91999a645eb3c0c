"""Two results folders side by side (``python -m experiments.report.compare_runs``)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from experiments.report.compare_runs import compare

COLUMNS = ("agent", "seed", "success", "time_to_goal", "solve_time_median")


def write_run(folder: Path, group: str, violations: list[int]) -> Path:
    """A folder whose episodes.csv holds one agent's episodes with ``group``'s column."""
    folder.mkdir()
    over = f"{group}_violation_steps_over_0.01"
    with (folder / "episodes.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=[*COLUMNS, over])
        writer.writeheader()
        for seed, v in enumerate(violations):
            writer.writerow(
                {
                    "agent": "robust",
                    "seed": seed,
                    "success": "True",
                    "time_to_goal": 7.0 + 0.1 * seed,
                    "solve_time_median": 0.001,
                    over: v,
                }
            )
    return folder


def test_the_group_defaults_to_the_worlds_own(tmp_path):
    ref = write_run(tmp_path / "a", "corridor", [0, 1, 0, 2, 0, 0])
    other = write_run(tmp_path / "b", "corridor", [3, 4, 5, 3, 4, 5])
    lines = compare(ref, other, None, 0.01)
    assert "| robust | corridor steps > 0.01 |" in lines[2]
    assert "| NO |" in lines[2]  # 4.0 lies outside the reference's interval
    assert lines[-1] == "metrics outside the reference's interval: 2"  # steps, zero-violation


def test_an_unknown_group_names_the_runs_groups(tmp_path):
    ref = write_run(tmp_path / "a", "corridor", [0, 1])
    other = write_run(tmp_path / "b", "corridor", [0, 1])
    with pytest.raises(SystemExit, match=r"--group 'track'.*\['corridor'\]"):
        compare(ref, other, "track", 0.01)
