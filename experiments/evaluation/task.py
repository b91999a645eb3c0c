"""One episode as a task of any executor: run it, save it, turn what it raises into an error row."""

from __future__ import annotations

import os
import pickle
import sys
import time
import traceback
from collections.abc import Sequence
from typing import Any

from controllers.agents.protocol import is_agent
from controllers.agents.registry import AgentSpec, AgentSpecError
from controllers.config import ExperimentConfig
from controllers.threads import limit_blas_threads
from experiments.evaluation.episode import _episode_metrics, _EpisodeRecorder, _error_row, _simulate
from experiments.evaluation.interrupts import raise_if_interrupted
from experiments.evaluation.limits import EpisodeLimit, EpisodeTimeout, timeout_text
from experiments.evaluation.storage import save_episode, stuck_row, write_table
from lfm_env.validation import one_line

#: The exit code of a process whose episode is stuck past its limit (module docstring).
EXIT_STUCK = 1


def _episode_task(
    agent: AgentSpec,
    config: ExperimentConfig,
    seed: int,
    out: str | None,
    record: bool,
    digest: str = "",
    limit: float | None = None,
    stuck: str = "",
    token: str = "",
) -> dict[str, Any]:
    """Run and save one episode (top level: picklable); never raises for an error of the episode.

    Any exception of the episode (``BaseException`` too) is its error row; only Ctrl-C propagates,
    in a serial run. ``limit`` [s] ends an episode; one stuck past it ends what ``stuck`` says:
    ``"run"`` (row and table saved, then exit :data:`EXIT_STUCK`), ``"worker"`` (a Dask worker:
    row saved with ``token``, then the worker ends) or ``""`` (a pool worker: its parent stops it).
    """
    limit_blas_threads()  # every executor's worker (serial, pool, Dask) runs this first
    name = agent.name
    if token and out is not None:
        saved = stuck_row(out, name, seed, token)
        if saved is not None:  # this episode got stuck in this run, in a worker it ended
            return saved
    t0 = time.perf_counter()
    rec = _EpisodeRecorder(config)
    tb = ""
    on_stuck = None
    if stuck:
        on_stuck = _StuckEpisode(name, seed, out, digest, limit, rec.columns, stuck, token, t0)
    try:
        with EpisodeLimit(limit, on_stuck):
            _simulate(agent, config, seed, rec)
        arrays = rec.arrays()
        row = {"agent": name, "seed": seed, **_episode_metrics(rec, arrays)}
        row.update(wall_time=time.perf_counter() - t0, error="")
        row = {c: row[c] for c in rec.columns}
    except KeyboardInterrupt:
        if stuck == "run":  # in this run's own process: Ctrl-C stays Ctrl-C
            raise
        # (workers ignore Ctrl-C: the agent raised it itself; an error like any other)
        row, arrays, tb = _failed_episode(name, seed, rec, limit, t0)
    except BaseException:  # one bad episode must not stop the others
        raise_if_interrupted()  # a Ctrl-C a library turned into another error: no error row
        row, arrays, tb = _failed_episode(name, seed, rec, limit, t0)
    if out is not None:
        save_episode(out, row, arrays if record else None, tb, digest, config=config.to_dict())
    return row


def _failed_episode(
    name: str, seed: int, rec: _EpisodeRecorder, limit: float | None, t0: float
) -> tuple[dict[str, Any], dict[str, Any], str]:
    """The error row, the arrays of the steps done and the traceback of the episode whose
    exception is being handled."""
    exc = sys.exc_info()[1]
    tb = traceback.format_exc()
    text = timeout_text(limit) if isinstance(exc, EpisodeTimeout) else one_line(exc)
    row = _error_row(name, seed, text, time.perf_counter() - t0, rec.columns)
    try:
        arrays = rec.arrays()  # the steps done before the error, for debugging
    except Exception:
        arrays = {}
    return row, arrays, tb


class _StuckEpisode:
    """What ends an episode stuck past its limit where Python cannot reach it (called in a
    watchdog thread): its error row is saved, a line on stderr says so, the process ends."""

    def __init__(
        self,
        name: str,
        seed: int,
        out: str | None,
        digest: str,
        limit: float | None,
        columns: Sequence[str],
        mode: str,
        token: str,
        t0: float,
    ) -> None:
        self.name, self.seed, self.out, self.digest = name, seed, out, digest
        self.limit, self.columns, self.mode, self.token, self.t0 = limit, columns, mode, token, t0

    def __call__(self) -> None:
        text = (
            f"{timeout_text(self.limit)}; it did not return to Python (stuck in native code, "
            "or blocking the signal), so its process was ended"
        )
        wall_time = time.perf_counter() - self.t0
        row = _error_row(self.name, self.seed, text, wall_time, self.columns)
        where = "its error row is not saved (no results folder)"
        if self.out is not None:
            save_episode(self.out, row, None, "", self.digest, run_token=self.token)
            if self.mode == "run":
                write_table(self.out)
            where = "its error row is saved"
        ending = (
            "ending this run (rerun to run the other episodes; with --jobs 2 a run goes on "
            "past such an episode)"
            if self.mode == "run"
            else "ending this worker process"
        )
        print(
            f"error: the episode of agent {self.name!r}, seed {self.seed} ran past its limit "
            f"of {self.limit:g} s and does not return to Python; {where}; {ending}",
            file=sys.stderr,
            flush=True,
        )
        os._exit(EXIT_STUCK)


def check_picklable(agent: AgentSpec, how: str) -> None:
    """Refuse a user's agent that cannot travel to the workers of ``how`` (``"pool"``: pickle by
    reference, ``"dask"``: cloudpickle).

    Raises:
        AgentSpecError: naming the agent and why.
    """
    if agent.factory is None or isinstance(agent.factory, str):
        return
    if how == "dask":
        import cloudpickle

        dumps = cloudpickle.dumps
    else:
        dumps = pickle.dumps
    try:
        dumps(agent)
    except Exception as exc:
        raise AgentSpecError(
            f"agent {agent.text!r}: cannot be sent to worker processes ({one_line(exc)}); "
            "define the factory at the top level of an importable module and pass it or "
            "'module:attribute', or run with jobs=1"
        ) from exc
    module = getattr(agent.factory, "__module__", None) or type(agent.factory).__module__
    main = sys.modules.get("__main__")
    if how == "pool" and module == "__main__" and not getattr(main, "__file__", None):
        raise AgentSpecError(
            f"agent {agent.text!r}: defined in an interactive session, which spawned "
            "workers cannot import; put it in a module and pass 'module:attribute', or "
            "run with jobs=1"
        )


def sendable_problem(agent: AgentSpec) -> str | None:
    """Why ``agent`` should not be sent to a fresh worker process that does not import the
    main script (a serial run's worker), else ``None``: an agent object (used as it is, in
    this process), a factory that does not pickle, or one that comes from ``__main__``."""
    if agent.factory is None or isinstance(agent.factory, str):
        return None
    if is_agent(agent.factory):  # used as it is: its own state stays in this process
        return f"agent {agent.text!r} is an agent object (run in this process, as it is)"
    module = getattr(agent.factory, "__module__", None) or type(agent.factory).__module__
    if module in ("__main__", "__mp_main__"):
        return f"agent {agent.text!r} is defined in the main script"
    try:
        pickle.dumps(agent)
    except Exception as exc:
        return f"agent {agent.text!r} cannot be pickled ({one_line(exc)})"
    return None
