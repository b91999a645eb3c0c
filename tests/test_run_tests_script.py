"""``scripts/run_tests.sh`` (the README's test command, which ``.ci/run`` calls): a run that
collects no test fails, and with ``CI=true`` the slow tests run too."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SLOW_FILE = "tests/experiments/test_winnable_worlds.py"  # holds one slow test only

pytestmark = pytest.mark.skipif(
    not (REPO / ".venv" / "bin" / "python").is_file() or shutil.which("bash") is None,
    reason="needs the clone's .venv (bash scripts/setup_env.sh test)",
)


def run_script(*args: str, ci: bool) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "CI"))}
    env["LFM_TEST_WORKERS"] = "0"  # no worker processes inside the test
    if ci:
        env["CI"] = "true"
    return subprocess.run(
        ["bash", "scripts/run_tests.sh", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )


def test_a_run_that_collects_no_test_fails():
    done = run_script(SLOW_FILE, "-k", "no_test_has_this_name", ci=False)
    assert done.returncode == 1, done.stdout[-2000:] + done.stderr[-2000:]
    assert "collected no tests; failing on purpose" in done.stderr


def test_ci_runs_the_slow_tests_and_the_default_run_does_not():
    local = run_script(SLOW_FILE, "--collect-only", "-q", ci=False)
    assert local.returncode == 1  # the only test is slow: none collected, which fails
    ci = run_script(SLOW_FILE, "--collect-only", "-q", ci=True)
    assert ci.returncode == 0, ci.stdout[-2000:] + ci.stderr[-2000:]
    assert "test_the_oracle_survives_every_quadrotor_seed_of_0_to_199" in ci.stdout
