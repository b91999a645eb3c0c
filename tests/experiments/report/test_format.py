"""How the report writes numbers and agents (``experiments.report.format``)."""

from __future__ import annotations

import math

from experiments.report.format import agent_label, fmt, fmt_estimate, long_label
from experiments.report.stats import Estimate


def test_numbers_keep_three_significant_digits_and_separate_thousands():
    assert fmt(0.0012345) == "0.00123" and fmt(12.345) == "12.3" and fmt(999.4) == "999"
    assert fmt(270487.2) == "270,487" and fmt(-1234.5) == "-1,234"
    assert fmt(math.nan) == "n/a" and fmt(None) == "n/a" and fmt(math.inf) == "n/a"
    assert fmt(0.123456, digits=5) == "0.12346"


def test_an_estimate_is_its_mean_and_interval_with_the_count_when_fewer():
    e = Estimate(mean=9.88, low=9.64, high=10.1, n=5)
    assert fmt_estimate(e) == "9.88 [9.64, 10.1]"
    assert fmt_estimate(e, n_total=6) == "9.88 [9.64, 10.1] (n=5)"
    assert fmt_estimate(e, n_total=5) == "9.88 [9.64, 10.1]"
    assert fmt_estimate(Estimate(mean=math.nan, low=math.nan, high=math.nan, n=0)) == "n/a"


def test_registered_agents_get_their_labels_and_others_their_name():
    assert agent_label("oracle") == "oracle (reads the truth)"
    assert agent_label("rl") == "RL baseline"
    assert agent_label("my_agent") == "my_agent"
    assert agent_label("scenario_particles", wrap=True) == "scenario MPC,\nparticle starts"
    assert long_label("scenario") == "PF + scenario MPC (paper)"
    assert long_label("my_agent") == "my_agent"
