"""Every function of the agents' layer that takes a config takes a preset's name, a path, a
file that inherits (``base:``) and ``KEY=VALUE`` settings (issue 35, items 3 and 5)."""

from __future__ import annotations

from pathlib import Path

import pytest

from controllers.agents import make_agent
from controllers.config import ConfigError, load_config

REPO = Path(__file__).resolve().parents[2]


def test_load_config_and_make_agent_take_a_preset_by_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # not the repository: no configs/ folder here
    assert load_config("paper") == load_config(REPO / "configs" / "paper.yaml")
    assert load_config("quadrotor").env_id == "lfm_env/QuadrotorGust-v1"
    agent = make_agent("pf", "quick")
    assert agent.settings == load_config(REPO / "configs" / "quick.yaml").agents


def test_settings_override_a_config_and_an_experiment_config():
    cfg = load_config("quick", ["agents.horizon=4", "agents.robust.backoff=[1, 0, 2]"])
    assert cfg.agents.horizon == 4 and cfg.agents.robust.backoff == (1.0, 0.0, 2.0)
    again = load_config(cfg, ["agents.n_particles=50"])
    assert again.agents.n_particles == 50 and again.agents.horizon == 4
    with pytest.raises(ConfigError, match=r"agents has no key 'horizn'; its keys are"):
        load_config("quick", ["agents.horizn=4"])
    with pytest.raises(ConfigError, match=r"agents.horizon='x': expected an integer"):
        load_config("quick", ["agents.horizon=x"])


def test_a_file_inherits_the_preset_it_names(tmp_path):
    path = tmp_path / "eval.yaml"
    path.write_text("base: paper\nagents:\n  n_particles: 500\n")
    cfg = load_config(path)
    paper = load_config("paper")
    assert cfg.agents.n_particles == 500
    assert cfg.agents.robust == paper.agents.robust and cfg.env == paper.env
