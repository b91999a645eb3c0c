"""Per-step times of the scenario agent in closed loop, by horizon, prediction and iteration
mode: each step's whole ``act`` timed, with its solve time, status and iterations. A
combination the config refuses is a row saying why; a step that raises is a failed step.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from controllers.config import AgentConfig, ConfigError, load_config
from controllers.problem import PREDICTIONS
from experiments.benchmark.failures import classify_failure
from experiments.benchmark.problems import DEFAULT_CONFIG, DEFAULT_SEEDS, config_path
from experiments.benchmark.solvers import p95, stat

#: The horizons of the closed-loop sweep.
CLOSED_LOOP_HORIZONS = (7, 15, 30, 50)
#: Steps per seed (from the episode's start).
CLOSED_LOOP_STEPS = 8
#: The iteration modes measured when the config has ``agents.iterations``.
ITERATION_MODES = ("converged", "rti")
#: The agent whose steps are timed (the paper's scenario MPC).
CLOSED_LOOP_AGENT = "scenario"


def iteration_modes() -> tuple[str, ...]:
    """``ITERATION_MODES`` where ``agents.iterations`` exists, else ``("converged",)``."""
    return ITERATION_MODES if "iterations" in AgentConfig.__dataclass_fields__ else ("converged",)


def _settings(horizon: int, prediction: str, iterations: str) -> list[str]:
    out = [f"agents.horizon={horizon}", f"agents.prediction={prediction}"]
    if "iterations" in AgentConfig.__dataclass_fields__:
        out.append(f"agents.iterations={iterations}")
    return out


def _episode_steps(config: Any, agent_name: str, seed: int, steps: int) -> list[dict[str, Any]]:
    """The first ``steps`` steps of one episode, each timed whole (module docstring)."""
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the envs)
    from controllers.agents import make_agent
    from controllers.agents.registry import AGENT_REGISTRY

    env = gym.make(config.env_id, config=config.env)
    records: list[dict[str, Any]] = []
    try:
        obs, _ = env.reset(seed=int(seed))
        truth = AGENT_REGISTRY[agent_name].reads_truth  # the oracle reads the env
        agent = make_agent(agent_name, config, env=env if truth else None)
        agent.reset(seed=int(seed))
        for step in range(steps):
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                action = agent.act(obs)
            except Exception as exc:  # a failed step, not a failed benchmark
                records.append(_failed_step(seed, step, time.perf_counter() - t0, exc))
                break
            step_time = time.perf_counter() - t0
            step_cpu = time.thread_time() - c0
            info = agent.last_info
            records.append(
                {
                    "seed": int(seed),
                    "step": step,
                    "step_time_ms": 1e3 * step_time,
                    "step_cpu_ms": 1e3 * step_cpu,
                    "solve_time_ms": 1e3 * float(info.get("solve_time", math.nan)),
                    "estimate_time_ms": 1e3 * float(info.get("estimate_time", math.nan)),
                    "iterations": int(info.get("iterations", 0)),
                    "success": bool(info.get("success", False)),
                    "usable": bool(info.get("usable", False)),
                    "status": str(info.get("status", "")),
                }
            )
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
    finally:
        env.close()
    return records


def _failed_step(seed: int, step: int, seconds: float, exc: Exception) -> dict[str, Any]:
    return {
        "seed": int(seed),
        "step": step,
        "step_time_ms": 1e3 * seconds,
        "step_cpu_ms": math.nan,
        "solve_time_ms": math.nan,
        "estimate_time_ms": math.nan,
        "iterations": 0,
        "success": False,
        "usable": False,
        "status": f"raised {type(exc).__name__}: {exc}",
    }


def _failed(record: dict[str, Any], iterations: str) -> bool:
    """A failed step: raised or without a usable plan; with converged solves, also one that
    did not converge (a real-time iteration stops by design at its iteration count)."""
    return not record["usable"] or (iterations == "converged" and not record["success"])


def _summary(records: list[dict[str, Any]], iterations: str) -> dict[str, Any]:
    """Per-step figures [ms] over every recorded step."""
    step = [r["step_time_ms"] for r in records]
    return {
        "n_steps": len(records),
        "step_ms_median": stat(step, np.median),
        "step_ms_p95": stat(step, p95),
        "step_ms_max": stat(step, np.max),
        # the step's CPU time in its thread (BLAS and the C library at one thread): what the
        # step costs without the waiting a loaded machine adds to its wall time
        "step_cpu_ms_median": stat([r["step_cpu_ms"] for r in records], np.median),
        "solve_ms_median": stat([r["solve_time_ms"] for r in records], np.median),
        "iterations_median": stat([r["iterations"] for r in records], np.median),
        "failed": int(sum(_failed(r, iterations) for r in records)),
        "not_usable": int(sum(not r["usable"] for r in records)),
    }


def closed_loop_steps(
    horizons: Sequence[int] = CLOSED_LOOP_HORIZONS,
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    steps: int = CLOSED_LOOP_STEPS,
    predictions: Sequence[str] = PREDICTIONS,
    agent: str = CLOSED_LOOP_AGENT,
    progress: bool = False,
) -> dict[str, Any]:
    """The agent's closed-loop steps at each horizon, prediction and iteration mode.

    Args:
        horizons: prediction steps ``N``.
        config: a preset's name, a YAML path, a dict or an ExperimentConfig.
        seeds: env seeds (one episode start each).
        steps: steps per seed from the episode's start.
        predictions: ``agents.prediction`` values.
        agent: the registered agent timed.
        progress: show progress bars.

    Returns:
        ``{"config", "agent", "seeds", "steps", "results": [{"horizon", "prediction",
        "iterations", "refused", "summary", "records", "failures"}]}``, times in ms.
    """
    base = load_config(config_path(config))
    rows = []
    for n in (int(h) for h in horizons):
        for prediction in predictions:
            for iterations in iteration_modes():
                row: dict[str, Any] = {
                    "horizon": n,
                    "prediction": prediction,
                    "iterations": iterations,
                    "refused": "",
                    "records": [],
                }
                try:
                    cfg = load_config(base, _settings(n, prediction, iterations))
                except (ConfigError, ValueError) as exc:
                    row["refused"] = " ".join(str(exc).split())
                else:
                    label = f"N={n} {prediction} {iterations}"
                    for seed in tqdm(list(seeds), desc=label, disable=not progress):
                        row["records"] += _episode_steps(cfg, agent, seed, steps)
                row["summary"] = _summary(row["records"], iterations)
                row["failures"] = [
                    {**_where(r), "kind": classify_failure(r["status"]), "status": r["status"]}
                    for r in row["records"]
                    if _failed(r, iterations)
                ]
                rows.append(row)
    return {
        "config": str(config),
        "agent": agent,
        "seeds": [int(s) for s in seeds],
        "steps": int(steps),
        "results": rows,
    }


def _where(record: dict[str, Any]) -> dict[str, Any]:
    return {"seed": record["seed"], "step": record["step"], "usable": record["usable"]}


def format_closed_loop(result: dict[str, Any]) -> str:
    """The table (one line per horizon, prediction and iteration mode) and the failed steps."""
    head = (
        f"{'N':>3} {'prediction':<10} {'iterations':<10} {'steps':>5} {'step med ms':>11} "
        f"{'p95 ms':>9} {'max ms':>9} {'cpu med':>8} {'solve med':>9} {'iter.':>6} "
        f"{'failed':>6} {'unusable':>8}"
    )
    lines = [
        f"closed-loop steps: agent {result['agent']}, config {result['config']}, seeds "
        f"{result['seeds']}, the first {result['steps']} steps of each (a step: the agent's "
        "act, estimator + solve; cpu: its thread's CPU time)",
        head,
        "-" * len(head),
    ]
    for row in result["results"]:
        s = row["summary"]
        lead = f"{row['horizon']:>3} {row['prediction']:<10} {row['iterations']:<10}"
        if row["refused"]:
            lines.append(f"{lead} refused by the config: {row['refused']}")
            continue
        lines.append(
            f"{lead} {s['n_steps']:>5} {s['step_ms_median']:>11.1f} {s['step_ms_p95']:>9.1f} "
            f"{s['step_ms_max']:>9.1f} {s['step_cpu_ms_median']:>8.2f} "
            f"{s['solve_ms_median']:>9.1f} {s['iterations_median']:>6.1f} {s['failed']:>6} "
            f"{s['not_usable']:>8}"
        )
    failed = [(row, f) for row in result["results"] for f in row["failures"]]
    lines.append(
        f"failed steps (raised, no usable plan, or a converged solve that did not converge; "
        f"a real-time iteration's first step is a converged solve): {len(failed)}"
    )
    for row, f in failed:
        lines.append(
            f"  N={row['horizon']} {row['prediction']} {row['iterations']} seed {f['seed']} "
            f"step {f['step']}: {f['status']} ({f['kind']}; "
            f"{'usable plan' if f['usable'] else 'no usable plan'})"
        )
    return "\n".join(lines)
