"""The local process pool of :func:`experiments.evaluation.run.evaluate` (``jobs > 1``): one
episode per worker at a time, so a worker that dies costs its own episode only.

``concurrent.futures.ProcessPoolExecutor`` breaks as a whole when one of its workers dies:
every unfinished episode fails with ``BrokenProcessPool``, none named. Here each worker is
a spawned process with a pipe of its own that runs one episode at a time, and the parent
knows which episode each worker runs and since when:

* a worker that dies (a crash in native code, SIGKILL, the out-of-memory killer) costs
  at most its own episode: a new worker takes its place and the other episodes run on; the
  episode is run once more (:data:`DEATH_RETRIES`: a worker killed from outside, say by
  the out-of-memory killer in a moment of need, costs nothing), and if its worker dies
  again it is an error row naming the agent, the seed and the signal (a one-line warning
  names each death);
* a worker whose episode runs past its time limit and a grace time
  (:func:`~experiments.evaluation.limits.grace_time`) is killed: an error row naming the
  limit. (The worker ends an episode at the limit itself when Python can reach it, with the
  steps done and a traceback: :mod:`experiments.evaluation.limits`.)

Workers end when the parent ends, even by SIGKILL, and ignore Ctrl-C: the parent stops
them (SIGTERM, then SIGKILL after a grace time) and raises ``KeyboardInterrupt``.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import wait
from typing import Any

from experiments.evaluation.limits import grace_time, timeout_text

STOP_TIMEOUT = 5.0  # [s] for stopped workers to end before they are killed
DEATH_RETRIES = 1  # new runs of an episode whose worker died, before it is an error row

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


def _worker(conn: Any) -> None:
    """A worker's loop: receive an episode's arguments, run it, send its row back."""
    _exit_with_parent()
    from experiments.evaluation.task import _episode_task

    while True:
        try:
            args = conn.recv()
        except (EOFError, OSError):
            return
        if args is None:
            return
        conn.send(_episode_task(*args))


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

    def __init__(self, ctx: Any) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker, args=(child,), daemon=True)
        self.process.start()
        child.close()
        self.pair: Pair | None = None
        self.deadline = math.inf

    def give(self, pair: Pair, args: tuple, hard_limit: float | None) -> None:
        self.pair = pair
        self.deadline = math.inf if hard_limit is None else time.monotonic() + hard_limit
        try:
            self.conn.send(args)
        except OSError:
            pass  # the worker died: seen as such below

    def row(self) -> dict | None:
        """The row the worker sent, if one is there (never waits)."""
        try:
            if self.conn.poll():
                return self.conn.recv()
        except (EOFError, OSError):
            pass
        return None

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
) -> None:
    """Run the episodes ``pairs`` on ``jobs`` worker processes (module docstring).

    Args:
        pairs: the (agent, seed) pairs, in order.
        jobs: worker processes at most.
        args_of: the arguments of ``_episode_task`` for a pair.
        done: called with each pair and its row, as they come.
        lost: the row of a pair whose worker died or was stopped at its limit, given the
            error's text (it saves it).
        limit: the episodes' time limit [s] (``None``: none); a worker is killed at the
            limit plus :func:`~experiments.evaluation.limits.grace_time`.
    """
    ctx = multiprocessing.get_context("spawn")  # no forked CasADi state
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
                slots.append(_Slot(ctx))
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


__all__ = ["death_text", "run_on_pool"]
