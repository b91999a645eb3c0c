"""Real ``lfm-evaluate`` runs for the tests of interrupts and shared folders: started as a
process group on a small config, waited for, and checked for orphan workers and a
consistent folder."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
LFM_EVALUATE = Path(sys.executable).with_name("lfm-evaluate")
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
#: The small config of these runs.
SMALL = {
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
