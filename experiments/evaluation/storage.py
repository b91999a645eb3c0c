"""The results folder of an evaluation, written: episode files, the table, the config, the lock.

Layout and guarantees are those of :mod:`experiments.evaluation.run` (every file written
atomically, the npz before the json; one config per folder; one run at a time).
:func:`save_episode` writes an episode, :func:`saved_rows` and :func:`load_trajectory` read
them back (verified), :func:`finished_row` tells a resumed run which episodes are done,
:func:`write_table` rebuilds ``episodes.csv``, :class:`FolderLock` owns the folder while a
run writes into it. Downstream readers use
:func:`experiments.report.results.load_results`.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import hashlib
import io
import json
import math
import os
import secrets
import socket
import sys
import time
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
from experiments.evaluation.episode import (
    agent_seed,
    resolve_config,
)
from lfm_env.config import load_yaml
from lfm_env.validation import one_line

_EPISODES = "episodes"
_TABLE = "episodes.csv"
_CONFIG = "config.yaml"
_LOCK = ".lock"  # the owner's pid and host while a run writes into the folder


class ResultsFolderError(ValueError):
    """The results folder cannot be used (e.g. it holds results of another config)."""


# --------------------------------------------------------------------------- storage


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
    text = yaml.safe_dump(config.to_dict(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save_episode(
    out: str | os.PathLike,
    row: dict[str, Any],
    trajectory: dict[str, np.ndarray] | None,
    traceback_text: str = "",
    config_digest: str = "",
    run_token: str = "",
) -> Path:
    """Save an episode as ``episodes/<agent>__seed<seed>.npz`` then ``.json``, atomically.

    Args:
        out: the results folder.
        row: the episode's row (:func:`row_columns`, in that order).
        trajectory: arrays for the npz; ``None`` writes the json only.
        traceback_text: the traceback of a failed episode, kept in the json.
        config_digest: :func:`config_hash` of the episode's config, kept in the json.
        run_token: the run's token, for the row of an episode that got stuck past its
            limit and ended its process (:func:`stuck_row`); kept in the json as ``run``.

    Returns:
        The json's path (its presence marks the episode finished).
    """
    folder = Path(out) / _EPISODES
    stem = episode_stem(row["agent"], row["seed"])
    if trajectory is not None:
        _atomic_write(folder / f"{stem}.npz", lambda fh: np.savez_compressed(fh, **trajectory))
    record = {c: _json_value(v) for c, v in row.items()}
    record["agent_seed"] = agent_seed(row["seed"], row["agent"])
    record["traceback"] = traceback_text
    record["config_hash"] = config_digest
    if run_token:
        record["run"] = run_token
    text = json.dumps(record, indent=1, allow_nan=False) + "\n"
    json_path = folder / f"{stem}.json"
    _atomic_write(json_path, lambda fh: fh.write(text.encode()))
    return json_path


_JSON_EXTRAS = (
    "agent_seed",
    "traceback",
    "config_hash",
    "run",
)  # keys of an episode json that are not columns


def _normalise_row(record: dict[str, Any]) -> dict[str, Any]:
    """A row with NaN for missing numbers and Python types per column.

    The columns are the fixed ones (missing ones NaN) around whatever constraint-group
    columns the record holds, in its order: a folder of any system, or of an older
    version with other groups, reads as it was written.
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
    """The checked record of an episode json whose name is ``<agent>__seed<seed>.json``.

    Raises:
        DamagedEpisodeError: naming the file, if it cannot be read or parsed, is not an
            episode record, or holds another (agent, seed) than its name.
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
    """Every saved row of a results folder, sorted by (agent, seed): the storage layer's
    reader of the episode records (:func:`experiments.report.results.load_results` reads a folder
    for analysis: its table, config and trajectories).

    Reads the episode json files (exact values; ``episodes.csv`` holds the same rows as
    text). Metrics of failed episodes are NaN; filter on ``row["error"] == ""``. Files
    that are damaged, or hold another episode than their name (a copy), are left out
    with a warning on stderr naming them, so each (agent, seed) counts once.
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


def load_trajectory(out: str | os.PathLike, agent_name: str, seed: int) -> dict[str, np.ndarray]:
    """The saved trajectory of one episode (see :func:`run_episode` for its arrays).

    Raises:
        FileNotFoundError: the episode has no npz.
        DamagedEpisodeError: naming the file, if it does not load (e.g. truncated).
    """
    path = Path(out) / _EPISODES / f"{episode_stem(agent_name, seed)}.npz"
    if not path.is_file():
        raise FileNotFoundError(f"episode file {str(path)!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {one_line(exc)}") from exc
    # Episodes saved before 0.2 call the true force "disturbance".
    if "disturbance" in arrays and "latent_force" not in arrays:
        arrays["latent_force"] = arrays.pop("disturbance")
    return arrays


def finished_row(
    out: Path, agent_name: str, seed: int, record: bool, digest: str = ""
) -> dict | None:
    """The saved and verified row of a finished episode, or ``None`` if it must (re-)run.

    The json must be an episode record of this (agent, seed) and of this config (when
    it carries a config hash); with ``record`` the npz must exist and, for an episode
    that ran, load with one reward per step. A damaged file is named on stderr.
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


def write_table(out: str | os.PathLike, columns: Sequence[str] | None = None) -> Path:
    """Rebuild ``out/episodes.csv`` from every episode json (sorted by agent, seed).

    Args:
        out: the results folder.
        columns: the table's columns in order; ``None`` for :func:`row_columns` of the
            system in the folder's ``config.yaml`` (without one: the columns the saved
            rows hold). A column a row lacks (e.g. a group added since it was saved) is
            written as ``nan``.
    """
    rows = saved_rows(out)
    if columns is None:
        columns = _folder_columns(Path(out)) or _table_columns(rows)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_csv_value(row.get(c, math.nan)) for c in columns])
    path = Path(out) / _TABLE
    _atomic_write(path, lambda fh: fh.write(buf.getvalue().encode()))
    return path


def _remove_stale_temp_files(out: Path) -> None:
    """Delete temporary files a killed run may have left (only our ``.name.*.tmp``)."""
    for folder in (out, out / _EPISODES):
        for tmp in folder.glob(".*.tmp"):
            tmp.unlink(missing_ok=True)


def _config_differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    diffs = []
    for key in sorted(set(a) | set(b)):
        name = f"{prefix}{key}"
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            diffs += _config_differences(va, vb, f"{name}.")
        elif va != vb:
            diffs.append(f"{name}: {va!r} in the folder, {vb!r} now")
    return diffs


def check_folder(out: Path, config: ExperimentConfig) -> None:
    """Refuse a folder of another config (reads only).

    Its ``config.yaml`` must equal ``config``, and every episode json must carry
    :func:`config_hash` of ``config`` (or none: folders of older versions).
    """
    path = out / _CONFIG
    if out.exists() and not out.is_dir():
        raise ResultsFolderError(f"results folder {str(out)!r} is a file")
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


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


def _lock_owner(fd: int) -> tuple[bool, str]:
    """Whether the lock file names a live owner (a live process of this host, or one of
    another host), and a text naming it for a message."""
    try:
        parts = os.pread(fd, 200, 0).decode(errors="replace").split()
    except OSError:
        parts = []
    if len(parts) == 2 and parts[0].isdigit():
        alive = parts[1] != socket.gethostname() or _pid_alive(int(parts[0]))
        return alive, f"process {parts[0]} on {parts[1]}"
    return False, "another process"


def folder_in_use(out: str | os.PathLike) -> str | None:
    """Who holds the lock of the folder ``out`` (a text naming the process), or ``None``
    when no run writes into it. Looks without taking the lock for more than a moment
    (a run that starts meanwhile tries again: :meth:`FolderLock.acquire`)."""
    try:
        fd = os.open(Path(out) / _LOCK, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return None  # no lock file: no owner
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _lock_owner(fd)[1]
    except OSError:
        return None
    finally:
        os.close(fd)  # (releases a lock taken)
    return None


class FolderLock:
    """Ownership of a folder by one process: an operating-system lock on ``out/.lock``.

    The lock is ``flock`` (exclusive, not waiting) on the open lock file, which the kernel
    releases when its owner ends, however it ends (SIGKILL, the OOM killer, a crash): no
    stale lock is ever taken over, and of any number of processes trying at once exactly
    one owns the folder. The file holds ``<pid> <host>`` of the owner, for the message
    another process gets: a :class:`ResultsFolderError` naming it. The owner removes the
    file when it releases the lock (a lock file left by a killed owner is free to take).
    The lock is local to one machine's kernel (and NFS with its lock manager).

    Args:
        out: the folder (it must exist).
        what: how the messages call the folder.
        hint: what the message of a refusal advises.
    """

    def __init__(
        self,
        out: Path,
        what: str = "results folder",
        hint: str = "wait for that run to end or choose another output folder",
    ) -> None:
        self.path = Path(out) / _LOCK
        self.what, self.hint = what, hint
        self.text = f"{os.getpid()} {socket.gethostname()}\n"
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        """Take the lock, or raise :class:`ResultsFolderError` naming its owner.

        A lock held while the file names no live owner (an owner between taking the lock
        and writing its name, or a reader's short look: :func:`folder_in_use`) is tried
        again for a moment before the folder is refused.
        """
        folder = str(self.path.parent)
        for attempt in range(40):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                alive, owner = _lock_owner(fd)
                os.close(fd)
                if not alive and attempt < 39:
                    time.sleep(0.01)
                    continue
                raise ResultsFolderError(
                    f"{self.what} {folder!r} is in use by {owner} (lock file "
                    f"{str(self.path)!r}); {self.hint}"
                ) from None
            except BaseException:
                os.close(fd)
                raise
            # Its previous owner may have removed the file between our open and our lock:
            # the lock then holds a file no other process can find. Try again.
            try:
                current = os.stat(self.path)
                mine = os.fstat(fd)
                same = (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino)
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.pwrite(fd, self.text.encode(), 0)
            self._fd = fd
            return self
        raise ResultsFolderError(f"{self.what} {folder!r}: cannot take its lock {self.path}")

    def release(self) -> None:
        """Remove the lock file and release the lock (nothing if not held)."""
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)  # while still holding it
        finally:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


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
    "save_episode",
    "saved_rows",
    "stuck_row",
    "warn",
    "warnings_once",
    "write_table",
]
