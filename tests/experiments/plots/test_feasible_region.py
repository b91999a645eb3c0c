"""The feasible region read from a system's constraints (``experiments.plots.feasible_region``),
and the units of its groups, on a point mass defined in the tests."""

from __future__ import annotations

import pytest

from experiments import plots
from tests.experiments.plots.point_mass import GOAL, SPEED_MAX, SYSTEM, WALL_Y


def test_constraint_structure_and_units_come_from_the_system():
    deps = plots.constraint_dependencies(SYSTEM)
    assert deps == (frozenset({1}), frozenset({0, 1}), frozenset({2}))
    assert plots.constraints_on(SYSTEM, (0, 1)) == (0, 1)
    assert plots.constraints_on(SYSTEM, (2,)) == (2,)
    assert plots.group_unit(SYSTEM, "keep_out") == "m"
    assert plots.group_unit(SYSTEM, "speed") == "m/s"
    assert plots.force_unit(SYSTEM) == "m/s^2, N"
    with pytest.raises(ValueError, match="'track'.*keep_out"):
        plots.group_unit(SYSTEM, "track")


def test_state_bounds_are_the_zeros_of_constraints_on_that_state_alone():
    assert plots.state_bounds(SYSTEM, 2, -5.0, 5.0) == pytest.approx([SPEED_MAX], abs=1e-3)
    assert plots.state_bounds(SYSTEM, 1, -5.0, 5.0, GOAL) == pytest.approx([WALL_Y], abs=1e-3)
    # The obstacle depends on both positions: it bounds neither alone; v_y has no bound.
    assert plots.state_bounds(SYSTEM, 0, -10.0, 10.0) == []
    assert plots.state_bounds(SYSTEM, 3, -10.0, 10.0) == []
