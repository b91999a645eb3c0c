"""Evaluation of agents over env seeds, saved episode by episode so no result is lost.

:func:`evaluate` runs every (agent, seed) episode (paired design: on one env seed every agent
meets the same latent force and noise; its own randomness comes from :func:`agent_seed`) and
returns one row per episode, serially, on a process pool (:mod:`experiments.evaluation.pool`)
or on Dask (:mod:`experiments.evaluation.executors`). The results folder, its atomic writes,
lock and resume, time limits, interrupts and what each executor promises are described in
``docs/evaluation.md``. One episode is :mod:`experiments.evaluation.episode`, the columns
:mod:`experiments.evaluation.columns`, the folder :mod:`experiments.evaluation.storage`;
their public names are also importable from here.
"""

from __future__ import annotations

import math
import os
import secrets
import time
import traceback
from collections.abc import Iterable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import lfm_env  # noqa: F401  (registers the envs, also in spawned workers)
from controllers.agents.registry import AgentSpec, resolve_agents
from controllers.config import ExperimentConfig
from experiments.evaluation.columns import (
    HEAD_COLUMNS,
    TAIL_COLUMNS,
    TIMING_COLUMNS,
    group_columns,
    row_columns,
    tolerance_column,
    tolerance_columns,
    violation_counts,
)
from experiments.evaluation.episode import (
    MAX_SEEDS,
    SAVED_SCENARIOS,
    _error_row,
    agent_seed,
    check_seeds,
    parse_seeds,
    resolve_config,
    run_episode,
)
from experiments.evaluation.interrupts import raise_if_interrupted, remember_interrupts
from experiments.evaluation.limits import check_limit
from experiments.evaluation.pool import run_on_pool, safe_child_path
from experiments.evaluation.storage import (
    DamagedEpisodeError,
    FolderLock,
    ResultsFolderError,
    _prepare_folder,
    _remove_stale_temp_files,
    check_folder,
    config_hash,
    episode_stem,
    finished_row,
    load_trajectory,
    save_episode,
    saved_rows,
    stuck_row,
    warnings_once,
    write_table,
)
from experiments.evaluation.task import _episode_task, check_picklable, sendable_problem
from lfm_env import working_folder
from lfm_env.validation import one_line

_SCHEDULER_TIMEOUT = 5.0  # [s] to connect to a Dask scheduler AND hear it answer as one
_TABLE_REFRESH = 10.0  # [s] least time between rebuilds of episodes.csv during a run


def _connect_dask(scheduler: str | None, dask_workers: int | None, stack: Any):
    """A ``distributed.Client`` on an existing scheduler or on a new loopback cluster."""
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(
            "Dask runs need the 'distributed' package: pip install 'lfm-scenario-mpc[dist]'"
        ) from exc
    import logging

    from experiments.evaluation import executors

    if scheduler is not None:
        # Client's own timeout bounds only the TCP connect: check the answer first.
        executors.check_scheduler(scheduler, _SCHEDULER_TIMEOUT)
        try:
            client = distributed.Client(scheduler, timeout=f"{_SCHEDULER_TIMEOUT:g}s")
        except Exception as exc:  # OSError or TimeoutError, depending on the failure
            raise ConnectionError(
                f"cannot reach the Dask scheduler at {scheduler!r} within "
                f"{_SCHEDULER_TIMEOUT:g} s ({one_line(exc)})"
            ) from exc
        return stack.enter_context(client)
    # Loopback only, mutual TLS with a temporary certificate, no HTTP endpoint.
    logging.getLogger("distributed").setLevel(logging.ERROR)
    return executors.local_client(dask_workers, stack)


def evaluate(
    agents: Sequence[Any] | str,
    seeds: Iterable[int] | str,
    config: ExperimentConfig | str | os.PathLike | dict | None = None,
    out: str | os.PathLike | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    dask_workers: int | None = None,
    progress: bool = True,
    record: bool = True,
    retry_failed: bool = True,
    progress_label: str | None = None,
    episode_timeout: float | None = None,
    isolate: bool | None = None,
) -> list[dict[str, Any]]:
    """Run every (agent, env seed) episode and return one row of metrics per episode.

    Args:
        agents: registered names, factories ``factory(config)``, agent objects or
            ``"module:attribute"`` texts (:mod:`controllers.agents.registry`), or one comma
            list of names; each is built once before any episode.
        seeds: env seeds (integers >= 0), or a text for :func:`parse_seeds`.
        config: an :class:`~controllers.config.ExperimentConfig`, or a preset's name, YAML
            path, dict or ``None`` (paper defaults), resolved once.
        out: results folder; ``None`` keeps nothing on disk. Saved episodes are not re-run.
        jobs: local worker processes (``spawn``; a script needs the ``__main__`` guard);
            1 is serial.
        scheduler: address of an existing Dask scheduler (``"tcp://host:8786"``).
        dask_workers: start a private loopback Dask cluster of this many workers.
        progress: show a tqdm progress bar over episodes.
        record: save each episode's trajectory (npz) next to its row.
        retry_failed: re-run saved episodes whose ``error`` is not empty.
        progress_label: text before the progress bar.
        episode_timeout: wall-clock limit of one episode [s]; ``None`` for the config's
            ``evaluation.episode_timeout``, 0 for no limit.
        isolate: serial run in a child process (a native crash costs one episode);
            ``None``: when every agent can be sent to one, ``False``: in this process.

    Returns:
        The rows of the requested episodes sorted by (agent, seed), loaded ones included.

    Raises:
        ValueError: bad agents, seeds, config, run modes or a folder of another config,
            before any episode runs.
        ConnectionError: the Dask scheduler cannot be reached.
    """
    specs, seed_list, cfg, columns = _checked_arguments(
        agents, seeds, config, jobs, scheduler, dask_workers
    )
    in_process = _in_process(specs, cfg, isolate)
    limit = check_limit(
        cfg.evaluation.episode_timeout if episode_timeout is None else episode_timeout
    )
    out_path = None if out is None else Path(out).resolve()
    run = _Run(specs, seed_list, cfg, columns, out_path, record, retry_failed, limit)
    if out_path is not None:
        check_folder(out_path, cfg)

    with ExitStack() as stack:
        stack.enter_context(remember_interrupts())
        stack.enter_context(warnings_once())  # (the folder is read more than once)
        stack.enter_context(safe_child_path())  # (workers: no working folder on the path)
        # Closed after the executor below (last in, first out): the folder is finished
        # and unlocked only once no worker writes into it any more.
        folder_stack = stack.enter_context(ExitStack())
        if out_path is not None:
            run.load_finished()  # read only: whether a Dask cluster is needed at all
        # Connect before the first episode: an unreachable scheduler fails fast.
        client = None
        if run.todo() and (scheduler is not None or dask_workers is not None):
            client = _connect_dask(scheduler, dask_workers, stack)
        if out_path is not None:
            _take_folder(run, folder_stack)
            run.load_finished()
        todo = run.todo()
        run.bar = stack.enter_context(_progress_bar(run, progress, progress_label))
        if todo:
            _compile_ahead(specs, cfg)  # (before the first episode's clock starts)
        if client is not None and todo:
            _run_on_dask(run, client, todo)
        elif jobs > 1 and len(todo) > 1:
            _run_on_pool(run, jobs, todo)
        elif in_process or not todo:
            _run_serially(run, todo)
        else:  # serial, in one child process (replaced if it dies)
            run_on_pool(
                todo, 1, lambda pair: run.task_args(*pair), run.done, run.lost, limit, "exec"
            )

    return run.sorted_rows()


def _compile_ahead(specs: Sequence[AgentSpec], cfg: ExperimentConfig) -> None:
    """Compile the C libraries of the fast solvers before any episode runs, when a
    registered agent will solve with one (they are then found in the cache by every
    worker): a compile never counts against an episode's time limit."""
    solver = cfg.agents.solver
    solving = any(s.agent_class is not None and "solver" in s.uses for s in specs)
    if not solving or solver not in ("fast", "fast_c"):
        return
    from controllers.solvers.fast.codegen.build import CodegenUnavailable
    from controllers.solvers.fast.prepare import compile_ahead

    try:
        model = cfg.make_model()
        compile_ahead(model.system, model.dt, compiled_loop=solver == "fast_c")
    except CodegenUnavailable:  # (no compiler at all: the agents say so themselves)
        pass


def _in_process(specs: Sequence[AgentSpec], cfg: ExperimentConfig, isolate: Any) -> bool:
    """Whether a serial run runs its episodes in this process (``evaluate``'s ``isolate``).

    Raises:
        ValueError: ``isolate=True`` with an agent or a world that cannot be sent to a
            child process (naming it).
    """
    if isolate is not None and not isinstance(isolate, bool):
        raise ValueError(f"isolate={isolate!r}: must be True, False or None")
    if isolate is False:
        return True
    problems = [p for p in map(sendable_problem, specs) if p is not None]
    world = type(cfg.env).__module__
    if world in ("__main__", "__mp_main__"):
        problems.append(
            f"the world's config {type(cfg.env).__name__} is defined in the main script"
        )
    if problems and isolate:
        raise ValueError(
            f"isolate=True: {problems[0]}; a child process cannot import it (define it in a "
            "module, or pass isolate=False)"
        )
    return bool(problems)


def _checked_arguments(
    agents: Any, seeds: Any, config: Any, jobs: int, scheduler: str | None, dask_workers: int | None
) -> tuple[list[AgentSpec], list[int], ExperimentConfig, tuple[str, ...]]:
    """The run's agents, seeds, config and table columns, every argument checked (and
    every user agent built once) before any episode runs."""
    specs = resolve_agents(agents)
    seed_list = check_seeds(seeds)
    cfg = resolve_config(config, specs)  # every agent checked on it (a user's built once)
    columns = row_columns(cfg.make_system())
    modes = sum([jobs != 1, scheduler is not None, dask_workers is not None])
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs={jobs!r}: must be an integer >= 1")
    if dask_workers is not None and (
        isinstance(dask_workers, bool) or not isinstance(dask_workers, int) or dask_workers < 1
    ):
        raise ValueError(f"dask_workers={dask_workers!r}: must be an integer >= 1")
    if modes > 1:
        raise ValueError("choose one of jobs > 1, scheduler and dask_workers")
    if jobs > 1 or scheduler is not None or dask_workers is not None:
        for spec in specs:
            check_picklable(spec, "pool" if jobs > 1 else "dask")
    return specs, seed_list, cfg, columns


class _Run:
    """One call's episodes: the (agent, seed) pairs, the rows finished so far (loaded from
    the folder or just run), the progress bar and the table kept up to date."""

    def __init__(
        self,
        specs: Sequence[AgentSpec],
        seeds: Sequence[int],
        cfg: ExperimentConfig,
        columns: Sequence[str],
        out: Path | None,
        record: bool,
        retry_failed: bool,
        limit: float | None = None,
    ) -> None:
        names = [a.name for a in specs]
        self.spec_of = dict(zip(names, specs, strict=True))
        # Seed-major order: an interrupted run leaves complete pairs of agents per seed.
        self.pairs = [(a, s) for s in seeds for a in names]
        self.rows: dict[tuple[str, int], dict[str, Any]] = {}
        self.retried: set[tuple[str, int]] = set()  # pairs whose saved row is an error
        self.cfg, self.columns = cfg, columns
        self.out, self.record, self.retry_failed = out, record, retry_failed
        self.digest = config_hash(cfg)
        self.limit = limit
        self.token = secrets.token_hex(8)  # this call's (marks the rows of stuck episodes)
        self.bar: Any = None
        self.last_table = time.monotonic()
        self.n_errors = 0

    def load_finished(self) -> None:
        """The saved rows of this run's pairs (verified; an error row only without retry)."""
        self.rows.clear()
        self.retried.clear()
        for a, s in self.pairs:
            row = finished_row(self.out, a, s, self.record, self.digest)
            if row is not None and (row["error"] == "" or not self.retry_failed):
                self.rows[(a, s)] = row
            elif (self.out / "episodes" / f"{episode_stem(a, s)}.json").exists():
                self.retried.add((a, s))  # an error row, or a damaged or incomplete episode

    def todo(self) -> list[tuple[str, int]]:
        """The pairs still to run, in seed-major order: those never run first, then those
        whose saved row is an error (so an episode that fails again, or ends a serial run
        stuck past its limit, comes after the others)."""
        todo = [p for p in self.pairs if p not in self.rows]
        return [p for p in todo if p not in self.retried] + [p for p in todo if p in self.retried]

    def task_args(self, agent: str, seed: int, stuck: str = "") -> tuple:
        """The arguments of :func:`_episode_task` for one episode (``stuck``: what ends
        when it is stuck past its limit)."""
        out = None if self.out is None else str(self.out)
        spec = self.spec_of[agent]
        return spec, self.cfg, seed, out, self.record, self.digest, self.limit, stuck, self.token

    def done(self, pair: tuple[str, int], row: dict[str, Any]) -> None:
        """Record a finished episode; rebuild the table now and then."""
        self.rows[pair] = row
        self.n_errors += row["error"] != ""
        self.bar.update(1)
        if self.n_errors:
            self.bar.set_postfix(errors=self.n_errors)
        if self.out is not None and time.monotonic() - self.last_table > _TABLE_REFRESH:
            write_table(self.out, self.columns)
            self.last_table = time.monotonic()

    def lost(self, pair: tuple[str, int], error: str, tb: str = "") -> dict[str, Any]:
        """The row of an episode whose worker died (or whose task was lost), with the text
        ``error``: an error row, saved so that the rerun retries it, unless the episode
        was saved before the loss (or, stuck, saved its own)."""
        if self.out is not None:
            saved = finished_row(self.out, pair[0], pair[1], self.record, self.digest)
            if saved is not None and saved["error"] == "":
                return saved
            stuck = stuck_row(self.out, pair[0], pair[1], self.token)
            if stuck is not None:
                return stuck
        row = _error_row(pair[0], pair[1], error, math.nan, self.columns)
        if self.out is not None:
            save_episode(self.out, row, None, tb, self.digest, config=self.cfg.to_dict())
        return row

    def sorted_rows(self) -> list[dict[str, Any]]:
        """Every pair's row, sorted by (agent, seed)."""
        return sorted((self.rows[p] for p in self.pairs), key=lambda r: (r["agent"], r["seed"]))


def _take_folder(run: _Run, folder_stack: Any) -> None:
    """Create and lock the results folder (released, after the table is rebuilt, when
    ``folder_stack`` closes) and write its config, checked again under the lock."""
    run.out.mkdir(parents=True, exist_ok=True)
    lock = FolderLock(run.out).acquire()
    folder_stack.callback(lock.release)
    folder_stack.callback(_finish_folder, run.out, run.columns)  # runs before release
    check_folder(run.out, run.cfg)  # again: another run may have written meanwhile
    _prepare_folder(run.out, run.cfg)


def _progress_bar(run: _Run, progress: bool, label: str | None) -> Any:
    """A tqdm bar over every pair of the run, the finished ones counted."""
    from tqdm.auto import tqdm

    return tqdm(
        total=len(run.pairs),
        initial=len(run.rows),
        disable=not progress,
        unit="episode",
        desc=label,
    )


def _run_on_dask(run: _Run, client: Any, todo: Sequence[tuple[str, int]]) -> None:
    """Every episode of ``todo`` as a task of the Dask cluster; cancelled on an interrupt."""
    import distributed

    from experiments.evaluation import executors

    executors.find_named_modules(client, working_folder.state())
    futures = {}
    for a, s in todo:
        args = run.task_args(a, s, stuck="worker")
        futures[client.submit(_episode_task, *args, pure=False, key=f"episode-{a}-{s}")] = (a, s)
    try:
        for fut in distributed.as_completed(futures):
            try:
                row = fut.result()
            except Exception as exc:  # its workers died (KilledWorker), or the task was lost
                a, s = futures[fut]
                text = (
                    f"WorkerDied: the Dask workers running agent {a!r}, seed {s} died "
                    f"({one_line(exc)})"
                )
                row = run.lost(futures[fut], text, "".join(traceback.format_exception(exc)))
            run.done(futures[fut], row)
    except BaseException:
        client.cancel(list(futures), force=True)
        raise


def _run_on_pool(
    run: _Run, jobs: int, todo: Sequence[tuple[str, int]], kind: str = "spawn"
) -> None:
    """Every episode of ``todo`` on ``jobs`` worker processes, one episode per worker at a
    time (:mod:`experiments.evaluation.pool`; ``kind="exec"``: a serial run's worker): a
    worker that dies, or is stopped past the limit, costs its own episode only."""
    args_of = lambda pair: run.task_args(*pair)  # noqa: E731
    run_on_pool(todo, jobs, args_of, run.done, run.lost, run.limit, kind)


def _run_serially(run: _Run, todo: Sequence[tuple[str, int]]) -> None:
    """Every episode of ``todo`` in this process, one after the other."""
    for a, s in todo:
        raise_if_interrupted()
        run.done((a, s), _episode_task(*run.task_args(a, s, stuck="run")))


def _finish_folder(out: Path, columns: Sequence[str]) -> None:
    """End of a run, also an interrupted one: no temporary file, an up-to-date table."""
    # A worker killed mid-write (then rerun elsewhere) leaves its temporary file; the
    # folder is locked, so every temporary file in it is of this run.
    _remove_stale_temp_files(out)
    write_table(out, columns)


__all__ = [
    "MAX_SEEDS",
    "SAVED_SCENARIOS",
    "DamagedEpisodeError",
    "FolderLock",
    "HEAD_COLUMNS",
    "TAIL_COLUMNS",
    "TIMING_COLUMNS",
    "ResultsFolderError",
    "agent_seed",
    "config_hash",
    "evaluate",
    "episode_stem",
    "group_columns",
    "saved_rows",
    "load_trajectory",
    "parse_seeds",
    "resolve_config",
    "row_columns",
    "run_episode",
    "save_episode",
    "tolerance_column",
    "tolerance_columns",
    "violation_counts",
    "write_table",
]
