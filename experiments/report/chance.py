"""The chance constraint checked against its design (``docs/evidence.md``): how often the true
state violates each constraint group, at the plan's first step in closed loop
(:func:`closed_loop_first_step`, pooled over episodes with a bootstrap over episodes) and at
every step of the horizon offline (:func:`plan_violations`, :func:`offline_violations`: each
applied plan rolled out from the true state under :data:`DRAWS` draws of the true force's
law given the env's hidden latent state and of the process noise), beside the design's
epsilon (the config's, or :func:`design_epsilon` of ``Ns`` at :data:`DEFAULT_CONFIDENCE`).
"Joint" is any group at any step ``1..k``. For feedback or branching agents, steps
``k >= 2`` measure the nominal open-loop plan, not the policy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize, special

from controllers.agents.mpc import RobustMPCAgent
from controllers.agents.registry import AGENT_REGISTRY
from controllers.config import ExperimentConfig
from experiments.evaluation.episode import agent_seed
from experiments.plots.chance import chance_figure
from experiments.plots.style import agent_colour, save_figure
from experiments.report.document import Document
from experiments.report.format import agent_label, fmt, fmt_estimate
from experiments.report.results import Results, load_trajectory
from experiments.report.stats import Estimate, pooled_ratio_ci
from lfm_env.model import LatentForceModel

#: ``beta`` of the design when the config gives ``n_scenarios`` and no ``agents.confidence``.
DEFAULT_CONFIDENCE = 1.0e-3
#: Draws of the true force and noise per recorded step of the offline check (a run has
#: thousands of steps: the draws' own noise is small beside the spread over episodes).
DRAWS = 50
#: A plan's total slack above this [constraint units] counts as needing slack (the solvers
#: leave slacks of 1e-9 and below on feasible plans).
SLACK_TOLERANCE = 1.0e-6
#: Seed of the offline draws (with the env seed and the agent's name: the same report twice).
SEED = 0


def design_epsilon(n_scenarios: int, n_decision: int, beta: float) -> float:
    """The smallest ``epsilon`` whose Campi-Garatti bound ``Ns`` scenarios meet at ``beta``
    (:mod:`controllers.scenario_count`); 1 when ``Ns < d``.
    """
    d, ns = int(n_decision), int(n_scenarios)
    if ns < d:
        return 1.0
    return float(optimize.brentq(lambda e: special.bdtr(d - 1, ns, e) - beta, 1e-15, 1 - 1e-15))


@dataclass(frozen=True)
class Design:
    """An agent's chance-constraint design (``n_scenarios`` is ``None`` when it has none)."""

    n_scenarios: int | None
    n_decision: int  # d = nu N
    epsilon: float  # the violation level (NaN without a design)
    beta: float  # its confidence parameter
    source: str  # where epsilon comes from, one line

    @property
    def mean_bound(self) -> float:
        """The bound on the mean violation probability, ``d / (Ns + 1)`` (NaN without one)."""
        return math.nan if self.n_scenarios is None else self.n_decision / (self.n_scenarios + 1)

    def describe(self) -> str:
        if self.n_scenarios is None:
            return "none"
        return (
            f"Ns = {self.n_scenarios}, d = {self.n_decision}: epsilon = {self.epsilon:.3g} at "
            f"beta = {self.beta:g} ({self.source}); mean <= {self.mean_bound:.3g}"
        )


def scenario_count(agent: str, config: ExperimentConfig) -> int | None:
    """The number of sampled scenarios a registered agent plans with; ``None`` for an agent
    without sampled scenarios (one forecast, a fixed tree, a policy, a user's agent)."""
    spec = AGENT_REGISTRY.get(agent)
    if spec is None or not getattr(spec.agent_class, "uses_scenarios", False):
        return None
    if issubclass(spec.agent_class, RobustMPCAgent):
        r = config.agents.robust
        return None if r.forecast == "mean" else (r.n_scenarios or config.scenario_count())
    return config.scenario_count()


def agent_design(agent: str, config: ExperimentConfig) -> Design:
    """The design of ``agent`` under ``config`` (see the module docstring)."""
    a = config.agents
    d = config.make_system().nu * a.horizon
    ns = scenario_count(agent, config)
    if ns is None:
        return Design(None, d, math.nan, math.nan, "no sampled scenarios")
    if a.n_scenarios is None and ns == config.scenario_count():
        source = "agents.violation_level and agents.confidence"
        return Design(ns, d, float(a.violation_level), float(a.confidence), source)
    beta = DEFAULT_CONFIDENCE if a.confidence is None else float(a.confidence)
    source = "default beta" if a.confidence is None else "agents.confidence"
    return Design(ns, d, design_epsilon(ns, d, beta), beta, source)


def plan_violations(
    model: LatentForceModel,
    plans: np.ndarray,
    states: np.ndarray,
    latents: np.ndarray,
    n_draws: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """How often open-loop plans violate each constraint group under the true law.

    Args:
        model: the true model (the env's: its force and process noise).
        plans: ``(T, N, nu)`` input sequences, in the inputs' units (clipped to the bounds).
        states: ``(T, nx)`` true states the plans start from.
        latents: ``(T, p)`` true latent states at those steps (the force's conditional law).
        n_draws: draws per plan.
        rng: the draws' generator.

    Returns:
        ``(per_group (T, N, G), joint (T, N))``: the fraction of draws whose state at step
        ``k + 1`` violates group ``g``, and any group at any step ``1..k+1``.
    """
    system = model.system
    plans = system.clip_input(np.asarray(plans, dtype=float))
    T, N, _ = plans.shape
    groups = [list(idx) for idx in system.constraint_groups.values()]
    x = np.repeat(np.asarray(states, dtype=float), n_draws, axis=0)  # (T M, nx)
    z0 = np.repeat(np.asarray(latents, dtype=float), n_draws, axis=0)
    W = model.sample_latent_forecasts(z0, N, rng)  # (T M, N, nw); W[:, 0] = H z_t
    per_group = np.empty((T, N, len(groups)))
    joint = np.empty((T, N))
    seen = np.zeros(T * n_draws, dtype=bool)
    for k in range(N):
        u = np.repeat(plans[:, k], n_draws, axis=0)
        x = model.physical_step(x, u, W[:, k])
        x = x + rng.standard_normal(x.shape) * model.process_std
        g = np.asarray(system.constraint_values(x), dtype=float)
        hit = np.stack([np.max(g[:, idx], axis=1) > 0.0 for idx in groups], axis=1)
        per_group[:, k] = hit.reshape(T, n_draws, -1).mean(axis=1)
        seen |= hit.any(axis=1)
        joint[:, k] = seen.reshape(T, n_draws).mean(axis=1)
    return per_group, joint


@dataclass(frozen=True)
class ChanceCheck:
    """One agent's violation probabilities beside its design: ``closed_loop[g]`` (step 1),
    ``offline[g][k]`` (step ``k + 1``; ``()`` without plans) and ``joint[k]``.
    """

    agent: str
    design: Design
    groups: tuple[str, ...]
    closed_loop: tuple[Estimate, ...]
    offline: tuple[tuple[Estimate, ...], ...]
    joint: tuple[Estimate, ...]
    steps: int  # steps survived (closed loop)
    offline_steps: int  # steps whose applied plan was rolled out
    slack_steps: int  # steps whose plan needed constraint slack (the scenario program was
    # infeasible: no guarantee applies); -1 when unknown

    @property
    def has_offline(self) -> bool:
        return bool(self.joint)


def closed_loop_first_step(rows: Sequence[dict[str, Any]], group: str) -> Estimate:
    """The fraction of steps survived after which the true state violated ``group``."""
    counts = [float(r.get(f"{group}_violation_steps", math.nan)) for r in rows]
    steps = [float(r.get("steps", math.nan)) for r in rows]
    ok = [i for i, c in enumerate(counts) if np.isfinite(c) and np.isfinite(steps[i])]
    return pooled_ratio_ci([counts[i] for i in ok], [steps[i] for i in ok])


def _applied_plans(traj: dict[str, np.ndarray]) -> np.ndarray:
    """The steps whose recorded plan was applied: finite, solved, no fallback."""
    plan = np.asarray(traj.get("plan", np.zeros((0, 0, 0))), dtype=float)
    T = len(traj["action"])
    if plan.ndim != 3 or len(plan) != T or "latent_state" not in traj:
        return np.zeros(0, dtype=int)
    ok = np.all(np.isfinite(plan), axis=(1, 2))
    ok &= np.asarray(traj["solver_success"], dtype=bool)[:T]
    ok &= np.asarray(traj["fallback"]).astype(str)[:T] == ""
    return np.flatnonzero(ok)


def offline_violations(
    results: Results, agent: str, model: LatentForceModel, n_draws: int = DRAWS
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The offline sums of one agent's error-free episodes with saved plans: per episode
    :func:`plan_violations`' fractions summed over its applied plans ``(E, N, G)`` and
    ``(E, N)``, the plans used ``(E,)`` and the steps with constraint slack.
    """
    sums_g, sums_j, used, slack = [], [], [], 0
    for row in results.rows_of(agent):
        traj = load_trajectory(results, agent, row["seed"])
        if traj is None:
            continue
        s = np.asarray(traj.get("slack", ()), dtype=float)
        slack += int(np.sum(s[np.isfinite(s)] > SLACK_TOLERANCE))
        steps = _applied_plans(traj)
        if not len(steps):
            continue
        rng = np.random.default_rng([SEED, agent_seed(int(row["seed"]), agent)])
        per_group, joint = plan_violations(
            model,
            traj["plan"][steps],
            traj["true_state"][steps],
            traj["latent_state"][steps],
            n_draws,
            rng,
        )
        sums_g.append(per_group.sum(axis=0))
        sums_j.append(joint.sum(axis=0))
        used.append(len(steps))
    if not used:
        return np.zeros((0, 0, 0)), np.zeros((0, 0)), np.zeros(0), slack
    return np.array(sums_g), np.array(sums_j), np.array(used, dtype=float), slack


def chance_check(results: Results, n_draws: int = DRAWS) -> list[ChanceCheck]:
    """Every agent's closed-loop and offline violation probabilities beside its design."""
    config = results.experiment
    truth = results.config.make_model()  # the env's own force and noise: the truth
    groups = tuple(results.system.constraint_groups)
    out = []
    for agent in results.agents:
        rows = results.rows_of(agent)
        if not rows:
            continue
        closed = tuple(closed_loop_first_step(rows, g) for g in groups)
        sums_g, sums_j, used, slack = offline_violations(results, agent, truth, n_draws)
        offline: tuple[tuple[Estimate, ...], ...] = ()
        joint: tuple[Estimate, ...] = ()
        if len(used):
            N = sums_j.shape[1]
            offline = tuple(
                tuple(pooled_ratio_ci(sums_g[:, k, j], used) for k in range(N))
                for j in range(len(groups))
            )
            joint = tuple(pooled_ratio_ci(sums_j[:, k], used) for k in range(N))
        has_slack = any(np.isfinite(float(r.get("slack_total", math.nan))) for r in rows)
        out.append(
            ChanceCheck(
                agent=agent,
                design=agent_design(agent, config),
                groups=groups,
                closed_loop=closed,
                offline=offline,
                joint=joint,
                steps=int(sum(float(r.get("steps", 0)) for r in rows)),
                offline_steps=int(used.sum()) if len(used) else 0,
                slack_steps=slack if has_slack else -1,
            )
        )
    return out


FIGURE = "figures/chance_constraint.png"


def _verdict(e: Estimate, level: float) -> str:
    """Where an estimate lies against a level: above, below or not distinguishable."""
    if e.n == 0 or not np.isfinite(level):
        return "n/a"
    if e.low > level:
        return "above"
    if e.high < level:
        return "below"
    return "not distinguishable from"


def _readings(cals: Sequence[ChanceCheck]) -> list[str]:
    """One sentence per agent with a design: its worst group at k = 1 and its joint event
    against epsilon."""
    out = []
    for c in cals:
        d = c.design
        if d.n_scenarios is None:
            continue
        worst = int(np.nanargmax([e.mean if e.n else -1.0 for e in c.closed_loop]))
        e = c.closed_loop[worst]
        text = (
            f"`{c.agent}` (epsilon = {d.epsilon:.3g}): closed loop at k = 1 the `{c.groups[worst]}`"
            f" group is violated with probability {fmt_estimate(e)}, "
            f"{_verdict(e, d.epsilon)} epsilon"
        )
        if c.has_offline:
            j = c.joint[-1]
            text += (
                f"; offline, any group at any step 1..{len(c.joint)} (the bound's event): "
                f"{fmt_estimate(j)}, {_verdict(j, d.epsilon)} epsilon and "
                f"{_verdict(j, d.mean_bound)} the mean bound {d.mean_bound:.3g}"
            )
        if c.slack_steps > 0:
            text += (
                f"; {c.slack_steps} of {c.steps} plans needed constraint slack (an infeasible "
                "scenario program: no guarantee there)"
            )
        out.append(text + ".")
    return out


def _first_step_table(doc: Document, cals: Sequence[ChanceCheck]) -> None:
    groups = cals[0].groups
    header = ["agent", "design epsilon"]
    for g in groups:
        header += [f"`{g}` closed loop", f"`{g}` offline"]
    N = max((len(c.joint) for c in cals), default=0)
    header += [f"joint, steps 1..{N} (offline)", "plans rolled out / steps", "plans with slack"]
    rows = []
    for c in cals:
        d = c.design
        cells = [agent_label(c.agent), "none" if d.n_scenarios is None else f"{d.epsilon:.3g}"]
        for j in range(len(groups)):
            off = fmt_estimate(c.offline[j][0]) if c.has_offline else "no plan saved"
            cells += [fmt_estimate(c.closed_loop[j]), off]
        cells.append(fmt_estimate(c.joint[-1]) if c.has_offline else "n/a")
        cells.append(f"{c.offline_steps} / {c.steps}")
        cells.append("n/a" if c.slack_steps < 0 else str(c.slack_steps))
        rows.append(cells)
    doc.table(header, rows)


def _horizon_table(doc: Document, cals: Sequence[ChanceCheck]) -> list[str]:
    """Offline means at every k: per agent its groups that are ever violated, and the
    joint event. Returns the groups never violated (left out)."""
    with_plans = [c for c in cals if c.has_offline]
    groups = cals[0].groups
    N = max(len(c.joint) for c in with_plans)
    shown = [
        j for j in range(len(groups)) if any(e.mean > 0 for c in with_plans for e in c.offline[j])
    ]
    rows = []
    for c in with_plans:
        for j in shown:
            rows.append(
                [agent_label(c.agent), f"`{groups[j]}`", *(fmt(e.mean) for e in c.offline[j])]
            )
        rows.append([agent_label(c.agent), "joint, steps 1..k", *(fmt(e.mean) for e in c.joint)])
    doc.table(["agent", "event", *(f"k = {k}" for k in range(1, N + 1))], rows)
    return [groups[j] for j in range(len(groups)) if j not in shown]


def _figure(doc: Document, results: Results, cals: Sequence[ChanceCheck]) -> None:
    groups = cals[0].groups
    N = max((len(c.joint) for c in cals), default=1)
    panels = [f"`{g}` group" for g in groups] + ["joint: any group at steps 1..k"]
    nan3 = [np.nan] * 3

    def triple(e: Estimate) -> list[float]:
        return [e.mean, e.low, e.high] if e.n else nan3

    offline = np.full((len(cals), len(panels), N, 3), np.nan)
    closed = np.full((len(cals), len(panels), 3), np.nan)
    for a, c in enumerate(cals):
        closed[a, : len(groups)] = [triple(e) for e in c.closed_loop]
        if c.has_offline:
            for j in range(len(groups)):
                offline[a, j, : len(c.offline[j])] = [triple(e) for e in c.offline[j]]
            offline[a, -1, : len(c.joint)] = [triple(e) for e in c.joint]
    levels = {}
    for c in cals:
        d = c.design
        if d.n_scenarios is not None:
            levels.setdefault(f"epsilon = {d.epsilon:.3g} (Ns = {d.n_scenarios})", d.epsilon)
    agents = {agent_label(c.agent): agent_colour(c.agent) for c in cals}
    fig = chance_figure(panels, agents, offline, closed, levels)
    save_figure(fig, results.directory / FIGURE)
    doc.image(
        FIGURE,
        "The chance constraint against its design: per constraint group and for the joint "
        "event, the probability that the true state violates it at prediction step k, "
        "offline (lines, bands: 95% over episodes) and in closed loop at k = 1 (squares); "
        "dashed: the designs' epsilon.",
    )


def chance_section(doc: Document, results: Results, n_draws: int = DRAWS) -> list[ChanceCheck]:
    """The report's section: the closed-loop and offline tables, readings and the figure."""
    doc.heading("The chance constraint against its design")
    cals = chance_check(results, n_draws)
    if not cals:
        doc.paragraph("No error-free episode: nothing to check.")
        return cals
    designed = [c for c in cals if c.design.n_scenarios is not None]
    design_text = "; ".join(f"`{c.agent}`: {c.design.describe()}" for c in designed) or (
        "no agent of these results plans with sampled scenarios"
    )
    doc.paragraph(
        "How often the true state violates each constraint group (its excess above 0), "
        "beside the violation level epsilon the scenario count was designed for (the "
        "Campi-Garatti bound: the plan violates any constraint at any step of the horizon "
        "with probability above epsilon only with probability beta). **Closed loop**: the "
        "fraction of the steps survived after which the true state violated the group, the "
        "plan's first step (k = 1). **Offline**: every plan that was applied (no fallback) "
        f"rolled out open loop from the true state under {n_draws} draws of the true force's "
        "conditional law given the env's hidden latent state, and of the process noise; "
        "the fraction of draws violating the group at step k, averaged over the plans. "
        "**Joint**: any group at any step 1..k (at k = N the bound's event). Intervals: 95% "
        "bootstrap over episodes. Agents without sampled scenarios have no design; their "
        f"numbers are for comparison. Designs: {design_text}."
    )
    _first_step_table(doc, cals)
    readings = _readings(cals)
    if readings:
        doc.paragraph("Against the design:")
        doc.bullets(readings)
    if any(c.has_offline for c in cals):
        doc.paragraph("Offline, at every step of the horizon (means; intervals in the figure):")
        never = _horizon_table(doc, cals)
        if never:
            doc.paragraph(
                "Never violated offline by any agent (rows left out): "
                + ", ".join(f"`{g}`" for g in never)
                + "."
            )
    _figure(doc, results, cals)
    return cals
