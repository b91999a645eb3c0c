"""One closed-loop episode of an agent (:func:`run_episode`), and the inputs every run checks
first (:func:`resolve_config`, :func:`parse_seeds`, :func:`check_seeds`).
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

import lfm_env  # noqa: F401  (registers the envs, also in spawned workers)
from controllers.agents.protocol import INFO_DEFAULTS, last_info
from controllers.agents.registry import AgentSpec, resolve_agents
from controllers.config import ExperimentConfig, load_config
from experiments.evaluation.columns import (
    _metric_columns,
    group_columns,
    row_columns,
    violation_counts,
)
from experiments.evaluation.interrupts import raise_if_interrupted
from experiments.evaluation.limits import check_deadline
from lfm_env.config import show_value
from lfm_env.validation import one_line, real_vector


def agent_seed(seed: int, agent_name: str) -> int:
    """The seed of an agent's own randomness in the episode with env seed ``seed``: from the env
    seed and a stable hash of the agent's name, the same in every worker.
    """
    name_key = int.from_bytes(hashlib.sha256(agent_name.encode()).digest()[:8], "little")
    state = np.random.SeedSequence([int(seed), name_key]).generate_state(1, dtype=np.uint64)
    return int(state[0])


def resolve_config(
    config: ExperimentConfig | str | os.PathLike | dict | None = None, agents: Any = ()
) -> ExperimentConfig:
    """The full config, resolved once (:func:`~controllers.config.load_config`: an
    ``ExperimentConfig``, a preset's name, a YAML path, a dict or ``None``) and checked for
    ``agents`` (:meth:`~controllers.agents.registry.AgentSpec.check_config`).

    Raises:
        ConfigError: (a ``ValueError``) for unknown keys or out-of-range values.
    """
    resolved = config if isinstance(config, ExperimentConfig) else load_config(config)
    for spec in resolve_agents(list(agents)) if agents else ():
        spec.check_config(resolved)
    return resolved


MAX_SEEDS = 1_000_000  # seeds of one run (a larger range is a typo, not a plan)


def parse_seeds(text: str) -> list[int]:
    """Seeds from text: ``"0:20"`` (end exclusive), ``"3"``, ``"1,5,9"``, ``"0:10,20:25"``, in the
    order given, duplicates removed.

    Raises:
        ValueError: naming ``text`` for empty or reversed ranges or anything but
            non-negative integers and ranges.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"seeds {text!r}: expected e.g. '0:20', '3', '1,5,9' or '0:10,20:25'")
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        m = re.fullmatch(r"(-?\d+)(?:\s*:\s*(-?\d+))?", part)
        if m is None:
            raise ValueError(
                f"seeds {text!r}: {part!r} is not a seed or a range start:end "
                "(e.g. '0:20', '3', '1,5,9')"
            )
        start = int(m.group(1))
        stop = start + 1 if m.group(2) is None else int(m.group(2))
        if start < 0 or stop < 0:
            raise ValueError(f"seeds {text!r}: seeds must be >= 0")
        if stop <= start:
            raise ValueError(
                f"seeds {text!r}: range {part!r} is empty or reversed (the end is exclusive)"
            )
        if len(seeds) + (stop - start) > MAX_SEEDS:
            raise ValueError(f"seeds {text!r}: at most {MAX_SEEDS} seeds in one run")
        seeds.extend(range(start, stop))
    return list(dict.fromkeys(seeds))


def check_seeds(seeds: int | str | Iterable[int]) -> list[int]:
    """The env seeds of a run: integers >= 0, or a text for :func:`parse_seeds`.

    Raises:
        ValueError: naming the bad seed: empty, duplicates, more than :data:`MAX_SEEDS`.
    """
    if isinstance(seeds, str):
        return parse_seeds(seeds)
    if not isinstance(seeds, (int, np.integer, Iterable)):
        raise ValueError(f"seeds {seeds!r}: give integers >= 0, e.g. [0, 1, 2] or '0:20'")
    if isinstance(seeds, range) and len(seeds) > MAX_SEEDS:
        raise ValueError(f"seeds: {len(seeds)} of them; at most {MAX_SEEDS} in one run")
    values = [seeds] if isinstance(seeds, (int, np.integer)) else list(seeds)
    if len(values) > MAX_SEEDS:
        raise ValueError(f"seeds: {len(values)} of them; at most {MAX_SEEDS} in one run")
    if not values:
        raise ValueError("seeds: the list is empty; give at least one seed >= 0")
    out = []
    for s in values:
        if isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)) or s < 0:
            raise ValueError(f"seeds: {s!r} is not an integer >= 0")
        out.append(int(s))
    if len(set(out)) != len(out):
        raise ValueError(f"seeds: {out} holds duplicates")
    return out


#: Scenarios of the plan kept per step in ``predicted_scenarios`` (the first ones: the
#: scenarios are independent draws, so these are a random subset of the fan).
SAVED_SCENARIOS = 20


class _EpisodeRecorder:
    """Collects one episode step by step (a step appended whole, so a partial record is
    consistent); ``last_info`` keys default to :data:`controllers.agents.protocol.INFO_DEFAULTS`.
    """

    def __init__(self, config: ExperimentConfig) -> None:
        system = config.make_system()
        self.horizon = config.agents.horizon
        # [s] the control period (deadline misses; NaN for a config without a model)
        make_model = getattr(config, "make_model", None)
        self.dt = float(make_model().dt) if make_model is not None else math.nan
        self.nx, self.nu, self.nw = system.nx, system.nu, system.nw
        self.system = system
        self.groups = tuple(system.constraint_groups)
        self.columns = row_columns(system)
        self.lists: dict[str, list] = defaultdict(list)  # per array key, its steps
        self.has_filter = False
        self.latent_width = 0  # entries of the env's latent state (info["latent_state"])
        self.slack_reported: list[bool] = []  # per step: the agent gave its slack
        self.final_info: dict[str, Any] = {}

    def start(self, obs: np.ndarray, info: dict[str, Any]) -> None:
        self.lists["true_state"].append(np.asarray(info["true_state"], dtype=float))
        self.lists["obs"].append(np.asarray(obs, dtype=float))
        self.lists["time"].append(float(info["time"]))
        # The hidden latent state, for the offline chance-constraint check (the evaluation
        # layer's, never an agent's); an env whose info lacks it records none.
        self.latent_width = len(np.ravel(info.get("latent_state", ())))
        self._record_latent(info)

    def _record_latent(self, info: dict[str, Any]) -> None:
        if self.latent_width:
            self.lists["latent_state"].append(
                np.asarray(info["latent_state"], dtype=float).reshape(self.latent_width)
            )

    def _plan(self, agent_info: dict[str, Any]) -> np.ndarray:
        """The agent's planned inputs ``(N, nu)`` (``last_info["plan"]``), NaN if it gives
        none of that shape."""
        plan = agent_info.get("plan")
        shape = (self.horizon, self.nu)
        if plan is not None and np.shape(plan) == shape:
            return np.array(plan, dtype=float)
        return np.full(shape, np.nan)

    def step(
        self,
        agent_info: dict[str, Any],
        obs: np.ndarray,
        reward: float,
        info: dict[str, Any],
        step_time: float = math.nan,
    ) -> None:
        self.has_filter = self.has_filter or agent_info.get("latent_force") is not None
        values = {
            "true_state": np.asarray(info["true_state"], dtype=float),
            "obs": np.asarray(obs, dtype=float),
            "time": float(info["time"]),
            "action": np.asarray(info["applied_action"], dtype=float),
            # w acting during this step: the quantity the agent estimated before it.
            "latent_force": self._force(info["latent_force"]),
            "reward": float(reward),
            "step_time": float(step_time),
            **self._agent_values(agent_info),
        }
        # The largest excess of each constraint group after the step, in its unit.
        values.update((k, float(info[k])) for k in self._excess_keys())
        for k, v in values.items():
            self.lists[k].append(v)
        self._record_latent(info)
        self.slack_reported.append(agent_info.get("slack") is not None)
        self.final_info = info

    def _agent_values(self, agent_info: dict[str, Any]) -> dict[str, Any]:
        """The step's values from the agent's ``last_info``, each converted and checked.

        Raises:
            ValueError: naming the key, for a value of the wrong kind or shape.
        """
        nan_pred = np.full((self.horizon + 1, self.nx), np.nan)
        no_force = np.full(self.nw, np.nan)
        get = self._get

        def checked(key: str, convert: Callable[[], Any]) -> Any:
            try:
                return convert()
            except (TypeError, ValueError, IndexError) as exc:
                raise ValueError(
                    f"last_info[{key!r}] of the agent is {show_value(agent_info.get(key))}: "
                    f"{one_line(exc)} (expected {INFO_EXPECTED.get(key, 'see AgentInfo')}; "
                    "controllers.agents.protocol.AgentInfo)"
                ) from None

        predicted = agent_info.get("predicted")
        if predicted is None:
            first, fan = nan_pred, nan_pred[None]
        else:
            first = checked("predicted", lambda: np.array(predicted, dtype=float)[0])
            fan = checked("predicted", lambda: np.asarray(predicted, dtype=float))
            fan = fan[:SAVED_SCENARIOS]
        estimate, estimate_std = self._estimate(agent_info, checked)
        return {
            "estimate": estimate,
            "estimate_std": estimate_std,
            "latent_force_est": checked(
                "latent_force", lambda: self._force(get(agent_info, "latent_force", no_force))
            ),
            "latent_force_std": checked(
                "latent_force_std",
                lambda: self._force(get(agent_info, "latent_force_std", no_force)),
            ),
            "predicted": first,
            # A compact fan: the first SAVED_SCENARIOS predicted trajectories, float32.
            "predicted_scenarios": fan.astype(np.float32),
            "solve_time": checked("solve_time", lambda: float(get(agent_info, "solve_time"))),
            "slack": checked("slack", lambda: float(get(agent_info, "slack"))),
            "solver_success": bool(get(agent_info, "success")),
            # (an agent that does not say: usable exactly when it succeeded)
            "solver_usable": bool(get(agent_info, "usable", get(agent_info, "success"))),
            "fallback": str(get(agent_info, "fallback")),
            "deadline_stop": str(get(agent_info, "deadline_stop")),
            "filter_reset": bool(get(agent_info, "filter_reset")),
            # The estimator's name, from agents that say which one they run (it may differ
            # from agents.estimator: the robust agent has its own).
            "estimator": str(get(agent_info, "estimator")),
            "plan": self._plan(agent_info),
        }

    @staticmethod
    def _get(agent_info: dict[str, Any], key: str, default: Any = None) -> Any:
        """``agent_info[key]``, or its documented default when absent or ``None``."""
        value = agent_info.get(key)
        if value is not None:
            return value
        return INFO_DEFAULTS[key] if default is None else default

    def _estimate(
        self, agent_info: dict[str, Any], checked: Callable[[str, Callable[[], Any]], Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The step's estimate and its std, copied; NaN (of the episode's width) if absent."""
        previous = self.lists["estimate"]
        width = len(previous[0]) if previous else self.nx
        est = agent_info.get("estimate")
        if est is None:
            est = np.full(width, np.nan)
        else:
            est = checked(
                "estimate",
                lambda: real_vector(est, width if previous else None, "estimate", finite=False),
            )
        std = agent_info.get("estimate_std")
        if std is None:
            std = np.full(est.shape, np.nan)
        else:
            std = checked(
                "estimate_std", lambda: real_vector(std, est.size, "estimate_std", finite=False)
            )
        return est, std

    def _fan(self) -> np.ndarray:
        """``(T, S, N+1, nx)`` float32 saved scenario predictions, NaN-padded to the widest
        step's ``S`` (an agent's scenario count may change, e.g. after a fallback)."""
        fans = self.lists["predicted_scenarios"]
        width = max((len(f) for f in fans), default=1)
        out = np.full((len(fans), width, self.horizon + 1, self.nx), np.nan, dtype=np.float32)
        for k, f in enumerate(fans):
            out[k, : len(f)] = f
        return out

    def _excess_keys(self) -> tuple[str, ...]:
        """``info`` keys (and trajectory arrays) of the groups' excess: ``<group>_excess``."""
        return tuple(f"{g}_excess" for g in self.groups)

    def _force(self, w: Any) -> float | np.ndarray:
        """A latent force as a float (one component) or an ``(nw,)`` array."""
        w = np.asarray(w, dtype=float).reshape(self.nw)
        return float(w[0]) if self.nw == 1 else w

    def arrays(self) -> dict[str, np.ndarray]:
        """The trajectory; ``T`` steps give ``(T+1, ...)`` states and ``(T, ...)`` the rest."""
        lst = self.lists
        T = len(lst["reward"])
        d = len(lst["estimate"][0]) if T else self.nx
        force = (0,) if self.nw == 1 else (0, self.nw)

        def stack(key: str, shape: tuple[int, ...], dtype: Any = float) -> np.ndarray:
            if lst[key]:
                return np.asarray(lst[key], dtype=dtype)
            return np.zeros(shape, dtype=dtype)

        return {
            "true_state": stack("true_state", (0, self.nx)),
            "obs": stack("obs", (0, self.nx)),
            "time": stack("time", (0,)),
            "action": stack("action", (0, self.nu)),
            "latent_force": stack("latent_force", force),
            "reward": stack("reward", (0,)),
            "estimate": stack("estimate", (0, d)),
            "estimate_std": stack("estimate_std", (0, d)),
            "latent_force_est": stack("latent_force_est", force),
            "latent_force_std": stack("latent_force_std", force),
            "predicted": stack("predicted", (0, self.horizon + 1, self.nx)),
            "predicted_scenarios": self._fan(),
            "solve_time": stack("solve_time", (0,)),
            "step_time": stack("step_time", (0,)),
            "deadline_stop": stack("deadline_stop", (0,), str),
            "slack": stack("slack", (0,)),
            "solver_success": stack("solver_success", (0,), bool),
            "solver_usable": stack("solver_usable", (0,), bool),
            "fallback": stack("fallback", (0,), str),
            "filter_reset": stack("filter_reset", (0,), bool),
            "estimator": stack("estimator", (0,), str),
            "plan": stack("plan", (0, self.horizon, self.nu)),
            **({"latent_state": stack("latent_state", (0,))} if self.latent_width else {}),
            **{k: stack(k, (0,)) for k in self._excess_keys()},
        }


#: What each ``last_info`` key must hold, for the error of a bad value.
INFO_EXPECTED = {
    "estimate": "a vector of d >= nx numbers, the same d at every step",
    "estimate_std": "a vector as long as the estimate",
    "latent_force": "nw numbers",
    "latent_force_std": "nw numbers",
    "predicted": "an array (S, N+1, nx) of predicted states",
    "solve_time": "a number of seconds",
    "slack": "a number >= 0",
}


def _simulate(spec: AgentSpec, config: ExperimentConfig, seed: int, rec: _EpisodeRecorder) -> None:
    """Run one episode into ``rec``; exceptions propagate with ``rec`` holding the steps done."""
    env = gym.make(config.env_id, config=config.env)
    try:
        obs, info = env.reset(seed=seed)
        agent = spec.build(config, env=env if spec.reads_truth else None)  # the oracle's truth
        agent.reset(seed=agent_seed(seed, spec.name))
        rec.start(obs, info)
        terminated = truncated = False
        while not (terminated or truncated):
            raise_if_interrupted()  # a Ctrl-C that a library swallowed
            check_deadline()  # the episode's time limit, if a library swallowed it
            # The agent's estimate made with obs k is compared with the w of step k.
            t_act = time.perf_counter()
            action = agent.act(obs)
            step_time = time.perf_counter() - t_act  # the step's compute, whatever the agent
            agent_info = last_info(agent)
            obs, reward, terminated, truncated, info = env.step(action)
            rec.step(agent_info, obs, reward, info, step_time)
    finally:
        env.close()


def _episode_metrics(rec: _EpisodeRecorder, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """The metric columns of a finished episode."""
    T = len(arrays["reward"])
    info = rec.final_info
    success = bool(info.get("is_success", False))
    solve = arrays["solve_time"]
    solve = solve[np.isfinite(solve)]  # steps without a solve time are not counted
    step = arrays.get("step_time", np.zeros(0))
    step = step[np.isfinite(step)]
    stops = arrays.get("deadline_stop", np.zeros(0, dtype=str))
    slack = arrays["slack"][np.asarray(rec.slack_reported[:T], dtype=bool)]
    if rec.has_filter and T:
        err = arrays["latent_force_est"] - arrays["latent_force"]
        latent_rmse = float(np.sqrt(np.mean(err**2)))
        latent_coverage = float(np.mean(np.abs(err) <= 2.0 * arrays["latent_force_std"]))
    else:
        latent_rmse = latent_coverage = math.nan

    # Episodes saved before 'solver_usable' existed: usable exactly when it succeeded.
    usable = arrays.get("solver_usable", arrays["solver_success"])

    def stat(fn: Callable[[np.ndarray], Any], x: np.ndarray) -> float:
        return float(fn(x)) if len(x) else math.nan

    metrics: dict[str, Any] = {
        "success": success,
        "steps": int(T),
        "time_to_goal": float(info["time"]) if success else math.nan,
        "cost": float(-np.sum(arrays["reward"])),
    }
    counts = violation_counts(arrays, rec.system)
    for c in group_columns(rec.system):  # in the row's order
        metrics[c] = stat(np.max, arrays[c[4:]]) if c.startswith("max_") else counts[c]
    return {
        **metrics,
        "failure": bool(info.get("failure", False)),
        "latent_rmse": latent_rmse,
        "latent_coverage": latent_coverage,
        "solve_time_median": stat(np.median, solve),
        "solve_time_p95": stat(lambda x: np.percentile(x, 95), solve),
        "solve_time_max": stat(np.max, solve),
        "step_time_median": stat(np.median, step),
        "step_time_max": stat(np.max, step),
        "deadline_misses": int(np.sum(step > rec.dt)),
        "solver_failures": int(np.sum(~usable)),
        "unconverged_solves": int(np.sum(usable & ~arrays["solver_success"])),
        "fallback_steps": int(np.sum(arrays["fallback"] != "")),
        "deadline_plans": int(np.sum(stops == "plan")),
        "deadline_shifted": int(np.sum(stops == "previous_plan")),
        "deadline_fallbacks": int(np.sum(stops == "fallback")),
        "filter_resets": int(np.sum(arrays["filter_reset"])) if rec.has_filter else 0,
        "slack_total": float(np.sum(slack)) if len(slack) else math.nan,
    }


def _error_row(
    agent_name: str, seed: int, error: str, wall_time: float, columns: Sequence[str]
) -> dict[str, Any]:
    """The row of an episode that raised: NaN metrics, the error text, ``columns`` order."""
    row: dict[str, Any] = {"agent": agent_name, "seed": int(seed)}
    row.update({c: math.nan for c in _metric_columns(columns)})
    row.update(wall_time=float(wall_time), error=error)
    return {c: row[c] for c in columns}


def run_episode(
    agent: Any, config: Any, seed: int, record: bool = True
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Run one closed-loop episode of ``agent`` on the config's env with seed ``seed``.

    Args:
        agent: a registered name, a factory ``factory(config)``, an agent, or
            ``"module:attribute"`` (:mod:`controllers.agents.registry`).
        config: a YAML path, a dict, an ``ExperimentConfig`` or ``None`` (paper defaults).
        seed: env seed, an integer >= 0 (the agent's own: :func:`agent_seed`).
        record: return the trajectory; ``False`` gives an empty dict.

    Returns:
        ``(row, trajectory)``: ``row`` maps :func:`row_columns` to values. With ``T`` steps
        the trajectory holds ``true_state``, ``obs`` (noisy) ``(T+1, nx)``, ``time (T+1,)``
        [s], ``action (T, nu)``, ``latent_force`` (acting in step k; ``(T,)`` or ``(T, nw)``),
        ``reward``, ``estimate`` and ``estimate_std (T, d)`` (from ``obs[k]``; ``d`` = nx plus
        any latent states), ``latent_force_est``/``_std`` (NaN without a filter),
        ``predicted (T, N+1, nx)`` (first scenario), ``solve_time`` [s], ``slack``,
        ``solver_success``, ``solver_usable``, ``fallback`` ('' or its name), ``estimator``,
        ``<group>_excess (T,)`` per constraint group (largest excess after step k),
        ``plan (T, N, nu)`` (NaN when none) and ``latent_state (T+1, p)`` (the env's hidden
        state, for offline checks only), in the units of the system's names.

    Raises:
        ValueError: unknown agent or negative seed; the episode's own errors propagate.
    """
    (spec,) = resolve_agents([agent])
    (seed,) = check_seeds([seed])
    cfg = resolve_config(config, [spec])
    t0 = time.perf_counter()
    rec = _EpisodeRecorder(cfg)
    _simulate(spec, cfg, seed, rec)
    arrays = rec.arrays()
    row = {"agent": spec.name, "seed": seed, **_episode_metrics(rec, arrays)}
    row.update(wall_time=time.perf_counter() - t0, error="")
    return {c: row[c] for c in rec.columns}, (arrays if record else {})
