"""A world of one's own, from one's own module (issue 35, item 4 and "Done when"): a world
defined in a file outside the package, in a temporary folder, named by ``module:EnvId`` in a
YAML config, runs through ``lfm-evaluate --jobs 2``, ``lfm-report`` and ``lfm-calibrate``
started from that folder, as a user would."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
WORLD = REPO / "tests" / "data" / "own_world" / "unicycle_world.py"
CONFIG = """\
env_id: mine:Mine/Unicycle-v0
env:
  max_steps: 20
agents:
  horizon: 5
  n_scenarios: 10
  n_particles: 200
  Q: [1.0, 2.0, 0.5, 0.1]
  Qf: [1.0, 2.0, 0.5, 0.1]
  R: [0.1, 0.1]
  goal_state: [4.0, 0.0, 1.0, 0.0]
"""


def command(name: str) -> list[str]:
    """The installed console script ``name`` beside this interpreter (the user's command),
    else the same ``main`` through this interpreter."""
    script = Path(sys.executable).parent / name
    if script.is_file():
        return [str(script)]
    main = name.removeprefix("lfm-") + "_main"
    return [sys.executable, "-c", f"import sys; from experiments.cli import {main}; "
            f"sys.exit({main}())"]  # fmt: skip


def run(folder: Path, name: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    env.pop("PYTHONPATH", None)  # the world is found from the folder, not from a path
    done = subprocess.run(
        [*command(name), *args], cwd=folder, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, f"{name} {args}: {done.stderr[-3000:]}"
    return done


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    shutil.copy(WORLD, tmp_path / "mine.py")
    (tmp_path / "mine.yaml").write_text(CONFIG)
    return tmp_path


def test_a_world_from_a_users_folder_runs_through_evaluate_report_and_calibrate(folder):
    run(folder, "lfm-evaluate", "--config", "mine.yaml", "--agents", "nominal,pf",
        "--seeds", "0:2", "--jobs", "2", "--out", "results", "--no-report", "--quiet")  # fmt: skip
    results = folder / "results"
    saved = yaml.safe_load((results / "config.yaml").read_text())
    assert saved["env_id"] == "mine:Mine/Unicycle-v0"  # the folder names its world's module
    rows = (results / "episodes.csv").read_text().splitlines()
    assert len(rows) == 5 and all(line.endswith(",") for line in rows[1:])  # no error

    report = run(folder, "lfm-report", "results")
    assert "report:" in report.stdout
    md = (results / "report.md").read_text()
    assert "`Mine/Unicycle-v0` (system `unicycle`)" in md
    assert "Paper vs measured" not in md  # the sine track's own section
    # No scene of its own: the replay is the plan's panel alone.
    assert "the world has no scene of its own" in md
    assert (results / "figures" / "episode.gif").stat().st_size > 1000

    out = run(folder, "lfm-calibrate", "--config", "mine.yaml", "--seeds", "1000:1002",
              "--out", "learned.yaml").stdout  # fmt: skip
    assert "samples of v [m/s] on mine:Mine/Unicycle-v0" in out
    learned = yaml.safe_load((folder / "learned.yaml").read_text())
    assert learned["env_id"] == "mine:Mine/Unicycle-v0"
    assert learned["agents"]["latent_force"]["variance"] > 0.0


def test_an_unimportable_world_module_is_a_one_line_error(folder):
    (folder / "bad.yaml").write_text("env_id: nomodule:Mine/Unicycle-v0\n")
    done = subprocess.run(
        [*command("lfm-evaluate"), "--config", "bad.yaml", "--out", "r"],
        cwd=folder, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 2
    last = done.stderr.strip().splitlines()[-1]
    assert "env_id='nomodule:Mine/Unicycle-v0': cannot import the module 'nomodule'" in last
