"""A risk sweep's table and figure (``experiments.report.sweep_summary``)."""

from __future__ import annotations

from experiments.report import sweep_summary
from experiments.report.stats import Metric
from tests.experiments.evaluation.tiny_runs import corridor_system


def test_sweep_metrics_fall_back_to_raw_counts_without_tolerances():
    system = corridor_system()  # tolerances on the corridor, none for the speed
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
