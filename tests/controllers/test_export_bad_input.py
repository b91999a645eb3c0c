"""The exported controller on bad input: sizes checked before memory is taken, a defined input
on every return, nothing printed as a plan that was not solved.

The paper's ``robust`` agent is exported and built with the real compiler (``make``,
``CC=cc``); its ``example`` program and its library (through ctypes) get the inputs a careless
caller or a broken sensor gives: a repeat count near ``2^63``, NaN and infinite numbers in a
problem or a measurement, a force array of the wrong shape.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from controllers.config import load_config
from controllers.export import ExportedController, export_controller, write_problem

REPO = Path(__file__).resolve().parents[2]
RECORDED = dict(np.load(REPO / "tests" / "data" / "recorded_problems.npz"))

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler (cc)")


@pytest.fixture(scope="module")
def robust(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "robust"
    export_controller(str(REPO / "configs" / "paper.yaml"), "robust", out)
    done = subprocess.run(["make", "-C", str(out), "CC=cc"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return out


@pytest.fixture(scope="module")
def fallback() -> np.ndarray:
    """The sine track's fallback input (full braking, wheels straight)."""
    return np.asarray(load_config("paper").make_system().fallback_input, dtype=float)


def example(folder: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(folder / "example"), *args], capture_output=True, text=True, timeout=120
    )


def test_a_huge_repeat_count_is_refused_before_any_memory_is_taken(robust, tmp_path):
    """``--time K`` took ``8 K`` bytes unchecked: SIGSEGV at K = 2^60, heap corruption at
    2^61. Now K out of its range (or not a number) is one line and exit code 2."""
    problem = tmp_path / "problem.txt"
    write_problem(problem, RECORDED["x0"][0], RECORDED["W"][0][:1])
    steps = tmp_path / "y.txt"
    steps.write_text("0 0 1 0.7853981633974483\n0.2 0.2 1.5 0.78\n")
    for k in (str(2**60), str(2**61), str(2**63 - 1), "99999999999999999999", "12x", "0", "-3"):
        for mode in ([str(problem)], ["--steps", str(steps)]):
            done = example(robust, "--time", k, *mode)
            assert done.returncode == 2, (k, mode, done.returncode, done.stderr[-300:])
            assert "--time" in done.stderr and done.stdout == "", (k, done.stderr)
    done = example(robust, "--time", "3", str(problem))
    assert done.returncode == 0 and done.stderr.startswith("time_us ")


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_a_problem_with_a_non_finite_number_prints_no_plan(robust, tmp_path, bad):
    """``example PROBLEM`` printed an all-zero plan on stdout (with a nonzero exit) for a
    problem it did not solve. Now stdout stays empty, stderr names the problem, exit 2."""
    problem = tmp_path / "problem.txt"
    write_problem(problem, RECORDED["x0"][0], RECORDED["W"][0][:1])
    numbers = problem.read_text().split()
    numbers[5] = bad  # an entry of W
    problem.write_text(" ".join(numbers) + "\n")
    done = example(robust, str(problem))
    assert done.stdout == "", done.stdout
    assert done.returncode == 2 and "Bad_Input" in done.stderr, done.stderr


def test_a_bad_measurement_gives_the_documented_fallback_input(robust, tmp_path, fallback):
    """A NaN or infinite measurement wrote no ``u`` (``LFM_BAD_INPUT``): the header's loop
    applied a stale input, and ``example --steps`` printed ``0 0`` from uninitialised
    memory. Now ``u`` is the system's fallback input, ``lfm_info.action`` says so, and the
    next good measurement is served as usual."""
    steps = tmp_path / "y.txt"
    steps.write_text("0 0 1 0.7853981633974483\nnan 0.2 1.5 0.78\n0.2 0.2 1.5 inf\n")
    done = example(robust, "--steps", str(steps))
    assert done.returncode == 1, done.stderr  # some steps did not succeed
    rows = [np.array(line.split(), dtype=float) for line in done.stdout.splitlines()]
    assert len(rows) == 3
    np.testing.assert_array_equal(rows[1], fallback)
    np.testing.assert_array_equal(rows[2], fallback)
    controller = ExportedController(robust)
    controller.reset(0)
    good = np.array([0.0, 0.0, 1.0, np.pi / 4])
    u0, status = controller.step(good)
    assert status == "Solve_Succeeded" and controller.info()["action"] == "plan"
    for bad in (np.nan, np.inf):
        u, status = controller.step(np.array([0.2, bad, 1.5, 0.78]))
        assert status == "Bad_Input"
        np.testing.assert_array_equal(u, fallback)
        info = controller.info()
        assert info["action"] == "fallback" and not info["usable"]
    u, status = controller.step(good + 0.01)
    assert status == "Solve_Succeeded" and np.all(np.isfinite(u))


def test_solve_checks_the_forces_full_shape_and_finiteness(robust):
    """``ExportedController.solve`` only reshaped ``W``: a transposed array passed with
    ``Solve_Succeeded`` and a plan far from the problem's. Now a shape other than
    ``(Ns, N, nw)`` (or ``(Ns, N)`` for one force) and a non-finite number are refused,
    naming the expected shape."""
    controller = ExportedController(robust)
    n, ns, nw = controller.horizon, controller.n_scenarios, controller.nw
    x0 = RECORDED["x0"][0]
    W = np.linspace(-1.0, 1.0, ns * n * nw).reshape(ns, n, nw)
    plan, status = controller.solve(x0, W)
    assert status == "Solve_Succeeded" and plan.shape == (n, controller.nu)
    assert nw == 1
    controller.solve(x0, W[..., 0])  # (Ns, N) for one force component
    for bad in (W.transpose(1, 0, 2), W.reshape(-1), W[:, :-1], np.concatenate([W, W], 2)):
        with pytest.raises(ValueError, match=rf"\({ns}, {n}, {nw}\)"):
            controller.solve(x0, bad)
    for bad_value in (np.nan, np.inf):
        broken = W.copy()
        broken[0, 2, 0] = bad_value
        with pytest.raises(ValueError, match="finite"):
            controller.solve(x0, broken)
    with pytest.raises(ValueError, match=rf"\({controller.nx},\)"):
        controller.solve(x0[:-1], W)
    with pytest.raises(ValueError, match="finite"):
        controller.solve(np.full(controller.nx, np.nan), W)
    with pytest.raises(ValueError, match=rf"\({controller.nx},\)"):
        controller.step(np.zeros(controller.nx + 1))
