"""Agents that crash, hang or exit on one env seed, for the tests of episode isolation.

Importable as ``tests.experiments.crashing_agents`` (``lfm-evaluate --agents
tests.experiments.crashing_agents:SegfaultAgent`` from the repository root). Each behaves as
:class:`tests.experiments.own_agents.ProportionalAgent` (a few microseconds per step) on
every env seed but :data:`BAD_SEED`, where its first ``act`` misbehaves. An agent knows its
episode's env seed from the seed of its ``reset`` (the paired design's
:func:`experiments.evaluation.episode.agent_seed` of the env seed and its name).
"""

from __future__ import annotations

import ctypes
import os
import signal
import time
from typing import Any

from experiments.evaluation.episode import agent_seed
from tests.experiments.own_agents import ProportionalAgent

BAD_SEED = 3


class _OnOneSeed(ProportionalAgent):
    """A proportional agent that calls :meth:`misbehave` at the first step on BAD_SEED."""

    name = "on_one_seed"

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.bad = seed == agent_seed(BAD_SEED, self.name)

    def act(self, obs: Any):
        if self.bad:
            self.misbehave()
        return super().act(obs)

    def misbehave(self) -> None:
        raise NotImplementedError


class SegfaultAgent(_OnOneSeed):
    """Dies of SIGSEGV: reads memory at address 0 through ctypes (a crash in native code)."""

    name = "segfault"

    def misbehave(self) -> None:
        ctypes.string_at(0)


class KilledAgent(_OnOneSeed):
    """Dies of SIGKILL (as by the out-of-memory killer)."""

    name = "killed"

    def misbehave(self) -> None:
        os.kill(os.getpid(), signal.SIGKILL)


class LoopingAgent(_OnOneSeed):
    """Never returns from ``act``: an infinite loop in Python."""

    name = "looping"

    def misbehave(self) -> None:
        while True:
            pass


class StuckAgent(_OnOneSeed):
    """Never returns to Python in time: blocks SIGALRM and sleeps (as a native call that
    ignores signals would); in a thread other than the main one, a plain sleep."""

    name = "stuck"

    def misbehave(self) -> None:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
        time.sleep(10_000)


class ExitingAgent(_OnOneSeed):
    """Raises ``SystemExit(5)`` (a ``sys.exit`` in a library it calls)."""

    name = "exiting"

    def misbehave(self) -> None:
        raise SystemExit(5)


class InterruptedAgent(_OnOneSeed):
    """Raises ``KeyboardInterrupt`` (a Ctrl-C that reached it)."""

    name = "interrupted"

    def misbehave(self) -> None:
        raise KeyboardInterrupt


class AbortingAgent(_OnOneSeed):
    """Dies of SIGABRT (``abort()`` in a native library, e.g. a failed assertion)."""

    name = "aborting"

    def misbehave(self) -> None:
        os.abort()


class QuittingAgent(_OnOneSeed):
    """Ends its process with exit code 3 (``os._exit`` in a library, no cleanup)."""

    name = "quitting"

    def misbehave(self) -> None:
        os._exit(3)
