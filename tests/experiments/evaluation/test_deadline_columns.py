"""episodes.csv counts the steps whose compute (the agent's act) exceeded the control period,
and the steps agents.deadline stopped, by what was applied."""

from __future__ import annotations

import time

import numpy as np

from controllers.config import load_config
from experiments.evaluation import run_episode
from experiments.evaluation.columns import TIMING_COLUMNS, row_columns

SLOW_STEPS = (1, 3)  # the steps whose act() outlasts the control period


class SlowSometimes:
    """Brakes; thinks longer than the control period at SLOW_STEPS and says what a deadline
    made it apply at the others (as the MPC agents' last_info does)."""

    def __init__(self, config):
        self.dt = config.make_model().dt
        self.k = 0
        self.last_info = {}

    def reset(self, seed=None):
        self.k = 0

    def act(self, obs):
        if self.k in SLOW_STEPS:
            time.sleep(self.dt + 0.02)
        stop = ("plan", "previous_plan", "fallback", "")[self.k % 4]
        self.last_info = {"deadline_stop": stop, "solve_time": 1e-3}
        self.k += 1
        return np.array([-1.0, 0.0])


def test_deadline_misses_and_stops_are_counted():
    cfg = load_config("quick", ["env.max_steps=8"])
    row, traj = run_episode(SlowSometimes, cfg, seed=0)
    assert row["steps"] == 8
    assert row["deadline_misses"] >= len(SLOW_STEPS)  # (sleep lasts at least that long)
    assert np.all(traj["step_time"][list(SLOW_STEPS)] > cfg.make_model().dt)
    assert row["step_time_max"] > cfg.make_model().dt
    assert (row["deadline_plans"], row["deadline_shifted"], row["deadline_fallbacks"]) == (2, 2, 2)
    assert list(traj["deadline_stop"][:4]) == ["plan", "previous_plan", "fallback", ""]


def test_the_columns_are_in_the_table_and_timing_ones_are_marked():
    columns = row_columns(load_config("quick").make_system())
    for c in ("step_time_median", "step_time_max", "deadline_misses", "deadline_plans"):
        assert c in columns
    assert {"step_time_median", "step_time_max", "deadline_misses"} <= set(TIMING_COLUMNS)
