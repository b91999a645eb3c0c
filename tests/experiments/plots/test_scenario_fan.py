"""The plan's scenario fan (``experiments.plots.scenario_fan``)."""

from __future__ import annotations

import numpy as np

from experiments import plots
from experiments.plots import scenario_fan
from tests.experiments.plots.point_mass import DT, GOAL, SYSTEM, synthetic_episode


def fanned_episode(T: int = 30, S: int = 6, N: int = 5) -> dict[str, np.ndarray]:
    """The synthetic episode with a fan of ``S`` straight predictions of ``N`` steps per step:
    scenario ``s`` drifts by ``0.002 s`` m per step in y (a known, small spread)."""
    traj = synthetic_episode(T)
    x = traj["true_state"]
    steps = np.arange(N + 1)[:, None] * (x[1] - x[0])  # (N+1, nx) straight ahead
    fans = x[:T, None, None, :] + steps[None, None]  # (T, 1, N+1, nx)
    fans = np.repeat(fans, S, axis=1)
    fans[..., 1] += 0.002 * np.arange(S)[None, :, None] * np.arange(N + 1)[None, None, :]
    traj["predicted_scenarios"] = fans.astype(np.float32)
    traj["predicted"] = fans[:, 0]
    return traj


def fan_collections(ax) -> list:
    from matplotlib.collections import LineCollection

    return [c for c in ax.collections if isinstance(c, LineCollection)]


def test_scenario_fan_figure_draws_every_saved_scenario_at_four_steps():
    traj = fanned_episode()
    traj["predicted_scenarios"][10, 4:] = np.nan  # a step with fewer scenarios (padding)
    fig = plots.scenario_fan_figure(SYSTEM, traj, DT, steps=[0, 10, 20, 29], goal_state=GOAL)
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.get_title().startswith("t = ")]
    assert len(panels) == 4
    for ax, k, n in zip(panels, (0, 10, 20, 29), (6, 4, 6, 6), strict=True):
        assert f"(step {k})" in ax.get_title()
        (fan,) = fan_collections(ax)  # one collection: one line per saved scenario
        assert len(fan.get_segments()) == n
        np.testing.assert_allclose(fan.get_segments()[0][0], traj["true_state"][k, :2], atol=1e-5)
        assert ax.get_aspect() == 1.0  # lengths to scale
    # The spread at the horizon's end, in the plane's unit: (S - 1) * 0.002 * N.
    assert "0.05 m" in panels[0].get_title()
    # The fan is far narrower than the panel: an inset magnifies its end.
    insets = [a for ax in panels for a in ax.child_axes if a.get_title().startswith("its end")]
    assert len(insets) == 4 and all(len(fan_collections(ax)) == 1 for ax in insets)


def test_scenario_fan_figure_default_steps_and_older_files():
    traj = fanned_episode(T=30)
    assert scenario_fan.fan_steps(traj["predicted_scenarios"]) == [0, 10, 19, 29]
    del traj["predicted_scenarios"]  # a file of before the saved fans: one scenario each
    fig = plots.scenario_fan_figure(SYSTEM, traj, DT, goal_state=GOAL)
    panels = [ax for ax in fig.axes if ax.get_title().startswith("t = ")]
    assert [len(fan_collections(ax)[0].get_segments()) for ax in panels] == [1, 1, 1, 1]
    assert "only the first scenario" in fig._suptitle.get_text()
    traj["predicted"] = np.full_like(traj["predicted"], np.nan)  # an agent without a plan
    assert plots.scenario_fan_figure(SYSTEM, traj, DT) is None


def test_plan_panel_frames_show_the_estimate_and_the_fan():
    traj = fanned_episode(T=12)
    frames = plots.plan_panel_frames(SYSTEM, traj, size=(320, 160), goal_state=GOAL)
    assert len(frames) == 13 and frames[0].shape == (160, 320, 3)
    for frame in frames[:-1]:
        f = frame.astype(int)
        red = (f[..., 0] > 180) & (f[..., 1] < 90) & (f[..., 2] < 90)
        navy = (f[..., 0] < 60) & (f[..., 1] < 60) & (f[..., 2] > 90)
        assert red.sum() > 5 and navy.sum() > 5
    last = frames[-1].astype(int)  # after the final step: no estimate, no plan
    assert not ((last[..., 0] > 180) & (last[..., 1] < 90) & (last[..., 2] < 90)).any()
    stacked = plots.stack_frames([np.zeros((50, 300, 3), np.uint8)] * 13, frames)
    assert stacked[0].shape == (210, 320, 3) and (stacked[0][:50, 300:] == 255).all()
