"""The agent protocol: what evaluation needs of a controller, and nothing more.

An agent is any object with two methods (:class:`Agent`):

* ``reset(seed=None)``: start a new episode; ``seed`` fixes the agent's own randomness
  (evaluation passes a seed derived from the env seed and the agent's name).
* ``act(obs) -> action``: the action ``(nu,)`` for an observation ``(nx,)`` of the env
  (float32 or float64; agents here compute in float64).

An agent may also keep ``last_info``, a dict describing its last :meth:`Agent.act`.
Every key is optional; evaluation reads each one with the default of :data:`INFO_DEFAULTS`,
so an agent with only ``reset`` and ``act`` is evaluated correctly: no solver failures, no
fallbacks, and ``n/a`` (NaN) for the estimate and solve-time metrics.

================  ===========================================  ===========================
key               meaning                                      when absent
================  ===========================================  ===========================
estimate          state estimate ``(d,)`` (``d >= nx``)        NaN (``nx``,)
estimate_std      its standard deviation ``(d,)``              NaN, shaped like estimate
latent_force      estimate of the latent force ``(nw,)``       NaN; latent metrics NaN
latent_force_std  its standard deviation ``(nw,)``             NaN
predicted         predicted states ``(S, N+1, nx)``            NaN
solve_time        [s] time of the step's optimisation          not counted (NaN)
slack             the plan's constraint slack (>= 0)           not counted (NaN)
success           the step's solve succeeded (converged)       True (no solver, no failure)
usable            the solve returned a plan to apply           the value of success
fallback          '' or the name of the fallback action used   '' (none)
filter_reset      the estimator restarted after divergence     False
estimator         the name of the agent's estimator            ''
deadline_stop     what the step's budget made it apply         '' (no budget stopped it)
================  ===========================================  ===========================

The MPC agents of :mod:`controllers.agents.mpc` fill every key. They also have
stable-baselines3's ``predict`` (:class:`SB3Predict`), so SB3's
``evaluate_policy(agent, env)`` runs them; :class:`SB3Policy` gives any protocol agent
that face.
"""

from __future__ import annotations

import math
from typing import Any, Protocol, TypedDict, runtime_checkable

import numpy as np


@runtime_checkable
class Agent(Protocol):
    """A controller evaluation can run: ``reset(seed=None)`` and ``act(obs) -> action``.

    ``isinstance(x, Agent)`` checks that both methods exist. The optional ``last_info``
    dict (keys and defaults in :data:`INFO_DEFAULTS`) is not part of the check; a
    ``name`` attribute (a string of letters, digits, ``._+-``) names the agent in tables.
    """

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; ``seed`` fixes the agent's own randomness."""

    def act(self, obs: Any) -> Any:
        """The action ``(nu,)`` in the inputs' units for an observation ``(nx,)``."""


class AgentInfo(TypedDict, total=False):
    """The keys evaluation reads from ``last_info`` (all optional; see the module table)."""

    estimate: np.ndarray  # (d,) state estimate, d >= nx (physical states first)
    estimate_std: np.ndarray  # (d,) its standard deviation
    latent_force: np.ndarray  # (nw,) estimate of the latent force
    latent_force_std: np.ndarray  # (nw,) its standard deviation
    predicted: np.ndarray  # (S, N+1, nx) predicted states of the plan's scenarios
    solve_time: float  # [s] the step's optimisation
    slack: float  # the plan's constraint slack (>= 0)
    success: bool  # the step's solve succeeded (converged)
    usable: bool  # the solve returned a plan to apply, converged or not
    fallback: str  # '' or the name of the fallback action used
    filter_reset: bool  # the estimator restarted after divergence
    estimator: str  # the name of the agent's estimator
    # '' or, when agents.deadline stopped the step's solve, what was applied: "plan" (the
    # best usable plan reached), "previous_plan" (shifted) or "fallback"
    deadline_stop: str


#: Every optional ``last_info`` key and the value evaluation assumes when it is absent.
#: ``None`` for the arrays means "NaN of the documented shape" (see the module docstring).
INFO_DEFAULTS: dict[str, Any] = {
    "estimate": None,
    "estimate_std": None,
    "latent_force": None,
    "latent_force_std": None,
    "predicted": None,
    "solve_time": math.nan,
    "slack": math.nan,
    "success": True,
    "usable": None,  # (the step's success)
    "fallback": "",
    "filter_reset": False,
    "estimator": "",
    "deadline_stop": "",
}


def is_agent(obj: Any) -> bool:
    """Whether ``obj`` is an agent object (not a class): callable ``reset`` and ``act``."""
    return (
        not isinstance(obj, type)
        and callable(getattr(obj, "reset", None))
        and callable(getattr(obj, "act", None))
    )


def last_info(agent: Any) -> dict[str, Any]:
    """The agent's ``last_info`` (``{}`` when it keeps none).

    Raises:
        TypeError: ``last_info`` exists but is not a dict (or another mapping).
    """
    info = getattr(agent, "last_info", None)
    if info is None:
        return {}
    if not hasattr(info, "get") or not hasattr(info, "keys"):
        raise TypeError(
            f"last_info of agent {type(agent).__name__!r} is a {type(info).__name__}; "
            "expected a dict (keys in controllers.agents.protocol.INFO_DEFAULTS) or none"
        )
    return info


class SB3Predict:
    """Mixin: stable-baselines3's ``predict`` for an object with ``reset`` and ``act``.

    SB3's ``evaluate_policy(agent, env)`` calls ``predict(obs, state, episode_start,
    deterministic)`` with a batch of observations ``(n_envs, obs_dim)`` from a ``VecEnv``.
    One agent controls one env, so the batch must hold one observation (``n_envs = 1``;
    a plain ``(obs_dim,)`` observation works too and gives a plain action). At each
    episode start (``episode_start[0]`` true, or the first call when ``episode_start``
    is ``None``) the agent is reset with seed ``predict_seed + k`` for the ``k``-th
    episode it sees through ``predict`` (``k = 0, 1, ...``), so a rerun is identical.
    ``deterministic`` is accepted for SB3's signature: the agent's randomness is its own
    seeded generator either way. ``state`` is returned as ``None`` (no recurrent state).
    """

    #: Seed of the first episode run through :meth:`predict`; episode k gets this + k.
    predict_seed: int = 0

    def predict(
        self,
        observation: Any,
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """The action for ``observation`` ``(obs_dim,)`` or ``(1, obs_dim)``, SB3 style.

        Returns:
            ``(action, None)``: the action ``(nu,)`` for an unbatched observation, else
            ``(1, nu)``, in the inputs' units (float64).

        Raises:
            ValueError: naming the shape, for a batch of more than one observation
                (one agent per env: wrap each env's agent in its own ``predict``).
        """
        obs = np.asarray(observation)
        single = obs.ndim == 1
        batch = obs[None] if single else obs
        if batch.ndim != 2 or batch.shape[0] != 1:
            raise ValueError(
                f"predict: observation of shape {obs.shape}; one agent controls one env: "
                "give (obs_dim,) or (1, obs_dim) (a VecEnv with n_envs=1), and use one "
                "agent per env for more"
            )
        starts = None if episode_start is None else np.asarray(episode_start).reshape(-1)
        if starts is not None and starts.shape != (1,):
            raise ValueError(
                f"predict: episode_start of shape {np.shape(episode_start)}; expected one "
                "flag for the one env"
            )
        episodes = getattr(self, "_predict_episodes", 0)
        if (starts is None and episodes == 0) or (starts is not None and bool(starts[0])):
            self.reset(seed=int(self.predict_seed) + episodes)
            self._predict_episodes = episodes + 1
        action = np.asarray(self.act(batch[0]), dtype=float)
        return (action if single else action[None]), None


class SB3Policy(SB3Predict):
    """Any protocol agent with stable-baselines3's ``predict`` (see :class:`SB3Predict`).

    ``evaluate_policy(SB3Policy(my_agent), env)``; ``reset``, ``act`` and ``last_info``
    are those of the wrapped agent.

    Args:
        agent: an object with ``reset(seed=None)`` and ``act(obs)`` (:class:`Agent`).
        predict_seed: seed of the first episode; episode ``k`` gets ``predict_seed + k``.
    """

    def __init__(self, agent: Any, predict_seed: int = 0) -> None:
        if not is_agent(agent):
            raise TypeError(
                f"SB3Policy: {type(agent).__name__!r} has no reset(seed=None) and act(obs)"
            )
        self.agent = agent
        self.predict_seed = int(predict_seed)

    def reset(self, seed: int | None = None) -> None:
        """Reset the wrapped agent."""
        self.agent.reset(seed=seed)

    def act(self, obs: Any) -> Any:
        """The wrapped agent's action."""
        return self.agent.act(obs)

    @property
    def last_info(self) -> dict[str, Any]:
        """The wrapped agent's ``last_info`` (``{}`` when it keeps none)."""
        return last_info(self.agent)


__all__ = [
    "INFO_DEFAULTS",
    "Agent",
    "AgentInfo",
    "SB3Policy",
    "SB3Predict",
    "is_agent",
    "last_info",
]
