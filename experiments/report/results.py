"""A results folder of the evaluation, read back: its table, its config and its episodes.

:func:`load_results` is the one reader of a results folder for everything downstream of
the evaluation (the report, the sweep's tables, a user's own analysis): it returns a
:class:`Results` with the rows of ``episodes.csv`` (parsed: numbers as floats, ``agent``
and ``error`` as text), the world's config and system from ``config.yaml``, and the
episodes' saved arrays on demand (:func:`load_trajectory`). The storage layer's own
reader of the episode records is :func:`experiments.evaluation.storage.saved_rows`.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from controllers.agents.registry import AGENT_REGISTRY
from controllers.config import ExperimentConfig, load_config
from experiments.evaluation.columns import tolerance_columns, violation_counts
from experiments.evaluation.storage import episode_stem
from lfm_env.config import WorldConfig, to_dict
from lfm_env.system import ControlSystem

_TEXT_COLUMNS = ("agent", "error")
_FALSY = ("", "0", "0.0", "false", "no", "none", "nan")


@dataclass
class Results:
    """The saved results of one evaluation run."""

    directory: Path
    rows: list[dict[str, Any]]  # one per episode; numbers as float, agent/error as str
    config: WorldConfig  # the ``env`` section, as the config of the file's world (env_id)
    agent_settings: dict = field(default_factory=dict)  # the ``agents`` section, plain
    # Episode files that did not load, each with why (left out, named once on stderr).
    damaged: dict[Path, str] = field(default_factory=dict)
    # The whole config of the run (config.yaml, read once by load_results).
    experiment: ExperimentConfig | None = None

    @cached_property
    def system(self) -> ControlSystem:
        """The world's system (labels, units, constraints, groups) of the run."""
        return self.config.make_system()

    @property
    def agents(self) -> list[str]:
        """Agent names, the registered ones in their order, then the rest (a user's own) sorted."""
        names = {r["agent"] for r in self.rows}
        known = [a for a in AGENT_REGISTRY if a in names]
        return known + sorted(names - set(known))

    def rows_of(self, agent: str, include_errors: bool = False) -> list[dict[str, Any]]:
        """Rows of ``agent`` sorted by seed; episodes with errors only if asked."""
        rows = [r for r in self.rows if r["agent"] == agent and (include_errors or not r["error"])]
        return sorted(rows, key=lambda r: r["seed"])

    @property
    def error_rows(self) -> list[dict[str, Any]]:
        """Episodes that ended with an error, sorted by agent and seed."""
        return sorted((r for r in self.rows if r["error"]), key=lambda r: (r["agent"], r["seed"]))

    def trajectory_path(self, agent: str, seed: int) -> Path:
        """Where the arrays of one episode are saved."""
        return self.directory / "episodes" / f"{episode_stem(agent, seed)}.npz"


def _parse_value(column: str, text: str | None) -> Any:
    """A CSV cell as float (booleans as 0/1, empty or "nan" as NaN); text columns as str."""
    text = "" if text is None else text.strip()
    if column in _TEXT_COLUMNS:
        return "" if text.lower() in ("nan", "none") else text
    if column == "seed":
        return int(float(text))
    low = text.lower()
    if low in ("true", "yes"):
        return 1.0
    if low in ("false", "no"):
        return 0.0
    if low in ("", "nan", "none"):
        return math.nan
    try:
        return float(text)
    except ValueError:
        # A free-text outcome (e.g. a failure reason) counts as "happened".
        return 0.0 if low in _FALSY else 1.0


def read_episodes_csv(path: str | Path) -> list[dict[str, Any]]:
    """The rows of an ``episodes.csv``, parsed (see :func:`_parse_value`).

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: if it has no ``agent``/``seed`` columns or no rows.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no episodes table at {path}")
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        missing = {"agent", "seed"} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(f"{path}: missing column(s) {sorted(missing)}")
        rows = []
        for line in reader:
            row = {k: _parse_value(k, v) for k, v in line.items() if k is not None}
            row.setdefault("error", "")
            rows.append(row)
    if not rows:
        raise ValueError(f"{path} holds no episodes")
    return rows


def load_results(results_dir: str | Path) -> Results:
    """Load ``episodes.csv`` and ``config.yaml`` of a results folder.

    A table written before the tolerance-aware columns existed
    (``{g}_violation_steps_over_{t:g}``, see :func:`~experiments.evaluation.columns.row_columns`)
    gets them from the saved trajectories where those exist; episodes without one keep
    them missing (NaN), and the report leaves such metrics out.

    Raises:
        FileNotFoundError: if the folder, its ``episodes.csv`` or its ``config.yaml`` is
            missing (the message names the path).
        ValueError: if the table holds no episodes.
    """
    directory = Path(results_dir)
    if not directory.is_dir():
        problem = "is a file, not a folder" if directory.exists() else "does not exist"
        raise FileNotFoundError(f"results folder {directory} {problem}")
    rows = read_episodes_csv(directory / "episodes.csv")
    config_path = directory / "config.yaml"
    if not config_path.is_file():
        raise FileNotFoundError(f"no config.yaml in {directory} (needed for dt and the system)")
    experiment = load_config(config_path)  # the folder's config, read once
    agents_section = to_dict(experiment.agents)
    results = Results(directory, rows, experiment.env, agents_section, experiment=experiment)
    _complete_tolerance_columns(results)
    return results


def _complete_tolerance_columns(results: Results) -> None:
    """Fill missing tolerance-aware counts of error-free rows from their trajectories."""
    columns = [c for _, _, c in tolerance_columns(results.system)]
    for row in results.rows:
        missing = [c for c in columns if not np.isfinite(row.get(c, math.nan))]
        if not missing or row["error"]:
            continue
        traj = load_trajectory(results, row["agent"], row["seed"])
        if traj is None:  # not saved, or damaged: leave them missing
            continue
        counts = violation_counts(traj, results.system)
        row.update((c, float(counts[c])) for c in missing if c in counts)


def load_trajectory(results: Results, agent: str, seed: int) -> dict[str, np.ndarray] | None:
    """The saved arrays of one episode, or ``None`` if none were saved or its file is
    damaged: a damaged file (truncated, not an npz) is left out, named in a warning on
    stderr and recorded in :attr:`Results.damaged` (for the report to say so)."""
    path = results.trajectory_path(agent, seed)
    if not path.is_file() or path in results.damaged:
        return None
    from experiments.evaluation.storage import DamagedEpisodeError, warn
    from experiments.evaluation.storage import load_trajectory as load_saved

    try:
        return load_saved(path.parent.parent, agent, seed)
    except DamagedEpisodeError as exc:
        results.damaged[path] = str(exc)
        warn(f"{exc}; left out")
        return None


__all__ = [
    "Results",
    "load_results",
    "load_trajectory",
    "read_episodes_csv",
]
