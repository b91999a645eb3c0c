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
