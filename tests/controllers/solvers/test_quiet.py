"""Third-party solvers print nothing (:mod:`controllers.solvers.quiet`): qpOASES's licence
banner, printed whenever a qpOASES instance is created, is discarded at its source, in the
commands' real output and in their worker processes, whether standard output is a terminal, a
pipe or a file (buffered or not)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

BANNER = "qpOASES -- An Implementation of the Online Active Set Strategy"
BIN = Path(sys.executable).parent


def quiet_env() -> dict[str, str]:
    """The environment of a user's shell: Python's stdout block-buffered when it is a pipe
    (no ``PYTHONUNBUFFERED``), which is what let the banner through."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    env["OPENBLAS_NUM_THREADS"] = "1"
    return env


def run_python(code: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=quiet_env(), timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_a_qpoases_conic_built_in_a_section_prints_nothing_into_a_pipe():
    out = run_python(
        "import casadi as ca\n"
        "from controllers.solvers.quiet import silenced_output\n"
        "OPTS = {'printLevel': 'none'}\n"
        "for i in range(5):\n"
        "    with silenced_output():\n"
        "        c = ca.conic('q', 'qpoases', {'h': ca.Sparsity.dense(2, 2)}, OPTS)\n"
        "        c.buffer()\n"
        "    print('step', i)\n"
    )
    assert BANNER not in out
    assert out.split() == [w for i in range(5) for w in ("step", str(i))]  # the rest is kept


def test_the_banner_is_there_to_be_silenced():
    """Without a section, the same conic prints its banner (so the tests above can fail)."""
    out = run_python(
        "import casadi as ca\n"
        "ca.conic('q', 'qpoases', {'h': ca.Sparsity.dense(2, 2)}, {'printLevel': 'none'})\n"
    )
    assert BANNER in out


def test_python_and_c_output_is_discarded_and_stdout_restored(capfd):
    from controllers.solvers.quiet import silenced_output

    libc = ctypes.CDLL(None)
    print("before", flush=True)
    with silenced_output():
        print("python inside")
        libc.printf(b"c inside\n")
        with silenced_output():  # sections nest
            print("nested")
        print("still inside")
    libc.fflush(None)
    print("after", flush=True)
    out = capfd.readouterr().out
    assert out.split() == ["before", "after"]


def test_overlapping_sections_of_threads_restore_stdout(capfd):
    from controllers.solvers.quiet import silenced_output

    stdout = sys.stdout
    inside, release = threading.Barrier(2), threading.Event()

    def worker():
        with silenced_output():
            inside.wait()
            release.wait()

    thread = threading.Thread(target=worker)
    thread.start()
    with silenced_output():
        inside.wait()
    release.set()  # the other thread leaves last
    thread.join()
    assert sys.stdout is stdout
    print("restored", flush=True)
    assert capfd.readouterr().out == "restored\n"


def test_sqpmethod_prints_no_banner():
    out = run_python(
        "from controllers.config import load_config\n"
        "from controllers.solvers import make_solver\n"
        "problem = load_config('quick').make_problem()\n"
        "make_solver(problem, 'sqpmethod', jit=False)\n"
        "print('built')\n"
    )
    assert out.strip() == "built"


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_lfm_evaluate_prints_no_banner(tmp_path, jobs):
    """``robust`` and ``pf`` start each episode on a fresh qpOASES memory (38 banners in two
    episodes each before): none in the output, with worker processes too."""
    argv = [str(BIN / "lfm-evaluate"), "--config", "quick", "--agents", "robust,pf"]
    argv += ["--seeds", "0:2", "--jobs", jobs, "--out", str(tmp_path / "run"), "--no-report"]
    done = subprocess.run(argv, capture_output=True, text=True, env=quiet_env(), timeout=600)
    assert done.returncode == 0, done.stderr
    assert (done.stdout + done.stderr).count(BANNER) == 0
    assert "robust: 2 episodes" in done.stdout


def test_lfm_calibrate_prints_no_banner(tmp_path):
    """The calibration's nominal MPC on the quadrotor (29 banners in two episodes before)."""
    argv = [str(BIN / "lfm-calibrate"), "--config", "quadrotor", "--seeds", "1000:1002"]
    argv += ["--out", str(tmp_path / "learned.yaml")]
    done = subprocess.run(argv, capture_output=True, text=True, env=quiet_env(), timeout=600)
    assert done.returncode == 0, done.stderr
    assert (done.stdout + done.stderr).count(BANNER) == 0
    assert "learned config" in done.stdout
