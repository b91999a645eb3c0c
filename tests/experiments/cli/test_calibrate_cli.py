"""``lfm-calibrate`` (``experiments.cli.calibrate``): the learned config it writes, and its
one-line errors."""

from __future__ import annotations

import pytest

from controllers.agents import make_agent
from controllers.config import load_config
from experiments.cli import calibrate_main as main
from lfm_env.worlds.registry import load_env_config


def test_cli_writes_a_config_whose_agents_model_the_learned_force(tmp_path, capsys):
    out = tmp_path / "learned.yaml"
    cfg = tmp_path / "small.yaml"
    cfg.write_text("env:\n  max_steps: 20\nagents:\n  n_particles: 200\n  n_scenarios: 5\n")
    assert main(["--config", str(cfg), "--seeds", "0:2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "variance" in printed and "lengthscale" in printed
    agent = make_agent("pf", str(out))
    learned = agent.model.kernel
    # The env keeps the true (hidden) force; the agents use the learned one.
    assert load_env_config(str(out)).latent_force.variance == 4.0
    assert learned.variance != 4.0


def test_cli_rejects_a_bad_seed_range(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--seeds", "5:2"])
    assert exc.value.code == 2
    assert "5:2" in capsys.readouterr().err


def test_cli_calibrates_the_quadrotor_preset(tmp_path, capsys):
    """Issue 35, item 2: lfm-calibrate --config quadrotor crashed (a hard-coded sine track)."""
    out = tmp_path / "learned.yaml"
    assert main(["--config", "quadrotor", "--seeds", "1000:1003", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "samples of v_x [m/s] on lfm_env/QuadrotorGust-v1" in printed
    cfg = load_config(str(out))
    assert cfg.env_id == "lfm_env/QuadrotorGust-v1" and cfg.env == load_config("quadrotor").env
    learned = cfg.agents.latent_force
    # Three short episodes: the gust's std 2.0 m/s^2 and lengthscale 2.5 s, within a factor 3.
    assert 4.0 / 9 < learned.variance < 4.0 * 9 and 2.5 / 3 < learned.lengthscale < 2.5 * 3


def test_an_existing_out_is_refused_before_any_episode_unless_forced(tmp_path, capsys):
    """``lfm-calibrate --out`` overwrote an existing file silently. Now it is refused
    before any episode runs (exit 2, naming --force); --force replaces it."""
    out = tmp_path / "learned.yaml"
    out.write_text("# a learned config of yesterday\n")
    cfg = tmp_path / "small.yaml"
    cfg.write_text("env:\n  max_steps: 20\nagents:\n  n_particles: 200\n  n_scenarios: 5\n")
    with pytest.raises(SystemExit) as exc:
        main(["--config", str(cfg), "--seeds", "0:2", "--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("lfm-calibrate: error: --out") and "--force" in err
    assert str(out) in err and "calibration:" not in capsys.readouterr().out
    assert out.read_text() == "# a learned config of yesterday\n"
    assert main(["--config", str(cfg), "--seeds", "0:2", "--out", str(out), "--force"]) == 0
    assert "agents:" in out.read_text()
