"""Figures over agents and seeds (``experiments.plots.summary``)."""

from __future__ import annotations

import numpy as np

from experiments import plots
from tests.experiments.plots.point_mass import SYSTEM, rendered


def test_calibration_figure_sets_estimators_side_by_side():
    quantities = [*SYSTEM.state_names, *(f"latent force {w}" for w in SYSTEM.force_names)]
    rng = np.random.default_rng(0)
    coverage = np.sort(rng.uniform(0.6, 1.0, size=(2, len(quantities), 3)), axis=-1)[..., [1, 0, 2]]
    rmse = np.sort(rng.uniform(0.1, 1.0, size=(2, len(quantities), 3)), axis=-1)[..., [1, 0, 2]]
    agents = {"PF (bootstrap)": "tab:orange", "robust (rbpf)": "tab:red"}
    fig = plots.coverage_figure(quantities, agents, coverage, rmse)
    axes = np.array(fig.axes).reshape(2, len(quantities))
    for q, name in enumerate(quantities):
        top, bottom = axes[:, q]
        np.testing.assert_allclose([b.get_height() for b in top.patches], coverage[:, q, 0])
        np.testing.assert_allclose([b.get_height() for b in bottom.patches], rmse[:, q, 0])
        assert top.get_title() == name.split(" [")[0]
        assert bottom.get_ylabel() == f"RMSE [{plots.unit_of(name)}]"
        # The calibrated level is drawn in every coverage panel.
        assert any(np.allclose(line.get_ydata(), 0.9545) for line in top.lines)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == list(agents)
    assert rendered(fig).std() > 10


def test_pareto_figure_leaves_out_undefined_points():
    fig = plots.pareto_figure(
        [("a", [0.1, 0.0, 0.2], [-1.0, -2.0, 0.0]), ("b", [np.nan] * 3, [1.0, 0.0, 2.0])],
        baseline="pf",
        xlabel="x",
        ylabel="y",
    )
    assert fig.axes[0].get_legend_handles_labels()[1] == ["pf (baseline)", "a"]
