"""The time limit of the registered envs: Gymnasium's ``TimeLimit`` with the config's length.

The envs take their episode length from their config (``max_steps``), which is a
``gym.make`` keyword, so it cannot be the registration's fixed ``max_episode_steps``. The
registrations therefore add :class:`ConfigTimeLimit` as their outermost wrapper: it truncates
after the config's ``max_steps`` steps, unless ``gym.make(id, max_episode_steps=K)`` already
put a ``TimeLimit`` of ``K`` steps underneath it, in which case ``K`` wins. Either way
``env.spec.max_episode_steps`` is the number of steps after which the episode truncates.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium.wrappers import TimeLimit


def inner_time_limit(env: gym.Env) -> TimeLimit | None:
    """The outermost ``TimeLimit`` wrapping ``env`` (``env`` itself included), or ``None``."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, TimeLimit):
            return env
        env = env.env
    return None


class ConfigTimeLimit(TimeLimit):
    """``TimeLimit`` whose default length is the env's ``max_steps`` (its config's).

    Args:
        env: the env to limit; its ``unwrapped.max_steps`` is the default length [steps].
        max_episode_steps: the length [steps]; ``None``: the length of a ``TimeLimit``
            already wrapping ``env`` (``gym.make(id, max_episode_steps=K)``), else
            ``env.unwrapped.max_steps``.

    Raises:
        ValueError: if ``max_episode_steps`` is ``None`` and the env has no integer
            ``max_steps`` >= 1.
    """

    def __init__(self, env: gym.Env, max_episode_steps: int | None = None) -> None:
        if max_episode_steps is None:
            inner = inner_time_limit(env)
            if inner is not None:
                max_episode_steps = int(inner._max_episode_steps)
            else:
                max_episode_steps = _config_length(env.unwrapped)
        super().__init__(env, max_episode_steps)


def _config_length(env: Any) -> int:
    steps = getattr(env, "max_steps", None)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(
            f"{type(env).__name__}.max_steps={steps!r}: must be an integer >= 1 for the "
            "time limit (or pass max_episode_steps)"
        )
    return steps


__all__ = ["ConfigTimeLimit", "inner_time_limit"]
