"""The benchmark's targets: PASS/FAIL per target, judged from a run's measured figures.

:func:`evaluate_targets` judges every target of :data:`DEFAULT_THRESHOLDS` (the solver
issue's, plus the filter's and an episode's) from a benchmark result; a threshold can be
changed by key (``lfm-benchmark --threshold KEY=VALUE``, :func:`check_thresholds`). A target
whose figure was not measured (a part or solver left out) is SKIP (``passed`` is ``None``).
Unless said otherwise the figures are of the closed-loop problems at the config's size
(``N = 7``, ``Ns = 150``), warm-started, all solvers side by side in one run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from experiments.benchmark.solvers import FAST_SOLVERS, GAP_TOL, SOLVER_VARIANTS

TEXTBOOK = "ipopt_multiple_shooting"
ANCHOR = "sqpmethod"  # CasADi sqpmethod + qpOASES, JIT-compiled
LARGE_NS = 5000  # the scenario sweep's count of the large-Ns target
PF_PARTICLES = 7000  # the filter size of the filter target

# key -> threshold; the comparison and unit of each are in _SPECS.
DEFAULT_THRESHOLDS: dict[str, float] = {
    "fast_median_ms": 1.5,  # fast median solve [ms]
    "fast_p95_ms": 5.0,  # fast p95 solve [ms]
    "anchor_over_fast": 10.0,  # sqpmethod median / fast median
    "textbook_over_fast": 300.0,  # textbook IPOPT median / fast median
    "worse_share_pct": 2.0,  # [%] problems where fast ends > GAP_TOL above the textbook
    "violation_no_slack": 1e-6,  # fast's largest violation where the reference needs none
    "csnlp_over_fast": 1.0,  # csnlp median / fast median (strictly above)
    "horizon_15_median_ms": 5.0,  # fast median at N = 15 [ms]
    "horizon_30_median_ms": 25.0,  # fast median at N = 30 [ms]
    "fast_failures": 0.0,  # failed fast solves, every horizon
    "within_share_pct": 98.0,  # [%] fast within GAP_TOL of IPOPT, worst horizon
    "large_ns_median_ms": 30.0,  # fast median at Ns = LARGE_NS [ms]
    "qp_failed": 0.0,  # QP_Failed of the fast solvers over the whole run
    "pf_step_ms": 0.6,  # particle-filter step at PF_PARTICLES [ms]
    "cold_build_s": 5.0,  # fast solver built with an empty C library cache + first solve [s]
    "episode_s": 3.0,  # a whole paper episode [s]
    # Issue 37, the compiled loop (fast_c) and the exported controller
    # (experiments.benchmark.compiled):
    "fast_c_median_ms": 0.8,  # fast_c median solve [ms]
    "fast_c_p95_ms": 3.0,  # fast_c p95 solve [ms]
    "anchor_over_fast_c": 25.0,  # sqpmethod median / fast_c median
    "textbook_over_fast_c": 500.0,  # textbook IPOPT median / fast_c median
    "fast_c_ns1000_median_ms": 4.0,  # fast_c median at Ns = 1000 [ms]
    "fast_c_ns5000_median_ms": 15.0,  # fast_c median at Ns = 5000 [ms]
    "robust_step_ms": 1.0,  # the exported robust agent's whole step, median [ms]
    "export_plan_diff": 1e-8,  # exported example vs Python loop, largest plan difference
    "export_dependencies": 0.0,  # run-time dependencies of the export beyond libc and libm
}
_OPS = {"<=": np.less_equal, ">=": np.greater_equal, ">": np.greater}


def check_thresholds(overrides: Mapping[str, Any] | None) -> dict[str, float]:
    """:data:`DEFAULT_THRESHOLDS` with ``overrides`` applied.

    Raises:
        ValueError: naming an unknown key (and the known ones) or a non-finite value.
    """
    out = dict(DEFAULT_THRESHOLDS)
    for key, value in (overrides or {}).items():
        if key not in DEFAULT_THRESHOLDS:
            raise ValueError(f"threshold {key!r}: unknown; one of {sorted(DEFAULT_THRESHOLDS)}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if not math.isfinite(number):
            raise ValueError(f"threshold {key}={value!r}: must be a finite number")
        out[key] = number
    return out


def target(
    text: str,
    value: float | None,
    threshold: float,
    op: str,
    unit: str = "",
    note: str = "",
    key: str = "",
) -> dict[str, Any]:
    """One target, judged from a measured ``value`` (``None`` or NaN: not measured, SKIP).

    Args:
        text: what is required, as printed.
        value: the measured figure.
        threshold: the bound.
        op: ``"<="``, ``">="`` or ``">"``: ``value op threshold`` passes.
        unit: unit of ``value`` and ``threshold`` (``"x"`` for a ratio).
        note: printed after the figure.
        key: the threshold's key in :data:`DEFAULT_THRESHOLDS`.

    Raises:
        ValueError: for another ``op``.
    """
    if op not in _OPS:
        raise ValueError(f"op={op!r}: must be one of {sorted(_OPS)}")
    measured = value is not None and math.isfinite(value)
    return {
        "key": key,
        "target": text,
        "value": value,
        "threshold": threshold,
        "op": op,
        "unit": unit,
        "passed": bool(_OPS[op](value, threshold)) if measured else None,
        "note": note,
    }


def _fmt(x: Any, spec: str = ".1f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b <= 0:
        return None
    return a / b


def _get(d: Mapping | None, key: str) -> Any:
    return None if d is None else d.get(key)


def _problem_list(worse: list[dict[str, Any]], limit: int = 12) -> str:
    items = [
        f"seed {w['seed']} step {w['step']} ({_fmt(w['rel_gap'], '+.1e')})" for w in worse[:limit]
    ]
    more = f", and {len(worse) - limit} more" if len(worse) > limit else ""
    return ", ".join(items) + more


def speed_targets(
    medians: Mapping[str, float | None],
    fast_p95_ms: float | None,
    worse: list[dict[str, Any]] | None,
    n_compared: int | None,
    thresholds: Mapping[str, float] | None = None,
    where: str = "N=7, Ns=150",
) -> list[dict[str, Any]]:
    """The issue's latency, speed-ratio and accuracy targets at the main problem size.

    Args:
        medians: median solve time [ms] by solver name (side by side); missing or
            ``None``: not measured.
        fast_p95_ms: the fast solver's 95th percentile [ms].
        worse: the problems where fast ends more than :data:`GAP_TOL` (relative) above the
            textbook (``{"seed", "step", "rel_gap"}``), ``None`` if not compared.
        n_compared: how many problems the textbook solved (the share's denominator).
        thresholds: :func:`check_thresholds` (default :data:`DEFAULT_THRESHOLDS`).
        where: the problem size, for the texts.

    Returns:
        Five :func:`target` dicts: fast median, fast p95, sqpmethod / fast,
        textbook / fast, the share where fast ends above the textbook.
    """
    th = check_thresholds(thresholds)
    fast = medians.get("fast")
    measured = f"fast {_fmt(fast, '.2f')} ms"
    share = 100.0 * len(worse) / n_compared if worse is not None and n_compared else None
    if worse is None or not n_compared:
        worse_note = "textbook not run or unavailable"
    elif worse:
        worse_note = f"{len(worse)} of {n_compared}: {_problem_list(worse)}"
    else:
        worse_note = f"none of {n_compared}"

    def ratio(key: str, name: str, label: str) -> dict[str, Any]:
        return target(
            f"{label} / fast median solve time >= {th[key]:g} ({where}, side by side)",
            _ratio(medians.get(name), fast),
            th[key],
            ">=",
            "x",
            f"{measured}, {name} {_fmt(medians.get(name), '.2f')} ms",
            key,
        )

    return [
        target(
            f"fast median solve <= {th['fast_median_ms']:g} ms ({where}, side by side)",
            fast,
            th["fast_median_ms"],
            "<=",
            "ms",
            key="fast_median_ms",
        ),
        target(
            f"fast p95 solve <= {th['fast_p95_ms']:g} ms ({where}, side by side)",
            fast_p95_ms,
            th["fast_p95_ms"],
            "<=",
            "ms",
            key="fast_p95_ms",
        ),
        ratio("anchor_over_fast", ANCHOR, "sqpmethod + qpOASES (JIT)"),
        ratio("textbook_over_fast", TEXTBOOK, f"textbook ({TEXTBOOK})"),
        target(
            f"problems where fast ends > {GAP_TOL:g} (relative) above the textbook "
            f"<= {th['worse_share_pct']:g}%",
            share,
            th["worse_share_pct"],
            "<=",
            "%",
            worse_note,
            "worse_share_pct",
        ),
    ]


def _closed_loop_targets(closed: dict[str, Any], th: Mapping[str, float]) -> list[dict]:
    """The speed targets, fast's violations and csnlp (closed loop, main problem size)."""
    summary = closed.get("summary", {})
    fast = summary.get("fast")
    problem = closed.get("problem", {})
    where = f"N={problem.get('horizon')}, Ns={problem.get('n_scenarios')}"
    compared = closed.get("reference") == TEXTBOOK and fast is not None
    medians = {name: s.get("solve_ms_median") for name, s in summary.items()}
    targets = speed_targets(
        medians,
        _get(fast, "solve_ms_p95"),
        fast.get("worse_than_reference") if compared else None,
        fast.get("n_reference_ok") if compared else None,
        th,
        where,
    )
    speed = closed.get("speedup", {})
    fast_note = "" if fast else "fast solver unavailable"
    targets += [
        target(
            f"fast max violation <= {th['violation_no_slack']:g} where the reference needs "
            "no slack",
            _get(fast, "max_violation_no_slack"),
            th["violation_no_slack"],
            "<=",
            "",
            (
                f"reference {closed.get('reference')}; {_get(fast, 'n_no_slack')} problems"
                if fast
                else fast_note
            ),
            "violation_no_slack",
        ),
        target(
            f"csnlp / fast median solve time > {th['csnlp_over_fast']:g}",
            _get(speed.get("csnlp"), "median_ratio"),
            th["csnlp_over_fast"],
            ">",
            "x",
            fast_note or ("" if "csnlp" in speed else "csnlp not run or unavailable"),
            "csnlp_over_fast",
        ),
    ]
    return targets


def _fast_failures(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The fast solver's failed solves over every horizon (main comparison included)."""
    parts = ("closed_loop", "closed_loop_alone", "horizon_sweep")
    return [f for f in results.get("failures", []) if f["solver"] == "fast" and f["part"] in parts]


def _horizon_targets(results: dict[str, Any], th: Mapping[str, float]) -> list[dict]:
    """Fast medians at N = 15 and 30, failures at every horizon, agreement with IPOPT."""
    rows = {r["horizon"]: r for r in results.get("horizons", {}).get("results", [])}
    targets = []
    for n in (15, 30):
        key = f"horizon_{n}_median_ms"
        fast = (rows.get(n) or {}).get("summary", {}).get("fast")
        note = f"{rows[n]['n_problems']} problems" if n in rows else "horizon not run"
        targets.append(
            target(
                f"fast median solve <= {th[key]:g} ms at N={n}, Ns=150 (closed loop)",
                _get(fast, "solve_ms_median"),
                th[key],
                "<=",
                "ms",
                note,
                key,
            )
        )
    measured = bool(rows) or "closed_loop" in results
    failed = _fast_failures(results)
    where = ", ".join(f"N={n}" for n in sorted(rows)) or "-"
    listed = "; ".join(f"seed {f['seed']} step {f['step']} N={f['N']}: {f['kind']}" for f in failed)
    targets.append(
        target(
            f"failed fast solves <= {th['fast_failures']:g} at every horizon ({where})",
            float(len(failed)) if measured else None,
            th["fast_failures"],
            "<=",
            "",
            listed[:400],
            "fast_failures",
        )
    )
    shares = {
        n: r["agreement"]["share_within_pct"]
        for n, r in sorted(rows.items())
        if r.get("agreement") and r["agreement"]["n_compared"]
    }
    targets.append(
        target(
            f"problems where fast is within {GAP_TOL:g} (relative) of IPOPT's objective "
            f">= {th['within_share_pct']:g}% at every horizon",
            min(shares.values()) if shares else None,
            th["within_share_pct"],
            ">=",
            "%",
            ", ".join(f"N={n}: {_fmt(v, '.1f')}%" for n, v in shares.items()),
            "within_share_pct",
        )
    )
    return targets


def large_ns_median(results: dict[str, Any], name: str = "fast") -> float | None:
    """``name``'s median solve time [ms] at ``Ns`` = :data:`LARGE_NS` in the sweep."""
    for row in results.get("sweep", {}).get("results", []):
        if row["n_scenarios"] == LARGE_NS and name in row["summary"]:
            return row["summary"][name]["solve_ms_median"]
    return None


def _other_targets(results: dict[str, Any], th: Mapping[str, float]) -> list[dict]:
    """Large Ns, QP failures, the particle filter, a cold first build and a whole episode."""
    sweep_n = results.get("sweep", {}).get("horizon")
    qp = [
        f
        for f in results.get("failures", [])
        if f["kind"] == "QP_Failed"
        and (f["solver"] in FAST_SOLVERS or f["solver"] in SOLVER_VARIANTS)
    ]
    others = sum(f["kind"] == "QP_Failed" for f in results.get("failures", [])) - len(qp)
    pf_rows = results.get("particle_filter", {}).get("results", [])
    pf = next((r for r in pf_rows if r["n_particles"] == PF_PARTICLES), None)
    episode = results.get("episode")
    first = results.get("first_solve", {})
    cold = next(
        (
            r
            for r in first.get("results", [])
            if r.get("codegen_cache") == "fresh" and "total_s" in r
        ),
        None,
    )
    return [
        target(
            f"fast median solve <= {th['large_ns_median_ms']:g} ms at N={sweep_n}, Ns={LARGE_NS}",
            large_ns_median(results),
            th["large_ns_median_ms"],
            "<=",
            "ms",
            key="large_ns_median_ms",
        ),
        target(
            f"QP_Failed of the fast solvers over the whole run <= {th['qp_failed']:g}",
            float(len(qp)) if "closed_loop" in results else None,
            th["qp_failed"],
            "<=",
            "",
            f"other solvers: {others}",
            "qp_failed",
        ),
        target(
            f"PF step (transition + update), {PF_PARTICLES} particles, median "
            f"<= {th['pf_step_ms']:g} ms",
            _get(pf, "step_ms_median"),
            th["pf_step_ms"],
            "<=",
            "ms",
            (
                f"with NumPy's ziggurat normals: "
                f"{_fmt(pf.get('numpy_normals_step_ms_median'), '.3f')} ms"
                if pf
                else ""
            ),
            "pf_step_ms",
        ),
        target(
            f"fast solver built with an empty C library cache, build + first solve "
            f"<= {th['cold_build_s']:g} s",
            _get(cold, "total_s"),
            th["cold_build_s"],
            "<=",
            "s",
            (
                f"C library compile {_fmt(cold.get('codegen_compile_time_s'), '.2f')} s, "
                f"first solve {_fmt(cold.get('first_solve_ms'), '.1f')} ms, "
                f"backend {cold.get('backend')}"
                if cold
                else "first-solve part not run"
            ),
            "cold_build_s",
        ),
        target(
            f"whole paper episode, scenario agent, <= {th['episode_s']:g} s wall",
            _get(episode, "episode_s"),
            th["episode_s"],
            "<=",
            "s",
            "" if episode is None else f"solver {episode['solver']}, {episode['steps']} steps",
            "episode_s",
        ),
    ]


def evaluate_targets(
    results: dict[str, Any], thresholds: Mapping[str, float] | None = None
) -> list[dict[str, Any]]:
    """PASS/FAIL of every target but issue 37's (the compiled loop and the export, judged by
    :func:`experiments.benchmark.compiled.compiled_targets`, which imports this module), from
    the measurements in a benchmark result.

    Args:
        results: a benchmark result (``closed_loop``, ``horizons``, ``sweep``,
            ``particle_filter``, ``episode``, ``failures``; missing parts give SKIP).
        thresholds: overrides of :data:`DEFAULT_THRESHOLDS` by key.

    Returns:
        :func:`target` dicts: the main size's speed and accuracy, the horizons, then large
        ``Ns``, QP failures, the filter, the cold first build and the episode.
    """
    th = check_thresholds(thresholds)
    closed = results.get("closed_loop", {})
    return (
        _closed_loop_targets(closed, th)
        + _horizon_targets(results, th)
        + _other_targets(results, th)
    )


def failed_targets(targets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The targets that FAIL (SKIP is not a failure)."""
    return [t for t in targets if t["passed"] is False]


__all__ = [
    "ANCHOR",
    "DEFAULT_THRESHOLDS",
    "LARGE_NS",
    "TEXTBOOK",
    "check_thresholds",
    "evaluate_targets",
    "failed_targets",
    "large_ns_median",
    "speed_targets",
    "target",
]
