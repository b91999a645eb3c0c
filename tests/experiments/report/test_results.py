"""A results folder read back (``experiments.report.results``)."""

from __future__ import annotations

import pytest

from experiments.evaluation import run as evaluation
from experiments.evaluation.run import evaluate
from experiments.report.write import (
    Results,
    load_results,
)
from tests.experiments.evaluation.live_runs import SMALL
from tests.experiments.saved_results import AGENTS


def test_one_load_results_for_every_reader(results_dir):
    from experiments import sweep
    from experiments.report import results
    from experiments.report import write as report

    assert report.load_results is results.load_results is load_results
    for module in (evaluation, sweep):
        assert not hasattr(module, "load_results")
    loaded = load_results(results_dir)
    assert isinstance(loaded, Results) and loaded.directory == results_dir
    assert loaded.system.name == "sine_track" and loaded.agents == AGENTS
    saved = evaluation.saved_rows(results_dir)  # the storage layer's episode records
    table = sorted(loaded.rows, key=lambda r: (r["agent"], r["seed"]))
    assert [(r["agent"], r["seed"]) for r in table] == [(r["agent"], r["seed"]) for r in saved]
    for a, b in zip(table, saved, strict=True):
        for column in ("success", "steps", "cost", "max_track_excess", "latent_rmse"):
            assert a[column] == pytest.approx(float(b[column]), nan_ok=True), column


def test_registered_agents_come_in_their_order_then_the_others_sorted(tmp_path):
    names = ["zeta", "rl", "oracle", "alpha", "nominal", "pf"]
    rows = [{"agent": n, "seed": 0, "error": ""} for n in names]
    results = Results(directory=tmp_path, rows=rows, config=None)
    assert results.agents == ["nominal", "pf", "oracle", "rl", "alpha", "zeta"]


def test_the_report_names_a_truncated_episode_file_instead_of_a_bare_zip_error(tmp_path, capsys):
    """The report leaves a truncated episode file out, naming it (it failed as a whole)."""
    from experiments.cli import report_main

    out = tmp_path / "results"
    evaluate(["nominal"], [0, 1], SMALL, out=out, progress=False)
    damaged = out / "episodes" / "nominal__seed1.npz"
    damaged.write_bytes(damaged.read_bytes()[:200])
    code = report_main([str(out)])
    err = capsys.readouterr().err
    assert code == 0
    assert err.count("nominal__seed1.npz") == 1 and "Traceback" not in err
    assert "left out" in err
