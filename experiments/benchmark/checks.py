"""The benchmark's checks: named bounds on a run's figures, judged by ``lfm-benchmark --check``.

Speed bounds are about twice the documented run's figures (``docs/benchmark.md``); accuracy
bounds hold on any machine. ``--threshold KEY=VALUE`` changes a bound; a figure not measured
is SKIP. Figures are of the closed-loop problems at the config's size unless said otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from experiments.benchmark.solvers import FAST_SOLVERS, GAP_TOL, SOLVER_VARIANTS

TEXTBOOK = "ipopt_multiple_shooting"  # IPOPT on the textbook form: the objective reference
ANCHOR = "sqpmethod"  # CasADi sqpmethod + qpOASES, JIT-compiled
LARGE_NS = 5000  # the scenario sweep's count of the large-Ns check
PF_PARTICLES = 7000  # the filter size of the filter check
_FAST_PARTS = ("closed_loop", "closed_loop_alone", "horizon_sweep")

Figure = Callable[[Mapping[str, Any]], "float | None"]


@dataclass(frozen=True)
class Check:
    """One named bound: ``key`` (``--threshold KEY=VALUE``), ``text``, ``op`` (``"<="`` or
    ``">="``), ``default``, ``unit`` (``"x"``, ``"%"``, ...) and ``figure`` (reads it from a
    result; ``None``: not measured).
    """

    key: str
    text: str
    op: str
    default: float
    unit: str
    figure: Figure


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def _summary(r: Mapping[str, Any], name: str) -> Mapping[str, Any]:
    return r.get("closed_loop", {}).get("summary", {}).get(name) or {}


def _median(name: str, key: str = "solve_ms_median") -> Figure:
    return lambda r: _finite(_summary(r, name).get(key))


def _ratio(slow: str, fast: str) -> Figure:
    def figure(r: Mapping[str, Any]) -> float | None:
        a, b = _median(slow)(r), _median(fast)(r)
        return a / b if a is not None and b is not None and b > 0 else None

    return figure


def _horizon_median(n: int) -> Figure:
    def figure(r: Mapping[str, Any]) -> float | None:
        for row in r.get("horizons", {}).get("results", []):
            if row["horizon"] == n:
                return _finite((row["summary"].get("fast") or {}).get("solve_ms_median"))
        return None

    return figure


def large_ns_median(r: Mapping[str, Any], name: str = "fast") -> float | None:
    """``name``'s median solve time [ms] at ``Ns`` = :data:`LARGE_NS` in the sweep."""
    for row in r.get("sweep", {}).get("results", []):
        if row["n_scenarios"] == LARGE_NS and name in row["summary"]:
            return _finite(row["summary"][name]["solve_ms_median"])
    return None


def _worse_share(r: Mapping[str, Any]) -> float | None:
    """[%] problems where fast ends more than GAP_TOL above the textbook's objective."""
    closed = r.get("closed_loop", {})
    fast = _summary(r, "fast")
    n = fast.get("n_reference_ok")
    if closed.get("reference") != TEXTBOOK or not n:
        return None
    return 100.0 * len(fast.get("worse_than_reference", [])) / n


def _within_share(r: Mapping[str, Any]) -> float | None:
    """[%] problems within GAP_TOL of IPOPT, at the worst horizon."""
    shares = [
        row["agreement"]["share_within_pct"]
        for row in r.get("horizons", {}).get("results", [])
        if row.get("agreement") and row["agreement"]["n_compared"]
    ]
    return min(shares) if shares else None


def _fast_failures(r: Mapping[str, Any]) -> float | None:
    if "closed_loop" not in r:
        return None
    failed = [
        f for f in r.get("failures", []) if f["solver"] == "fast" and f["part"] in _FAST_PARTS
    ]
    return float(len(failed))


def _qp_failed(r: Mapping[str, Any]) -> float | None:
    if "closed_loop" not in r:
        return None
    fast = set(FAST_SOLVERS) | set(SOLVER_VARIANTS)
    return float(
        sum(f["kind"] == "QP_Failed" and f["solver"] in fast for f in r.get("failures", []))
    )


def _pf_step(r: Mapping[str, Any]) -> float | None:
    rows = r.get("particle_filter", {}).get("results", [])
    row = next((x for x in rows if x["n_particles"] == PF_PARTICLES), None)
    return None if row is None else _finite(row["step_ms_median"])


def _cold_build(r: Mapping[str, Any]) -> float | None:
    rows = r.get("first_solve", {}).get("results", [])
    row = next((x for x in rows if x.get("codegen_cache") == "fresh" and "total_s" in x), None)
    return None if row is None else _finite(row["total_s"])


def _export(key: str) -> Figure:
    return lambda r: _finite(r.get("compiled", {}).get("export", {}).get(key))


def _robust_step(r: Mapping[str, Any]) -> float | None:
    us = _finite(r.get("compiled", {}).get("export", {}).get("robust", {}).get("c_step_us_median"))
    return None if us is None else us / 1e3


def _export_dependencies(r: Mapping[str, Any]) -> float | None:
    deps = r.get("compiled", {}).get("export", {}).get("dependencies")
    if not deps:
        return None
    return float(len(deps["other_libraries"]) + len(deps["outside_libc_libm"]))


CHECKS: tuple[Check, ...] = (
    # Speed at the main size (the documented run: 0.77 / 2.47, 2.64 / 10.05 ms, 33.6x, 476x).
    Check("fast_c_median_ms", "fast_c median solve", "<=", 1.5, "ms", _median("fast_c")),
    Check("fast_c_p95_ms", "fast_c p95 solve", "<=", 5.0, "ms", _median("fast_c", "solve_ms_p95")),
    Check("fast_median_ms", "fast median solve", "<=", 5.0, "ms", _median("fast")),
    Check("fast_p95_ms", "fast p95 solve", "<=", 20.0, "ms", _median("fast", "solve_ms_p95")),
    Check(
        "anchor_over_fast_c",
        f"{ANCHOR} + qpOASES median / fast_c median",
        ">=",
        15.0,
        "x",
        _ratio(ANCHOR, "fast_c"),
    ),
    Check(
        "textbook_over_fast_c",
        f"textbook IPOPT ({TEXTBOOK}) median / fast_c median",
        ">=",
        200.0,
        "x",
        _ratio(TEXTBOOK, "fast_c"),
    ),
    # Long horizons and many scenarios (11.0 and 504 ms; 24.0 ms).
    Check("horizon_15_median_ms", "fast median at N = 15", "<=", 25.0, "ms", _horizon_median(15)),
    Check("horizon_30_median_ms", "fast median at N = 30", "<=", 1000.0, "ms", _horizon_median(30)),
    Check(
        "fast_c_ns5000_median_ms",
        f"fast_c median at Ns = {LARGE_NS}",
        "<=",
        50.0,
        "ms",
        lambda r: large_ns_median(r, "fast_c"),
    ),
    # Accuracy: on any machine.
    Check(
        "worse_share_pct",
        f"problems where fast ends > {GAP_TOL:g} (relative) above the textbook",
        "<=",
        2.0,
        "%",
        _worse_share,
    ),
    Check(
        "violation_no_slack",
        "fast's largest violation where the reference (IPOPT) needs no slack",
        "<=",
        1e-6,
        "",
        _median("fast", "max_violation_no_slack"),
    ),
    Check(
        "within_share_pct",
        f"problems where fast is within {GAP_TOL:g} of IPOPT, worst horizon",
        ">=",
        98.0,
        "%",
        _within_share,
    ),
    Check("fast_failures", "failed fast solves, every horizon", "<=", 0.0, "", _fast_failures),
    Check("qp_failed", "QP_Failed of the fast solvers, whole run", "<=", 0.0, "", _qp_failed),
    # The other parts (0.487 ms, 1.37 s, 0.17 s).
    Check(
        "pf_step_ms", f"particle-filter step, {PF_PARTICLES} particles", "<=", 1.0, "ms", _pf_step
    ),
    Check(
        "cold_build_s",
        "fast solver built in an empty C library cache, with its first solve",
        "<=",
        5.0,
        "s",
        _cold_build,
    ),
    Check(
        "episode_s",
        "a whole paper episode of the scenario agent",
        "<=",
        1.0,
        "s",
        lambda r: _finite((r.get("episode") or {}).get("episode_s")),
    ),
    # The exported controller (0.081 ms).
    Check(
        "robust_step_ms",
        "exported robust agent's whole step from C, median",
        "<=",
        0.5,
        "ms",
        _robust_step,
    ),
    Check(
        "export_plan_diff",
        "exported example's plans vs the Python loop's, largest difference",
        "<=",
        1e-6,  # 1e-8 but where no input satisfies the scenarios and builds stop apart
        "",
        _export("plan_diff_max"),
    ),
    Check(
        "export_dependencies",
        "exported library's run-time dependencies beyond libc and libm",
        "<=",
        0.0,
        "",
        _export_dependencies,
    ),
)
DEFAULT_THRESHOLDS: dict[str, float] = {c.key: c.default for c in CHECKS}
_OPS = {"<=": lambda a, b: a <= b, ">=": lambda a, b: a >= b}


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


def run_checks(
    results: Mapping[str, Any], thresholds: Mapping[str, Any] | None = None
) -> list[dict[str, Any]]:
    """Every check of :data:`CHECKS` judged on a run's result: ``key``, ``check``, ``value``
    (``None``: not measured), ``threshold``, ``op``, ``unit``, ``passed`` (``None``: SKIP).
    """
    th = check_thresholds(thresholds)
    out = []
    for c in CHECKS:
        value = c.figure(results)
        out.append(
            {
                "key": c.key,
                "check": c.text,
                "value": value,
                "threshold": th[c.key],
                "op": c.op,
                "unit": c.unit,
                "passed": None if value is None else bool(_OPS[c.op](value, th[c.key])),
            }
        )
    return out


def failed_checks(checks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The checks that FAIL (SKIP is not a failure)."""
    return [c for c in checks if c["passed"] is False]


def _shown(value: float | None, unit: str) -> str:
    if value is None:
        return "-"
    text = f"{value:.3g}"
    return f"{text}{unit}" if unit in ("x", "%") else f"{text} {unit}".rstrip()


def check_lines(checks: list[dict[str, Any]]) -> list[str]:
    """The checks as a text table: verdict, key, measured figure, bound, what it is."""
    width = max((len(c["key"]) for c in checks), default=0)
    lines = []
    for c in checks:
        verdict = {True: "PASS", False: "FAIL", None: "SKIP"}[c["passed"]]
        bound = f"{c['op']} {_shown(c['threshold'], c['unit'])}"
        lines.append(
            f"{verdict}  {c['key']:<{width}}  {_shown(c['value'], c['unit']):>10}  "
            f"{bound:<12}  {c['check']}"
        )
    return lines
