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


# --------------------------------------------------------------------------- the world's own cost

#: The unicycle world with a goal off the lane's centre line: the sine track's goal state
#: (x 62.83 m on y = 0) would drive past it, 0.5 m away, and never reach its 0.3 m disc.
OFF_CENTRE = {
    "env": {"goal": [4.0, 0.5], "goal_state": [4.0, 0.5, 0.5, 0.0], "max_steps": 40},
    "agents": {"horizon": 5, "n_scenarios": 10, "n_particles": 300},
}


@pytest.fixture
def own_world(tmp_path: Path, monkeypatch) -> str:
    """The unicycle world as the module ``own_goal_world`` (registered, then forgotten)."""
    import gymnasium as gym

    from lfm_env.worlds.registry import WORLDS

    shutil.copy(WORLD, tmp_path / "own_goal_world.py")
    monkeypatch.syspath_prepend(str(tmp_path))
    worlds, envs = dict(WORLDS), dict(gym.envs.registry)
    WORLDS.pop("Mine/Unicycle-v0", None)  # (another test's copy of the module may hold it)
    gym.envs.registry.pop("Mine/Unicycle-v0", None)
    yield "own_goal_world:Mine/Unicycle-v0"
    WORLDS.clear()
    WORLDS.update(worlds)
    gym.envs.registry.clear()
    gym.envs.registry.update(envs)
    sys.modules.pop("own_goal_world", None)


def test_the_agents_reach_a_worlds_own_goal_with_no_agents_cost(own_world, tmp_path):
    """With ``agents:`` giving no cost, the agents steer to the world's goal with its weights
    (Qf = Q), the results folder's config.yaml and the report say so; before, they steered to
    the sine track's goal state and never reached this one."""
    from controllers.config import load_config
    from experiments.evaluation import evaluate
    from experiments.report import write_report

    config = load_config({"env_id": own_world, **OFF_CENTRE})
    world = config.env
    assert (config.agents.Q, config.agents.Qf, config.agents.R) == (world.Q, world.Q, world.R)
    assert config.agents.goal_state == (4.0, 0.5, 0.5, 0.0)
    rows = evaluate(["nominal", "pf"], [0, 1], config, out=tmp_path / "results", progress=False)
    assert [(r["agent"], r["error"], bool(r["success"])) for r in rows] == [
        (a, "", True) for a in ("nominal", "pf") for _ in (0, 1)
    ]
    saved = yaml.safe_load((tmp_path / "results" / "config.yaml").read_text())["agents"]
    assert saved["goal_state"] == [4.0, 0.5, 0.5, 0.0] and saved["Qf"] == list(world.Q)
    write_report(tmp_path / "results", gif=False)
    md = (tmp_path / "results" / "report.md").read_text()
    assert "`goal_state` [4.0, 0.5, 0.5, 0.0] (the world's own;" in md


def test_an_agents_cost_of_another_worlds_size_names_both(own_world):
    from controllers.config import ConfigError, load_config

    source = {"env_id": own_world, "agents": {"Q": [2.0, 2.0, 1.0, 0.0, 1.0, 1.0]}}
    with pytest.raises(ConfigError) as exc:
        load_config(source)
    message = str(exc.value)
    assert "agents.Q=[2.0, 2.0, 1.0, 0.0, 1.0, 1.0]: has 6 values" in message
    assert "has 4 states" in message and "env.Q=[1.0, 2.0, 0.5, 0.1]" in message
    assert "\n" not in message
