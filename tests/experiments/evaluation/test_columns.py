"""The episode table's columns (``experiments.evaluation.columns``): from the system's
constraint groups and tolerances."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.config import load_config
from experiments.evaluation.run import (
    HEAD_COLUMNS,
    TAIL_COLUMNS,
    group_columns,
    row_columns,
    tolerance_column,
    tolerance_columns,
    violation_counts,
)
from tests.experiments.evaluation.tiny_runs import (
    RAW_GROUP_COLUMNS,
    SINE_TRACK_COLUMNS,
    TINY,
    corridor_system,
)


def test_row_columns_follow_the_systems_constraint_groups():
    system = load_config(TINY).make_system()
    assert row_columns(system) == SINE_TRACK_COLUMNS
    assert row_columns(["track", "x", "speed"]) == RAW_GROUP_COLUMNS
    assert group_columns(system) == SINE_TRACK_COLUMNS[6:17]
    assert row_columns(corridor_system()) == (
        *HEAD_COLUMNS,
        *("corridor_violation_steps", "max_corridor_excess"),
        *("corridor_violation_steps_over_0.01", "corridor_violation_steps_over_0.1"),
        *("speed_violation_steps", "max_speed_excess"),
        *TAIL_COLUMNS,
    )
    assert tolerance_columns(system) == (
        ("track", 0.01, "track_violation_steps_over_0.01"),
        ("track", 0.05, "track_violation_steps_over_0.05"),
        ("x", 0.01, "x_violation_steps_over_0.01"),
        ("x", 0.05, "x_violation_steps_over_0.05"),
        ("speed", 0.05, "speed_violation_steps_over_0.05"),
    )
    assert tolerance_column("track", 0.010) == "track_violation_steps_over_0.01"
    assert row_columns(()) == HEAD_COLUMNS + TAIL_COLUMNS
    with pytest.raises(ValueError, match="constraint-group names"):
        row_columns("track")


def test_violation_counts_of_a_made_up_trajectory():
    """Steps count beyond a tolerance only when the excess is strictly above it."""
    system = corridor_system()
    trajectory = {
        "corridor_excess": np.array([0.0, 0.004, 0.01, 0.02, 0.1, 0.3, 0.0]),
        "speed_excess": np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0]),
    }
    assert violation_counts(trajectory, system) == {
        "corridor_violation_steps": 5,
        "speed_violation_steps": 1,
        "corridor_violation_steps_over_0.01": 3,  # 0.01 itself is not beyond 0.01
        "corridor_violation_steps_over_0.1": 1,
    }
    # A group the trajectory does not hold is left out, its tolerances too.
    assert violation_counts({"speed_excess": np.zeros(3)}, system) == {"speed_violation_steps": 0}
