"""Fixtures shared by the test tree: the paper's world, its system and its latent-force model.

All three are frozen, so one instance per session is safe to share.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem
from lfm_env.worlds.registry import load_env_config
from lfm_env.worlds.sine_track.config import SineTrackConfig

#: The paper's configuration file (``configs/paper.yaml``), independent of the working dir.
PAPER_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "paper.yaml"


@pytest.fixture(scope="session")
def paper_config() -> SineTrackConfig:
    """The ``env`` section of ``configs/paper.yaml``."""
    return load_env_config(PAPER_CONFIG)


@pytest.fixture(scope="session")
def sine_track_system(paper_config: SineTrackConfig) -> ControlSystem:
    """The bicycle on the paper's sine track."""
    return paper_config.make_system()


@pytest.fixture(scope="session")
def paper_model(
    paper_config: SineTrackConfig, sine_track_system: ControlSystem
) -> LatentForceModel:
    """The paper's latent-force model (the env's truth): Matern 5/2 force, exact steps."""
    return paper_config.make_model(system=sine_track_system)


def pytest_collection_modifyitems(config, items):
    """For pytest-xdist's ``--dist loadgroup`` (``scripts/run_tests.sh``): the tests that use a
    module-scoped fixture run in one worker per module, so each such fixture (a quick benchmark
    run, three exported C projects, ...) is built once; every other test goes to whichever
    worker is free, which balances the two workers better than one file per worker."""
    if getattr(config.option, "dist", "no") != "loadgroup":
        return
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        defs = getattr(info, "name2fixturedefs", {}) if info is not None else {}
        if any(d.scope == "module" for chain in defs.values() for d in chain):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))
