"""Evaluation of agents over env seeds, saved episode by episode so no result is lost.

The shape follows stable-baselines3's ``evaluate_policy``: one library function,
:func:`evaluate`, runs every (agent, seed) episode and returns one row of metrics per
episode; command lines (:mod:`experiments.cli`) only parse arguments and call it.

Paired design: for a given env seed every agent faces the same hidden disturbance and
the same measurement and process noise (the env draws them from its own seed), while
each agent's own randomness (particle filter, scenario draws) comes from a seed derived
from the env seed and the agent's name (:func:`agent_seed`). Differences between agents
on one seed are therefore due to the agents alone.

Results folder (``out``)::

    out/config.yaml                         the resolved config (env and agents sections)
    out/episodes/<agent>__seed<seed>.npz    the trajectory (np.savez_compressed)
    out/episodes/<agent>__seed<seed>.json   the row, plus agent_seed and traceback
    out/episodes.csv                        every json row, sorted by (agent, seed)

Every file is written atomically (a temporary file in the same folder, then
``os.replace``), the npz before the json: a json marks a finished episode, so a killed
run loses at most the episodes in flight, and rerunning the same call resumes it. An
episode that raises is saved as a row whose ``error`` holds the exception (its json also
holds the traceback, its npz the steps done before the error); such rows are kept in the
table but, with ``retry_failed=True`` (the default), re-run by the next call. A folder
holds the results of one config only: :func:`evaluate` refuses to resume into a folder
whose ``config.yaml`` differs or whose episodes carry another :func:`config_hash`. A
folder is owned by one run at a time (``out/.lock`` holds its pid and host; a second run
is refused naming it; the lock of a dead process is taken over). Every saved episode is
verified before it is skipped on resume (its json names its own agent and seed, its npz
loads with one step per row step); a damaged one is named on stderr and run again.

An interrupt (Ctrl-C, or SIGTERM while :func:`evaluate` runs in the main thread) ends the
workers at once, removes temporary files and rebuilds ``episodes.csv`` before
``KeyboardInterrupt`` propagates; pool and Dask workers ignore Ctrl-C themselves. An
interrupt is also remembered and checked at every step (:mod:`experiments.interrupts`), so
one that a library swallowed (CasADi clears errors raised inside its type conversions)
still stops the run.

Agents are registered names, or a user's own agents (:class:`controllers.protocol.Agent`)
given as factories, agent objects or ``"module:attribute"`` (:mod:`experiments.agent_specs`);
an agent's ``last_info`` keys are all optional, read with their documented defaults.

Runs are serial (``jobs=1``), on local processes (``jobs > 1``) or on a Dask cluster
(``scheduler=`` an existing one, checked to answer as Dask within 5 s, or
``dask_workers=`` a private local one: loopback, TLS, no HTTP endpoint,
:mod:`experiments.executors`). Every worker writes its own episode files, so the folder
must be visible to all workers (any single machine; a shared file system for a
multi-machine cluster, whose workers must also have this package installed). Serial,
parallel and distributed runs give identical rows apart from the timing columns
:data:`TIMING_COLUMNS`.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import re
import secrets
import socket
import time
import traceback
import zipfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import lfm_env  # noqa: F401  (registers the envs, also in spawned workers)
from controllers.agents import AGENTS, check_agent_config, make_agent
from controllers.config import ExperimentConfig, load_config
from controllers.protocol import INFO_DEFAULTS, last_info
from experiments.agent_specs import (
    AgentSpec,
    check_agent,
    check_picklable,
    resolve_agents,
)
from experiments.agent_specs import agent_name as name_of
from experiments.interrupts import raise_if_interrupted, remember_interrupts
from lfm_env.config import load_yaml

#: Columns of every row before the constraint-group columns, in table order.
HEAD_COLUMNS: tuple[str, ...] = (
    "agent",  # agent name
    "seed",  # env seed
    "success",  # reached the goal
    "steps",  # steps taken
    "time_to_goal",  # [s], NaN without success
    "cost",  # sum of the true stage cost (= -reward) over the episode
)
#: Columns of every row after the constraint-group columns, in table order.
TAIL_COLUMNS: tuple[str, ...] = (
    "failure",  # the env ended the episode as a failure (e.g. left the safety box)
    "latent_rmse",  # [force unit] RMSE of the latent-force estimate; NaN without a filter
    "latent_coverage",  # fraction of steps with the true force in the 2-sigma band
    "solve_time_median",  # [s]
    "solve_time_p95",  # [s]
    "solve_time_max",  # [s]
    "solver_failures",  # steps whose solve did not succeed
    "fallback_steps",  # steps that applied a fallback action (previous plan or brake)
    "filter_resets",  # particle-filter restarts after divergence (filter agents)
    "slack_total",  # sum of the per-step constraint slack
    "wall_time",  # [s] whole episode, including building the agent
    "error",  # '' if the episode ran, else "ExceptionType: message"
)

#: Columns that measure time and so differ between otherwise identical runs.
TIMING_COLUMNS: tuple[str, ...] = (
    "solve_time_median",
    "solve_time_p95",
    "solve_time_max",
    "wall_time",
)

_STR_COLUMNS = ("agent", "error")
_INT_COLUMNS = ("seed", "steps", "solver_failures", "fallback_steps", "filter_resets")
_BOOL_COLUMNS = ("success", "failure")
_FIXED_COLUMNS = HEAD_COLUMNS + TAIL_COLUMNS
_VIOLATION_SUFFIX = "_violation_steps"  # int columns of the constraint groups
_OVER = "_over_"  # {g}_violation_steps_over_{t}: the steps beyond tolerance t


def _group_names(system: Any) -> tuple[str, ...]:
    """The constraint-group names of a system (or of a sequence of names), in order."""
    groups = getattr(system, "constraint_groups", system)
    if isinstance(groups, str) or not isinstance(groups, Iterable):
        raise ValueError(
            f"{groups!r}: give a ControlSystem or a sequence of constraint-group names"
        )
    return tuple(str(g) for g in groups)


def tolerance_column(group: str, tolerance: float) -> str:
    """The column of a group's violation steps beyond ``tolerance`` [group unit].

    ``{group}_violation_steps_over_{tolerance:g}``, e.g. ``track_violation_steps_over_0.01``.
    """
    return f"{group}{_VIOLATION_SUFFIX}{_OVER}{float(tolerance):g}"


def tolerance_columns(system: Any) -> tuple[tuple[str, float, str], ...]:
    """``(group, tolerance, column)`` of every tolerance-aware violation count of a system.

    From ``system.violation_tolerances`` (group -> excesses [group unit]), in the order
    of the groups and of each group's tolerances; empty for a sequence of group names.
    """
    tolerances = getattr(system, "violation_tolerances", None) or {}
    return tuple(
        (g, float(t), tolerance_column(g, t))
        for g in _group_names(system)
        for t in tolerances.get(g, ())
    )


def group_columns(system: Any) -> tuple[str, ...]:
    """The metric columns of a system's constraint groups, in the groups' order.

    Per group ``g`` (a key of ``system.constraint_groups``): ``{g}_violation_steps``
    (steps ending with the group's excess above 0), ``max_{g}_excess`` (its largest
    excess over the episode, in the group's constraint unit), then per tolerance ``t`` of
    ``system.violation_tolerances[g]`` ``{g}_violation_steps_over_{t:g}`` (steps ending
    with the excess above ``t``: a millimetre over a bound is not a crash). For the sine
    track: ``track_violation_steps, max_track_excess, track_violation_steps_over_0.01,
    track_violation_steps_over_0.05``, the same for ``x``, then ``speed_violation_steps,
    max_speed_excess, speed_violation_steps_over_0.05``.

    Args:
        system: a :class:`~lfm_env.system.ControlSystem`, or its group names (then
            without tolerance columns).
    """
    over: dict[str, list[str]] = {}
    for g, _, column in tolerance_columns(system):
        over.setdefault(g, []).append(column)
    return tuple(
        c
        for g in _group_names(system)
        for c in (f"{g}{_VIOLATION_SUFFIX}", f"max_{g}_excess", *over.get(g, ()))
    )


def row_columns(system: Any) -> tuple[str, ...]:
    """Columns of a row of an episode on ``system``, in table order.

    :data:`HEAD_COLUMNS`, then :func:`group_columns` of the system's constraint groups
    (with their tolerance-aware counts), then :data:`TAIL_COLUMNS`.

    Args:
        system: a :class:`~lfm_env.system.ControlSystem` (e.g. ``config.make_system()``),
            or its constraint-group names.
    """
    return HEAD_COLUMNS + group_columns(system) + TAIL_COLUMNS


_GROUP_COLUMN = re.compile(
    rf"(?P<steps>.+){_VIOLATION_SUFFIX}|max_(?P<max>.+)_excess"
    rf"|(?P<over>.+){_VIOLATION_SUFFIX}{_OVER}(?P<tol>[0-9.eE+-]+)"
)


def _table_columns(rows: Iterable[dict[str, Any]]) -> tuple[str, ...]:
    """The columns of saved rows: the fixed ones around the group columns they hold.

    Groups come in first-seen order, each with the columns of it that some row holds
    (``{g}_violation_steps``, ``max_{g}_excess``, then its tolerance counts by
    increasing tolerance); other keys follow them.
    """
    seen: dict[str, None] = {}
    for row in rows:
        seen.update((k, None) for k in row if k not in _FIXED_COLUMNS)
    groups: dict[str, list[tuple[float, str]]] = {}
    for key in seen:
        m = _GROUP_COLUMN.fullmatch(key)
        if m is None:
            continue
        if m.group("over") is not None:
            try:
                tol = float(m.group("tol"))
            except ValueError:
                continue
            groups.setdefault(m.group("over"), []).append((tol, key))
        else:
            groups.setdefault(m.group("steps") or m.group("max"), [])
    ordered = []
    for g, over in groups.items():
        raw = (f"{g}{_VIOLATION_SUFFIX}", f"max_{g}_excess")
        ordered += [c for c in raw if c in seen] + [c for _, c in sorted(over)]
    ordered += [c for c in seen if c not in ordered]
    return HEAD_COLUMNS + tuple(ordered) + TAIL_COLUMNS


def _is_count_column(column: str) -> bool:
    """Integer columns of the constraint groups: raw and tolerance-aware violation steps."""
    return column.endswith(_VIOLATION_SUFFIX) or (
        (m := _GROUP_COLUMN.fullmatch(column)) is not None and m.group("over") is not None
    )


def violation_counts(trajectory: dict[str, np.ndarray], system: Any) -> dict[str, int]:
    """The raw and tolerance-aware violation steps of a trajectory's ``<group>_excess``.

    ``{g}_violation_steps`` counts the steps whose group excess is above 0 and
    ``{g}_violation_steps_over_{t:g}`` those above ``t`` (:func:`tolerance_columns`).
    Groups whose ``<group>_excess`` array the trajectory lacks are left out, so an older
    saved episode gives what it can.

    Args:
        trajectory: arrays of one episode (:func:`run_episode`), ``<group>_excess (T,)``.
        system: the episode's :class:`~lfm_env.system.ControlSystem`.
    """
    counts: dict[str, int] = {}
    for g in _group_names(system):
        if f"{g}_excess" in trajectory:
            excess = np.asarray(trajectory[f"{g}_excess"], dtype=float)
            counts[f"{g}{_VIOLATION_SUFFIX}"] = int(np.sum(excess > 0.0))
    for g, t, column in tolerance_columns(system):
        if f"{g}_excess" in trajectory:
            counts[column] = int(np.sum(np.asarray(trajectory[f"{g}_excess"], float) > t))
    return counts


def _metric_columns(columns: Sequence[str]) -> tuple[str, ...]:
    return tuple(c for c in columns if c not in ("agent", "seed", "wall_time", "error"))


_EPISODES = "episodes"
_TABLE = "episodes.csv"
_CONFIG = "config.yaml"
_LOCK = ".lock"  # the owner's pid and host while a run writes into the folder
_SCHEDULER_TIMEOUT = 5.0  # [s] to connect to a Dask scheduler AND hear it answer as one
_STOP_TIMEOUT = 5.0  # [s] for interrupted pool workers to end before they are killed
_TABLE_REFRESH = 10.0  # [s] least time between rebuilds of episodes.csv during a run
_POOL_RESTARTS = 3  # new process pools after a worker died, before lost episodes count as errors


class ResultsFolderError(ValueError):
    """The results folder cannot be used (e.g. it holds results of another config)."""


# --------------------------------------------------------------------------- small helpers


def agent_seed(seed: int, agent_name: str) -> int:
    """The seed of an agent's own randomness in the episode with env seed ``seed``.

    Derived from the env seed and a stable hash of the agent's name (``hash()`` of a str
    changes between processes), so it is the same in every worker and independent of the
    env's streams and of the other agents'.
    """
    name_key = int.from_bytes(hashlib.sha256(agent_name.encode()).digest()[:8], "little")
    state = np.random.SeedSequence([int(seed), name_key]).generate_state(1, dtype=np.uint64)
    return int(state[0])


def resolve_config(
    config: Any = None, agent_names: Iterable[str | AgentSpec] = ()
) -> ExperimentConfig:
    """The full config, read and validated once: workers get this object, not a path.

    Args:
        config: a YAML path, a dict (whole file), an
            :class:`~controllers.config.ExperimentConfig`, or ``None`` for the built-in
            defaults (the paper's values). Missing keys take their defaults.
        agent_names: agents that will run on it; what each registered agent needs is
            checked too (user agents, :class:`~experiments.agent_specs.AgentSpec`, are
            checked by building one: :func:`~experiments.agent_specs.check_agent`).

    Raises:
        ConfigError: (a ``ValueError``) for unknown keys or out-of-range values.
    """
    resolved = load_config(config)
    for name in agent_names:
        if isinstance(name, str):
            check_agent_config(name, resolved)
    return resolved


MAX_SEEDS = 1_000_000  # seeds of one run (a larger range is a typo, not a plan)


def parse_seeds(text: str) -> list[int]:
    """Seeds from text: ``"0:20"`` (end exclusive), ``"3"``, ``"1,5,9"``, ``"0:10,20:25"``.

    Returns:
        The seeds in the order given, duplicates removed.

    Raises:
        ValueError: naming ``text`` for empty or reversed ranges, negative numbers or
            anything else that is not a list of non-negative integers and ranges.
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


def _check_agents(agents: Any) -> list[str]:
    """Registered agent names only (for callers that store names, e.g. the sweep)."""
    specs = resolve_agents(agents)
    own = [s.text for s in specs if isinstance(s, AgentSpec)]
    if own:
        raise ValueError(f"agents {own}: only registered agents here; choose from {_known()}")
    return specs


def _known() -> list[str]:
    return sorted(AGENTS)


def _check_seeds(seeds: int | Iterable[int]) -> list[int]:
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


def _one_line(exc: BaseException) -> str:
    """``"Type: message"`` on one line, so the error fits a CSV cell and a log line."""
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


# --------------------------------------------------------------------------- one episode


#: Scenarios of the plan kept per step in ``predicted_scenarios`` (the first ones: the
#: scenarios are independent draws, so these are a random subset of the fan).
SAVED_SCENARIOS = 20


class _EpisodeRecorder:
    """Collects one episode step by step; a step is appended whole, so a partial record
    (after an exception) is still consistent.

    Every key of the agent's ``last_info`` is optional, read with the default of
    :data:`controllers.protocol.INFO_DEFAULTS`: an agent with only ``reset`` and ``act``
    has no solver failures, no fallbacks and NaN estimates.
    """

    def __init__(self, config: ExperimentConfig) -> None:
        system = config.make_system()
        self.horizon = config.agents.horizon
        self.nx, self.nu, self.nw = system.nx, system.nu, system.nw
        self.system = system
        self.groups = tuple(system.constraint_groups)
        self.columns = row_columns(system)
        self.lists: dict[str, list] = {
            k: []
            for k in (
                "true_state",
                "obs",
                "time",
                "action",
                "disturbance",
                "reward",
                "estimate",
                "estimate_std",
                "latent_force_est",
                "latent_force_std",
                "predicted",
                "predicted_scenarios",
                "solve_time",
                "slack",
                "solver_success",
                "fallback",
                "filter_reset",
                "estimator",
                *self._excess_keys(),
            )
        }
        self.has_filter = False
        self.slack_reported: list[bool] = []  # per step: the agent gave its slack
        self.final_info: dict[str, Any] = {}

    def start(self, obs: np.ndarray, info: dict[str, Any]) -> None:
        self.lists["true_state"].append(np.asarray(info["true_state"], dtype=float))
        self.lists["obs"].append(np.asarray(obs, dtype=float))
        self.lists["time"].append(float(info["time"]))

    def step(
        self, agent_info: dict[str, Any], obs: np.ndarray, reward: float, info: dict[str, Any]
    ) -> None:
        nan_pred = np.full((self.horizon + 1, self.nx), np.nan)
        no_force = np.full(self.nw, np.nan)
        predicted = agent_info.get("predicted")
        self.has_filter = self.has_filter or agent_info.get("latent_force") is not None
        estimate, estimate_std = self._estimate(agent_info)
        values = {
            "true_state": np.asarray(info["true_state"], dtype=float),
            "obs": np.asarray(obs, dtype=float),
            "time": float(info["time"]),
            "action": np.asarray(info["applied_action"], dtype=float),
            # w acting during this step: the quantity the agent estimated before it.
            "disturbance": self._force(info["disturbance"]),
            "reward": float(reward),
            "estimate": estimate,
            "estimate_std": estimate_std,
            "latent_force_est": self._force(self._get(agent_info, "latent_force", no_force)),
            "latent_force_std": self._force(self._get(agent_info, "latent_force_std", no_force)),
            "predicted": nan_pred if predicted is None else np.array(predicted, dtype=float)[0],
            # A compact fan: the first SAVED_SCENARIOS predicted trajectories, float32.
            "predicted_scenarios": (
                nan_pred[None] if predicted is None else np.asarray(predicted)[:SAVED_SCENARIOS]
            ).astype(np.float32),
            "solve_time": float(self._get(agent_info, "solve_time")),
            "slack": float(self._get(agent_info, "slack")),
            "solver_success": bool(self._get(agent_info, "success")),
            "fallback": str(self._get(agent_info, "fallback")),
            "filter_reset": bool(self._get(agent_info, "filter_reset")),
            # The estimator's name, from agents that say which one they run (it may differ
            # from agents.estimator: the robust agent has its own).
            "estimator": str(self._get(agent_info, "estimator")),
        }
        # The largest excess of each constraint group after the step, in its unit.
        values.update((k, float(info[k])) for k in self._excess_keys())
        for k, v in values.items():
            self.lists[k].append(v)
        self.slack_reported.append(agent_info.get("slack") is not None)
        self.final_info = info

    @staticmethod
    def _get(agent_info: dict[str, Any], key: str, default: Any = None) -> Any:
        """``agent_info[key]``, or its documented default when absent or ``None``."""
        value = agent_info.get(key)
        if value is not None:
            return value
        return INFO_DEFAULTS[key] if default is None else default

    def _estimate(self, agent_info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """The step's estimate and its std, copied; NaN (of the episode's width) if absent."""
        previous = self.lists["estimate"]
        width = len(previous[0]) if previous else self.nx
        est = agent_info.get("estimate")
        est = np.full(width, np.nan) if est is None else np.array(est, dtype=float)
        std = agent_info.get("estimate_std")
        std = np.full(est.shape, np.nan) if std is None else np.array(std, dtype=float)
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
            "disturbance": stack("disturbance", force),
            "reward": stack("reward", (0,)),
            "estimate": stack("estimate", (0, d)),
            "estimate_std": stack("estimate_std", (0, d)),
            "latent_force_est": stack("latent_force_est", force),
            "latent_force_std": stack("latent_force_std", force),
            "predicted": stack("predicted", (0, self.horizon + 1, self.nx)),
            "predicted_scenarios": self._fan(),
            "solve_time": stack("solve_time", (0,)),
            "slack": stack("slack", (0,)),
            "solver_success": stack("solver_success", (0,), bool),
            "fallback": stack("fallback", (0,), str),
            "filter_reset": stack("filter_reset", (0,), bool),
            "estimator": stack("estimator", (0,), str),
            **{k: stack(k, (0,)) for k in self._excess_keys()},
        }


def _simulate(
    agent_spec: str | AgentSpec, config: ExperimentConfig, seed: int, rec: _EpisodeRecorder
) -> None:
    """Run one episode into ``rec``; exceptions propagate with ``rec`` holding the steps done."""
    name = name_of(agent_spec)
    env = gym.make(config.env_id, config=config.env)
    try:
        obs, info = env.reset(seed=seed)
        if isinstance(agent_spec, AgentSpec):
            agent = agent_spec.build(config)
        else:
            agent = make_agent(name, config, env=env if name == "oracle" else None)
        agent.reset(seed=agent_seed(seed, name))
        rec.start(obs, info)
        terminated = truncated = False
        while not (terminated or truncated):
            raise_if_interrupted()  # a Ctrl-C that a library swallowed
            # The agent's estimate made with obs k is compared with the w of step k.
            action = agent.act(obs)
            agent_info = last_info(agent)
            obs, reward, terminated, truncated, info = env.step(action)
            rec.step(agent_info, obs, reward, info)
    finally:
        env.close()


def _episode_metrics(rec: _EpisodeRecorder, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """The metric columns of a finished episode."""
    T = len(arrays["reward"])
    info = rec.final_info
    success = bool(info.get("is_success", False))
    solve = arrays["solve_time"]
    solve = solve[np.isfinite(solve)]  # steps without a solve time are not counted
    slack = arrays["slack"][np.asarray(rec.slack_reported[:T], dtype=bool)]
    if rec.has_filter and T:
        err = arrays["latent_force_est"] - arrays["disturbance"]
        latent_rmse = float(np.sqrt(np.mean(err**2)))
        latent_coverage = float(np.mean(np.abs(err) <= 2.0 * arrays["latent_force_std"]))
    else:
        latent_rmse = latent_coverage = math.nan

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
        "solver_failures": int(np.sum(~arrays["solver_success"])),
        "fallback_steps": int(np.sum(arrays["fallback"] != "")),
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
    """Run one closed-loop episode of ``agent`` on the env with seed ``seed``.

    The env is the config's world, ``gym.make(cfg.env_id, config=cfg.env)``, reset with
    ``seed``; the agent's own randomness is seeded with :func:`agent_seed` (paired
    design). The oracle (an upper bound that reads the hidden truth) is given the env.

    Args:
        agent: a registered name (``"nominal"``, ``"pf"``, ``"scenario"``, ``"oracle"``,
            ...), an agent factory called as ``factory(config)``, an agent, or
            ``"module:attribute"`` (:mod:`experiments.agent_specs`; the row's ``agent``
            is the agent's name there).
        config: a YAML path, a dict (whole file), an ``ExperimentConfig`` or ``None``
            (paper defaults).
        seed: env seed, an integer >= 0.
        record: return the trajectory; ``False`` gives an empty dict.

    Returns:
        ``(row, trajectory)``. ``row`` maps :func:`row_columns` of the config's system to
        values. With ``T`` steps, ``nx`` states, ``nu`` inputs and ``nw`` force components
        (in the units of the system's ``state_names``, ``input_names`` and
        ``force_names``), the trajectory holds ``true_state (T+1, nx)``, ``obs (T+1, nx)``
        (noisy measurement of ``true_state``), ``time (T+1,)`` [s], ``action (T, nu)``
        (applied), ``disturbance`` (the force acting during step k: ``(T,)`` when
        ``nw == 1``, else ``(T, nw)``), ``reward (T,)``, ``estimate (T, d)`` and
        ``estimate_std (T, d)`` (the agent's state estimate from ``obs[k]``; ``d`` = nx,
        or nx + latent states for filter agents), ``latent_force_est`` and
        ``latent_force_std`` (its estimate of ``disturbance[k]``, shaped like it; NaN
        without a filter), ``predicted (T, N+1, nx)`` (first scenario's predicted
        states), ``solve_time (T,)`` [s], ``slack (T,)``, ``solver_success (T,)``,
        ``fallback (T,)`` ('' or the fallback used), ``estimator (T,)`` (the name the
        agent gives its estimator in ``last_info["estimator"]``, '' when it gives none),
        and ``<group>_excess (T,)`` per constraint group of the system (its largest
        excess after step k, in its unit; ``track_excess``, ``x_excess``, ``speed_excess``
        on the sine track).

    Raises:
        ValueError: unknown agent or bad agent spec (naming it) or negative seed; any
            error of the episode itself propagates (:func:`evaluate` records it instead).
    """
    (spec,) = resolve_agents([agent])
    (seed,) = _check_seeds([seed])
    cfg = resolve_config(config, [spec])
    t0 = time.perf_counter()
    rec = _EpisodeRecorder(cfg)
    _simulate(spec, cfg, seed, rec)
    arrays = rec.arrays()
    row = {"agent": name_of(spec), "seed": seed, **_episode_metrics(rec, arrays)}
    row.update(wall_time=time.perf_counter() - t0, error="")
    return {c: row[c] for c in rec.columns}, (arrays if record else {})


# --------------------------------------------------------------------------- storage


def episode_stem(agent_name: str, seed: int) -> str:
    """File name (without suffix) of an episode: ``<agent>__seed<seed>``."""
    return f"{agent_name}__seed{int(seed)}"


def _atomic_write(path: Path, write: Callable[[io.BufferedWriter], None]) -> None:
    """Write ``path`` through a temporary file in its folder, then ``os.replace`` it.

    Readers see the old file or the complete new one, never a torn one, even if the
    process is killed mid-write (only a ``.<name>.*.tmp`` file may be left behind).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    # os.open with mode 0o666 honours the umask (mkstemp would make the file private).
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _json_value(v: Any) -> Any:
    """Strict JSON: NaN becomes null, NumPy scalars become Python ones."""
    if isinstance(v, (np.generic,)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else v
    return v


def config_hash(config: ExperimentConfig) -> str:
    """A short stable hash of a resolved config (16 hex digits of SHA-256 of its YAML).

    Stored with every episode (``config_hash`` in its json), so a folder's episodes stay
    bound to their config even if ``config.yaml`` is deleted or replaced.
    """
    text = yaml.safe_dump(config.to_dict(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save_episode(
    out: str | os.PathLike,
    row: dict[str, Any],
    trajectory: dict[str, np.ndarray] | None,
    traceback_text: str = "",
    config_digest: str = "",
) -> Path:
    """Save an episode as ``episodes/<agent>__seed<seed>.npz`` then ``.json``, atomically.

    Args:
        out: the results folder.
        row: the episode's row (:func:`row_columns`, in that order).
        trajectory: arrays for the npz; ``None`` writes the json only.
        traceback_text: the traceback of a failed episode, kept in the json.
        config_digest: :func:`config_hash` of the episode's config, kept in the json.

    Returns:
        The json's path (its presence marks the episode finished).
    """
    folder = Path(out) / _EPISODES
    stem = episode_stem(row["agent"], row["seed"])
    if trajectory is not None:
        _atomic_write(folder / f"{stem}.npz", lambda fh: np.savez_compressed(fh, **trajectory))
    record = {c: _json_value(v) for c, v in row.items()}
    record["agent_seed"] = agent_seed(row["seed"], row["agent"])
    record["traceback"] = traceback_text
    record["config_hash"] = config_digest
    text = json.dumps(record, indent=1, allow_nan=False) + "\n"
    json_path = folder / f"{stem}.json"
    _atomic_write(json_path, lambda fh: fh.write(text.encode()))
    return json_path


_JSON_EXTRAS = (
    "agent_seed",
    "traceback",
    "config_hash",
)  # keys of an episode json that are not columns


def _normalise_row(record: dict[str, Any]) -> dict[str, Any]:
    """A row with NaN for missing numbers and Python types per column.

    The columns are the fixed ones (missing ones NaN) around whatever constraint-group
    columns the record holds, in its order: a folder of any system, or of an older
    version with other groups, reads as it was written.
    """
    columns = _table_columns([{k: None for k in record if k not in _JSON_EXTRAS}])
    row: dict[str, Any] = {}
    for c in columns:
        v = record.get(c)
        if c in _STR_COLUMNS:
            row[c] = "" if v is None else str(v)
        elif v is None or (isinstance(v, float) and math.isnan(v)):
            row[c] = math.nan
        elif c in _BOOL_COLUMNS:
            row[c] = bool(v)
        elif c in _INT_COLUMNS or _is_count_column(c):
            row[c] = int(v)
        else:
            row[c] = float(v)
    return row


class DamagedEpisodeError(ValueError):
    """An episode file that cannot be trusted (torn, garbage, or not the episode named)."""


def _read_record(path: Path) -> dict[str, Any]:
    """The checked record of an episode json whose name is ``<agent>__seed<seed>.json``.

    Raises:
        DamagedEpisodeError: naming the file, if it cannot be read or parsed, is not an
            episode record, or holds another (agent, seed) than its name.
    """
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {_one_line(exc)}") from exc
    if not isinstance(record, dict) or "agent" not in record or "seed" not in record:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: not an episode record")
    try:
        stem = episode_stem(str(record["agent"]), int(record["seed"]))
        row = _normalise_row(record)
    except (TypeError, ValueError) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {_one_line(exc)}") from exc
    if path.name != f"{stem}.json":
        raise DamagedEpisodeError(
            f"episode file {str(path)!r} holds the row of {stem} (a copy or a renamed file)"
        )
    return {**row, **{k: record.get(k) for k in _JSON_EXTRAS}}


def _read_row(path: Path) -> dict[str, Any] | None:
    """The row of an episode json, or ``None`` if it is missing or damaged."""
    try:
        record = _read_record(path)
    except DamagedEpisodeError:
        return None
    return {k: v for k, v in record.items() if k not in _JSON_EXTRAS}


def _warn(message: str) -> None:
    """One line on stderr: a damaged file is named, never dropped silently."""
    import sys

    print(f"warning: {message}", file=sys.stderr, flush=True)


def saved_rows(out: str | os.PathLike) -> list[dict[str, Any]]:
    """Every saved row of a results folder, sorted by (agent, seed): the storage layer's
    reader of the episode records (:func:`experiments.results.load_results` reads a folder
    for analysis: its table, config and trajectories).

    Reads the episode json files (exact values; ``episodes.csv`` holds the same rows as
    text). Metrics of failed episodes are NaN; filter on ``row["error"] == ""``. Files
    that are damaged, or hold another episode than their name (a copy), are left out
    with a warning on stderr naming them, so each (agent, seed) counts once.
    """
    folder = Path(out) / _EPISODES
    rows = []
    for p in sorted(folder.glob("*.json")):
        try:
            record = _read_record(p)
        except DamagedEpisodeError as exc:
            _warn(f"{exc}; left out")
            continue
        rows.append({k: v for k, v in record.items() if k not in _JSON_EXTRAS})
    return sorted(rows, key=lambda r: (r["agent"], r["seed"]))


def load_trajectory(out: str | os.PathLike, agent_name: str, seed: int) -> dict[str, np.ndarray]:
    """The saved trajectory of one episode (see :func:`run_episode` for its arrays).

    Raises:
        FileNotFoundError: the episode has no npz.
        DamagedEpisodeError: naming the file, if it does not load (e.g. truncated).
    """
    path = Path(out) / _EPISODES / f"{episode_stem(agent_name, seed)}.npz"
    if not path.is_file():
        raise FileNotFoundError(f"episode file {str(path)!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DamagedEpisodeError(f"episode file {str(path)!r}: {_one_line(exc)}") from exc


def _csv_value(v: Any) -> str:
    if isinstance(v, float):
        return repr(v)  # shortest exact text; NaN as "nan"
    return str(v)


def _folder_columns(out: Path) -> tuple[str, ...] | None:
    """:func:`row_columns` of the system in the folder's ``config.yaml``; ``None`` without one."""
    path = out / _CONFIG
    if not path.is_file():
        return None
    try:
        return row_columns(resolve_config(load_yaml(path)).make_system())
    except ValueError:
        return None


def write_table(out: str | os.PathLike, columns: Sequence[str] | None = None) -> Path:
    """Rebuild ``out/episodes.csv`` from every episode json (sorted by agent, seed).

    Args:
        out: the results folder.
        columns: the table's columns in order; ``None`` for :func:`row_columns` of the
            system in the folder's ``config.yaml`` (without one: the columns the saved
            rows hold). A column a row lacks (e.g. a group added since it was saved) is
            written as ``nan``.
    """
    rows = saved_rows(out)
    if columns is None:
        columns = _folder_columns(Path(out)) or _table_columns(rows)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_csv_value(row.get(c, math.nan)) for c in columns])
    path = Path(out) / _TABLE
    _atomic_write(path, lambda fh: fh.write(buf.getvalue().encode()))
    return path


def _remove_stale_temp_files(out: Path) -> None:
    """Delete temporary files a killed run may have left (only our ``.name.*.tmp``)."""
    for folder in (out, out / _EPISODES):
        for tmp in folder.glob(".*.tmp"):
            tmp.unlink(missing_ok=True)


def _config_differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    diffs = []
    for key in sorted(set(a) | set(b)):
        name = f"{prefix}{key}"
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            diffs += _config_differences(va, vb, f"{name}.")
        elif va != vb:
            diffs.append(f"{name}: {va!r} in the folder, {vb!r} now")
    return diffs


def _check_folder(out: Path, config: ExperimentConfig) -> None:
    """Refuse a folder of another config (reads only).

    Its ``config.yaml`` must equal ``config``, and every episode json must carry
    :func:`config_hash` of ``config`` (or none: folders of older versions).
    """
    path = out / _CONFIG
    if out.exists() and not out.is_dir():
        raise ResultsFolderError(f"results folder {str(out)!r} is a file")
    if path.exists():
        try:
            saved = resolve_config(load_yaml(path))
        except ValueError as exc:
            raise ResultsFolderError(f"results folder {str(out)!r}: bad {_CONFIG}: {exc}") from exc
        diffs = _config_differences(saved.to_dict(), config.to_dict())
        if diffs:
            shown = "; ".join(diffs[:5]) + ("; ..." if len(diffs) > 5 else "")
            raise ResultsFolderError(
                f"results folder {str(out)!r} holds results of a different config ({shown}); "
                "choose another output folder or delete this one"
            )
    digest = config_hash(config)
    for json_path in sorted((out / _EPISODES).glob("*.json")):
        try:
            other = json.loads(json_path.read_text()).get("config_hash")
        except (OSError, ValueError, AttributeError):
            continue  # a damaged file is named and re-run later
        if other not in (None, "", digest):
            raise ResultsFolderError(
                f"results folder {str(out)!r} holds results of a different config "
                f"({json_path.name} has config hash {other}, this config {digest}); "
                "choose another output folder or delete this one"
            )


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


class FolderLock:
    """Ownership of a results folder by one run: ``out/.lock`` holds ``<pid> <host>``.

    Taken with ``O_EXCL``; a lock of a process that no longer runs on this host is stale
    and taken over. Another live owner gets a :class:`ResultsFolderError` naming it.
    """

    def __init__(self, out: Path) -> None:
        self.path = Path(out) / _LOCK
        self.text = f"{os.getpid()} {socket.gethostname()}\n"

    def _owner(self) -> tuple[int, str] | None:
        for _ in range(10):  # the owner may be between creating and writing it
            try:
                parts = self.path.read_text().split()
            except FileNotFoundError:
                return None
            if len(parts) == 2 and parts[0].isdigit():
                return int(parts[0]), parts[1]
            time.sleep(0.05)
        return -1, ""  # garbage: treated as stale

    def acquire(self) -> FolderLock:
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                owner = self._owner()
                if owner is None:
                    continue
                pid, host = owner
                if pid > 0 and (host != socket.gethostname() or _pid_alive(pid)):
                    raise ResultsFolderError(
                        f"results folder {str(self.path.parent)!r} is in use by process {pid} "
                        f"on {host} (lock file {str(self.path)!r}); wait for that run to end "
                        "or choose another output folder"
                    ) from None
                # Stale (its process is gone): move it aside, so only one taker wins.
                try:
                    os.rename(self.path, self.path.with_name(f"{_LOCK}.stale.{os.getpid()}"))
                    self.path.with_name(f"{_LOCK}.stale.{os.getpid()}").unlink()
                except FileNotFoundError:
                    pass
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(self.text)
            return self
        raise ResultsFolderError(f"results folder {str(self.path.parent)!r}: cannot take its lock")

    def release(self) -> None:
        try:
            if self.path.read_text() == self.text:
                self.path.unlink()
        except FileNotFoundError:
            pass


def _prepare_folder(out: Path, config: ExperimentConfig) -> None:
    """Create the folder and its ``config.yaml``; remove temp files of a killed run."""
    path = out / _CONFIG
    out.mkdir(parents=True, exist_ok=True)
    (out / _EPISODES).mkdir(exist_ok=True)
    _remove_stale_temp_files(out)
    if not path.exists():
        text = "# Resolved config of the episodes in this folder.\n" + yaml.safe_dump(
            config.to_dict(), sort_keys=False
        )
        _atomic_write(path, lambda fh: fh.write(text.encode()))


# --------------------------------------------------------------------------- evaluate


def _episode_task(
    agent: str | AgentSpec,
    config: ExperimentConfig,
    seed: int,
    out: str | None,
    record: bool,
    digest: str = "",
) -> dict[str, Any]:
    """Run and save one episode; never raises for an error of the episode itself.

    Top-level (picklable by reference) so process pools and Dask workers can run it; the
    resolved config travels with the task, so workers parse nothing. ``agent`` is a
    registered name or a user agent's :class:`~experiments.agent_specs.AgentSpec`.
    """
    name = name_of(agent)
    t0 = time.perf_counter()
    rec = _EpisodeRecorder(config)
    tb = ""
    try:
        _simulate(agent, config, seed, rec)
        arrays = rec.arrays()
        row = {"agent": name, "seed": seed, **_episode_metrics(rec, arrays)}
        row.update(wall_time=time.perf_counter() - t0, error="")
        row = {c: row[c] for c in rec.columns}
    except Exception as exc:  # one bad episode must not stop the others
        raise_if_interrupted()  # a Ctrl-C a library turned into another error: no error row
        tb = traceback.format_exc()
        wall_time = time.perf_counter() - t0
        row = _error_row(name, seed, _one_line(exc), wall_time, rec.columns)
        try:
            arrays = rec.arrays()  # the steps done before the error, for debugging
        except Exception:
            arrays = {}
    if out is not None:
        save_episode(out, row, arrays if record else None, tb, digest)
    return row


def _exit_with_parent() -> None:
    """Process-pool initializer: end this worker as soon as the parent process ends.

    Pool workers otherwise outlive a parent killed with SIGKILL (or by the OOM killer),
    blocked forever on the task queue. A worker ended mid-write leaves only a temporary
    file, which the next run removes.
    """
    import multiprocessing
    import signal
    import threading

    # Ctrl-C goes to the whole process group: the parent alone handles it (and ends the
    # workers), so workers print no KeyboardInterrupt tracebacks.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()  # returns when the parent's end of the spawn pipe closes
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _finished_row(
    out: Path, agent_name: str, seed: int, record: bool, digest: str = ""
) -> dict | None:
    """The saved and verified row of a finished episode, or ``None`` if it must (re-)run.

    The json must be an episode record of this (agent, seed) and of this config (when
    it carries a config hash); with ``record`` the npz must exist and, for an episode
    that ran, load with one reward per step. A damaged file is named on stderr.
    """
    stem = out / _EPISODES / episode_stem(agent_name, seed)
    json_path, npz_path = stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".npz")
    if not json_path.exists():
        return None
    try:
        record_ = _read_record(json_path)
        if digest and record_["config_hash"] not in (None, "", digest):
            raise DamagedEpisodeError(f"episode file {str(json_path)!r} is of another config")
        if record and not npz_path.exists():
            return None
        if record and record_["error"] == "":
            steps = len(load_trajectory(out, agent_name, seed)["reward"])
            if steps != record_["steps"]:
                raise DamagedEpisodeError(
                    f"episode file {str(npz_path)!r} holds {steps} steps, its row "
                    f"{record_['steps']}"
                )
    except (DamagedEpisodeError, KeyError) as exc:
        _warn(f"{exc}; running the episode again")
        return None
    return {k: v for k, v in record_.items() if k not in _JSON_EXTRAS}


def _connect_dask(scheduler: str | None, dask_workers: int | None, stack: Any):
    """A ``distributed.Client`` on an existing scheduler or on a new loopback cluster."""
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(
            "Dask runs need the 'distributed' package: pip install 'lfm-scenario-mpc[dist]'"
        ) from exc
    import logging

    from experiments import executors

    if scheduler is not None:
        # Client's own timeout bounds only the TCP connect: check the answer first.
        executors.check_scheduler(scheduler, _SCHEDULER_TIMEOUT)
        try:
            client = distributed.Client(scheduler, timeout=f"{_SCHEDULER_TIMEOUT:g}s")
        except Exception as exc:  # OSError or TimeoutError, depending on the failure
            raise ConnectionError(
                f"cannot reach the Dask scheduler at {scheduler!r} within "
                f"{_SCHEDULER_TIMEOUT:g} s ({_one_line(exc)})"
            ) from exc
        return stack.enter_context(client)
    # Loopback only, mutual TLS with a temporary certificate, no HTTP endpoint.
    logging.getLogger("distributed").setLevel(logging.ERROR)
    return executors.local_client(dask_workers, stack)


def evaluate(
    agents: Sequence[Any] | str,
    seeds: Iterable[int] | str,
    config: Any = None,
    out: str | os.PathLike | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    dask_workers: int | None = None,
    progress: bool = True,
    record: bool = True,
    retry_failed: bool = True,
    progress_label: str | None = None,
) -> list[dict[str, Any]]:
    """Run every (agent, env seed) episode and return one row of metrics per episode.

    Args:
        agents: the agents, each a registered name (``"nominal"``, ``"pf"``,
            ``"scenario"``, ``"oracle"``; the oracle is an upper bound that reads the
            hidden truth), an agent factory called as ``factory(config)`` with the
            resolved :class:`~controllers.config.ExperimentConfig`, an agent object, or
            ``"module:attribute"`` of a factory (:mod:`experiments.agent_specs`: how
            they are named, and what ``jobs > 1`` and Dask need); or one comma list of
            names and ``module:attribute`` texts. A user agent follows
            :class:`controllers.protocol.Agent`; it is built once before any episode,
            so a bad factory fails early.
        seeds: env seeds (integers >= 0), or a text for :func:`parse_seeds`.
        config: a YAML path, a dict (whole file) or ``None`` (paper defaults).
        out: results folder (see the module docstring); ``None`` keeps nothing on disk.
            Episodes already saved there are not re-run.
        jobs: local worker processes (``spawn`` context, safe with CasADi); 1 is serial.
            A script that uses ``jobs > 1`` needs the ``if __name__ == "__main__":``
            guard, as with any spawned process.
        scheduler: address of an existing Dask scheduler (``"tcp://host:8786"``).
        dask_workers: start a local Dask cluster of this many single-threaded worker
            processes on 127.0.0.1 for this call.
        progress: show a tqdm progress bar over episodes.
        record: save each episode's trajectory (npz) next to its row.
        retry_failed: re-run saved episodes whose ``error`` is not empty.
        progress_label: text before the progress bar (e.g. the sweep's value).

    Returns:
        The rows (:func:`row_columns` of the config's system) of the requested episodes,
        sorted by (agent, seed), including those loaded from ``out``. Trajectories are not
        kept in memory; read them with :func:`load_trajectory`, all rows with
        :func:`saved_rows`.

    Raises:
        ValueError: unknown agents or a bad agent spec (naming it), empty or negative
            seeds, a bad config, conflicting run modes or a results folder of another
            config, before any episode runs.
        ConnectionError: the Dask scheduler cannot be reached.
    """
    specs = resolve_agents(agents)
    names = [name_of(a) for a in specs]
    spec_of = dict(zip(names, specs, strict=True))
    seed_list = _check_seeds(seeds)
    cfg = resolve_config(config, specs)
    columns = row_columns(cfg.make_system())
    modes = sum([jobs != 1, scheduler is not None, dask_workers is not None])
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs={jobs!r}: must be an integer >= 1")
    if dask_workers is not None and (
        isinstance(dask_workers, bool) or not isinstance(dask_workers, int) or dask_workers < 1
    ):
        raise ValueError(f"dask_workers={dask_workers!r}: must be an integer >= 1")
    if modes > 1:
        raise ValueError("choose one of jobs > 1, scheduler and dask_workers")
    for spec in specs:
        if jobs > 1 or scheduler is not None or dask_workers is not None:
            check_picklable(spec, "pool" if jobs > 1 else "dask")
        check_agent(spec, cfg)

    out_path = None if out is None else Path(out).resolve()
    digest = config_hash(cfg)
    if out_path is not None:
        _check_folder(out_path, cfg)

    # Seed-major order: an interrupted run leaves complete pairs of agents per seed.
    pairs = [(a, s) for s in seed_list for a in names]
    rows: dict[tuple[str, int], dict[str, Any]] = {}

    def load_finished() -> None:
        rows.clear()
        for a, s in pairs:
            row = _finished_row(out_path, a, s, record, digest)
            if row is not None and (row["error"] == "" or not retry_failed):
                rows[(a, s)] = row

    out_str = None if out_path is None else str(out_path)

    from contextlib import ExitStack

    from tqdm.auto import tqdm

    with ExitStack() as stack:
        stack.enter_context(remember_interrupts())
        # Closed after the executor below (last in, first out): the folder is finished
        # and unlocked only once no worker writes into it any more.
        folder_stack = stack.enter_context(ExitStack())
        if out_path is not None:
            load_finished()  # read only: whether a Dask cluster is needed at all
        # Connect before the first episode: an unreachable scheduler fails fast.
        client = None
        if len(rows) < len(pairs) and (scheduler is not None or dask_workers is not None):
            client = _connect_dask(scheduler, dask_workers, stack)
        if out_path is not None:
            out_path.mkdir(parents=True, exist_ok=True)
            lock = FolderLock(out_path).acquire()
            folder_stack.callback(lock.release)
            folder_stack.callback(_finish_folder, out_path, columns)  # runs before release
            _check_folder(out_path, cfg)  # again: another run may have written meanwhile
            _prepare_folder(out_path, cfg)
            load_finished()
        todo = [p for p in pairs if p not in rows]
        bar = stack.enter_context(
            tqdm(
                total=len(pairs),
                initial=len(rows),
                disable=not progress,
                unit="episode",
                desc=progress_label,
            )
        )
        last_table = time.monotonic()
        n_errors = 0

        def done(pair: tuple[str, int], row: dict[str, Any]) -> None:
            nonlocal last_table, n_errors
            rows[pair] = row
            n_errors += row["error"] != ""
            bar.update(1)
            if n_errors:
                bar.set_postfix(errors=n_errors)
            if out_path is not None and time.monotonic() - last_table > _TABLE_REFRESH:
                write_table(out_path, columns)
                last_table = time.monotonic()

        def lost(pair: tuple[str, int], exc: BaseException) -> dict[str, Any]:
            # The worker died (or the task was lost): record it so the rerun retries it,
            # unless the episode was saved before the loss.
            if out_path is not None:
                saved = _finished_row(out_path, pair[0], pair[1], record, digest)
                if saved is not None and saved["error"] == "":
                    return saved
            row = _error_row(pair[0], pair[1], _one_line(exc), math.nan, columns)
            if out_path is not None:
                tb = "".join(traceback.format_exception(exc))
                save_episode(out_path, row, None, tb, digest)
            return row

        def task_args(a: str, s: int) -> tuple:
            return spec_of[a], cfg, s, out_str, record, digest

        if client is not None and todo:
            import distributed

            futures = {
                client.submit(
                    _episode_task,
                    spec_of[a],
                    cfg,
                    s,
                    out_str,
                    record,
                    digest,
                    pure=False,
                    key=f"episode-{a}-{s}",
                ): (a, s)
                for a, s in todo
            }
            try:
                for fut in distributed.as_completed(futures):
                    try:
                        row = fut.result()
                    except Exception as exc:
                        row = lost(futures[fut], exc)
                    done(futures[fut], row)
            except BaseException:
                client.cancel(list(futures), force=True)
                raise
        elif jobs > 1 and len(todo) > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor, as_completed
            from concurrent.futures.process import BrokenProcessPool

            # A worker that dies (OOM killer, a crash in native code) breaks the whole pool
            # and fails every unfinished episode; rerun those on a new pool, a few times.
            pending = todo
            for restart in range(_POOL_RESTARTS + 1):
                broken = []
                pool = ProcessPoolExecutor(
                    max_workers=min(jobs, len(pending)),
                    mp_context=multiprocessing.get_context("spawn"),  # no forked CasADi state
                    initializer=_exit_with_parent,
                )
                try:
                    futs = {
                        pool.submit(_episode_task, *task_args(a, s)): (a, s) for a, s in pending
                    }
                    for fut in as_completed(futs):
                        try:
                            row = fut.result()
                        except BrokenProcessPool as exc:
                            if restart < _POOL_RESTARTS:
                                broken.append(futs[fut])
                                continue
                            row = lost(futs[fut], exc)
                        except Exception as exc:
                            row = lost(futs[fut], exc)
                        done(futs[fut], row)
                except BaseException:
                    _stop_pool(pool)  # Ctrl-C or SIGTERM: end the workers now
                    raise
                pool.shutdown(wait=True, cancel_futures=True)
                if not broken:
                    break
                pending = sorted(broken, key=pairs.index)
        else:
            for a, s in todo:
                raise_if_interrupted()
                done((a, s), _episode_task(*task_args(a, s)))

    return sorted((rows[p] for p in pairs), key=lambda r: (r["agent"], r["seed"]))


def _finish_folder(out: Path, columns: Sequence[str]) -> None:
    """End of a run, also an interrupted one: no temporary file, an up-to-date table."""
    # A worker killed mid-write (then rerun elsewhere) leaves its temporary file; the
    # folder is locked, so every temporary file in it is of this run.
    _remove_stale_temp_files(out)
    write_table(out, columns)


def _stop_pool(pool: Any) -> None:
    """End a process pool's workers at once (SIGTERM, then SIGKILL after a grace time)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + _STOP_TIMEOUT
    for p in processes:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join()


__all__ = [
    "DamagedEpisodeError",
    "FolderLock",
    "HEAD_COLUMNS",
    "TAIL_COLUMNS",
    "TIMING_COLUMNS",
    "ResultsFolderError",
    "agent_seed",
    "config_hash",
    "evaluate",
    "episode_stem",
    "group_columns",
    "saved_rows",
    "load_trajectory",
    "parse_seeds",
    "resolve_config",
    "row_columns",
    "run_episode",
    "save_episode",
    "tolerance_column",
    "tolerance_columns",
    "violation_counts",
    "write_table",
]
