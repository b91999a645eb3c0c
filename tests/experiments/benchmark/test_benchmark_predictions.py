"""The benchmark's prediction sweep (``experiments.benchmark.predictions``, ``--predictions``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.benchmark.predictions import format_predictions, sweep_predictions
from experiments.cli.benchmark import benchmark_main


def test_the_sweep_solves_the_same_problems_in_both_predictions() -> None:
    out = sweep_predictions((3, 5), config="quick", seeds=(0,), steps_per_seed=2, first_step=1)
    rows = out["results"]
    assert [(r["horizon"], r["prediction"]) for r in rows] == [
        (3, "open_loop"),
        (3, "feedback"),
        (5, "open_loop"),
        (5, "feedback"),
    ]
    for row in rows:
        recs = row["records"]
        # the same problems in both predictions: the same draws per N
        twin = next(r for r in rows if r["horizon"] == row["horizon"] and r is not row)
        assert [r["step"] for r in twin["records"]] == [r["step"] for r in recs]
        assert [(r["seed"], r["step"]) for r in recs] == [(0, 1), (0, 2)]
        assert row["summary"]["n_problems"] == 2
        assert row["summary"]["failed"] == len(row["failures"])
        assert [(f["seed"], f["step"]) for f in row["failures"]] == [
            (r["seed"], r["step"]) for r in recs if not r["success"]
        ]
        assert all(np.isfinite(r["objective"]) and r["slack"] >= 0 for r in recs)
    table = format_predictions(out)
    assert table.count("open_loop") == 2 and table.count("feedback") == 2
    assert "failed solves (not converged): " in table


def test_the_command_runs_the_sweep_alone_and_refuses_bad_horizons(tmp_path, capsys) -> None:
    out = tmp_path / "p.json"
    argv = ["--config", "quick", "--seeds", "0", "--horizon-steps", "1", "--no-progress"]
    assert benchmark_main([*argv, "--predictions-replay", "3", "--out", str(out)]) == 0
    saved = json.loads(out.read_text())
    assert [r["prediction"] for r in saved["results"]] == ["open_loop", "feedback"]
    assert "prediction sweep" in out.with_suffix(".md").read_text()
    assert benchmark_main([*argv, "--predictions", "3", "--out", str(out)]) == 0
    saved = json.loads(out.read_text())
    assert {r["prediction"] for r in saved["results"]} == {"open_loop", "feedback"}
    assert "closed-loop steps" in out.with_suffix(".md").read_text()
    with pytest.raises(SystemExit) as exc:
        benchmark_main([*argv, "--predictions", "0,7", "--out", str(out)])
    assert exc.value.code == 2
    assert "predictions='0,7'" in capsys.readouterr().err
