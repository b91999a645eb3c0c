"""The report's figures (drawn by :mod:`experiments.plots`): files in ``figures/``, captions."""

from __future__ import annotations

import math

import numpy as np

from experiments import plots
from experiments.report.document import Document
from experiments.report.format import agent_label
from experiments.report.results import Results, load_trajectory
from experiments.report.stats import REFERENCE_AGENT


def _main_agent(results: Results) -> str:
    """The agent of the episode figures: the paper's, else the first one."""
    return REFERENCE_AGENT if REFERENCE_AGENT in results.agents else results.agents[0]


def check_figure_seed(results: Results, figure_seed: int | None) -> None:
    """Raise ``ValueError`` if ``figure_seed`` has no saved trajectory to draw."""
    if figure_seed is None:
        return
    agent = _main_agent(results)
    path = results.trajectory_path(agent, figure_seed)
    if not path.is_file():
        raise ValueError(
            f"no saved trajectory of agent {agent!r} for seed {figure_seed}: {path} does not exist"
        )


def _steps(row: dict) -> float:
    """The ``steps`` of an episode row as a number (NaN when missing or unreadable)."""
    try:
        return float(row.get("steps", math.nan))
    except (TypeError, ValueError):
        return math.nan


def _default_figure_seed(results: Results, agent: str) -> tuple[int | None, str]:
    """The smallest seed with a saved trajectory of an error-free ``agent`` episode of at least one
    step (else any with a trajectory), and a sentence saying why.
    """
    rows = results.rows_of(agent, include_errors=True)
    saved = [
        r
        for r in rows
        if results.trajectory_path(agent, r["seed"]).is_file()
        and results.trajectory_path(agent, r["seed"]) not in results.damaged
    ]
    good = [r for r in saved if not r.get("error") and _steps(r) > 0]
    skipped = sorted({int(r["seed"]) for r in saved if r not in good})
    if good:
        seed = int(good[0]["seed"])
        why = f"the smallest seed whose `{agent}` episode ran without error for at least one step"
        earlier = [s for s in skipped if s < seed]
        if earlier:
            shown = ", ".join(str(s) for s in earlier[:10]) + (", ..." if len(earlier) > 10 else "")
            why += f"; seeds {shown} skipped: their episodes failed or have no step"
        return seed, why
    if saved:
        seed = int(saved[0]["seed"])
        return seed, (
            f"no `{agent}` episode ran without error for a step, so this failed episode is "
            "drawn: its figures may be empty"
        )
    return None, ""


def _metric_values(results: Results, column: str) -> dict[str, np.ndarray]:
    return {
        agent_label(a): np.array([r.get(column, math.nan) for r in results.rows_of(a)])
        for a in results.agents
    }


def _goal(results: Results) -> tuple[np.ndarray, float | None]:
    """The task's goal state and goal radius of the results' world (:func:`world_goal`)."""
    return world_goal(results.config)


def world_goal(cfg: object) -> tuple[np.ndarray, float | None]:
    """The task's goal state (SI units) and the world's goal radius, if it has one."""
    goal_state = np.array(cfg.goal_state_rad, dtype=float)
    goal, radius = getattr(cfg, "goal", None), getattr(cfg, "goal_radius", None)
    if goal is not None and np.shape(goal) == (2,) and radius is not None:
        goal_state[:2] = goal
        return goal_state, float(radius)
    return goal_state, None


def figures_section(doc: Document, results: Results, figure_seed: int | None, gif: bool) -> None:
    """The figures across seeds, then one episode's (``figure_seed``, by default
    :func:`_default_figure_seed`): its own figures, every agent on its seed, the plan's
    scenario fan and, with ``gif``, its replay."""
    (results.directory / "figures").mkdir(exist_ok=True)
    _across_seeds_section(doc, results)
    _episode_section(doc, results, figure_seed, gif)


def _across_seeds_section(doc: Document, results: Results) -> None:
    """Per-episode metrics and solve times, one box per agent."""
    fig_dir = results.directory / "figures"
    cfg = results.config
    system = results.system
    agents = results.agents

    doc.heading("Across seeds")
    dists = {}
    for g in system.constraint_groups:
        unit = plots.group_unit(system, g)
        dists[f"max {g} excess" + (f" [{unit}]" if unit else "")] = _metric_values(
            results, f"max_{g}_excess"
        )
        dists[f"{g} violation steps"] = _metric_values(results, f"{g}_violation_steps")
    dists["cost (log scale)"] = _metric_values(results, "cost")
    dists["time to goal [s] (successes)"] = _metric_values(results, "time_to_goal")
    fig = plots.metric_distributions_figure(dists, agents, log_scale=["cost (log scale)"])
    plots.save_figure(fig, fig_dir / "metrics_by_agent.png")
    doc.image(
        "figures/metrics_by_agent.png",
        "Per-episode metrics by agent: box (quartiles, median) and one point per seed.",
    )
    fig = plots.solve_time_figure(
        _metric_values(results, "solve_time_median"),
        _metric_values(results, "solve_time_p95"),
        agents,
        cfg.dt,
    )
    plots.save_figure(fig, fig_dir / "solve_time.png")
    doc.image(
        "figures/solve_time.png",
        f"Solve time per MPC step (log scale) against the sampling time {cfg.dt:g} s.",
    )


def _episode_seed(results: Results, agent: str, figure_seed: int | None) -> tuple[int | None, str]:
    """The seed of the episode figures and why (the default's reason, or a warning when the
    chosen episode failed or has no step)."""
    if figure_seed is None:
        return _default_figure_seed(results, agent)
    why = "chosen with --seed"
    row = next((r for r in results.rows_of(agent, True) if r["seed"] == figure_seed), {})
    if row.get("error") or not _steps(row) > 0:
        why += "; this episode failed or has no step, so its figures may be empty"
    return figure_seed, why


def _episode_section(doc: Document, results: Results, figure_seed: int | None, gif: bool) -> None:
    """One episode of the main agent: its figures, every agent on its seed, the fan, the GIF."""
    cfg = results.config
    system = results.system
    main_agent = _main_agent(results)

    doc.heading("One episode")
    chosen = figure_seed
    while True:
        figure_seed, why = _episode_seed(results, main_agent, chosen)
        if figure_seed is None:
            doc.paragraph(f"No saved trajectory of `{main_agent}`: no episode figures.")
            return
        traj = load_trajectory(results, main_agent, figure_seed)
        if traj is not None:
            break
        path = results.trajectory_path(main_agent, figure_seed)
        if path not in results.damaged:
            raise ValueError(
                f"no saved trajectory of agent {main_agent!r} for seed {figure_seed}: "
                f"{path} does not exist"
            )
        if chosen is not None:  # the seed asked for: its file is damaged
            doc.paragraph(
                f"The episode file of `{main_agent}` on seed {figure_seed} is damaged and left "
                f"out (`{path.name}`): no episode figures."
            )
            return
        # the default seed's file is damaged: the next one (_default_figure_seed skips it)
    label = agent_label(main_agent)
    goal = _goal(results)
    doc.paragraph(
        f"Env seed {figure_seed} ({why}), agent {label}, on the `{system.name}` system. "
        "Time in seconds, "
        f"dt = {cfg.dt:g} s. The figures are drawn from the system's definition: its state, "
        "input and force names, its input bounds and its constraint functions."
    )
    _episode_figures(doc, results, traj, main_agent, figure_seed, goal)
    _same_seed_figures(doc, results, traj, main_agent, figure_seed, goal)
    _fan_figure(doc, results, traj, main_agent, figure_seed, *goal)
    if gif:
        _replay_gif(doc, results, traj, label, goal)


def _episode_figures(
    doc: Document,
    results: Results,
    traj: dict[str, np.ndarray],
    agent: str,
    seed: int,
    goal: tuple[np.ndarray, float | None],
) -> None:
    """The episode's own figures, drawn from the system's definition."""
    names = results.system.state_labels
    region = (
        "infeasible region of the constraints on these two states shaded, their bounds "
        "dashed (evaluated with the other states at the goal state)"
    )
    captions = {
        "trajectory": f"Trajectory in the plane {names[0]} / {names[1]}: true path (green "
        f"dashed), estimate (red) with 2-sigma ellipses, goal; {region}.",
        "latent_force": "Latent force: true (dashed) and estimated with its 2-sigma band.",
        "inputs": "Inputs with their bounds (dash-dotted); a force in an input's unit is "
        "drawn beside it with its negative: an input on -w would cancel the force exactly.",
        "states": "The other states: true (dashed) and estimated with the 2-sigma band; "
        "bounds on a state alone dashed, their infeasible side shaded.",
        "constraints": "Largest excess of each constraint group over time (0: inside).",
    }
    goal_state, goal_radius = goal
    figures = plots.episode_figures(
        traj,
        results.system,
        results.config.dt,
        goal_state=goal_state,
        goal_radius=goal_radius,
        label=agent_label(agent),
    )
    for name, fig in figures.items():
        rel = f"figures/seed{seed}_{agent}_{name}.png"
        plots.save_figure(fig, results.directory / rel)
        doc.image(rel, captions.get(name, name))


def _same_seed_figures(
    doc: Document,
    results: Results,
    traj: dict[str, np.ndarray],
    main_agent: str,
    seed: int,
    goal: tuple[np.ndarray, float | None],
) -> None:
    """Every agent on the same seed, the main one first, each in its own colour."""
    system = results.system
    same_seed = {main_agent: traj}
    for a in results.agents:
        if a != main_agent:
            t = load_trajectory(results, a, seed)
            if t is not None:
                same_seed[a] = t
    if len(same_seed) < 2:
        return
    goal_state, goal_radius = goal
    doc.paragraph("All agents on the same seed (same latent force and noise):")
    fig = plots.paths_figure(
        system,
        {agent_label(a): (t["true_state"], plots.agent_colour(a)) for a, t in same_seed.items()},
        goal_state=goal_state,
        goal_radius=goal_radius,
        title=f"True paths of all agents, seed {seed}",
    )
    rel = f"figures/seed{seed}_agents_trajectory.png"
    plots.save_figure(fig, results.directory / rel)
    doc.image(rel, "True paths of all agents on the same seed (x: end of the episode).")
    fig = plots.constraint_excess_figure(
        system,
        results.config.dt,
        {
            agent_label(a): (plots.group_excess_of(t, system), plots.agent_colour(a))
            for a, t in same_seed.items()
        },
        title=f"Constraint excess of all agents, seed {seed}",
    )
    if fig is not None:
        rel = f"figures/seed{seed}_agents_constraints.png"
        plots.save_figure(fig, results.directory / rel)
        doc.image(rel, "Constraint-group excess of all agents on the same seed.")


def _replay_gif(
    doc: Document,
    results: Results,
    traj: dict[str, np.ndarray],
    label: str,
    goal: tuple[np.ndarray, float | None],
) -> None:
    """The episode replayed from its saved true states, the plan's panel below the scene."""
    cfg = results.config
    goal_state, goal_radius = goal
    draws = plots.world_draws(cfg)
    frames = plots.replay_frames(traj["true_state"], cfg, caption=label) if draws else []
    width = frames[0].shape[1] if frames else 480
    panels = plots.plan_panel_frames(
        results.system, traj, size=(width, max(160, width // 3)), goal_state=goal_state,
        goal_radius=goal_radius,
    )  # fmt: skip
    if draws:
        frames = plots.stack_frames(frames, panels)
        where = "above, the world's own scene; below, "
    else:
        frames = [plots.annotate_frame(p, f"{label} | t = {k * cfg.dt:.1f} s")
                  for k, p in enumerate(panels)]  # fmt: skip
        where = "the world has no scene of its own (its env draws none), so only "
    rel = "figures/episode.gif"
    plots.write_gif(frames, results.directory / rel, 1.0 / cfg.dt)
    doc.image(
        rel,
        f"The episode replayed from its saved true states ({len(frames)} frames, "
        f"{1.0 / cfg.dt:g} frames/s): {where}a camera "
        "following the true state (green square) in the plane of the first two states, "
        "with the estimate and its 2-sigma ellipse (red), the plan's scenario "
        "predictions (blue) and their mean (navy) at each step.",
    )


def _fan_figure(
    doc: Document,
    results: Results,
    traj: dict[str, np.ndarray],
    agent: str,
    seed: int,
    goal_state: np.ndarray,
    goal_radius: float | None,
) -> None:
    """What the scenario MPC plans: the fan of scenario predictions at four steps."""
    fig = plots.scenario_fan_figure(
        results.system,
        traj,
        results.config.dt,
        goal_state=goal_state,
        goal_radius=goal_radius,
        title=f"The plan's scenario fan - {agent_label(agent)}, seed {seed}",
    )
    if fig is None:
        doc.paragraph(f"`{agent}` saved no predicted trajectories: no scenario-fan figure.")
        return
    fans, compact = plots.saved_fans(traj)
    rel = f"figures/seed{seed}_{agent}_scenario_fan.png"
    plots.save_figure(fig, results.directory / rel)
    shown = (
        f"up to {fans.shape[1]} of the plan's scenarios (the first ones saved per step)"
        if compact
        else "only the first scenario (this episode file predates the saved fans)"
    )
    doc.image(
        rel,
        f"What the MPC of {agent_label(agent)} plans, at four steps of the episode (for the "
        "scenario MPC, its scenario fan): from the estimate (red, "
        "2-sigma ellipse) one input sequence is planned for all scenarios of the latent "
        f"force; each thin blue line is one scenario's predicted path ({shown}), the navy "
        "line their mean; the true path so far (grey) and over the next horizon (green "
        "dashed) with the infeasible region shaded. Equal axes: lengths to scale.",
    )
