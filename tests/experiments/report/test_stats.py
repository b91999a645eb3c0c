"""The report's statistics (``experiments.report.stats``): bootstrap intervals, paired
differences, pooled ratios and the estimators' coverage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from experiments.report.format import fmt_estimate
from experiments.report.write import (
    Results,
    bootstrap_ci,
    estimator_coverage,
    load_results,
    paired_differences,
    pooled_ratio_ci,
    write_report,
)
from lfm_env.worlds.registry import load_env_config
from tests.experiments.saved_results import (
    as_if_run_with,
    csv_values,
    resave_trajectory,
    table_line,
)


def test_bootstrap_ci_contains_mean_and_is_deterministic():
    values = np.random.default_rng(1).gamma(2.0, 1.5, size=25)
    est = bootstrap_ci(values)
    assert est.low <= est.mean <= est.high
    assert est.mean == pytest.approx(values.mean())
    assert est.n == 25 and est.high > est.low
    assert bootstrap_ci(values) == est  # same seed, same interval
    assert bootstrap_ci(list(values) + [np.nan]) == est  # NaN is left out
    wider = bootstrap_ci(values, level=0.99)
    assert wider.low <= est.low and wider.high >= est.high
    one = bootstrap_ci([3.0])
    assert (one.mean, one.low, one.high, one.n) == (3.0, 3.0, 3.0, 1)
    assert np.isnan(bootstrap_ci([np.nan]).mean) and bootstrap_ci([]).n == 0


def _row(agent: str, seed: int, cost: float, error: str = "") -> dict:
    return {"agent": agent, "seed": seed, "cost": cost, "time_to_goal": np.nan, "error": error}


def test_paired_differences_use_matching_seeds_only():
    rows = [
        _row("scenario", 0, 10.0),
        _row("scenario", 1, 20.0),
        _row("scenario", 2, 30.0),
        _row("scenario", 3, 40.0, error="RuntimeError: x"),  # errors never pair
        _row("pf", 1, 25.0),
        _row("pf", 2, 29.0),
        _row("pf", 3, 50.0),
        _row("pf", 4, 70.0),  # no scenario episode on seed 4
        _row("pf", 5, np.nan),
    ]
    results = Results(Path("."), rows, load_env_config(None))
    d = paired_differences(results, "cost", "pf")
    assert d.seeds == (1, 2)
    assert d.differences == (5.0, -1.0)
    assert d.estimate.mean == pytest.approx(2.0) and d.estimate.n == 2
    assert (d.agent_lower, d.reference_lower, d.ties) == (1, 1, 0)
    none = paired_differences(results, "time_to_goal", "pf")
    assert none.seeds == () and np.isnan(none.estimate.mean)


def test_pooled_ratio_ci():
    est = pooled_ratio_ci([1.0, 2.0, 6.0], [2.0, 4.0, 6.0])
    assert est.mean == pytest.approx(9.0 / 12.0) and est.n == 3
    assert 0.5 <= est.low <= est.mean <= est.high <= 1.0  # between the episodes' own ratios
    assert pooled_ratio_ci([1.0, 2.0, 6.0], [2.0, 4.0, 6.0]) == est  # seeded
    root = pooled_ratio_ci([1.0, 2.0, 6.0], [2.0, 4.0, 6.0], root=True)
    assert (root.mean, root.low, root.high) == pytest.approx(
        (np.sqrt(est.mean), np.sqrt(est.low), np.sqrt(est.high))
    )
    assert pooled_ratio_ci([3.0, 5.0], [0.0, 5.0]).n == 1  # episodes without steps: out
    assert np.isnan(pooled_ratio_ci([], []).mean)


def test_calibration_pools_the_evaluations_per_episode_metrics(results_dir, report_path):
    """The pooled latent-force coverage and RMSE agree with the rows' per-episode values
    weighted by their steps (computed by the evaluation, another code path)."""
    results = load_results(results_dir)
    cals = {c.agent: c for c in estimator_coverage(results)}
    assert list(cals) == ["pf", "scenario"]  # the nominal MPC and the oracle have no filter
    for agent, cal in cals.items():
        steps = csv_values(results_dir, agent, "steps")
        coverage = csv_values(results_dir, agent, "latent_coverage")
        rmse = csv_values(results_dir, agent, "latent_rmse")
        assert cal.quantities[-1] == "latent force w [m/s^2]"
        assert cal.quantities[:4] == results.system.state_names
        assert cal.coverage[-1].mean == pytest.approx(np.sum(coverage * steps) / steps.sum())
        assert cal.rmse[-1].mean == pytest.approx(np.sqrt(np.sum(rmse**2 * steps) / steps.sum()))
        assert cal.steps == steps.sum() and cal.episodes == 3
        assert (cal.estimator, cal.estimator_source) == ("bootstrap", "recorded")
        for e in (*cal.coverage, *cal.rmse):
            assert e.low <= e.mean <= e.high
    md = report_path.read_text()
    assert "| quantity | PF + CE MPC: `bootstrap` | scenario MPC (paper): `bootstrap` |" in md
    row = table_line(md, "2-sigma coverage, latent force w", "## Estimator coverage")
    assert row == [
        fmt_estimate(cals["pf"].coverage[-1]),
        fmt_estimate(cals["scenario"].coverage[-1]),
    ]
    assert table_line(md, "RMSE, p_x [m]", "## Estimator coverage")[0] == fmt_estimate(
        cals["pf"].rmse[0]
    )
    assert (report_path.parent / "figures" / "estimator_coverage.png").is_file()


def test_calibration_names_the_configs_estimator_when_none_was_recorded(results_copy):
    for path in (results_copy / "episodes").glob("pf__seed*.npz"):
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files if k != "estimator"}
        resave_trajectory(path, arrays)
    # as if the run had used it
    as_if_run_with(results_copy, lambda config: config["agents"].update(estimator="ukf"))
    cals = {c.agent: c for c in estimator_coverage(load_results(results_copy))}
    assert (cals["pf"].estimator, cals["pf"].estimator_source) == ("ukf", "config.yaml")
    assert (cals["scenario"].estimator, cals["scenario"].estimator_source) == (
        "bootstrap",
        "recorded",
    )
    md = write_report(results_copy, gif=False).read_text()
    assert "PF + CE MPC: `ukf`" in md and "The estimator of PF + CE MPC is the" in md
