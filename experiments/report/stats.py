"""The numbers of a report: its metrics, bootstrap intervals, paired differences and
the estimators' coverage, computed from a loaded results folder
(:func:`experiments.report.results.load_results`); :mod:`experiments.report.write` writes them down.

The metrics are the columns of ``episodes.csv``
(:func:`~experiments.evaluation.columns.row_columns`) as the report names them, per
constraint group of the world's system with its unit. Every interval is SciPy's BCa
bootstrap (``scipy.stats.bootstrap``; paired where the values are paired) with a fixed
resampling seed, so the same results give the same report.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from experiments.evaluation.columns import tolerance_columns
from experiments.plots.style import force_unit, group_unit
from experiments.report.results import Results, load_trajectory
from lfm_env.system import ControlSystem, split_unit

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
#: Below this many seeds a bootstrap interval is rough (the resamples of a small sample
#: under-cover): the report and the sweep call their claims about intervals hints.
FEW_SEEDS = 20
REFERENCE_AGENT = "scenario"  # the paper's agent: the default baseline and episode figures


@dataclass(frozen=True)
class Metric:
    """One column of ``episodes.csv`` as it appears in the report."""

    column: str
    label: str
    unit: str = ""
    lower_is_better: bool = True
    fewer: str = ""  # plain-language comparative, e.g. "fewer track violation steps"
    zero_count: bool = False  # the value is 1 where the column is 0, else 0 (a fraction)

    @property
    def title(self) -> str:
        """Label with its unit in brackets."""
        return f"{self.label} [{self.unit}]" if self.unit else self.label

    def value(self, row: dict[str, Any]) -> float:
        """The metric of one episode's row: the column, or whether it is 0; NaN if missing."""
        v = row.get(self.column, math.nan)
        v = math.nan if v is None else float(v)
        if self.zero_count and not math.isnan(v):
            return float(v == 0.0)
        return v


def group_metrics(system: ControlSystem) -> tuple[Metric, ...]:
    """Per constraint group ``g`` of the system: violation steps, then the largest excess.

    The columns are the evaluation's (``{g}_violation_steps``, ``max_{g}_excess``); the
    excess is in the unit of the group's constraints (``system.constraint_names``).
    """
    out = []
    for g in system.constraint_groups:
        unit = group_unit(system, g)
        out.append(Metric(f"{g}_violation_steps", f"{g} violation steps", "steps"))
        out.append(Metric(f"max_{g}_excess", f"max {g} excess", unit))
    return tuple(out)


def _beyond(system: ControlSystem, group: str, tolerance: float) -> str:
    """``"> 0.01 m"``: a tolerance with its group's unit."""
    unit = group_unit(system, group)
    return f"> {tolerance:g} {unit}" if unit else f"> {tolerance:g}"


def tolerance_metrics(system: ControlSystem, group: str | None = None) -> tuple[Metric, ...]:
    """Violation steps beyond each tolerance of ``system.violation_tolerances``.

    The evaluation's ``{g}_violation_steps_over_{t:g}`` columns, labelled with the
    tolerance and its unit ("track violation steps > 0.01 m").

    Args:
        system: the world's system.
        group: only this group's; ``None`` for every group's, in the groups' order.
    """
    return tuple(
        Metric(column, f"{g} violation steps {_beyond(system, g, t)}", "steps")
        for g, t, column in tolerance_columns(system)
        if group is None or g == group
    )


def zero_violation_metrics(system: ControlSystem, group: str) -> tuple[Metric, ...]:
    """The fraction of episodes without violation steps of ``group``: raw, then per tolerance.

    Each is the mean over episodes of "this episode has 0 such steps", so its bootstrap
    interval is that of a proportion.
    """
    out = [
        Metric(
            f"{group}_violation_steps",
            f"{group} zero-violation episodes",
            lower_is_better=False,
            zero_count=True,
        )
    ]
    for g, t, column in tolerance_columns(system):
        if g == group:
            out.append(
                Metric(
                    column,
                    f"{g} zero-violation episodes ({_beyond(system, g, t)})",
                    lower_is_better=False,
                    zero_count=True,
                )
            )
    return tuple(out)


def summary_metrics(system: ControlSystem) -> tuple[Metric, ...]:
    """The rows of the per-agent table for a system: its group metrics among the fixed ones.

    Per constraint group: violation steps, the largest excess, the violation steps beyond
    each of its tolerances, then the zero-violation episodes (raw and per tolerance).
    """
    force = force_unit(system)
    groups = []
    for g in system.constraint_groups:
        groups += [Metric(f"{g}_violation_steps", f"{g} violation steps", "steps")]
        groups += [Metric(f"max_{g}_excess", f"max {g} excess", group_unit(system, g))]
        groups += [*tolerance_metrics(system, g), *zero_violation_metrics(system, g)]
    return (
        Metric("success", "success rate", lower_is_better=False),
        Metric("failure", "failure rate (the env ended the episode as a failure)"),
        Metric("time_to_goal", "time to goal (successful episodes)", "s"),
        Metric("cost", "cost (sum of stage costs)"),
        *groups,
        Metric("latent_rmse", "latent-force RMSE", force),
        Metric("latent_coverage", "latent-force 2-sigma coverage", lower_is_better=False),
        Metric("solve_time_median", "solve time, episode median", "s"),
        Metric("solve_time_p95", "solve time, episode p95", "s"),
        Metric("step_time_median", "step compute (estimator + solve), episode median", "s"),
        Metric("deadline_misses", "deadline misses (compute over the control period)", "steps"),
        Metric("solver_failures", "solver failures (no usable plan)", "steps"),
        Metric("unconverged_solves", "unconverged solves (usable plan applied)", "steps"),
        Metric("fallback_steps", "fallback steps", "steps"),
        Metric("deadline_plans", "deadline stops, best usable plan applied", "steps"),
        Metric("deadline_shifted", "deadline stops, previous plan applied", "steps"),
        Metric("deadline_fallbacks", "deadline stops, fallback input applied", "steps"),
        Metric("filter_resets", "particle-filter restarts", "per episode"),
    )


def paired_metrics(system: ControlSystem) -> tuple[Metric, ...]:
    """The rows of the paired-difference table: cost, each group's metrics (with its
    tolerance-aware violation steps), time to goal."""
    groups = []
    for m in group_metrics(system):
        if m.column.startswith("max_"):
            groups.append(Metric(m.column, m.label, m.unit, fewer=f"a smaller {m.label}"))
            g = m.column[len("max_") : -len("_excess")]
            for t in tolerance_metrics(system, g):
                groups.append(Metric(t.column, t.label, t.unit, fewer=f"fewer {t.label}"))
        else:
            groups.append(Metric(m.column, m.label, m.unit, fewer=f"fewer {m.label}"))
    return (
        Metric("cost", "cost", fewer="a lower cost"),
        *groups,
        Metric("time_to_goal", "time to goal", "s", fewer="a shorter time to goal"),
    )


# --------------------------------------------------------------------------- statistics


#: How the intervals are computed, as the report names it.
BOOTSTRAP_METHOD = (
    "BCa bootstrap (bias-corrected and accelerated, scipy.stats.bootstrap; paired "
    "resampling of the seeds for differences and of whole episodes for pooled ratios)"
)


@dataclass(frozen=True)
class Estimate:
    """A mean (or pooled value) with its bootstrap confidence interval.

    ``method`` says how the interval was found: ``"BCa"``; ``"percentile"`` where BCa is
    undefined for the sample (e.g. a single differing value makes its acceleration
    infinite); ``"exact"`` where every value is equal (or one value: a zero-width
    interval); ``""`` without values.
    """

    mean: float
    low: float
    high: float
    n: int  # number of finite values used
    method: str = ""


def _rng_argument(seed: int) -> dict[str, Any]:
    """The seeded generator of ``scipy.stats.bootstrap``: ``rng=`` (SciPy >= 1.15), else
    ``random_state=``."""
    import inspect

    from scipy import stats

    name = "rng" if "rng" in inspect.signature(stats.bootstrap).parameters else "random_state"
    return {name: np.random.default_rng(seed)}


def _scipy_interval(
    data: tuple[np.ndarray, ...],
    statistic: Any,
    value: float,
    n_resamples: int,
    level: float,
    seed: int,
) -> Estimate:
    """``scipy.stats.bootstrap`` of ``statistic`` over the (paired) samples ``data``: BCa,
    the percentile interval where BCa is undefined, a zero-width one where every resample
    gives the same value."""
    import warnings

    from scipy import stats

    n = len(data[0])
    if all(np.all(d == d[0]) for d in data):
        return Estimate(value, value, value, n, "exact")
    for method in ("BCa", "percentile"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a degenerate BCa: the percentile one instead
            ci = stats.bootstrap(
                data,
                statistic,
                n_resamples=n_resamples,
                confidence_level=level,
                method=method,
                paired=len(data) > 1,
                vectorized=True,
                **_rng_argument(seed),
            ).confidence_interval
        low, high = float(ci.low), float(ci.high)
        if math.isfinite(low) and math.isfinite(high):
            # Rounding in the resampled statistics can put a bound a hair past the value.
            return Estimate(value, min(low, value), max(high, value), n, method)
    return Estimate(value, value, value, n, "exact")  # every resample equal


def few_seeds_caveat(n_seeds: int) -> str:
    """A sentence for claims about intervals over ``n_seeds`` seeds; ``""`` from
    :data:`FEW_SEEDS` seeds on."""
    if n_seeds >= FEW_SEEDS:
        return ""
    return (
        f"Only {n_seeds} seed{'s' if n_seeds != 1 else ''}: with fewer than {FEW_SEEDS} the "
        "bootstrap intervals are rough (they cover less often than their level says), so an "
        "interval that excludes 0 is a hint to check on more seeds, not a finding."
    )


def _mean(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


def _mean_difference(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(a - b, axis=axis)


def bootstrap_ci(
    values: Iterable[float],
    n_resamples: int = BOOTSTRAP_RESAMPLES,
    level: float = 0.95,
    seed: int = BOOTSTRAP_SEED,
) -> Estimate:
    """Mean and BCa bootstrap CI of the finite values (NaNs are left out).

    The interval is ``scipy.stats.bootstrap``'s BCa interval of the mean (the percentile
    interval where BCa is undefined for the sample); the resampling generator is seeded,
    so the same values give the same interval.

    Args:
        values: the sample (e.g. one metric over seeds).
        n_resamples: bootstrap resamples.
        level: confidence level of the interval.
        seed: seed of the resampling generator.

    Returns:
        The mean and interval; all NaN for an empty sample, a zero-width interval for one
        value or equal values.
    """
    x = np.asarray(list(values), dtype=float)
    x = x[np.isfinite(x)]
    n = len(x)
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    return _scipy_interval((x,), _mean, mean, n_resamples, level, seed)


def paired_ci(
    values: Iterable[float],
    reference: Iterable[float],
    n_resamples: int = BOOTSTRAP_RESAMPLES,
    level: float = 0.95,
    seed: int = BOOTSTRAP_SEED,
) -> Estimate:
    """Mean of ``values - reference`` (pairs of one seed) and its paired BCa bootstrap CI.

    The pairs are resampled together (``scipy.stats.bootstrap(..., paired=True)``).

    Raises:
        ValueError: if the two samples differ in length.
    """
    a = np.asarray(list(values), dtype=float)
    b = np.asarray(list(reference), dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples of different lengths: {a.shape} and {b.shape}")
    if len(a) == 0:
        return Estimate(math.nan, math.nan, math.nan, 0)
    mean = float(np.mean(a - b))
    return _scipy_interval((a, b), _mean_difference, mean, n_resamples, level, seed)


def summarize(results: Results, metrics: Sequence[Metric] | None = None) -> dict:
    """Per agent and metric, the mean and bootstrap CI over error-free episodes.

    Args:
        results: the loaded results.
        metrics: the metrics; ``None`` for :func:`summary_metrics` of the run's system.

    Returns:
        ``{agent: {column: Estimate}}`` (a zero-violation metric's key is
        ``"zero:" + column``); a column missing from the table gives NaNs.
    """
    if metrics is None:
        metrics = summary_metrics(results.system)
    out = {}
    for agent in results.agents:
        rows = results.rows_of(agent)
        out[agent] = {_key(m): bootstrap_ci([m.value(r) for r in rows]) for m in metrics}
    return out


def _key(metric: Metric) -> str:
    """The key of a metric in :func:`summarize`'s result: its column, ``zero:`` marked."""
    return f"zero:{metric.column}" if metric.zero_count else metric.column


@dataclass(frozen=True)
class PairedDifference:
    """``agent - reference`` of one metric over the seeds both have (error-free)."""

    metric: str
    agent: str
    reference: str
    seeds: tuple[int, ...]
    differences: tuple[float, ...]
    estimate: Estimate
    agent_lower: int  # seeds where the agent's value is lower than the reference's
    reference_lower: int
    ties: int


def paired_differences(
    results: Results, metric: str | Metric, agent: str, reference: str = REFERENCE_AGENT
) -> PairedDifference:
    """Differences ``agent - reference`` of ``metric`` on matching seeds only.

    A seed counts when both agents have an error-free episode on it and both values are
    finite (e.g. time to goal only where both reached the goal).

    Args:
        results: the loaded results.
        metric: a column, or a :class:`Metric` (e.g. a zero-violation fraction).
        agent: the agent whose values come first.
        reference: the agent subtracted.
    """
    return paired_rows_difference(
        results.rows_of(agent), results.rows_of(reference), metric, agent, reference
    )


def paired_rows_difference(
    rows: Iterable[dict[str, Any]],
    reference_rows: Iterable[dict[str, Any]],
    metric: str | Metric,
    agent: str = "",
    reference: str = "",
) -> PairedDifference:
    """Differences ``row - reference row`` of ``metric`` on the seeds both lists hold.

    Rows with an error are left out; a seed counts when both values are finite. This is
    :func:`paired_differences` for rows of two different folders (the risk sweep's).

    Args:
        rows: episode rows (``seed`` and the metric's column).
        reference_rows: the rows subtracted.
        metric: a column, or a :class:`Metric`.
        agent: name of ``rows``' side, recorded in the result.
        reference: name of the reference side.
    """
    m = metric if isinstance(metric, Metric) else Metric(str(metric), str(metric))
    ref = {r["seed"]: m.value(r) for r in reference_rows if not r.get("error")}
    seeds, diffs, pairs_a, pairs_b = [], [], [], []
    for r in sorted((r for r in rows if not r.get("error")), key=lambda r: r["seed"]):
        s = r["seed"]
        a, b = m.value(r), ref.get(s, math.nan)
        if s in ref and np.isfinite(a) and np.isfinite(b):
            seeds.append(s)
            diffs.append(float(a - b))
            pairs_a.append(a)
            pairs_b.append(b)
    d = np.asarray(diffs)
    return PairedDifference(
        metric=m.column,
        agent=agent,
        reference=reference,
        seeds=tuple(seeds),
        differences=tuple(diffs),
        estimate=paired_ci(pairs_a, pairs_b),
        agent_lower=int(np.sum(d < 0)),
        reference_lower=int(np.sum(d > 0)),
        ties=int(np.sum(d == 0)),
    )


TWO_SIGMA_COVERAGE = 0.9545  # P(|e| <= 2 sigma) of a Gaussian: a calibrated 2-sigma band


def pooled_ratio_ci(
    numerators: Sequence[float],
    denominators: Sequence[float],
    root: bool = False,
    n_resamples: int = BOOTSTRAP_RESAMPLES,
    level: float = 0.95,
    seed: int = BOOTSTRAP_SEED,
) -> Estimate:
    """A ratio pooled over episodes, ``sum(num) / sum(den)``, with a bootstrap over episodes.

    The episodes are resampled whole (a cluster bootstrap: numerator and denominator of
    one episode paired, ``scipy.stats.bootstrap(..., paired=True)``, BCa), so the interval
    accounts for the steps of one episode being correlated.

    Args:
        numerators: per episode, e.g. the steps inside the 2-sigma band, or the sum of
            squared errors.
        denominators: per episode, the steps counted.
        root: report the square root of the ratio (an RMSE from squared errors).
        n_resamples: bootstrap resamples.
        level: confidence level of the interval.
        seed: seed of the resampling generator.

    Returns:
        The pooled value and interval, ``n`` the number of episodes with steps; all NaN
        when no episode has any.
    """
    num = np.asarray(numerators, dtype=float)
    den = np.asarray(denominators, dtype=float)
    keep = den > 0
    num, den = num[keep], den[keep]
    n = len(den)
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, 0)
    f = np.sqrt if root else (lambda x: x)
    value = float(f(num.sum() / den.sum()))

    def ratio(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
        return f(np.sum(a, axis=axis) / np.sum(b, axis=axis))

    return _scipy_interval((num, den), ratio, value, n_resamples, level, seed)


@dataclass(frozen=True)
class EstimatorCoverage:
    """How well one agent's estimator knows what it does not see, over its episodes.

    ``quantities`` are the system's states then its latent-force components (labels with
    units); ``coverage[i]`` is the fraction of steps with the truth inside the estimate's
    2-sigma band and ``rmse[i]`` the root-mean-square estimate error [the quantity's
    unit], both pooled over steps and episodes with a bootstrap interval over episodes.
    """

    agent: str
    estimator: str  # the estimator's name
    estimator_source: str  # "recorded" (last_info) or "config.yaml"
    quantities: tuple[str, ...]
    coverage: tuple[Estimate, ...]
    rmse: tuple[Estimate, ...]
    episodes: int
    steps: int


def _estimate_errors(traj: dict[str, np.ndarray], system: ControlSystem) -> tuple:
    """``(error, std)`` arrays ``(T, nx + nw)``: the states', then the force's.

    The estimate made from ``obs[k]`` is compared with ``true_state[k]`` and the force
    estimate with the force acting during step ``k``; errors of states in rad are
    wrapped to ``[-pi, pi)``.
    """
    nx, nw = system.nx, system.nw
    est = np.asarray(traj["estimate"], dtype=float)
    T = len(est)
    err_x = est[:, :nx] - np.asarray(traj["true_state"], dtype=float)[:T]
    for i, name in enumerate(system.state_names):
        if split_unit(name)[1] == "rad":
            err_x[:, i] = (err_x[:, i] + math.pi) % (2.0 * math.pi) - math.pi
    std_x = np.asarray(traj["estimate_std"], dtype=float)[:, :nx]
    force = np.asarray(traj["latent_force_est"], dtype=float).reshape(T, nw)
    truth = np.asarray(traj["latent_force"], dtype=float).reshape(T, nw)
    std_w = np.asarray(traj["latent_force_std"], dtype=float).reshape(T, nw)
    return np.hstack([err_x, force - truth]), np.hstack([std_x, std_w])


def _estimator_name(results: Results, recorded: Iterable[str], agent: str = "") -> tuple[str, str]:
    """The estimator's name: the most frequent one the agent recorded, else config.yaml's
    (``agents.robust.estimator`` for the robust agent, ``agents.estimator`` otherwise)."""
    names = [str(n) for n in recorded if str(n)]
    if names:
        values, counts = np.unique(names, return_counts=True)
        return str(values[np.argmax(counts)]), "recorded"
    # A folder written before the agents said it: the agents section's (the bootstrap
    # filter, the only one, when the section predates agents.estimator).
    settings = results.agent_settings
    if agent == "robust" and isinstance(settings.get("robust"), dict):
        return str(settings["robust"].get("estimator", "ukf")), "config.yaml"
    return str(settings.get("estimator", "bootstrap")), "config.yaml"


def estimator_coverage(results: Results) -> list[EstimatorCoverage]:
    """The estimator coverage (2-sigma coverage and RMSE) of every agent with a filter (saved
    trajectories only).

    An agent counts when some error-free episode of it has a saved trajectory with a
    finite latent-force estimate (the nominal MPC and the oracle have none).
    """
    system = results.system
    labels = tuple(system.state_names) + tuple(f"latent force {w}" for w in system.force_names)
    out = []
    for agent in results.agents:
        hits, squares, counts, recorded = [], [], [], []
        for row in results.rows_of(agent):
            traj = load_trajectory(results, agent, row["seed"])
            if traj is None or not np.any(np.isfinite(traj.get("latent_force_est", np.nan))):
                continue
            err, std = _estimate_errors(traj, system)
            ok = np.isfinite(err) & np.isfinite(std)
            hits.append(np.sum(ok & (np.abs(np.where(ok, err, 0.0)) <= 2.0 * std), axis=0))
            squares.append(np.sum(np.where(ok, err, 0.0) ** 2, axis=0))
            counts.append(np.sum(ok, axis=0))
            recorded += list(traj.get("estimator", ()))
        if not counts:
            continue
        hits_a, sq_a, n_a = np.array(hits), np.array(squares), np.array(counts)
        name, source = _estimator_name(results, recorded, agent)
        columns = range(len(labels))
        out.append(
            EstimatorCoverage(
                agent=agent,
                estimator=name,
                estimator_source=source,
                quantities=labels,
                coverage=tuple(pooled_ratio_ci(hits_a[:, i], n_a[:, i]) for i in columns),
                rmse=tuple(pooled_ratio_ci(sq_a[:, i], n_a[:, i], root=True) for i in columns),
                episodes=len(counts),
                steps=int(n_a[:, -1].sum()),
            )
        )
    return out


__all__ = [
    "BOOTSTRAP_METHOD",
    "FEW_SEEDS",
    "BOOTSTRAP_RESAMPLES",
    "BOOTSTRAP_SEED",
    "REFERENCE_AGENT",
    "TWO_SIGMA_COVERAGE",
    "EstimatorCoverage",
    "Estimate",
    "Metric",
    "PairedDifference",
    "bootstrap_ci",
    "estimator_coverage",
    "few_seeds_caveat",
    "group_metrics",
    "paired_ci",
    "paired_differences",
    "paired_metrics",
    "paired_rows_difference",
    "pooled_ratio_ci",
    "summarize",
    "summary_metrics",
    "tolerance_metrics",
    "zero_violation_metrics",
]
