"""``lfm-train`` (``experiments.cli.train``): a run from the command line, and its one-line
errors."""

from __future__ import annotations

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
    assert f"policy: {out / 'policy.zip'}" in capsys.readouterr().out
