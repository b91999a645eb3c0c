"""An honest report (issue 35, items 6 and "Intervals from SciPy"): SciPy's BCa bootstrap,
paired where paired, named in the report; a caveat on intervals over few seeds; the
settings of the agents present only; a sweep of another config refused or listed."""

from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest
from scipy import stats as scipy_stats

from experiments.report.stats import (
    BOOTSTRAP_RESAMPLES,
    FEW_SEEDS,
    _rng_argument,
    bootstrap_ci,
    few_seeds_caveat,
    paired_ci,
    pooled_ratio_ci,
)
from experiments.report.sweep_section import config_differences
from experiments.report.write import write_report
from tests.experiments.saved_results import as_if_run_with, rewrite_episodes


def scipy_bca(*data, statistic, paired=False):
    ci = scipy_stats.bootstrap(
        data, statistic, n_resamples=BOOTSTRAP_RESAMPLES, method="BCa", paired=paired,
        vectorized=True, **_rng_argument(0),
    ).confidence_interval  # fmt: skip
    return float(ci.low), float(ci.high)


def test_the_intervals_are_scipys_bca():
    x = np.random.default_rng(1).gamma(2.0, 1.5, size=30)
    est = bootstrap_ci(x)
    assert est.method == "BCa"
    assert (est.low, est.high) == pytest.approx(scipy_bca(x, statistic=np.mean))
    y = x + np.random.default_rng(2).normal(size=30)
    d = paired_ci(y, x)
    low, high = scipy_bca(y, x, statistic=lambda a, b, axis: np.mean(a - b, axis), paired=True)
    assert d.mean == pytest.approx(np.mean(y - x)) and (d.low, d.high) == pytest.approx((low, high))
    assert d.method == "BCa"
    num, den = np.arange(1.0, 11.0), np.full(10, 20.0)
    r = pooled_ratio_ci(num, den)
    low, high = scipy_bca(
        num, den, statistic=lambda a, b, axis: a.sum(axis) / b.sum(axis), paired=True
    )
    assert (r.mean, r.low, r.high, r.method) == pytest.approx((55 / 200, low, high, "BCa"))


def test_degenerate_samples_get_the_percentile_or_a_zero_width_interval():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no DegenerateDataWarning escapes
        same = bootstrap_ci([1.0] * 12)
        shifted = paired_ci([1.0, 2.0, 3.0], [0.0, 1.0, 2.0])  # every difference is 1
    assert (same.mean, same.low, same.high, same.method) == (1.0, 1.0, 1.0, "exact")
    assert (shifted.mean, shifted.low, shifted.high) == (1.0, 1.0, 1.0)
    assert shifted.method == "percentile"  # BCa is undefined: every resample is the mean
    assert bootstrap_ci([3.0]).method == "exact"
    with pytest.raises(ValueError, match="paired samples of different lengths"):
        paired_ci([1.0, 2.0], [1.0])


def test_the_report_names_the_method_and_warns_about_few_seeds(report_path):
    md = report_path.read_text()
    assert (
        "95% BCa bootstrap interval (bias-corrected and accelerated, `scipy.stats.bootstrap`" in md
    )
    assert "95% paired BCa bootstrap interval over seeds" in md
    caveat = few_seeds_caveat(3)
    assert caveat.startswith("Only 3 seeds: with fewer than 20") and f"**{caveat}**" in md
    assert few_seeds_caveat(FEW_SEEDS) == ""


def _keep_agents(folder, agents):
    rewrite_episodes(folder, {a: a for a in agents})


def test_the_settings_paragraph_describes_only_the_agents_present(results_copy):
    """Issue 35, item 6: a report of agents that are not MPC stated horizon, scenarios,
    particles and "agents know the hidden force's hyperparameters"."""
    _keep_agents(results_copy, {"nominal", "oracle"})
    md = write_report(results_copy, gif=False).read_text()
    intro = md.split("## Latent force")[0]
    assert "horizon = 5" in intro and "solver = fast_c" in intro
    assert "n_scenarios" not in intro and "n_particles" not in intro
    model = md.split("## Latent force: hidden truth and the agents' model")[1].split("\n## ")[0]
    assert "No agent here models it" in model and "know the hidden force" not in model


def test_the_full_settings_and_the_agents_that_model_the_force(report_path):
    md = report_path.read_text()
    intro = md.split("## Latent force")[0]
    assert "horizon = 5, n_scenarios = 5, n_particles = 300, solver = fast_c" in intro
    model = md.split("## Latent force: hidden truth and the agents' model")[1].split("\n## ")[0]
    assert "The agents that model the force (`pf`, `scenario`) know the hidden force's" in model


def test_the_settings_name_a_feedback_prediction_and_only_that(results_copy, report_path):
    # The open-loop default is not mentioned (the paper's formulation); feedback is.
    assert "prediction" not in report_path.read_text().split("## Latent force")[0]
    as_if_run_with(results_copy, lambda data: data["agents"].update(prediction="feedback"))
    md = write_report(results_copy, gif=False).read_text()
    assert "solver = fast_c, prediction = feedback" in md.split("## Latent force")[0]


def test_config_differences_list_every_field():
    ours = {"env_id": "a", "env": {"dt": 0.2, "lf": {"v": 1}}, "agents": {"n": 5}}
    theirs = {"env_id": "a", "env": {"dt": 0.1, "lf": {"v": 1, "w": 2}}, "agents": {"n": 5}}
    assert config_differences(ours, theirs) == [("env.dt", 0.2, 0.1), ("env.lf.w", "(none)", 2)]


def test_a_sweep_of_another_config_is_refused_or_listed(results_copy, tmp_path):
    """Issue 35, item 6: lfm-report --sweep embedded a sweep run on another config."""
    from experiments.sweep import run_sweep

    sweep_dir = tmp_path / "sweep"
    run_sweep("nominal", "agents.horizon=4", [0], config={"env": {"max_steps": 5},
              "agents": {"n_particles": 300}}, out=sweep_dir, baseline="nominal",
              progress=False)  # fmt: skip
    with pytest.raises(ValueError, match=r"ran on another config than .*env.max_steps \(20 here, "
                       r"5 there\).*--allow-other-config"):  # fmt: skip
        write_report(results_copy, gif=False, sweep_dir=sweep_dir)
    md = write_report(
        results_copy, gif=False, sweep_dir=sweep_dir, allow_other_config=True
    ).read_text()
    section = md.split("## Risk trade-off")[1]
    assert "**The sweep ran on another config than this report**" in section
    assert "| `env.max_steps` | 20 | 5 |" in section
    assert "only 1 seeds" in section or "Only 1 seed:" in section
    shutil.rmtree(sweep_dir)
