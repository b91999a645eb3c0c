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
