"""The figures: one episode's (states, inputs, latent force, constraint excess), the
summaries over seeds, the feasible region and the scenario fan, and the replays. They read
saved results; they never run episodes. ``from experiments import plots`` gives every one of
them as ``plots.X``."""

from experiments.plots.episode import (
    constraint_excess_figure,
    episode_figures,
    group_excess_of,
    inputs_figure,
    latent_force_figure,
    paths_figure,
    states_figure,
    trajectory_figure,
)
from experiments.plots.feasible_region import constraint_dependencies, constraints_on, state_bounds
from experiments.plots.replay import (
    annotate_frame,
    make_render_env,
    replay_frames,
    stack_frames,
    world_draws,
    write_gif,
)
from experiments.plots.scenario_fan import plan_panel_frames, saved_fans, scenario_fan_figure
from experiments.plots.style import (
    agent_colour,
    force_unit,
    group_unit,
    new_figure,
    sample_times,
    save_figure,
    unit_of,
)
from experiments.plots.summary import (
    coverage_figure,
    distribution_axes,
    metric_distributions_figure,
    pareto_figure,
    solve_time_figure,
)

# Every figure of the experiment layer under one name (``plots.X``), wherever it lives.
__all__ = [
    "agent_colour",
    "annotate_frame",
    "coverage_figure",
    "constraint_dependencies",
    "constraint_excess_figure",
    "constraints_on",
    "distribution_axes",
    "episode_figures",
    "force_unit",
    "group_excess_of",
    "group_unit",
    "inputs_figure",
    "latent_force_figure",
    "make_render_env",
    "metric_distributions_figure",
    "new_figure",
    "pareto_figure",
    "paths_figure",
    "plan_panel_frames",
    "replay_frames",
    "world_draws",
    "sample_times",
    "save_figure",
    "saved_fans",
    "scenario_fan_figure",
    "solve_time_figure",
    "stack_frames",
    "state_bounds",
    "states_figure",
    "trajectory_figure",
    "unit_of",
    "write_gif",
]
