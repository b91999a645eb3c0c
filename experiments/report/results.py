"""A results folder read back (:func:`load_results`: the table, the config and system, the
saved arrays on demand): the one reader for everything downstream of the evaluation.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from controllers.agents.registry import AGENT_REGISTRY
from controllers.config import ExperimentConfig, load_config
from experiments.evaluation.columns import tolerance_columns, violation_counts
from experiments.evaluation.storage import episode_stem, write_table
from lfm_env.config import WorldConfig, load_yaml, to_dict
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
        ValueError: naming the file, if it is unreadable, lacks ``agent``/``seed`` or rows.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no episodes table at {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"episodes table {str(path)!r} is not UTF-8 text ({exc.reason})") from None
    return _parse_table(text, path)


def _parse_table(text: str, path: Path) -> list[dict[str, Any]]:
    """The parsed rows of the text of an ``episodes.csv`` (``path`` names it in errors)."""
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        missing = {"agent", "seed"} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(f"{path}: missing column(s) {sorted(missing)}")
        rows = []
        for line in reader:
            row = {k: _parse_value(k, v) for k, v in line.items() if k is not None}
            row.setdefault("error", "")
            rows.append(row)
    except (csv.Error, ValueError) as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"episodes table {str(path)!r}: {exc}") from None
    if not rows:
        raise ValueError(f"{path} holds no episodes")
    return rows


def _disagreement(found: list[dict[str, Any]], expected: list[dict[str, Any]]) -> str | None:
    """How the table's rows differ from the records' (its rows, agents and seeds, then
    each value of a column both have), or ``None``."""

    def key(r: dict[str, Any]) -> tuple[str, int]:
        return r["agent"], r["seed"]

    def describe(rows: list[dict[str, Any]]) -> str:
        agents, seeds = {r["agent"] for r in rows}, {r["seed"] for r in rows}
        return f"{len(rows)} rows of {len(agents)} agents and {len(seeds)} seeds"

    if sorted(map(key, found)) != sorted(map(key, expected)):
        return f"holds {describe(found)}, the episode records {describe(expected)}"
    mine = {key(r): r for r in expected}
    for row in found:
        theirs = mine[key(row)]
        for column, value in row.items():
            other = theirs.get(column, value)
            if value != other and not (_is_nan(value) and _is_nan(other)):
                return f"differs from the records in {column} of {row['agent']}, seed {row['seed']}"
    return None


def _is_nan(value: Any) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _trusted_rows(directory: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The folder's table rows, checked against its episode records, and the records: a missing
    or disagreeing table is rebuilt from the records (one warning; rewritten unless a run still
    writes the folder).
    """
    from experiments.evaluation.storage import folder_in_use, saved_records, table_text, warn

    table = directory / "episodes.csv"
    records = saved_records(directory)
    if not records:
        return read_episodes_csv(table), records
    expected = _parse_table(table_text(directory), table)
    try:
        problem = _disagreement(read_episodes_csv(table), expected)
    except (OSError, ValueError) as exc:  # missing, not text, not a table
        problem = " ".join(str(exc).split())
    if problem is None or folder_in_use(directory) is not None:
        return expected if problem else read_episodes_csv(table), records
    warn(
        f"episodes table {str(table)!r} {problem}; rebuilt from the {len(records)} episode "
        f"records in {str(directory / 'episodes')!r}"
    )
    try:
        write_table(directory)
    except OSError as exc:
        warn(f"episodes table {str(table)!r} cannot be rewritten ({exc.strerror or exc})")
    return expected, records


def _checked_config(directory: Path, records: list[dict[str, Any]]) -> dict[str, Any]:
    """The config the folder's episodes ran with: ``config.yaml``, or the records' config when
    it was edited (one warning naming the fields).

    Raises:
        ValueError: ``config.yaml`` was edited and the records do not hold their config.
    """
    from experiments.evaluation.storage import edited_config, warn

    config_path = directory / "config.yaml"
    problem = edited_config(directory, records)
    if problem is None:
        return load_yaml(config_path)
    ran = next((r["config"] for r in records if isinstance(r.get("config"), dict)), None)
    if ran is None:
        raise ValueError(
            f"results folder {str(directory)!r}: {problem}; restore config.yaml to report it"
        )
    warn(f"results folder {str(directory)!r}: {problem}; the report uses the episodes' config")
    return ran


def load_results(results_dir: str | Path) -> Results:
    """Load ``episodes.csv`` and ``config.yaml`` of a results folder, checked against its
    episode records (a bad table is rebuilt from them, an edited config replaced by theirs,
    each with one warning); tolerance columns missing from an older table are computed from
    the saved trajectories.

    Raises:
        FileNotFoundError: the folder, its ``config.yaml`` or (without records) its
            ``episodes.csv`` is missing (naming the path).
        ValueError: no episodes, an unreadable table, or an edited config the records do
            not hold.
    """
    directory = Path(results_dir)
    if not directory.is_dir():
        problem = "is a file, not a folder" if directory.exists() else "does not exist"
        raise FileNotFoundError(f"results folder {directory} {problem}")
    config_path = directory / "config.yaml"
    if not config_path.is_file():
        read_episodes_csv(directory / "episodes.csv")  # (a missing or empty table first)
        raise FileNotFoundError(f"no config.yaml in {directory} (needed for dt and the system)")
    rows, records = _trusted_rows(directory)
    experiment = load_config(_checked_config(directory, records))  # read once
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
