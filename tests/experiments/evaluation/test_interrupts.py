"""Interrupts (``experiments.evaluation.interrupts``): Ctrl-C and SIGTERM end a real
``lfm-evaluate`` promptly with an up-to-date table and no orphan; a Ctrl-C that a library
swallows or turns into a status still stops the run; the remembered interrupts nest.

Real parts only: real signals to a real ``lfm-evaluate`` process group, the real process
pool, a real local Dask cluster on loopback."""

from __future__ import annotations

import os
import signal
import threading
import time

import casadi as ca
import numpy as np
import pytest

from experiments.benchmark.problems import problem_from_config
from experiments.benchmark.solvers import build_solver, solve_record
from experiments.evaluation.interrupts import raise_if_interrupted, remember_interrupts
from experiments.evaluation.run import evaluate
from tests.experiments.evaluation.live_runs import (
    REPO,
    assert_folder_consistent,
    quick_yaml,
    start_evaluate,
    wait_for_episodes,
)


def descendants(pid: int) -> list:
    psutil = pytest.importorskip("psutil")
    return psutil.Process(pid).children(recursive=True)


def assert_no_orphans(children: list) -> None:
    """Every process the run started ends with it (a few seconds' grace for helpers)."""
    psutil = pytest.importorskip("psutil")
    _, alive = psutil.wait_procs(children, timeout=5)
    assert not alive, [(p.pid, p.cmdline()) for p in alive]


EXECUTORS = [
    pytest.param([], id="serial"),
    pytest.param(["--jobs", "2"], id="pool"),
    pytest.param(["--dask-workers", "2"], id="dask", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("args", EXECUTORS)
def test_ctrl_c_stops_promptly_with_an_up_to_date_table(args, tmp_path):
    """Case 1 and 7: Ctrl-C (SIGINT to the process group) mid-run, in every executor."""
    out = tmp_path / "out"
    config = quick_yaml(tmp_path)
    proc = start_evaluate(
        ["--config", str(config), "--agents", "nominal,pf", "--seeds", "0:200", "--out", str(out)]
        + args,
        tmp_path,
    )
    try:
        wait_for_episodes(out, proc, 2)
        children = descendants(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
        _, stderr = proc.communicate(timeout=10)  # the bound for promptness
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, stderr
    assert "interrupted" in stderr
    assert "Traceback" not in stderr, stderr
    assert_no_orphans(children)
    assert_folder_consistent(out)


def test_sigterm_ends_workers_and_rebuilds_the_table(tmp_path):
    """Case 7: SIGTERM to the main process alone (``kill PID``) with a process pool."""
    out = tmp_path / "out"
    config = quick_yaml(tmp_path)
    proc = start_evaluate(
        ["--config", str(config), "--agents", "nominal", "--seeds", "0:200", "--out", str(out)]
        + ["--jobs", "2"],
        tmp_path,
    )
    try:
        wait_for_episodes(out, proc, 3)
        children = descendants(proc.pid)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode != 0
    assert "Traceback" not in stderr, stderr
    assert_no_orphans(children)
    assert_folder_consistent(out)


class _CtrlCInConversion:
    """Presses Ctrl-C (SIGINT to this process) when CasADi tries it as a numeric matrix."""

    def __DM__(self):  # CasADi's conversion hooks, tried in turn by its bindings
        signal.raise_signal(signal.SIGINT)  # the handler raises KeyboardInterrupt here
        return ca.DM(1.0)

    def __SX__(self):
        return ca.SX(1.0)


class CtrlCSwallowingAgent:
    """Zero inputs; at its third step a Ctrl-C lands inside CasADi, which swallows it.

    CasADi's bindings try an argument's conversions in turn and clear the error of a
    failed one, KeyboardInterrupt included (measured with CasADi 3.8.2, and seen in a
    real run inside its NumPy conversion): the expression is built as if nothing
    happened.
    """

    name = "swallower"

    def __init__(self, config) -> None:
        self.nu = config.make_system().nu
        self.steps = 0

    def reset(self, seed=None) -> None:
        self.steps = 0

    def act(self, obs):
        self.steps += 1
        if self.steps == 3:
            value = ca.DM(2.0) + _CtrlCInConversion()
            assert str(value) == "3"  # computed: the Ctrl-C did not reach this code
        return np.zeros(self.nu)


class CtrlCConvertingAgent(CtrlCSwallowingAgent):
    """At its third step a library turns the Ctrl-C into an error of its own."""

    name = "converter"

    def act(self, obs):
        self.steps += 1
        if self.steps == 3:
            try:
                signal.raise_signal(signal.SIGINT)
            except KeyboardInterrupt:
                raise RuntimeError("solver stopped by the user") from None
        return np.zeros(self.nu)


@pytest.mark.parametrize("agent", [CtrlCSwallowingAgent, CtrlCConvertingAgent])
def test_a_ctrl_c_that_a_library_swallows_still_stops_the_run(agent, tmp_path):
    """Case 1: a run whose episodes run in its own process (``isolate=False``) stops at the
    next step and saves no error row for it. (A serial run's child process and pool workers
    ignore Ctrl-C: there the run's process, which runs no agent code, gets it.)

    (Found under load: ``lfm-evaluate`` went on after Ctrl-C when the signal landed in
    a CasADi expression being built, e.g. in an agent's constructor.)
    """
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal's
    try:
        out = tmp_path / "out"
        with pytest.raises(KeyboardInterrupt):
            evaluate(
                [agent],
                [0, 1],
                config=quick_yaml(tmp_path, max_steps=10),
                out=out,
                progress=False,
                isolate=False,
            )
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, previous)
    assert not list((out / "episodes").glob("*.json"))  # no error row for the interrupt
    assert_folder_consistent(out)


def test_a_ctrl_c_during_an_ipopt_solve_stops_the_benchmark(paper_problem_data):
    """CasADi's IPOPT ends a solve on Ctrl-C with a status instead of an error; the
    benchmark's solve loop raises it (found: ``lfm-benchmark`` went on after Ctrl-C)."""
    problem, x0, W = paper_problem_data
    solver, _, reason = build_solver("ipopt", problem)
    assert solver is not None, reason
    solve_record(solver, problem, x0, W)  # warm (the JIT, the first call's set-up)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal's
    timer = threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT))
    try:
        with remember_interrupts():
            timer.start()  # lands inside the solve (about 0.3 s)
            with pytest.raises(KeyboardInterrupt):
                solve_record(solver, problem, x0, W)
                time.sleep(5.0)  # (only reached if the solve ended before the timer)
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)


def test_remembered_interrupts_nest_and_restore_the_handlers():
    """The outermost context installs and restores; a nested one (``evaluate`` inside a
    command line) shares its record; the record is cleared on leaving the outermost."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    term = signal.getsignal(signal.SIGTERM)
    try:
        with remember_interrupts():
            outer = signal.getsignal(signal.SIGINT)
            assert outer is not signal.default_int_handler
            with remember_interrupts():
                assert signal.getsignal(signal.SIGINT) is outer
                with pytest.raises(KeyboardInterrupt):
                    signal.raise_signal(signal.SIGINT)
            with pytest.raises(KeyboardInterrupt):  # still remembered by the outer one
                raise_if_interrupted()
        raise_if_interrupted()  # cleared
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.getsignal(signal.SIGTERM) is term
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # an ignored Ctrl-C stays ignored
        with remember_interrupts():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.fixture(scope="module")
def paper_problem_data():
    """The paper's problem at N = 7, Ns = 150 and a recorded closed-loop problem of it."""
    data = np.load(REPO / "tests" / "data" / "recorded_problems.npz")
    W = data["W"][0]
    problem = problem_from_config(horizon=W.shape[1], n_scenarios=W.shape[0])
    return problem, data["x0"][0], W
