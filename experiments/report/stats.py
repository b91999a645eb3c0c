"""The numbers of a report: metrics, SciPy's BCa bootstrap intervals (seeded, paired where the
values are), paired differences and the estimators' coverage, from a loaded results folder.
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
    """Per constraint group ``g``: violation steps, then the largest excess (constraint units)."""
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
    """Violation steps beyond each tolerance of ``system.violation_tolerances`` ("track violation
    steps > 0.01 m"), of ``group`` only or of every group.
    """
    return tuple(
        Metric(column, f"{g} violation steps {_beyond(system, g, t)}", "steps")
        for g, t, column in tolerance_columns(system)
        if group is None or g == group
    )


def zero_violation_metrics(system: ControlSystem, group: str) -> tuple[Metric, ...]:
    """The fraction of episodes without violation steps of ``group``: raw, then per tolerance."""
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
    """The rows of the per-agent table: per group its violation steps, largest excess, steps
    beyond each tolerance and zero-violation episodes, among the fixed metrics.
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


#: How the intervals are computed, as the report names it.
BOOTSTRAP_METHOD = (
    "BCa bootstrap (bias-corrected and accelerated, scipy.stats.bootstrap; paired "
    "resampling of the seeds for differences and of whole episodes for pooled ratios)"
)


@dataclass(frozen=True)
class Estimate:
    """A mean (or pooled value) with its bootstrap confidence interval; ``method``: ``"BCa"``,
    ``"percentile"`` (BCa undefined), ``"exact"`` (equal values) or ``""`` (none).
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
    """Mean and seeded BCa bootstrap CI (percentile where BCa is undefined) of the finite values.

    Args:
        values: the sample (e.g. one metric over seeds).
        n_resamples: bootstrap resamples.
        level: confidence level of the interval.
        seed: seed of the resampling generator.

    Returns:
        The estimate; all NaN when empty, zero-width for equal values.
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
    """Per agent and metric (default :func:`summary_metrics`), the mean and bootstrap CI over
    error-free episodes: ``{agent: {column: Estimate}}`` (zero-violation keys ``"zero:" + column``).
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
    """Differences ``agent - reference`` of ``metric`` (a column or :class:`Metric`) on the seeds
    where both have an error-free episode and finite values.
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
    """:func:`paired_differences` for rows of two folders (the risk sweep's): ``row - reference
    row`` of ``metric`` on the seeds both hold, error rows left out; ``agent`` and
    ``reference`` name the sides.
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
    """A ratio pooled over episodes, ``sum(num) / sum(den)``, with a cluster bootstrap over
    whole episodes (paired BCa).

    Args:
        numerators: per episode, e.g. steps inside the 2-sigma band or squared errors summed.
        denominators: per episode, the steps counted.
        root: report the square root of the ratio (an RMSE from squared errors).
        n_resamples: bootstrap resamples.
        level: confidence level of the interval.
        seed: seed of the resampling generator.

    Returns:
        The pooled value and interval (``n`` episodes with steps); NaN when none has any.
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
    """One agent's estimator over its episodes: per state, then force component (``quantities``),
    the 2-sigma ``coverage`` and the ``rmse`` [its unit], pooled with a bootstrap over episodes.
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
    """``(error, std)`` arrays ``(T, nx + nw)``: estimate from ``obs[k]`` against
    ``true_state[k]`` and the force of step ``k``; angles wrapped to ``[-pi, pi)``.
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
    """The estimator coverage of every agent with a filter (a saved trajectory with a finite
    latent-force estimate).
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
