"""The worlds' registry (``lfm_env.worlds.registry``): a world of one's own registers from
its own module, and a config names it ``module:EnvId`` so that any process finds it."""

from __future__ import annotations

import sys
from pathlib import Path

import gymnasium as gym
import pytest

from controllers.config import load_config
from lfm_env import register_world
from lfm_env.config import ConfigError
from lfm_env.worlds.registry import WORLDS, load_env_config, qualified_env_id, world_spec

OWN_WORLD = Path(__file__).resolve().parents[1] / "data" / "own_world"


@pytest.fixture
def own_world(monkeypatch):
    """``unicycle_world`` (tests/data/own_world) imported as a user's module."""
    monkeypatch.syspath_prepend(str(OWN_WORLD))
    import unicycle_world

    return unicycle_world


def test_the_built_in_worlds_need_no_module():
    for env_id in ("lfm_env/SineTrack-v0", "lfm_env/QuadrotorGust-v1"):
        assert WORLDS[env_id].module is None and qualified_env_id(env_id) == env_id
    assert load_config("paper").to_dict()["env_id"] == "lfm_env/SineTrack-v0"


def test_a_world_registered_by_a_module_is_named_by_it(own_world):
    spec = WORLDS["Mine/Unicycle-v0"]
    assert spec.module == "unicycle_world" and spec.config_class is own_world.UnicycleConfig
    qualified = "unicycle_world:Mine/Unicycle-v0"
    assert qualified_env_id("Mine/Unicycle-v0") == qualified
    agents = {"Q": [1, 1, 1, 1], "Qf": [1, 1, 1, 1], "R": [1, 1], "goal_state": [4, 0, 1, 0]}
    cfg = load_config({"env_id": qualified, "env": {"max_steps": 7}, "agents": agents})
    assert cfg.env_id == qualified and cfg.to_dict()["env_id"] == qualified
    assert load_env_config({"env_id": "Mine/Unicycle-v0"}).max_steps == 40  # plain id: known
    env = gym.make(qualified, config=cfg.env)
    assert env.unwrapped.config.max_steps == 7 and env.spec.max_episode_steps == 7


def test_a_module_is_found_in_the_working_folder_too(own_world, tmp_path, monkeypatch):
    (tmp_path / "fallback_world.py").write_text(
        "from lfm_env import register_world\n"
        "from unicycle_world import UnicycleConfig, UnicycleEnv\n"
        "class Config(UnicycleConfig):\n    pass\n"
        "class Env(UnicycleEnv):\n    CONFIG = Config\n"
        "register_world('Mine/Fallback-v0', Config, Env)\n"
    )
    (tmp_path / "json.py").write_text("raise ImportError('the working folder json.py')\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    assert world_spec("fallback_world:Mine/Fallback-v0").module == "fallback_world"
    # That module alone, last: the folder is not on sys.path, and its json.py (a standard
    # module's name) is never imported.
    assert str(tmp_path) not in sys.path
    assert sys.modules["fallback_world"].__file__ == str(tmp_path / "fallback_world.py")
    with pytest.raises(ConfigError, match="registered no world"):
        world_spec("json:Mine/Other-v0")
    sys.modules.pop("fallback_world", None)


@pytest.mark.parametrize(
    "env_id, message",
    [
        ("no_such_module:Mine/X-v0", "cannot import the module 'no_such_module'"),
        ("json:Mine/X-v0", "importing 'json' registered no world of that id"),
        ("Mine/X-v0", "a world of your own: env_id: your.module:Name-v0 imports it first"),
    ],
)
def test_unknown_worlds_are_one_line_errors_naming_the_id(env_id, message):
    with pytest.raises(ConfigError, match=message):
        load_env_config({"env_id": env_id})


@pytest.mark.parametrize("env_id", ["", "mine:Mine/X-v0", 3])
def test_register_world_refuses_a_bad_id(env_id):
    from lfm_env.worlds.sine_track.config import SineTrackConfig

    with pytest.raises(ValueError, match="register_world: env_id="):
        register_world(env_id, SineTrackConfig, "lfm_env.worlds.sine_track.env:SineTrackEnv")


@pytest.mark.parametrize("annotation", ["tuple", "list", "list[float]", "dict", "object"])
def test_a_config_field_no_file_can_be_read_into_is_refused_at_registration(annotation):
    """A world config with a bare ``tuple`` annotation registered and ran its episodes, then
    crashed ``lfm-report`` reading its ``config.yaml`` (``TypeError: unsupported config type
    <class 'tuple'> for env.initial_state``, a traceback calling itself a bug). Now
    ``register_world`` refuses it, naming the class, the field and the annotations a file
    can be read into."""
    import dataclasses

    from lfm_env.worlds.sine_track.config import SineTrackConfig

    namespace: dict = {}
    exec(f"kind = {annotation}", namespace)  # the annotation object itself
    bare = dataclasses.make_dataclass(
        "BareConfig",
        [("extra_state", namespace["kind"], dataclasses.field(default=None))],
        bases=(SineTrackConfig,),
        frozen=True,
    )
    env_id = f"Bare/Annotation{len(WORLDS)}-v0"
    with pytest.raises(ValueError, match=r"BareConfig\.extra_state") as exc:
        register_world(env_id, bare, "lfm_env.worlds.sine_track.env:SineTrackEnv")
    assert "tuple[float, ...]" in str(exc.value)
    assert env_id not in WORLDS and env_id not in gym.registry
