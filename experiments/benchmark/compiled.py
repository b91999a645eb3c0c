"""The compiled SQP loop and the exported controller in the benchmark: :func:`plan_agreement`
(``fast_c``'s plans against the Python loop's with the same QP solver, from scratch) and
:func:`time_export` (the exported C projects built with ``make``, timed from C, their plans
and the robust agent's step against Python, and their run-time dependencies).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import subprocess
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from controllers.solvers.fast.compiled import CompiledScenarioSolver
from controllers.solvers.fast.solver import FastScenarioSolver
from experiments.benchmark.problems import ENV_ID, anchors_per_seed, scenario_draws
from experiments.evaluation.interrupts import raise_if_interrupted

SAME_QP = {"qp_solver": "elastic_ipm"}  # the Python loop's choice closest to the C loop's
PLAN_TOL = 1e-9  # [input units] plan agreement of the two loops counted as equal
EXPORT_PLAN_TOL = 1e-8  # [input units] the exported example's plans against Python's
EXPORT_REPEATS = 5  # example --time K per problem
STEP_REPEATS = 20  # example --steps --time K over the robust episode
AGREEMENT_NS = (1000, 5000)  # scenario counts of the plan agreement beyond the main size
AGREEMENT_STEPS = 2  # anchors per seed at those counts


def _stats(values: Sequence[float]) -> dict[str, float]:
    a = np.asarray([v for v in values if math.isfinite(v)], dtype=float)
    if not a.size:
        return {"median": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "max": float(np.max(a)),
    }


def plan_agreement(problem: Any, problems: Sequence[Any], label: str = "") -> dict[str, Any]:
    """The compiled loop against the Python loop with the same QP solvers, each problem from
    scratch (both reset): plan differences, objective gaps, iterations, times [ms]."""
    python = FastScenarioSolver(problem, **SAME_QP)
    compiled = CompiledScenarioSolver(problem, **SAME_QP)
    rows = []
    for seed, step, x0, W in problems:
        raise_if_interrupted()
        python.reset()
        compiled.reset()
        a, b = python.solve(x0, W), compiled.solve(x0, W)
        rows.append(
            {
                "seed": int(seed),
                "step": int(step),
                "diff": float(np.max(np.abs(a.u - b.u))),
                "rel_gap": (b.objective - a.objective) / max(abs(a.objective), 1e-12),
                "slack": float(a.slack),
                "same_iterations": a.iterations == b.iterations and a.status == b.status,
                "python_ms": 1e3 * a.solve_time,
                "c_ms": 1e3 * b.solve_time,
                "python_u": a.u,
            }
        )
    worst = max(rows, key=lambda r: r["diff"], default=None)
    return {
        "label": label,
        "horizon": problem.horizon,
        "n_scenarios": problem.n_scenarios,
        "n_problems": len(rows),
        "loop": compiled.loop,
        "max_abs_diff": worst["diff"] if worst else math.nan,
        "worst": {k: worst[k] for k in ("seed", "step", "diff", "rel_gap", "slack")}
        if worst
        else None,
        "n_above_tol": sum(r["diff"] > PLAN_TOL for r in rows),
        "rel_gap_abs_max": max((abs(r["rel_gap"]) for r in rows), default=math.nan),
        "n_same_iterations": sum(r["same_iterations"] for r in rows),
        "python_ms": _stats([r["python_ms"] for r in rows]),
        "c_ms": _stats([r["c_ms"] for r in rows]),
        "_python_u": [r["python_u"] for r in rows],  # (for the export's comparison; dropped)
    }


def _example_plans(folder: Path, problems: Sequence[Any], problem: Any, tmp: Path) -> list:
    """``example --time K`` on every problem: ``[(plan, median_us, status code)]``."""
    from controllers.export import read_plan, write_problem

    out = []
    path = tmp / "problem.txt"
    for _, _, x0, W in problems:
        raise_if_interrupted()
        write_problem(path, np.asarray(x0).reshape(-1)[: problem.nx], W)
        done = subprocess.run(
            [str(folder / "example"), "--time", str(EXPORT_REPEATS), str(path)],
            capture_output=True,
            text=True,
            check=False,
        )
        plan = read_plan(done.stdout, problem.horizon, problem.nu) if done.stdout else None
        timing = done.stderr.split("\n", 1)[0].split()
        median = float(timing[1]) if timing[:1] == ["time_us"] else math.nan
        out.append((plan, median, done.returncode))
    return out


def _robust_episode(config: Any, seed: int) -> dict[str, Any]:
    """A robust-agent episode in Python with the C loop's QP choice: measurements, inputs,
    step times (estimate + scenarios + solve) [ms]."""
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the worlds)
    from controllers.agents import make_agent
    from controllers.export import solver_options
    from controllers.solvers import make_solver

    env = gym.make(getattr(config, "env_id", ENV_ID), config=config.env)
    agent = make_agent("robust", config)
    options = dataclasses.asdict(solver_options(agent.settings))
    agent.solver = make_solver(agent.problem, "fast", **options)
    obs, _ = env.reset(seed=seed)
    agent.reset(seed=seed)
    ys, us, times = [], [], []
    for _ in range(env.spec.max_episode_steps or 150):
        raise_if_interrupted()
        t0 = time.perf_counter()
        u = agent.act(obs)
        times.append(1e3 * (time.perf_counter() - t0))
        ys.append(np.asarray(obs, dtype=float))
        us.append(np.asarray(u, dtype=float))
        obs, _, terminated, truncated, _ = env.step(u)
        if terminated or truncated:
            break
    return {"y": ys, "u": us, "step_ms": times}


def _robust_in_c(folder: Path, episode: dict[str, Any], seed: int, tmp: Path) -> dict[str, Any]:
    """The exported robust step on the episode's measurements: timed from C (``example
    --steps --time``), and its inputs through ctypes against the Python agent's."""
    from controllers.export import ExportedController

    path = tmp / "measurements.txt"
    path.write_text("\n".join(" ".join(repr(float(v)) for v in y) for y in episode["y"]) + "\n")
    done = subprocess.run(
        [str(folder / "example"), "--time", str(STEP_REPEATS), "--steps", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    timing = done.stderr.split("\n", 1)[0].split()
    controller = ExportedController(folder)
    controller.reset(seed)
    diffs = []
    for y, u in zip(episode["y"], episode["u"], strict=True):
        u_c, _ = controller.step(y)
        diffs.append(float(np.max(np.abs(u_c - u))))
    return {
        "steps": len(diffs),
        "c_step_us_median": float(timing[1]) if timing[:1] == ["time_us"] else math.nan,
        "c_step_us_p95": float(timing[2]) if timing[:1] == ["time_us"] else math.nan,
        "python_step_ms": _stats(episode["step_ms"]),
        "input_diff_max": max(diffs, default=math.nan),
        "example_returncode": done.returncode,
    }


def time_export(
    config: Any, problems: Sequence[Any], python_plans: Sequence[np.ndarray] | None, seed: int = 0
) -> dict[str, Any]:
    """The exported controllers (see the module docstring); ``python_plans``: the Python
    loop's plans of ``problems`` from scratch (:func:`plan_agreement`), to compare with."""
    from controllers.export import export_controller, external_dependencies, run_make

    if shutil.which("make") is None:
        return {"available": False, "reason": "make not found"}
    out: dict[str, Any] = {"available": True, "reason": ""}
    with tempfile.TemporaryDirectory(prefix="lfm-export-bench-") as folder:
        tmp = Path(folder)
        try:
            for agent in ("scenario", "robust"):
                export_controller(config, agent, tmp / agent, config_name="benchmark")
                out[f"{agent}_build_s"] = run_make(tmp / agent)
            out["dependencies"] = external_dependencies(tmp / "robust")
        except (RuntimeError, OSError, ValueError) as exc:
            return {"available": False, "reason": f"{type(exc).__name__}: {exc}"}
        problem = config.make_problem()
        runs = _example_plans(tmp / "scenario", problems, problem, tmp)
        out["solve_us"] = _stats([r[1] for r in runs])
        out["n_failed"] = sum(r[2] != 0 for r in runs)
        if python_plans is not None:
            diffs = [
                float(np.max(np.abs(r[0] - u))) if r[0] is not None else math.inf
                for r, u in zip(runs, python_plans, strict=True)
            ]
            worst = int(np.argmax(diffs)) if diffs else 0
            out["plan_diff_max"] = max(diffs, default=math.nan)
            out["n_plan_above_tol"] = sum(d > EXPORT_PLAN_TOL for d in diffs)
            if diffs:
                out["plan_diff_worst"] = {
                    "seed": int(problems[worst][0]),
                    "step": int(problems[worst][1]),
                }
        episode = _robust_episode(config, seed)
        out["robust"] = _robust_in_c(tmp / "robust", episode, seed, tmp)
    out["n_problems"] = len(problems)
    return out


def time_compiled(
    config: Any,
    problems: Sequence[Any],
    anchors: Sequence[Any] = (),
    sweep_ns: Sequence[int] = AGREEMENT_NS,
    export: bool = True,
) -> dict[str, Any]:
    """The plan agreement at the main size and at ``sweep_ns`` (drawn around ``anchors``, two
    per seed), and the exports (:func:`time_export`)."""
    ns, n = np.shape(problems[0][3])[:2] if problems else (None, None)
    main = config.make_problem(n_scenarios=ns, horizon=n) if problems else None
    out: dict[str, Any] = {"agreement": []}
    plans = None
    if main is not None:
        row = plan_agreement(main, problems, "closed loop")
        plans = row.pop("_python_u")
        out["agreement"].append(row)
    chosen = anchors_per_seed(anchors, AGREEMENT_STEPS)
    for count in sweep_ns:
        if not chosen:
            break
        problem = config.make_problem(n_scenarios=int(count), horizon=n)
        draws = scenario_draws(problem, chosen, np.random.default_rng([7, int(count)]))
        row = plan_agreement(problem, draws, f"drawn around {len(chosen)} estimates")
        row.pop("_python_u")
        out["agreement"].append(row)
    if export and problems:
        out["export"] = time_export(config, problems, plans)
    return out


def compiled_lines(results: Mapping[str, Any]) -> list[str]:
    """The report's lines of this part: the plan agreement and the exports."""
    compiled = results.get("compiled")
    if not compiled:
        return []
    lines = ["Compiled loop (fast_c) against the Python loop, same QP solvers, from scratch"]
    for row in compiled.get("agreement", []):
        worst = row.get("worst") or {}
        lines.append(
            f"  N={row['horizon']}, Ns={row['n_scenarios']} ({row['label']}, "
            f"{row['n_problems']} problems, loop {row['loop']}): plans max abs difference "
            f"{row['max_abs_diff']:.2e} (seed {worst.get('seed')} step {worst.get('step')}, "
            f"slack {worst.get('slack', math.nan):.3g}), {row['n_above_tol']} above "
            f"{PLAN_TOL:g}; objectives within {row['rel_gap_abs_max']:.1e} relative; same "
            f"iterations and status on {row['n_same_iterations']}; median solve Python "
            f"{row['python_ms']['median']:.2f} ms, C {row['c_ms']['median']:.2f} ms"
        )
    export = compiled.get("export")
    if export is not None and export.get("available"):
        robust = export["robust"]
        lines.append(
            f"Exported controllers (make: scenario {export['scenario_build_s']:.1f} s, robust "
            f"{export['robust_build_s']:.1f} s): example solve from C, median "
            f"{export['solve_us']['median']:.0f} us, p95 {export['solve_us']['p95']:.0f} us "
            f"({export['n_problems']} problems, {export['n_failed']} not solved); robust whole "
            f"step from C median {robust['c_step_us_median']:.0f} us, p95 "
            f"{robust['c_step_us_p95']:.0f} us ({robust['steps']} steps; Python agent "
            f"{robust['python_step_ms']['median']:.2f} ms)"
        )
    elif export is not None:
        lines.append(f"Exported controllers: not run ({export.get('reason')})")
    return lines
