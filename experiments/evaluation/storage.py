"""The results folder of an evaluation: episode files (:func:`save_episode`, read back verified
by :func:`saved_rows`, :func:`load_trajectory`, :func:`finished_row`), the table
(:func:`write_table`), the config check and the lock (:class:`FolderLock`). Layout and
guarantees: ``docs/evaluation.md``.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import os
import secrets
import sys
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from controllers.config import ExperimentConfig
from experiments.evaluation.columns import (
    _BOOL_COLUMNS,
    _INT_COLUMNS,
    _STR_COLUMNS,
    _is_count_column,
    _table_columns,
    row_columns,
)
from experiments.evaluation.episode import agent_seed, resolve_config
from experiments.evaluation.lock import FolderLock, ResultsFolderError, folder_in_use
from lfm_env.config import load_yaml
from lfm_env.validation import one_line

_EPISODES = "episodes"
_TABLE = "episodes.csv"
_CONFIG = "config.yaml"


def episode_stem(agent_name: str, seed: int) -> str:
    """File name (without suffix) of an episode: ``<agent>__seed<seed>``."""
    return f"{agent_name}__seed{int(seed)}"


def _atomic_write(path: Path, write: Callable[[io.BufferedWriter], None]) -> None:
    """Write ``path`` through a temporary file in its folder, then ``os.replace`` it.

    Readers see the old file or the complete new one, never a torn one, even if the
    process is killed mid-write (only a ``.<name>.*.tmp`` file may be left behind).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    # os.open with mode 0o666 honours the umask (mkstemp would make the file private).
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _json_value(v: Any) -> Any:
    """Strict JSON: NaN becomes null, NumPy scalars become Python ones."""
    if isinstance(v, (np.generic,)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else v
    return v


def config_hash(config: ExperimentConfig) -> str:
    """A short stable hash of a resolved config (16 hex digits of SHA-256 of its YAML).

    Stored with every episode (``config_hash`` in its json), so a folder's episodes stay
    bound to their config even if ``config.yaml`` is deleted or replaced.
    """
    return data_hash(config.to_dict())


def data_hash(data: dict) -> str:
    """:func:`config_hash` of a config as plain data (a ``config.yaml`` as read, or the
    ``config`` of an episode's record): equal exactly when the data are."""
    text = yaml.safe_dump(data, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save_episode(
    out: str | os.PathLike,
    row: dict[str, Any],
    trajectory: dict[str, np.ndarray] | None,
    traceback_text: str = "",
    config_digest: str = "",
    run_token: str = "",
    config: dict | None = None,
) -> Path:
    """Save an episode as ``episodes/<agent>__seed<seed>.npz`` then ``.json``, atomically.

    Args:
        out: the results folder.
        row: the episode's row (:func:`row_columns`, in that order).
        trajectory: arrays for the npz; ``None`` writes the json only.
        traceback_text: the traceback of a failed episode, kept in the json.
        config_digest: :func:`config_hash` of the episode's config, kept in the json.
        run_token: the run's token (json ``run``), for :func:`stuck_row`.
        config: the episode's config as plain data, kept in the json.

    Returns:
        The json's path (marks the episode finished; holds the npz's ``npz_sha256``).
    """
    folder = Path(out) / _EPISODES
    stem = episode_stem(row["agent"], row["seed"])
    digest = None
    if trajectory is not None:
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **trajectory)
        data = buffer.getvalue()
        digest = hashlib.sha256(data).hexdigest()
        _atomic_write(folder / f"{stem}.npz", lambda fh: fh.write(data))
    record = {c: _json_value(v) for c, v in row.items()}
    record["agent_seed"] = agent_seed(row["seed"], row["agent"])
    record["traceback"] = traceback_text
    record["config_hash"] = config_digest
    if run_token:
        record["run"] = run_token
    if digest is not None:
        record["npz_sha256"] = digest
    if config is not None:
        record["config"] = config
    text = json.dumps(record, indent=1, allow_nan=False) + "\n"
    json_path = folder / f"{stem}.json"
    _atomic_write(json_path, lambda fh: fh.write(text.encode()))
    return json_path


_JSON_EXTRAS = (
    "agent_seed",
    "traceback",
    "config_hash",
    "run",
    "npz_sha256",
    "config",
)  # keys of an episode json that are not columns


def _normalise_row(record: dict[str, Any]) -> dict[str, Any]:
    """A row with NaN for missing numbers and Python types per column; the fixed columns around
    the record's own constraint-group columns, in its order.
    """
    columns = _table_columns([{k: None for k in record if k not in _JSON_EXTRAS}])
    row: dict[str, Any] = {}
    for c in columns:
        v = record.get(c)
        if c in _STR_COLUMNS:
            row[c] = "" if v is None else str(v)
        elif v is None or (isinstance(v, float) and math.isnan(v)):
            row[c] = math.nan
        elif c in _BOOL_COLUMNS:
            row[c] = bool(v)
        elif c in _INT_COLUMNS or _is_count_column(c):
            row[c] = int(v)
        else:
            row[c] = float(v)
    return row


class DamagedEpisodeError(ValueError):
    """An episode file that cannot be trusted (torn, garbage, or not the episode named)."""


def _read_record(path: Path) -> dict[str, Any]:
    """The checked record of an episode json named ``<agent>__seed<seed>.json``.

    Raises:
        DamagedEpisodeError: naming the file: unreadable, not a record, or another episode.
    """
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {one_line(exc)}") from exc
    if not isinstance(record, dict) or "agent" not in record or "seed" not in record:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: not an episode record")
    try:
        stem = episode_stem(str(record["agent"]), int(record["seed"]))
        row = _normalise_row(record)
    except (TypeError, ValueError) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {one_line(exc)}") from exc
    if path.name != f"{stem}.json":
        raise DamagedEpisodeError(
            f"episode file {str(path)!r} holds the row of {stem} (a copy or a renamed file)"
        )
    return {**row, **{k: record.get(k) for k in _JSON_EXTRAS}}


# The warnings printed in the current warnings_once() scope (innermost last).
_WARNED: list[set[str]] = []


@contextlib.contextmanager
def warnings_once() -> Iterator[None]:
    """Within it, each warning of :func:`warn` is printed once (an evaluation reads its
    folder more than once; a report reads a trajectory in several sections)."""
    _WARNED.append(set())
    try:
        yield
    finally:
        _WARNED.pop()


def warn(message: str) -> None:
    """One line ``warning: <message>`` on stderr (once per :func:`warnings_once` scope): a
    damaged file is named, never dropped silently."""
    if _WARNED:
        if message in _WARNED[-1]:
            return
        _WARNED[-1].add(message)
    print(f"warning: {message}", file=sys.stderr, flush=True)


_warn = warn


def saved_rows(out: str | os.PathLike) -> list[dict[str, Any]]:
    """Every saved row of a results folder from its episode json files, sorted by (agent, seed).
    Failed episodes have NaN metrics; damaged files or copies are left out with a warning.
    """
    folder = Path(out) / _EPISODES
    rows = []
    for p in sorted(folder.glob("*.json")):
        try:
            record = _read_record(p)
        except DamagedEpisodeError as exc:
            _warn(f"{exc}; left out")
            continue
        rows.append({k: v for k, v in record.items() if k not in _JSON_EXTRAS})
    return sorted(rows, key=lambda r: (r["agent"], r["seed"]))


def saved_records(out: str | os.PathLike) -> list[dict[str, Any]]:
    """Every checked episode record of a folder (its row and the json's other keys: the
    config hash, the config, the trajectory's SHA-256, ...), sorted by (agent, seed);
    damaged ones are left out, named in a warning (as :func:`saved_rows`)."""
    records = []
    for p in sorted((Path(out) / _EPISODES).glob("*.json")):
        try:
            records.append(_read_record(p))
        except DamagedEpisodeError as exc:
            _warn(f"{exc}; left out")
    return sorted(records, key=lambda r: (r["agent"], r["seed"]))


def _recorded_digest(json_path: Path) -> str | None:
    """The trajectory's SHA-256 an episode's record names (``None``: no record, or one
    written before records held it)."""
    try:
        value = json.loads(json_path.read_text()).get("npz_sha256")
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def load_trajectory(out: str | os.PathLike, agent_name: str, seed: int) -> dict[str, np.ndarray]:
    """The saved trajectory of one episode (its arrays: :func:`run_episode`).

    Raises:
        FileNotFoundError: the episode has no npz.
        DamagedEpisodeError: naming the file, if it does not load or its SHA-256 differs.
    """
    path = Path(out) / _EPISODES / f"{episode_stem(agent_name, seed)}.npz"
    if not path.is_file():
        raise FileNotFoundError(f"episode file {str(path)!r} does not exist")
    try:
        content = path.read_bytes()
    except OSError as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {one_line(exc)}") from exc
    try:
        with np.load(io.BytesIO(content), allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {one_line(exc)}") from exc
    recorded = _recorded_digest(path.with_suffix(".json"))
    if recorded is not None and hashlib.sha256(content).hexdigest() != recorded:
        raise DamagedEpisodeError(
            f"episode file {str(path)!r} is not the trajectory its record names (its SHA-256 "
            f"differs from the one in {path.with_suffix('.json').name}: another episode's file?)"
        )
    # Episodes saved before 0.2 call the true force "disturbance".
    if "disturbance" in arrays and "latent_force" not in arrays:
        arrays["latent_force"] = arrays.pop("disturbance")
    return arrays


def finished_row(
    out: Path, agent_name: str, seed: int, record: bool, digest: str = ""
) -> dict | None:
    """The saved and verified row of a finished episode of this config, or ``None`` if it must
    (re-)run; with ``record`` its npz must load with one reward per step.
    """
    stem = out / _EPISODES / episode_stem(agent_name, seed)
    json_path, npz_path = stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".npz")
    if not json_path.exists():
        return None
    try:
        record_ = _read_record(json_path)
        if digest and record_["config_hash"] not in (None, "", digest):
            raise DamagedEpisodeError(f"episode file {str(json_path)!r} is of another config")
        if record and not npz_path.exists():
            return None
        if record and record_["error"] == "":
            steps = len(load_trajectory(out, agent_name, seed)["reward"])
            if steps != record_["steps"]:
                raise DamagedEpisodeError(
                    f"episode file {str(npz_path)!r} holds {steps} steps, its row "
                    f"{record_['steps']}"
                )
    except (DamagedEpisodeError, KeyError) as exc:
        _warn(f"{exc}; running the episode again")
        return None
    return {k: v for k, v in record_.items() if k not in _JSON_EXTRAS}


def stuck_row(out: str | os.PathLike, agent_name: str, seed: int, token: str) -> dict | None:
    """The row an episode saved when it got stuck past its limit in the run of ``token``
    and ended its process (``None`` if it did not): a task run again after that process
    ended (a Dask worker's) returns it instead of running the episode again."""
    path = Path(out) / _EPISODES / f"{episode_stem(agent_name, seed)}.json"
    if not token or not path.is_file():
        return None
    try:
        record = _read_record(path)
    except DamagedEpisodeError:
        return None
    if record.get("run") != token:
        return None
    return {k: v for k, v in record.items() if k not in _JSON_EXTRAS}


def _quiet_records(out: Path) -> list[dict[str, Any]]:
    """The records of a folder that can be read, without warnings (a damaged one is named
    and run again later)."""
    records = []
    for p in sorted((out / _EPISODES).glob("*.json")):
        with contextlib.suppress(DamagedEpisodeError):
            records.append(_read_record(p))
    return records


def _csv_value(v: Any) -> str:
    if isinstance(v, float):
        return repr(v)  # shortest exact text; NaN as "nan"
    return str(v)


def _folder_columns(out: Path) -> tuple[str, ...] | None:
    """:func:`row_columns` of the system in the folder's ``config.yaml``; ``None`` without one."""
    path = out / _CONFIG
    if not path.is_file():
        return None
    try:
        return row_columns(resolve_config(load_yaml(path)).make_system())
    except ValueError:
        return None


def table_text(out: str | os.PathLike, columns: Sequence[str] | None = None) -> str:
    """The text of ``episodes.csv`` as :func:`write_table` writes it from the records."""
    rows = saved_rows(out)
    if columns is None:
        columns = _folder_columns(Path(out)) or _table_columns(rows)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_csv_value(row.get(c, math.nan)) for c in columns])
    return buf.getvalue()


def write_table(out: str | os.PathLike, columns: Sequence[str] | None = None) -> Path:
    """Rebuild ``out/episodes.csv`` from every episode json (sorted by agent, seed); ``columns``
    ``None``: those of the folder's ``config.yaml`` (else of the rows); missing ones ``nan``.
    """
    text = table_text(out, columns)
    path = Path(out) / _TABLE
    _atomic_write(path, lambda fh: fh.write(text.encode()))
    return path


def _remove_stale_temp_files(out: Path) -> None:
    """Delete temporary files a killed run may have left (only our ``.name.*.tmp``)."""
    for folder in (out, out / _EPISODES):
        for tmp in folder.glob(".*.tmp"):
            tmp.unlink(missing_ok=True)


def _config_differences(
    a: dict, b: dict, labels: tuple[str, str] = ("in the folder", "now"), prefix: str = ""
) -> list[str]:
    """``key: A <labels[0]>, B <labels[1]>`` for each field (dotted) where ``a`` and ``b``
    differ."""
    diffs = []
    for key in sorted(set(a) | set(b)):
        name = f"{prefix}{key}"
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            diffs += _config_differences(va, vb, labels, f"{name}.")
        elif va != vb:
            diffs.append(f"{name}: {va!r} {labels[0]}, {vb!r} {labels[1]}")
    return diffs


def edited_config(out: Path, records: Sequence[dict[str, Any]]) -> str | None:
    """Why the folder's ``config.yaml`` is not the config its episodes ran with (the fields that
    differ), else ``None``.

    Raises:
        ResultsFolderError: for episodes of more than one config.
    """
    hashes = sorted({r["config_hash"] for r in records if r.get("config_hash")})
    path = out / _CONFIG
    if not hashes or not path.is_file():
        return None
    if len(hashes) > 1:
        raise ResultsFolderError(
            f"results folder {str(out)!r} holds episodes of {len(hashes)} configs (config "
            f"hashes {', '.join(hashes)}); choose another output folder or delete this one"
        )
    try:
        written = load_yaml(path)
    except ValueError as exc:
        raise ResultsFolderError(f"results folder {str(out)!r}: bad {_CONFIG}: {exc}") from exc
    if data_hash(written) == hashes[0]:
        return None
    ran = next((r["config"] for r in records if isinstance(r.get("config"), dict)), None)
    if ran is None:
        return (
            f"its {_CONFIG} is not the config its episodes ran with (config hash "
            f"{data_hash(written)}, the episodes' {hashes[0]}; their records, written by an "
            "earlier version, do not hold the config itself)"
        )
    diffs = _config_differences(ran, written, ("in the episodes", f"in {_CONFIG}"))
    shown = "; ".join(diffs[:5]) + ("; ..." if len(diffs) > 5 else "")
    return f"its {_CONFIG} is not the config its episodes ran with ({shown})"


def check_folder(out: Path, config: ExperimentConfig) -> None:
    """Refuse a folder of another config (reads only): its ``config.yaml`` must be what its
    episodes ran with and equal ``config``, and their config hashes match.
    """
    path = out / _CONFIG
    if out.exists() and not out.is_dir():
        raise ResultsFolderError(f"results folder {str(out)!r} is a file")
    if out.is_dir():
        edited = edited_config(out, _quiet_records(out))
        if edited is not None:
            raise ResultsFolderError(
                f"results folder {str(out)!r}: {edited}; restore it (or choose another output "
                "folder)"
            )
    if path.exists():
        try:
            saved = resolve_config(load_yaml(path))
        except ValueError as exc:
            raise ResultsFolderError(f"results folder {str(out)!r}: bad {_CONFIG}: {exc}") from exc
        diffs = _config_differences(saved.to_dict(), config.to_dict())
        if diffs:
            shown = "; ".join(diffs[:5]) + ("; ..." if len(diffs) > 5 else "")
            raise ResultsFolderError(
                f"results folder {str(out)!r} holds results of a different config ({shown}); "
                "choose another output folder or delete this one"
            )
    digest = config_hash(config)
    for json_path in sorted((out / _EPISODES).glob("*.json")):
        try:
            other = json.loads(json_path.read_text()).get("config_hash")
        except (OSError, ValueError, AttributeError):
            continue  # a damaged file is named and re-run later
        if other not in (None, "", digest):
            raise ResultsFolderError(
                f"results folder {str(out)!r} holds results of a different config "
                f"({json_path.name} has config hash {other}, this config {digest}); "
                "choose another output folder or delete this one"
            )


def _prepare_folder(out: Path, config: ExperimentConfig) -> None:
    """Create the folder and its ``config.yaml``; remove temp files of a killed run."""
    path = out / _CONFIG
    out.mkdir(parents=True, exist_ok=True)
    (out / _EPISODES).mkdir(exist_ok=True)
    _remove_stale_temp_files(out)
    if not path.exists():
        text = "# Resolved config of the episodes in this folder.\n" + yaml.safe_dump(
            config.to_dict(), sort_keys=False
        )
        _atomic_write(path, lambda fh: fh.write(text.encode()))


__all__ = [
    "check_folder",
    "config_hash",
    "DamagedEpisodeError",
    "episode_stem",
    "finished_row",
    "FolderLock",
    "folder_in_use",
    "load_trajectory",
    "ResultsFolderError",
    "data_hash",
    "edited_config",
    "save_episode",
    "saved_records",
    "saved_rows",
    "stuck_row",
    "table_text",
    "warn",
    "warnings_once",
    "write_table",
]
