"""The README's commands in a fresh shell (issue 35, item 1): after the two commands made
``.venv``, a new shell has neither the tools nor the packages until it activates it; then
every command and ``import lfm_env`` work, from the clone and from any other folder."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / ".venv"
CLEAN_PATH = "/usr/bin:/bin"  # a fresh login shell's PATH, without the venv's bin


def fresh_shell(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """``bash -c command`` with a clean PATH, no VIRTUAL_ENV and no PYTHONPATH."""
    env = {"PATH": CLEAN_PATH, "HOME": os.environ.get("HOME", "/root"), "LANG": "C.UTF-8"}
    return subprocess.run(
        ["bash", "-c", command], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def venv() -> Path:
    if not (VENV / "bin" / "activate").is_file():
        pytest.skip("no .venv in the clone: bash scripts/setup_env.sh (or run_tests.sh) makes it")
    if shutil.which("bash") is None:
        pytest.skip("no bash")
    return VENV


def test_without_activating_the_tools_are_not_found(venv):
    """The environment of the test is clean: what a user met before the README said how."""
    done = fresh_shell("lfm-evaluate --help", REPO)
    assert done.returncode == 127 and "lfm-evaluate" in done.stderr


@pytest.mark.parametrize(
    "command, expected",
    [
        ("lfm-evaluate --help", "usage: lfm-evaluate"),
        ("lfm-report --help", "usage: lfm-report"),
        (
            "python -c 'import lfm_env, controllers, experiments; print(lfm_env.__name__)'",
            "lfm_env",
        ),
    ],
)
def test_after_source_venv_activate_every_command_works(venv, command, expected, tmp_path):
    """``source .venv/bin/activate`` (the README's first screen), then the command: from the
    clone, and from another folder with the absolute path."""
    done = fresh_shell(f"source .venv/bin/activate && {command}", REPO)
    assert done.returncode == 0, done.stderr
    assert expected in done.stdout
    elsewhere = fresh_shell(f"source {venv}/bin/activate && {command}", tmp_path)
    assert elsewhere.returncode == 0, elsewhere.stderr
    assert expected in elsewhere.stdout
