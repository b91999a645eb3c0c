"""Configs by name from any folder, ``base:`` inheritance and ``KEY=VALUE`` overrides: a whole
config is read in one place (``controllers.config``), a world reads its ``env:`` section
(``lfm_env.worlds.registry.load_env_config``)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import pytest
import yaml

import lfm_env  # noqa: F401  (registers the envs)
from controllers.config import apply_overrides, load_config, read_document
from lfm_env.config import ConfigError, config_path, preset_names
from lfm_env.worlds.registry import load_env_config

REPO = Path(__file__).resolve().parents[2]


def test_presets_are_found_by_name_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert preset_names() == sorted(p.stem for p in (REPO / "configs").glob("*.yaml"))
    for name in preset_names():
        assert config_path(name).read_bytes() == (REPO / "configs" / f"{name}.yaml").read_bytes()
        assert config_path(f"{name}.yaml") == config_path(name)
    assert load_env_config("quadrotor").ENV_ID == "lfm_env/QuadrotorGust-v1"
    assert load_env_config("paper") == load_env_config(REPO / "configs" / "paper.yaml")
    # gym.make(..., config=NAME) reads the same file.
    env = gym.make("lfm_env/QuadrotorGust-v1", config="quadrotor")
    assert env.unwrapped.config == load_env_config("quadrotor")


def test_a_file_wins_over_a_preset_and_an_unknown_name_lists_the_presets(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "paper").write_text("env:\n  dt: 0.1\n")
    assert load_env_config("paper").dt == 0.1  # the file named like a preset is meant
    with pytest.raises(ConfigError, match=r"'nope': does not exist and names no preset; presets: "):
        load_env_config("nope")
    with pytest.raises(ConfigError, match="names no preset"):
        read_document("sub/quick.yaml")  # a relative path is a path, not a name


def test_base_inherits_a_preset_and_overrides_fields(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(
        "base: paper\nenv:\n  latent_force:\n    variance: 9.0\n"
        "agents:\n  Q: [1.0, 1.0, 1.0, 1.0]\n"
    )
    data = read_document(path)
    paper = yaml.safe_load((REPO / "configs" / "paper.yaml").read_text())
    assert "base" not in data
    lf = data["env"]["latent_force"]
    assert lf["variance"] == 9.0
    assert lf["lengthscale"] == paper["env"]["latent_force"]["lengthscale"]
    assert data["agents"]["Q"] == [1.0, 1.0, 1.0, 1.0]  # a list replaces the base's
    assert data["agents"]["robust"] == paper["agents"]["robust"]  # untouched sections kept
    assert load_config(path).env.latent_force.variance == 9.0
    # A world alone reads one file's env section: a file that inherits is read whole above.
    with pytest.raises(ConfigError, match=r"inherits \(base: 'paper'\).*load_config"):
        load_env_config(path)
    with pytest.raises(ConfigError, match=r"inherits \(base: 'paper'\)"):
        gym.make("lfm_env/SineTrack-v0", config=str(path))
    env = gym.make("lfm_env/SineTrack-v0", config=load_config(path).env)
    assert env.unwrapped.config.latent_force.variance == 9.0


def test_base_paths_are_relative_to_the_file_and_chain(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.yaml").write_text("base: quadrotor\nenv:\n  max_steps: 50\n")
    (tmp_path / "b.yaml").write_text("base: sub/a.yaml\nenv:\n  dt: 0.05\n")
    cfg = load_config(tmp_path / "b.yaml").env
    assert (cfg.ENV_ID, cfg.max_steps, cfg.dt) == ("lfm_env/QuadrotorGust-v1", 50, 0.05)
    # A dict may inherit too (a relative base path is then relative to the working folder).
    assert load_config({"base": "quadrotor"}).env.ENV_ID == "lfm_env/QuadrotorGust-v1"


def test_bad_bases_are_one_line_errors(tmp_path):
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(ConfigError, match="inherits from itself"):
        read_document(tmp_path / "a.yaml")
    (tmp_path / "c.yaml").write_text("base: [paper]\n")
    with pytest.raises(ConfigError, match=r"base=\['paper'\].*must be a preset's name"):
        read_document(tmp_path / "c.yaml")
    (tmp_path / "d.yaml").write_text("base: nope\n")
    with pytest.raises(ConfigError, match="base: config 'nope': does not exist"):
        read_document(tmp_path / "d.yaml")
    (tmp_path / "e.yaml").write_text("base: paper\nenvv: {}\n")
    with pytest.raises(ConfigError, match=r"unknown top-level config section\(s\) \['envv'\]"):
        load_config(tmp_path / "e.yaml")


def test_overrides_are_read_by_their_fields_type():
    data = apply_overrides(
        {"env": {"dt": 0.1}},
        [
            "env.latent_force.variance=1e-3",  # YAML alone would read text
            "env.measurement_noise_std=[0.1, 0.1, 0.1, 1]",
            "env.max_steps=20",
            "env.dt=0.2",  # later overrides win over the file
        ],
    )
    assert data["env"]["latent_force"] == {"variance": 1e-3}
    cfg = load_env_config(data)
    assert (cfg.dt, cfg.max_steps, cfg.latent_force.variance) == (0.2, 20, 1e-3)
    assert cfg.measurement_noise_std == (0.1, 0.1, 0.1, 1.0)
    # env_id first: the env keys are the fields of the world it names.
    quad = apply_overrides({}, ["env.pitch_max=0.3", "env_id=lfm_env/QuadrotorGust-v1"])
    assert load_env_config(quad).pitch_max == 0.3


@pytest.mark.parametrize(
    "setting, message",
    [
        ("env.dtt=1", r"--set env.dtt: env has no key 'dtt'; its keys are \[.*'dt'"),
        ("env.latent_force=1", "env.latent_force is a section; set one of its keys"),
        ("env.dt.x=1", r"env.dt is a value, not a section"),
        ("dt=1", "the key must start with one of"),
        ("env=1", "env is a section"),
        ("horizon", "expected KEY=VALUE"),
    ],
)
def test_bad_overrides_name_the_key(setting, message):
    with pytest.raises(ConfigError, match=message):
        apply_overrides({}, [setting])


def test_a_bad_value_names_the_field():
    with pytest.raises(ConfigError, match=r"env.max_steps='many': expected an integer"):
        load_env_config(read_document("paper", ["env.max_steps=many"]))
    with pytest.raises(ConfigError, match=r"agents.horizon='x': expected an integer"):
        load_config("paper", ["agents.horizon=x"])
    with pytest.raises(ConfigError, match=r"evaluation.episode_timeout='x': expected a number"):
        load_config("paper", ["evaluation.episode_timeout=x"])
