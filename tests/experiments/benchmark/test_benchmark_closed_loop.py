"""The closed-loop sweep (``experiments.benchmark.closed_loop``, ``lfm-benchmark --predictions``):
the scenario agent's whole steps at each horizon, prediction and iteration mode."""

from __future__ import annotations

import numpy as np

from controllers.config import FAST_MAX_HORIZON, AgentConfig
from experiments.benchmark.closed_loop import closed_loop_steps, format_closed_loop, iteration_modes


def test_every_step_is_timed_whole_and_a_refused_horizon_is_a_row_that_says_why():
    out = closed_loop_steps((3, FAST_MAX_HORIZON + 1), config="quick", seeds=(0, 1), steps=2)
    modes = iteration_modes()
    assert modes[0] == "converged"
    assert ("rti" in modes) == ("iterations" in AgentConfig.__dataclass_fields__)
    rows = out["results"]
    assert [(r["horizon"], r["prediction"], r["iterations"]) for r in rows] == [
        (n, p, m)
        for n in (3, FAST_MAX_HORIZON + 1)
        for p in ("open_loop", "feedback")
        for m in modes
    ]
    for row in rows:
        if row["horizon"] > FAST_MAX_HORIZON:  # beyond the compiled loop's bound: refused
            assert "agents.horizon" in row["refused"] and row["records"] == []
            continue
        recs = row["records"]
        assert row["refused"] == ""
        assert [(r["seed"], r["step"]) for r in recs] == [(0, 0), (0, 1), (1, 0), (1, 1)]
        for r in recs:  # the whole step holds the solve and the estimate
            assert np.isfinite(r["step_time_ms"]) and r["step_time_ms"] >= r["solve_time_ms"]
            assert r["step_time_ms"] >= r["estimate_time_ms"] > 0
        assert row["summary"]["n_steps"] == 4
        assert row["summary"]["failed"] == len(row["failures"])
    table = format_closed_loop(out)
    assert "refused by the config" in table and "failed steps" in table


def test_a_real_time_iteration_stopped_at_its_count_is_no_failed_step():
    from experiments.benchmark.closed_loop import _failed

    stopped = {"usable": True, "success": False}  # one SQP iteration, plan applied
    assert not _failed(stopped, "rti") and _failed(stopped, "converged")
    assert _failed({"usable": False, "success": False}, "rti")  # no usable plan (or raised)
    assert not _failed({"usable": True, "success": True}, "converged")
