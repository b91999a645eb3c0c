"""A world's env with a goal and a safety box: what the case studies' envs share.

:class:`GoalReachingEnv` builds a :class:`~lfm_env.env.LatentForceEnv` from a world config
(:class:`~lfm_env.config.WorldConfig`: the model, the reward's cost, the start, the noise and
the episode length) and adds the task both case studies have: success when the path travelled
in a step passes within ``goal_radius`` of the goal position (the first two states), failure
when the state is not finite or some constraint group of :attr:`SAFETY_GROUPS` is exceeded by
more than ``safety_margin``. A world's env sets :attr:`CONFIG` and :attr:`SAFETY_GROUPS` and
draws its scene.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lfm_env.config import WorldConfig, check_latent_step
from lfm_env.env import LatentForceEnv
from lfm_env.worlds.registry import load_env_config


def segment_point_distance(p0: np.ndarray, p1: np.ndarray, q: np.ndarray) -> float:
    """Distance [m] from point ``q`` to the segment ``p0 -> p1`` (all shape ``(2,)``)."""
    d = p1 - p0
    dd = float(d @ d)
    t = 0.0 if dd == 0.0 else float(np.clip((q - p0) @ d / dd, 0.0, 1.0))
    return float(np.linalg.norm(p0 + t * d - q))


class GoalReachingEnv(LatentForceEnv):
    """A :class:`LatentForceEnv` of a world config with a goal disc and a safety box.

    Args:
        config: a YAML path, a dict (whole file or its ``env`` section) or a config of
            :attr:`CONFIG`'s world; it needs ``goal``, ``goal_radius`` and ``safety_margin``.
        render_mode: ``None`` or ``"rgb_array"``.
    """

    CONFIG: type[WorldConfig] = WorldConfig  # the world's config class (sets ENV_ID)
    SAFETY_GROUPS: tuple[str, ...] = ()  # constraint groups whose excess ends an episode

    def __init__(self, config: Any = None, render_mode: str | None = None) -> None:
        self.config = check_latent_step(load_env_config(config, env_id=self.CONFIG.ENV_ID))
        self._goal = np.asarray(self.config.goal, dtype=float)
        super().__init__(
            self.config.make_model(),
            self.config.make_cost(),
            initial_state=self.config.initial_state_rad,
            measurement_std=self.config.measurement_std_rad,
            max_steps=self.config.max_steps,
            latent_start=self.config.latent_force.start,
            render_mode=render_mode,
            state_bounds=self.state_bounds(),
        )

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Per state, in SI units, the range the safety box keeps it in (``-inf``/``inf``
        for a state the box does not bound; ``None``: none is bounded). It sets the
        observation space (:func:`lfm_env.env.observation_bounds`).

        A world whose safety box bounds some states alone overrides this; the range should
        hold the state that leaves the box too (the last of a failed episode), e.g. the
        box widened once more by ``safety_margin``.
        """
        return None

    def _is_success(self, state: np.ndarray, next_state: np.ndarray) -> bool:
        """The segment travelled in the step passes within ``goal_radius`` of the goal."""
        distance = segment_point_distance(state[:2], next_state[:2], self._goal)
        return distance <= self.config.goal_radius

    def _is_failure(self, state: np.ndarray) -> bool:
        """Not finite, or ``safety_margin`` beyond one of :attr:`SAFETY_GROUPS`."""
        if not np.all(np.isfinite(state)):
            return True
        excess = self.system.group_excess(state)
        margin = self.config.safety_margin
        return any(float(excess[g]) > margin for g in self.SAFETY_GROUPS)


__all__ = ["GoalReachingEnv", "segment_point_distance"]
