"""A risk sweep's table and figure (``experiments.report.sweep_summary``)."""

from __future__ import annotations

from experiments.report import sweep_summary
from experiments.report.stats import Metric
from lfm_env.system import ControlSystem, xp


def test_sweep_metrics_fall_back_to_raw_counts_without_tolerances():
    def rhs(x, u, w):
        return xp.stack([xp.unstack(x)[1], xp.unstack(u)[0] + xp.unstack(w)[0]])

    def constraints(x):
        p, v = xp.unstack(x)
        return xp.stack([p - 0.2, v - 1.0])

    system = ControlSystem(
        name="corridor_1d",
        state_names=("p [m]", "v [m/s]"),
        input_names=("a [m/s^2]",),
        rhs=rhs,
        input_lower=[-1.0],
        input_upper=[1.0],
        constraints=constraints,
        constraint_names=("ceiling [m]", "v_max [m/s]"),
        constraint_groups={"corridor": (0,), "speed": (1,)},
        violation_tolerances={"corridor": (0.01, 0.1)},  # none for the speed
    )
    metrics = sweep_summary.sweep_metrics(system)
    columns = [(m.column, m.zero_count) for m in metrics]
    assert columns == [
        ("success", False),
        ("corridor_violation_steps_over_0.01", False),
        ("corridor_violation_steps_over_0.1", False),
        ("corridor_violation_steps_over_0.01", True),
        ("corridor_violation_steps_over_0.1", True),
        ("speed_violation_steps", False),
        ("speed_violation_steps", True),
        ("time_to_goal", False),
    ]
    assert isinstance(metrics[0], Metric)
