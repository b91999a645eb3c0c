"""What the evaluation's tests share: the quick world with short episodes and small agents,
the sine track's table columns, a system with other constraint groups, and comparisons
of rows and trajectories."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from experiments.evaluation.run import TIMING_COLUMNS
from lfm_env.system import ControlSystem
from lfm_env.xp import xp

# The quick world with short episodes and small agents: about 0.3 s per episode.
TINY = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 5, "n_particles": 300},
}
TIMING_ARRAYS = ("solve_time", "step_time")
#: The sine track's row: its constraint groups (track, x, speed), each with its raw
#: violation steps and largest excess, then the steps beyond each of its tolerances
#: (1 and 5 cm for track and x, 5 cm/s for the speed).
SINE_TRACK_COLUMNS = (
    *("agent", "seed", "success", "steps", "time_to_goal", "cost"),
    *("track_violation_steps", "max_track_excess"),
    *("track_violation_steps_over_0.01", "track_violation_steps_over_0.05"),
    *("x_violation_steps", "max_x_excess"),
    *("x_violation_steps_over_0.01", "x_violation_steps_over_0.05"),
    *("speed_violation_steps", "max_speed_excess", "speed_violation_steps_over_0.05"),
    *("failure", "latent_rmse", "latent_coverage"),
    *("solve_time_median", "solve_time_p95", "solve_time_max"),
    *("step_time_median", "step_time_max", "deadline_misses", "solver_failures"),
    *("unconverged_solves", "fallback_steps"),
    *("deadline_plans", "deadline_shifted", "deadline_fallbacks"),
    *("filter_resets", "slack_total", "wall_time"),
    "error",
)
#: The columns of the group names alone (no system, so no tolerances).
RAW_GROUP_COLUMNS = tuple(c for c in SINE_TRACK_COLUMNS if "_over_" not in c)


def comparable(rows: list[dict]) -> list[dict]:
    """Rows without timing columns, NaN replaced so that equal rows compare equal."""
    return [
        {
            k: ("NaN" if isinstance(v, float) and math.isnan(v) else v)
            for k, v in r.items()
            if k not in TIMING_COLUMNS
        }
        for r in rows
    ]


def assert_same_trajectory(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if k not in TIMING_ARRAYS:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def write_tiny_yaml(tmp_path: Path, max_steps: int = 15) -> Path:
    cfg = {"env": {**TINY["env"], "max_steps": max_steps}, "agents": TINY["agents"]}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def episode_files(out: Path, suffix: str) -> list[Path]:
    return sorted((out / "episodes").glob(f"*.{suffix}"))


def corridor_system() -> ControlSystem:
    """A 1-D double integrator between a floor and a ceiling [m], with speed bounds [m/s]."""

    def rhs(x, u, w):
        _, v = xp.unstack(x)
        (a,) = xp.unstack(u)
        (force,) = xp.unstack(w)
        return xp.stack([v, a + force])

    def constraints(x):
        p, v = xp.unstack(x)
        return xp.stack([-0.2 - p, p - 0.2, v - 1.0, -1.0 - v])

    return ControlSystem(
        name="corridor_1d",
        state_names=("p [m]", "v [m/s]"),
        input_names=("a [m/s^2]",),
        rhs=rhs,
        input_lower=[-1.0],
        input_upper=[1.0],
        constraints=constraints,
        constraint_names=("floor [m]", "ceiling [m]", "v_max [m/s]", "v_min [m/s]"),
        constraint_groups={"corridor": (0, 1), "speed": (2, 3)},
        violation_tolerances={"corridor": (0.01, 0.1)},  # none for the speed
    )
