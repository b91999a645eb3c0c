"""``lfm-train`` (``experiments.cli.train``): a run from the command line, and its one-line
errors."""

from __future__ import annotations

import dataclasses
import json

import pytest

pytest.importorskip("stable_baselines3")

from experiments.cli import train_main as main  # noqa: E402


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--minutes", "-1"], "minutes=-1.0: must be > 0"),
        (["--timesteps", "0"], "timesteps=0"),
        (["--algo", "dqn"], "invalid choice"),
        (["--config", "no/such.yaml"], "--config no/such.yaml: no such file"),
    ],
)
def test_command_line_errors_are_one_line_exit_2(tmp_path, capsys, argv, match):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(tmp_path / "out"), "--no-progress"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert match in err[-1] and err[-1].startswith("lfm-train: error:")


def test_command_line_run(tmp_path, capsys):
    config = tmp_path / "short.yaml"
    config.write_text("env:\n  max_steps: 20\n")
    out = tmp_path / "run"
    code = main(
        ["--config", str(config), "--timesteps", "64", "--n-envs", "1", "--out", str(out)]
        + ["--no-progress", "--seed", "5"]
    )
    assert code == 0
    assert json.loads((out / "policy.json").read_text())["seed"] == 5
    printed = capsys.readouterr().out
    assert f"policy: {out / 'policy.zip'}" in printed
    assert f"evaluate it: lfm-evaluate --config {out / 'eval.yaml'} --agents rl," in printed


def test_the_eval_config_beside_the_policy_evaluates_it_from_any_folder(
    tmp_path, monkeypatch, capsys
):
    """Issue 35, item 5: evaluating a trained policy meant copying a preset by hand."""
    from controllers.config import load_config
    from experiments.evaluation import evaluate

    out = tmp_path / "run"
    argv = ["--config", "quick", "--set", "env.max_steps=15", "--timesteps", "64"]
    assert main([*argv, "--n-envs", "1", "--out", str(out), "--no-progress"]) == 0
    cfg = load_config(out / "eval.yaml")
    assert cfg.agents.rl_policy == str((out / "policy.zip").resolve())
    quick = load_config("quick", ["env.max_steps=15"])
    assert cfg.env == quick.env
    assert cfg.agents == dataclasses.replace(quick.agents, rl_policy=cfg.agents.rl_policy)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    rows = evaluate(["rl"], [0], config=str(out / "eval.yaml"), progress=False)
    assert rows[0]["error"] == "" and rows[0]["steps"] > 0


def _train(tmp_path, out, *extra: str) -> int:
    config = tmp_path / "short.yaml"
    config.write_text("env:\n  max_steps: 20\n")
    argv = ["--config", str(config), "--timesteps", "64", "--n-envs", "1", "--out", str(out)]
    return main([*argv, "--no-progress", *extra])


def _steps(out) -> int:
    return json.loads((out / "policy.json").read_text())["timesteps"]


def test_a_folder_with_a_policy_is_refused_unless_resumed_or_replaced(tmp_path, capsys):
    """Case 10: a rerun silently replaced a longer-trained policy. Now it is refused naming
    --resume and --force, and the policy is kept; --resume trains it further, --force
    replaces it."""
    out = tmp_path / "run"
    assert _train(tmp_path, out) == 0
    first, policy = _steps(out), (out / "policy.zip").read_bytes()
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        _train(tmp_path, out)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("lfm-train: error: training folder")
    assert f"ppo policy trained for {first} steps" in err
    assert "--resume" in err and "--force" in err
    assert (out / "policy.zip").read_bytes() == policy and _steps(out) == first
    assert _train(tmp_path, out, "--resume") == 0
    resumed = json.loads((out / "policy.json").read_text())
    assert resumed["resumed_from"] == first and resumed["timesteps"] >= first + 64
    assert (out / "policy.zip").read_bytes() != policy
    with pytest.raises(SystemExit):
        _train(tmp_path, out, "--resume", "--algo", "sac")
    assert "resume it with --algo ppo" in capsys.readouterr().err
    assert _train(tmp_path, out, "--force", "--seed", "9") == 0
    replaced = json.loads((out / "policy.json").read_text())
    assert replaced["resumed_from"] == 0 and replaced["seed"] == 9 and replaced["timesteps"] < 128
    with pytest.raises(SystemExit):
        _train(tmp_path, tmp_path / "empty", "--resume")
    assert "holds no policy to resume" in capsys.readouterr().err


def test_two_runs_into_one_folder_cannot_both_train(tmp_path, capsys):
    """Case 10: two runs into one folder both succeeded (the last one's policy won). Now
    the second is refused while the first trains, naming it."""
    import subprocess
    import sys
    import time
    from pathlib import Path

    out = tmp_path / "run"
    first = subprocess.Popen(
        [str(Path(sys.executable).with_name("lfm-train")), "--timesteps", "100000000"]
        + ["--n-envs", "1", "--out", str(out), "--no-progress", "--minutes", "5"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not (out / ".lock").exists() or not (out / ".lock").read_text():
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline, "the first run never took its folder"
            time.sleep(0.1)
        with pytest.raises(SystemExit) as exc:
            _train(tmp_path, out)
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"is in use by process {first.pid} on " in err
        assert not (out / "policy.zip").exists()  # the second run trained nothing
    finally:
        first.kill()
        first.wait()


def test_a_policy_set_of_two_trainings_is_refused_by_name(tmp_path, capsys):
    """Defect 7: ``lfm-train`` wrote policy.zip, policy.npz and policy.json in place one
    after another; killed between the first two, a longer-trained zip sat beside the shorter
    run's npz and json, ``--resume`` recorded the wrong ``resumed_from`` and the ``rl`` agent
    loaded the mismatched set. Now the files are written to temporary files and renamed into
    place, policy.json last with the SHA-256 of the other two: a set of two trainings (here
    made as such a kill leaves it) is refused by the ``rl`` agent and by ``--resume``, naming
    the file."""
    import shutil

    from controllers.agents import make_agent
    from controllers.config import ConfigError, load_config

    short, longer = tmp_path / "short", tmp_path / "longer"
    assert _train(tmp_path, short) == 0
    shutil.copytree(short, longer)
    assert _train(tmp_path, longer, "--resume") == 0
    assert _steps(longer) > _steps(short)
    summary = json.loads((short / "policy.json").read_text())
    assert set(summary["files"]) == {"policy.zip", "policy.npz"}
    assert not list(short.glob("*.tmp")) and not list(short.glob(".*.tmp"))
    config = load_config(short / "eval.yaml")
    make_agent("rl", config)  # the set as written: loads
    shutil.copyfile(longer / "policy.zip", short / "policy.zip")  # the zip of the longer run
    with pytest.raises(ConfigError, match=r"policy\.zip.*policy\.json"):
        make_agent("rl", config)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        _train(tmp_path, short, "--resume")
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "policy.zip" in err and "--force" in err, err
    assert json.loads((short / "policy.json").read_text()) == summary  # nothing written
    assert _train(tmp_path, short, "--force") == 0  # replaced: a set again
    make_agent("rl", load_config(short / "eval.yaml"))
