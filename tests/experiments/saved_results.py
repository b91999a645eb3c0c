"""The small saved evaluation of the report's and figures' tests (its agents, seeds and
settings) and readers of what the report writes."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
TINY = {"env": {"max_steps": 20}, "agents": {"n_particles": 300, "n_scenarios": 5, "horizon": 5}}
AGENTS = ["nominal", "pf", "scenario", "oracle"]
SEEDS = [0, 1, 2]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def is_road(frame: np.ndarray) -> np.ndarray:
    """Pixels of the white lane lines drawn by highway-env."""
    return np.all(frame[..., :3] >= 240, axis=-1)


def is_car(frame: np.ndarray) -> np.ndarray:
    """Pixels of the yellow car (highway-env's default vehicle colour (255, 255, 0))."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return (r >= 200) & (g >= 200) & (b <= 80)


def referenced_files(text: str, html: bool) -> list[str]:
    pattern = r'src="([^"]+)"' if html else r"!\[[^\]]*\]\(([^)]+)\)"
    return re.findall(pattern, text)


def table_line(md: str, label: str, section: str = "## Results per agent") -> list[str]:
    """The cells of the table row starting with ``label`` in ``section``."""
    text = md.split(section)[1].split("\n## ")[0]
    line = next(x for x in text.splitlines() if x.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split(" | ")][1:]


def csv_values(results_dir: Path, agent: str, column: str) -> np.ndarray:
    with (results_dir / "episodes.csv").open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["agent"] == agent]
    return np.array([float(r[column]) for r in sorted(rows, key=lambda r: int(r["seed"]))])
