"""Reliability under real use (issue 15, cases 1, 2, 3, 4, 7, 9): interrupts, a scheduler
that is not one, shared results folders, damaged episode files, the local Dask cluster's
authentication.

Real parts only: real signals to a real ``lfm-evaluate`` process group, the real process
pool, a real local Dask cluster on loopback, real listening sockets and real files.
"""

from __future__ import annotations

import csv
import http.server
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from experiments.benchmark.problems import problem_from_config
from experiments.benchmark.solvers import build_solver, solve_record
from experiments.evaluation import run as evaluation
from experiments.evaluation.interrupts import raise_if_interrupted, remember_interrupts
from experiments.evaluation.run import (
    DamagedEpisodeError,
    FolderLock,
    ResultsFolderError,
    config_hash,
    evaluate,
    load_trajectory,
    saved_rows,
    write_table,
)

REPO = Path(__file__).resolve().parents[2]
LFM_EVALUATE = Path(sys.executable).with_name("lfm-evaluate")
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
TINY = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 4, "n_particles": 300},
}


def quick_yaml(tmp_path: Path, max_steps: int = 60) -> Path:
    """``configs/quick.yaml`` with fewer steps (episodes of about a second)."""
    text = (REPO / "configs" / "quick.yaml").read_text()
    text = text.replace("max_steps: 150", f"max_steps: {max_steps}")
    assert f"max_steps: {max_steps}" in text
    path = tmp_path / "quick_short.yaml"
    path.write_text(text)
    return path


def start_evaluate(args: list[str], cwd: Path) -> subprocess.Popen:
    """``lfm-evaluate`` in its own process group (as a terminal's foreground job)."""
    return subprocess.Popen(
        [str(LFM_EVALUATE), "--no-report", "--quiet", *args],
        cwd=cwd,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        # A suite started in the background (nohup ... &) ignores SIGINT, and its children
        # would inherit that: start the run with SIGINT as a terminal's job has it.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def wait_for_episodes(out: Path, proc: subprocess.Popen, n: int, limit: float = 120.0) -> None:
    deadline = time.monotonic() + limit
    while len(list((out / "episodes").glob("*.json"))) < n:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no episode finished"
        time.sleep(0.1)


def descendants(pid: int) -> list:
    psutil = pytest.importorskip("psutil")
    return psutil.Process(pid).children(recursive=True)


def assert_no_orphans(children: list) -> None:
    """Every process the run started ends with it (a few seconds' grace for helpers)."""
    psutil = pytest.importorskip("psutil")
    _, alive = psutil.wait_procs(children, timeout=5)
    assert not alive, [(p.pid, p.cmdline()) for p in alive]


def table_rows(out: Path) -> list[dict]:
    with open(out / "episodes.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def assert_folder_consistent(out: Path) -> None:
    """No temporary file, no lock, and episodes.csv holds exactly the saved episodes."""
    assert not list(out.rglob("*.tmp"))
    assert not (out / ".lock").exists()
    saved = sorted(p.stem for p in (out / "episodes").glob("*.json"))
    rows = sorted(f"{r['agent']}__seed{r['seed']}" for r in table_rows(out))
    assert rows == saved


# ====================================================================== 1, 7: interrupts

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
    """Case 1: the serial run stops at the next step and saves no error row for it.

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


# ================================================================ 2: not a Dask scheduler


class _Silent(threading.Thread):
    """A listener that accepts connections and never answers."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.held: list[socket.socket] = []

    def run(self) -> None:
        while True:
            try:
                self.held.append(self.sock.accept()[0])
            except OSError:
                return


class _Http(http.server.BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        self.send_response(200)
        self.end_headers()
        self.wfile.write(b"hello")

    def log_message(self, *args) -> None:
        pass


@pytest.mark.parametrize("kind", ["silent", "http"])
def test_a_scheduler_address_that_is_not_dask_fails_within_the_timeout(kind, tmp_path):
    """Case 2: a silent listener or an HTTP server given as --scheduler."""
    if kind == "silent":
        server = _Silent()
        server.start()
        port, stop = server.port, server.sock.close
    else:
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Http)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        port, stop = httpd.server_address[1], httpd.shutdown
    address = f"tcp://127.0.0.1:{port}"
    try:
        proc = subprocess.run(
            [str(LFM_EVALUATE), "--no-report", "--quiet", "--agents", "nominal", "--seeds", "0"]
            + ["--scheduler", address, "--out", str(tmp_path / "out")],
            cwd=tmp_path,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=60,  # generous: the stated timeout is 5 s
        )
    finally:
        stop()
    assert proc.returncode == 2, proc.stderr
    assert address in proc.stderr and "Dask scheduler" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


# ======================================================= 3: one run per results folder


def test_a_folder_in_use_by_a_live_run_is_refused_naming_it(tmp_path, monkeypatch):
    """Case 3: a second run into a folder another live process writes to."""
    out = tmp_path / "out"
    config = quick_yaml(tmp_path, max_steps=30)
    proc = start_evaluate(
        ["--config", str(config), "--agents", "nominal", "--seeds", "0:20", "--out", str(out)],
        tmp_path,
    )
    try:
        wait_for_episodes(out, proc, 1)
        assert (out / ".lock").read_text().split()[0] == str(proc.pid)
        monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
        with pytest.raises(ResultsFolderError, match=rf"in use by process {proc.pid} on "):
            evaluate(["nominal"], range(20), config, out=out, progress=False)
        _, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, stderr  # the first run was not disturbed
    assert len(table_rows(out)) == 20
    assert_folder_consistent(out)


def test_a_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    tmp_path.mkdir(exist_ok=True)
    (tmp_path / ".lock").write_text(f"{dead.pid} {socket.gethostname()}\n")
    rows = evaluate(["nominal"], [0], TINY, out=tmp_path, progress=False)
    assert rows[0]["error"] == ""
    assert not (tmp_path / ".lock").exists()


def test_the_lock_refuses_a_second_owner_and_is_released(tmp_path):
    lock = FolderLock(tmp_path).acquire()
    with pytest.raises(ResultsFolderError, match=r"lock file .*\.lock"):
        FolderLock(tmp_path).acquire()
    lock.release()
    FolderLock(tmp_path).acquire().release()
    assert not (tmp_path / ".lock").exists()


def test_another_config_cannot_resume_into_a_folder_without_config_yaml(tmp_path, monkeypatch):
    """Case 3: the config is bound to every episode, not only to config.yaml."""
    evaluate(["nominal"], [0], TINY, out=tmp_path, progress=False)
    saved = json.loads((tmp_path / "episodes" / "nominal__seed0.json").read_text())
    assert saved["config_hash"] == config_hash(evaluation.resolve_config(TINY))
    (tmp_path / "config.yaml").unlink()
    other = {**TINY, "env": {"max_steps": 16}}
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    with pytest.raises(ResultsFolderError, match=r"different config.*nominal__seed0\.json"):
        evaluate(["nominal"], [1], other, out=tmp_path, progress=False)


# ========================================================= 4: damaged episode files


@pytest.fixture
def counted_runs(monkeypatch):
    calls: list[tuple[str, int]] = []
    task = evaluation._episode_task

    def counting(agent_name, config, seed, *args):
        calls.append((agent_name, seed))
        return task(agent_name, config, seed, *args)

    monkeypatch.setattr(evaluation, "_episode_task", counting)
    return calls


def test_damaged_episode_files_are_named_and_run_again(tmp_path, counted_runs, capsys):
    """Case 4: a truncated npz, a json of another seed, a garbage json."""
    first = evaluate(["nominal"], range(4), TINY, out=tmp_path, progress=False)
    episodes = tmp_path / "episodes"
    npz = episodes / "nominal__seed1.npz"
    npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])  # truncated
    wrong = json.loads((episodes / "nominal__seed0.json").read_text())
    (episodes / "nominal__seed2.json").write_text(json.dumps(wrong))  # holds seed 0
    (episodes / "nominal__seed3.json").write_text("{garbage")
    with pytest.raises(DamagedEpisodeError, match=r"nominal__seed1\.npz"):
        load_trajectory(tmp_path, "nominal", 1)
    capsys.readouterr()
    counted_runs.clear()

    second = evaluate(["nominal"], range(4), TINY, out=tmp_path, progress=False)
    err = capsys.readouterr().err
    assert sorted(counted_runs) == [("nominal", 1), ("nominal", 2), ("nominal", 3)]
    for name in ("nominal__seed1.npz", "nominal__seed2.json", "nominal__seed3.json"):
        assert name in err
    key = [c for c in first[0] if c not in evaluation.TIMING_COLUMNS]
    assert [[r[c] for c in key] for r in second] == [[r[c] for c in key] for r in first]
    assert len(load_trajectory(tmp_path, "nominal", 1)["reward"]) == first[1]["steps"]
    assert_folder_consistent(tmp_path)


def test_a_copied_or_garbage_json_is_named_and_not_counted(tmp_path, capsys):
    """Case 4: a copy of an episode json counted once; garbage named, not dropped silently."""
    evaluate(["nominal"], range(3), TINY, out=tmp_path, progress=False)
    episodes = tmp_path / "episodes"
    copy = episodes / "nominal__seed1 (copy).json"
    copy.write_bytes((episodes / "nominal__seed1.json").read_bytes())
    junk = episodes / "notes.json"
    junk.write_text("[1, 2")
    capsys.readouterr()
    write_table(tmp_path)
    err = capsys.readouterr().err
    assert [(r["agent"], r["seed"]) for r in table_rows(tmp_path)] == [
        ("nominal", "0"),
        ("nominal", "1"),
        ("nominal", "2"),
    ]
    assert copy.name in err and junk.name in err
    assert len(saved_rows(tmp_path)) == 3


# ===================================================== 9: the local Dask cluster is private


def test_local_dask_cluster_refuses_foreign_clients_and_serves_no_http(tmp_path):
    """Case 9: TLS with a temporary certificate, and no HTTP endpoint at all."""
    pytest.importorskip("distributed")
    psutil = pytest.importorskip("psutil")
    from experiments.evaluation import executors

    with ExitStack() as stack:
        client = evaluation._connect_dask(None, 1, stack)
        address = client.scheduler.address
        assert address.startswith("tls://127.0.0.1:")
        assert client.submit(os.getpid).result() != os.getpid()  # our own client works
        info = client.scheduler_info()["workers"]
        ports = {int(address.rsplit(":", 1)[1])}
        for w, d in info.items():
            ports |= {int(w.rsplit(":", 1)[1]), int(d["nanny"].rsplit(":", 1)[1])}
        procs = [psutil.Process(), *psutil.Process().children(recursive=True)]
        listening = {
            c.laddr.port
            for p in procs
            for c in p.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        }
        assert listening == ports  # scheduler, worker, nanny: no dashboard, no /info page
        # Our own certificate is accepted; a foreign client is refused, without a
        # certificate, with a certificate of its own, over TLS or plain TCP.
        executors.check_scheduler(address, 10, client.security)
        plain = address.replace("tls://", "tcp://")
        for security in (None, executors.temporary_security(stack)):
            for addr in (address, plain):
                with pytest.raises(ConnectionError, match="Dask scheduler"):
                    executors.check_scheduler(addr, 10, security)


def test_the_report_names_a_truncated_episode_file_instead_of_a_bare_zip_error(tmp_path, capsys):
    from experiments.cli import report_main

    out = tmp_path / "results"
    evaluate(["nominal"], [0, 1], TINY, out=out, progress=False)
    damaged = out / "episodes" / "nominal__seed1.npz"
    damaged.write_bytes(damaged.read_bytes()[:200])
    try:
        code = report_main([str(out)])
    except SystemExit as exc:  # argparse's error path
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2
    assert "nominal__seed1.npz" in err and "Traceback" not in err
