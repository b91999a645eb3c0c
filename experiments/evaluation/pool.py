"""The local process pool of :func:`experiments.evaluation.run.evaluate` (``jobs > 1``): one
episode per worker at a time, so a worker that dies costs its own episode only.

Unlike ``ProcessPoolExecutor`` (broken as a whole by one dead worker), each worker has its
own pipe and the parent knows its episode and since when: a dead worker is replaced and its
episode run once more (:data:`DEATH_RETRIES`), then an error row naming the signal; a worker
past the limit plus :func:`~experiments.evaluation.limits.grace_time` is killed. Workers end
with the parent and ignore Ctrl-C. ``"spawn"`` workers re-import the main script (the
``--jobs`` pool); ``"exec"`` workers (``python -c``) do not (a serial run's one worker).
Neither imports from the working folder but the modules the run named.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from multiprocessing.connection import wait
from typing import Any

from experiments.evaluation.limits import grace_time, timeout_text
from lfm_env import working_folder

STOP_TIMEOUT = 5.0  # [s] for stopped workers to end before they are killed
DEATH_RETRIES = 1  # new runs of an episode whose worker died, before it is an error row
START_TIMEOUT = 300.0  # [s] for a worker to take an episode given to it (imports included)
#: The start of an ``"exec"`` worker: ``python -c`` puts the working folder (``""``) first on
#: ``sys.path``; it is dropped before anything is imported, then the parent's path is set.
_EXEC_BOOT = (
    "import sys; sys.path[:] = [p for p in sys.path if p]; import json; "
    "sys.path[:] = json.loads(sys.argv[1]); "
    "from experiments.evaluation.pool import _exec_worker; "
    "_exec_worker(int(sys.argv[2]), int(sys.argv[3]))"
)

Pair = tuple[str, int]


def _exit_with_parent() -> None:
    """In a worker: end this process as soon as the parent process ends, and leave Ctrl-C
    to the parent (it reaches the whole process group; the parent stops the workers).

    A worker ended mid-write leaves only a temporary file, which the next run removes.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()  # returns when the parent's end of the spawn pipe closes
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _worker(conn: Any, named: tuple = ()) -> None:
    """A ``"spawn"`` worker: ends with its parent, finds the named modules, then serves."""
    _exit_with_parent()
    restore_environment()
    working_folder.install(named)
    _serve(conn)


def _exec_worker(fd: int, parent_fd: int) -> None:
    """An ``"exec"`` worker (:data:`_EXEC_BOOT`): ends when ``parent_fd`` (a pipe whose
    other end only the parent holds) closes; the named modules come first on ``fd``."""
    from multiprocessing.connection import Connection

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while os.read(parent_fd, 1):
            pass
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
    restore_environment()
    conn = Connection(fd)
    working_folder.install(conn.recv())
    _serve(conn)


def _serve(conn: Any) -> None:
    """A worker's loop: receive an episode's arguments, say it is taken, run it, send its
    row back."""
    from experiments.evaluation.task import _episode_task

    while True:
        try:
            args = conn.recv()
        except (EOFError, OSError):
            return
        if args is None:
            return
        conn.send(_TAKEN)
        try:
            row = _episode_task(*args)
        except Exception as exc:  # not the episode's (a row): the run's, e.g. a full disk
            conn.send(_raised(exc))
            continue
        conn.send(row)


_TAKEN = "taken"  # a worker's word that it runs the episode just given (its limit starts)
_RAISED = "raised"  # a worker's word that its task raised: the run stops with that error


def _raised(exc: Exception) -> tuple[str, Exception]:
    """The message that carries an error of a worker's task to the run's process (the error
    itself when it pickles, else a RuntimeError with its text)."""
    import pickle

    try:
        pickle.dumps(exc)
    except Exception:
        exc = RuntimeError(f"{type(exc).__name__}: {exc}")
    return _RAISED, exc


class _ExecProcess:
    """A worker started as ``python -c`` (:data:`_EXEC_BOOT`), with the face of a
    ``multiprocessing.Process`` that :class:`_Slot` uses, and its end of the pipe."""

    def __init__(self, named: tuple) -> None:
        import json
        from multiprocessing.connection import Connection

        ours, theirs = socket.socketpair()
        watch_r, self._watch_w = os.pipe()  # the child sees EOF when this process ends
        cmd = [sys.executable, "-c", _EXEC_BOOT, json.dumps([p for p in sys.path if p])]
        cmd += [str(theirs.fileno()), str(watch_r)]
        try:
            self._popen = subprocess.Popen(
                cmd, pass_fds=(theirs.fileno(), watch_r), stdin=subprocess.DEVNULL
            )
        finally:
            theirs.close()
            os.close(watch_r)
        self.conn = Connection(ours.detach())
        self.conn.send(named)
        try:
            self.sentinel: Any = os.pidfd_open(self._popen.pid)
        except (AttributeError, OSError):
            self.sentinel = self.conn  # (no pidfd: its pipe ends with it)

    @property
    def exitcode(self) -> int | None:
        return self._popen.poll()

    def is_alive(self) -> bool:
        return self._popen.poll() is None

    def join(self, timeout: float | None = None) -> None:
        try:
            self._popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
        if self._popen.returncode is not None:
            self.close()

    def terminate(self) -> None:
        if self.is_alive():
            self._popen.terminate()

    def kill(self) -> None:
        if self.is_alive():
            self._popen.kill()

    def close(self) -> None:
        for fd in ("sentinel", "_watch_w"):
            value = getattr(self, fd, None)
            if isinstance(value, int):
                with contextlib.suppress(OSError):
                    os.close(value)
                setattr(self, fd, None)


@contextlib.contextmanager
def safe_child_path() -> Iterator[None]:
    """For the duration, Python processes started by this one (pool and Dask workers) put
    no working folder first on ``sys.path`` (``PYTHONSAFEPATH``, Python 3.11 and later), so
    a ``signal.py`` there cannot replace the real module before their first line runs."""
    previous = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    os.environ[_SAFEPATH_BEFORE] = "" if previous is None else f"={previous}"
    try:
        yield
    finally:
        os.environ.pop(_SAFEPATH_BEFORE, None)
        if previous is None:
            os.environ.pop("PYTHONSAFEPATH", None)
        else:
            os.environ["PYTHONSAFEPATH"] = previous


_SAFEPATH_BEFORE = "LFM_PYTHONSAFEPATH_BEFORE"  # the user's own value ("=value"; "": none)


def restore_environment() -> None:
    """In a worker, once started: ``PYTHONSAFEPATH`` as the user had it (:func:`safe_child_path`
    set it for the worker's own start only), for the processes an agent starts."""
    before = os.environ.pop(_SAFEPATH_BEFORE, None)
    if before is None:
        return
    if before.startswith("="):
        os.environ["PYTHONSAFEPATH"] = before[1:]
    else:
        os.environ.pop("PYTHONSAFEPATH", None)


def death_text(pair: Pair, exitcode: int | None, attempts: int = 1) -> str:
    """The error of an episode whose worker died (one line, for its row), after
    ``attempts`` runs."""
    agent, seed = pair
    if exitcode is not None and exitcode < 0:
        try:
            how = f"was killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            how = f"was killed by signal {-exitcode}"
    else:
        how = f"exited with code {exitcode}"
    again = f", at each of its {attempts} runs" if attempts > 1 else ""
    return (
        f"WorkerDied: the worker process running agent {agent!r}, seed {seed} {how}{again} "
        "(a crash in native code, the out-of-memory killer or a kill); the other episodes "
        "run on"
    )


class _Slot:
    """One worker process, its pipe, and the episode it runs (with its deadline)."""

    def __init__(self, kind: str, named: tuple) -> None:
        if kind == "exec":
            self.process: Any = _ExecProcess(named)
            self.conn = self.process.conn
        else:
            ctx = multiprocessing.get_context("spawn")  # no forked CasADi state
            self.conn, child = ctx.Pipe()
            self.process = ctx.Process(target=_worker, args=(child, named), daemon=True)
            self.process.start()
            child.close()
        self.pair: Pair | None = None
        self.deadline = math.inf
        self.hard_limit: float | None = None

    def give(self, pair: Pair, args: tuple, hard_limit: float | None) -> None:
        """Send an episode; its limit runs from when the worker takes it (the first
        episode of a new worker waits for its imports), at most :data:`START_TIMEOUT`."""
        self.pair, self.hard_limit = pair, hard_limit
        self.deadline = math.inf if hard_limit is None else time.monotonic() + START_TIMEOUT
        try:
            self.conn.send(args)
        except OSError:
            pass  # the worker died: seen as such below

    def row(self) -> dict | None:
        """The row the worker sent, if any (never waits); its "took" word starts the deadline.

        Raises:
            Exception: the error the worker's task raised outside its episode.
        """
        while True:
            try:
                if not self.conn.poll():
                    return None
                message = self.conn.recv()
            except (EOFError, OSError):
                return None
            if isinstance(message, tuple) and message[0] == _RAISED:
                raise message[1]  # (the run stops: a full disk is not an episode's error)
            if message != _TAKEN:
                return message
            if self.hard_limit is not None:
                self.deadline = time.monotonic() + self.hard_limit

    def stop(self, polite: bool) -> None:
        """End the worker: asked to (an idle one, ``polite``), else or if it does not end
        within :data:`STOP_TIMEOUT`, by SIGTERM and then SIGKILL."""
        if polite and self.pair is None and self.process.is_alive():
            try:
                self.conn.send(None)
            except OSError:
                pass
            self.process.join(STOP_TIMEOUT)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(STOP_TIMEOUT)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


def run_on_pool(
    pairs: Sequence[Pair],
    jobs: int,
    args_of: Callable[[Pair], tuple],
    done: Callable[[Pair, dict], None],
    lost: Callable[[Pair, str], dict],
    limit: float | None,
    kind: str = "spawn",
) -> None:
    """Run the episodes ``pairs`` on ``jobs`` worker processes.

    Args:
        pairs: the (agent, seed) pairs, in order.
        jobs: worker processes at most.
        args_of: the arguments of ``_episode_task`` for a pair.
        done: called with each pair and its row, as they come.
        lost: the (saved) row of a pair whose worker died or was stopped, given the error.
        limit: the episodes' time limit [s] (``None``: none).
        kind: ``"spawn"`` or ``"exec"`` workers.
    """
    named = working_folder.state()
    hard_limit = None if limit is None else limit + grace_time(limit)
    queue: deque[Pair] = deque(pairs)
    slots: list[_Slot] = []
    deaths: dict[Pair, int] = {}
    try:
        while queue or any(s.pair is not None for s in slots):
            for slot in slots:
                if slot.pair is None and queue:
                    pair = queue.popleft()
                    slot.give(pair, args_of(pair), hard_limit)
            while queue and len(slots) < jobs:
                slots.append(_Slot(kind, named))
                pair = queue.popleft()
                slots[-1].give(pair, args_of(pair), hard_limit)
            busy = [s for s in slots if s.pair is not None]
            nearest = min(s.deadline for s in busy)
            timeout = None if math.isinf(nearest) else max(0.0, nearest - time.monotonic())
            wait([s.conn for s in busy] + [s.process.sentinel for s in busy], timeout)
            for slot in busy:
                _collect(slot, slots, done, lost, limit, deaths, queue)
    except BaseException:
        for slot in slots:  # Ctrl-C or SIGTERM: end the workers now
            slot.stop(polite=False)
        raise
    for slot in slots:
        slot.stop(polite=True)


def _collect(
    slot: _Slot,
    slots: list[_Slot],
    done: Callable[[Pair, dict], None],
    lost: Callable[[Pair, str], dict],
    limit: float | None,
    deaths: dict[Pair, int],
    queue: deque[Pair],
) -> None:
    """The outcome of ``slot``'s episode if it has one: its row, or its worker's death (the
    episode back at the front of ``queue`` while ``deaths`` allow it) or the limit passed
    (the worker is then removed from ``slots``; a new one starts when there is work)."""
    pair = slot.pair
    row = slot.row()
    if row is not None:
        slot.pair, slot.deadline = None, math.inf
        done(pair, row)
        return
    if slot.process.is_alive() and time.monotonic() < slot.deadline:
        return
    slots.remove(slot)
    if slot.process.is_alive():  # past its limit and the grace time: stopped
        slot.process.kill()
        slot.process.join()
        slot.conn.close()
        text = f"{timeout_text(limit)}; its worker process did not return and was stopped"
        done(pair, lost(pair, text))
        return
    slot.process.join()
    row = slot.row()  # (sent just before it died)
    slot.conn.close()
    if row is not None:
        done(pair, row)
        return
    deaths[pair] = deaths.get(pair, 0) + 1
    text = death_text(pair, slot.process.exitcode, deaths[pair])
    if deaths[pair] <= DEATH_RETRIES:
        shown = death_text(pair, slot.process.exitcode).partition(": ")[2]
        shown = shown.replace("; the other episodes run on", "; running its episode again")
        print(f"warning: {shown}", file=sys.stderr, flush=True)
        queue.appendleft(pair)
        return
    print(f"warning: {text.partition(': ')[2]}", file=sys.stderr, flush=True)
    done(pair, lost(pair, text))
