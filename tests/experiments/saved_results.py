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


# Helpers that make a results folder look as if its run had been another one. The folder's
# table and config are checked against its episode records (experiments.report.results), so
# the records are changed with them, as that run would have written them.


def _records(folder: Path) -> list[Path]:
    return sorted((folder / "episodes").glob("*.json"))


def as_if_run_with(folder: Path, edit) -> None:
    """``edit(config_dict)`` applied to ``config.yaml`` and to every episode's record (its
    config and config hash), as a run with that config would have written them."""
    import json

    import yaml

    from experiments.evaluation.storage import data_hash

    path = folder / "config.yaml"
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    for record_path in _records(folder):
        record = json.loads(record_path.read_text())
        record["config_hash"] = data_hash(data)
        if isinstance(record.get("config"), dict):
            edit(record["config"])
        record_path.write_text(json.dumps(record, indent=1) + "\n")


def resave_trajectory(path: Path, arrays: dict) -> None:
    """Write an episode's npz anew, with the SHA-256 its record names."""
    import hashlib
    import json

    np.savez_compressed(path, **arrays)
    record_path = path.with_suffix(".json")
    record = json.loads(record_path.read_text())
    record["npz_sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    record_path.write_text(json.dumps(record, indent=1) + "\n")


def rewrite_episodes(folder: Path, agents: dict[str, str | None]) -> None:
    """Keep the episodes of the agents named in ``agents``, renamed to their values (``None``:
    removed), and rebuild ``episodes.csv`` from the records."""
    import json

    from experiments.evaluation.storage import episode_stem, write_table

    for record_path in _records(folder):
        record = json.loads(record_path.read_text())
        new = agents.get(record["agent"])
        npz = record_path.with_suffix(".npz")
        if new is None:
            record_path.unlink()
            npz.unlink(missing_ok=True)
            continue
        if new != record["agent"]:
            stem = episode_stem(new, record["seed"])
            record["agent"] = new
            (folder / "episodes" / f"{stem}.json").write_text(json.dumps(record, indent=1))
            if npz.exists():
                npz.rename(folder / "episodes" / f"{stem}.npz")
            record_path.unlink()
    write_table(folder)


def add_error_row(folder: Path, agent: str, seed: int, error: str) -> None:
    """Save an error row of ``agent`` on ``seed`` as a run would (no trajectory), and
    rebuild ``episodes.csv``."""
    import json
    import math

    from experiments.evaluation.columns import row_columns
    from experiments.evaluation.episode import _error_row
    from experiments.evaluation.storage import save_episode, write_table
    from experiments.report.results import load_results

    columns = row_columns(load_results(folder).system)
    digest = json.loads(_records(folder)[0].read_text())["config_hash"]
    save_episode(folder, _error_row(agent, seed, error, math.nan, columns), None, "", digest)
    write_table(folder)


def copy_episodes(folder: Path, agent: str, new: str) -> None:
    """Add the episodes of ``agent`` again as those of an agent ``new`` (records and
    trajectories), and rebuild ``episodes.csv``."""
    import json
    import shutil

    from experiments.evaluation.storage import episode_stem, write_table

    for record_path in _records(folder):
        record = json.loads(record_path.read_text())
        if record["agent"] != agent:
            continue
        stem = episode_stem(new, record["seed"])
        record["agent"] = new
        (folder / "episodes" / f"{stem}.json").write_text(json.dumps(record, indent=1))
        npz = record_path.with_suffix(".npz")
        if npz.exists():
            shutil.copyfile(npz, folder / "episodes" / f"{stem}.npz")
    write_table(folder)
