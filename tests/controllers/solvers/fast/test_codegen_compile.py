"""The C compile never costs an episode: it runs before the first episode's clock, it is
installed in the cache even when the one who asked stops waiting, and a compiler slower than
the bound gives the NumPy backend with one notice.

Each case uses the real compiler behind a script that first sleeps (a slow or loaded
machine's compiler), an empty cache folder of the test's own (``$LFM_CACHE_DIR``), and real
``lfm-evaluate`` runs or builds in processes of their own. Before, with an empty cache and
``--episode-timeout 2``, a compile slower than the limit lost every episode on every rerun
(the compile was killed with its episode and never cached), and a slow compiler never fell
back to NumPy.
"""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[4]
LFM_EVALUATE = Path(sys.executable).with_name("lfm-evaluate")

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler (cc)")


def slow_compiler(tmp_path: Path, seconds: float) -> tuple[Path, Path]:
    """The real ``cc`` behind a script that sleeps ``seconds`` first and logs each call."""
    log = tmp_path / "calls.log"
    script = tmp_path / f"cc-slow-{seconds:g}"
    script.write_text(f'#!/bin/sh\necho "$@" >> "{log}"\nsleep {seconds}\nexec cc "$@"\n')
    script.chmod(0o755)
    return script, log


def environment(cache: Path, compiler: Path, **extra: str) -> dict[str, str]:
    env = {**os.environ, "LFM_CACHE_DIR": str(cache), "CC": str(compiler), **extra}
    env.update(OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    for name in ("LFM_BACKEND", "LFM_COMPILE_TIMEOUT", "LFM_NOTICES_SHOWN"):
        if name not in extra:
            env.pop(name, None)
    return env


def evaluate_cli(
    tmp_path: Path, env: dict, *options: str
) -> tuple[subprocess.CompletedProcess, list]:
    config = tmp_path / "tiny.yaml"
    config.write_text(
        "env:\n  max_steps: 15\nagents:\n  horizon: 5\n  n_scenarios: 5\n  n_particles: 300\n"
    )
    out = tmp_path / "out"
    cmd = [str(LFM_EVALUATE), "--config", str(config), "--agents", "nominal,scenario"]
    cmd += ["--seeds", "0:2", "--out", str(out), "--no-report", "--quiet", *options]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    with open(out / "episodes.csv", newline="") as fh:
        return proc, list(csv.DictReader(fh))


def wait_for_library(cache: Path, limit: float = 300.0) -> list[Path]:
    """The libraries of the cache once no build runs there any more (a build that was left
    to go on in the background ends by itself)."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        busy = list(cache.glob("*.tmp")) + [c for c in cache.glob("*.c") if c.stem.count(".")]
        if not busy and list(cache.glob("lfm_codegen_*.so")):
            return sorted(cache.glob("*.so"))
        time.sleep(0.2)
    raise AssertionError(f"no library was built in {cache}: {sorted(cache.iterdir())}")


@pytest.mark.parametrize("options", [[], ["--jobs", "2"]], ids=["serial", "pool"])
def test_the_compile_does_not_count_against_the_episode_limit(options, tmp_path):
    """An empty cache, a compile of about 4 s and a limit of 2 s on episodes that take well
    under a second: every episode ran (the libraries are compiled before the first
    episode's clock starts), and the compiler ran once per library."""
    compiler, log = slow_compiler(tmp_path, 4)
    env = environment(tmp_path / "cache", compiler)
    proc, rows = evaluate_cli(tmp_path, env, "--episode-timeout", "2", *options)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [r["error"] for r in rows] == [""] * 4
    assert not [line for line in proc.stderr.splitlines() if "NumPy" in line], proc.stderr
    libraries = sorted(p.name.split("_")[1] for p in (tmp_path / "cache").glob("*.so"))
    assert "codegen" in libraries
    builds: dict[str, set[str]] = {}  # library -> the builds that compiled it
    for call in log.read_text().splitlines():
        output = Path(call.split(" -o ")[1].split()[0]).name  # <name>.<build>.so.tmp
        name, build = output.split(".")[:2]
        builds.setdefault(name, set()).add(build)
    assert len(builds) == len(libraries) and all(len(b) == 1 for b in builds.values()), builds


def test_a_build_whose_asker_stops_waiting_is_finished_and_cached(tmp_path):
    """A compile interrupted with its episode (at the episode's limit) was never cached, so
    every later episode compiled again and was interrupted again. Now the build runs in a
    process of its own, which finishes and installs the library: the next process finds it
    in the cache and runs no compiler."""
    compiler, log = slow_compiler(tmp_path, 3)
    cache = tmp_path / "cache"
    build_in_episode = (
        "from experiments.evaluation.limits import EpisodeLimit, EpisodeTimeout\n"
        "from experiments.benchmark.problems import problem_from_config\n"
        "from controllers.solvers.fast.codegen.build import build_library\n"
        "problem = problem_from_config(n_scenarios=5)\n"
        "try:\n"
        "    with EpisodeLimit(1.0):\n"
        "        build_library(problem.system, problem.dt)\n"
        "    print('built')\n"
        "except EpisodeTimeout:\n"
        "    print('cancelled')\n"
    )
    env = environment(cache, compiler)
    done = subprocess.run(
        [sys.executable, "-c", build_in_episode], cwd=ROOT, env=env, capture_output=True,
        text=True, timeout=300,
    )  # fmt: skip
    assert done.stdout.strip() == "cancelled", done.stderr[-2000:]
    (library,) = wait_for_library(cache)
    assert library.with_suffix(".json").is_file()
    n_calls = len(log.read_text().splitlines())
    again = subprocess.run(
        [sys.executable, "-m", "tests.controllers.solvers.fast.cache_runs", "paper"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    assert '"cache_hits": [true]' in again.stdout and '"backend": "compiled-c"' in again.stdout
    assert len(log.read_text().splitlines()) == n_calls  # no compiler ran


def test_a_compiler_slower_than_the_bound_falls_back_to_numpy_with_one_notice(tmp_path):
    """A compiler of 40 s against a bound of 3 s (``$LFM_COMPILE_TIMEOUT``): the run gives
    the compile up after the bound and runs every episode with the NumPy backend, with one
    notice naming the bound, also with a worker process per episode batch; the build goes
    on and is cached for the next run."""
    compiler, _ = slow_compiler(tmp_path, 40)
    cache = tmp_path / "cache"
    env = environment(cache, compiler, LFM_COMPILE_TIMEOUT="3")
    proc, rows = evaluate_cli(tmp_path, env, "--episode-timeout", "60")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [r["error"] for r in rows] == [""] * 4
    notices = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
    assert len(notices) == 1, proc.stderr
    assert "NumPy" in notices[0] and "did not finish within 3 s" in notices[0]
    assert "LFM_COMPILE_TIMEOUT" in notices[0]
    assert "lfm_codegen" in " ".join(p.name for p in wait_for_library(cache, 600))
