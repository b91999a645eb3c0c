"""The benchmark's verdicts and report: PASS/FAIL per target, text, Markdown and JSON.

:func:`speed_targets` judges the issue's speed and accuracy targets from measured numbers
alone; :func:`evaluate_targets` collects those numbers (and the other targets') from a
benchmark result; :func:`format_report` prints the speed table, the detailed tables and
the targets; :func:`format_markdown` gives the speed table as Markdown (for the README);
:func:`json_ready` makes a result strict JSON.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from experiments.bench_solvers import GAP_TOL, NO_SLACK_TOL

TEXTBOOK = "ipopt_multiple_shooting"
SPEED_TABLE_SOLVERS = ("fast", "fast_bicycle", "ipopt", TEXTBOOK, "csnlp")
LARGE_NS = 1000  # the sweep's scenario count of the large-Ns target

# Targets of the issue (N = 7, Ns = 150 closed-loop problems unless said otherwise).
GENERIC_OVER_HAND_MAX = 1.5  # generic fast median / hand-written (fast_bicycle) median
TEXTBOOK_OVER_FAST_MIN = 30.0  # textbook median / fast median
LARGE_NS_MEDIAN_MAX_MS = 50.0  # [ms] fast median at Ns = LARGE_NS
WORSE_SHARE_MAX_PCT = 2.0  # [%] problems where fast ends > GAP_TOL above the textbook
FAST_MEDIAN_MAX_MS = 10.0  # [ms]
FAST_P95_MAX_MS = 25.0  # [ms]
VIOLATION_TOL = 1e-6  # largest scenario violation allowed where no slack is needed
PF_STEP_MAX_MS = 1.0  # [ms] 7000 particles
EPISODE_MAX_S = 3.0  # [s] a whole paper episode


def target(
    text: str, value: float | None, threshold: float, op: str, unit: str = "", note: str = ""
) -> dict[str, Any]:
    """One target, judged from a measured ``value`` (``None`` or NaN: not measured, SKIP).

    Args:
        text: what is required, as printed.
        value: the measured figure.
        threshold: the bound.
        op: ``"<="``, ``">="`` or ``">"``: ``value op threshold`` passes.
        unit: unit of ``value`` and ``threshold`` (``"x"`` for a ratio).
        note: printed after the figure.

    Raises:
        ValueError: for another ``op``.
    """
    ops = {"<=": np.less_equal, ">=": np.greater_equal, ">": np.greater}
    if op not in ops:
        raise ValueError(f"op={op!r}: must be one of {sorted(ops)}")
    measured = value is not None and math.isfinite(value)
    return {
        "target": text,
        "value": value,
        "threshold": threshold,
        "op": op,
        "unit": unit,
        "passed": bool(ops[op](value, threshold)) if measured else None,
        "note": note,
    }


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b <= 0:
        return None
    return a / b


def _problem_list(worse: list[dict[str, Any]], limit: int = 12) -> str:
    items = [
        f"seed {w['seed']} step {w['step']} ({_fmt(w['rel_gap'], '+.1e')})" for w in worse[:limit]
    ]
    more = f", and {len(worse) - limit} more" if len(worse) > limit else ""
    return ", ".join(items) + more


def speed_targets(
    fast_ms: float | None,
    fast_bicycle_ms: float | None,
    textbook_ms: float | None,
    fast_large_ns_ms: float | None,
    worse: list[dict[str, Any]] | None,
    n_compared: int | None,
    where: str = "N=7, Ns=150",
) -> list[dict[str, Any]]:
    """The issue's four speed and accuracy targets, judged from measured figures.

    Args:
        fast_ms: median solve time of the generic fast solver [ms], side by side.
        fast_bicycle_ms: the same of the hand-written one (today's fast solver) [ms].
        textbook_ms: the same of the textbook IPOPT formulation [ms].
        fast_large_ns_ms: fast median at ``Ns`` = :data:`LARGE_NS` [ms].
        worse: the problems where fast ends more than :data:`GAP_TOL` (relative) above the
            textbook (``{"seed", "step", "rel_gap"}``), ``None`` if not compared.
        n_compared: how many problems the textbook solved (the share's denominator).
        where: the problem size, for the texts.

    Returns:
        Four :func:`target` dicts: generic / hand-written, textbook / fast, the large-Ns
        median and the share of problems where fast ends above the textbook.
    """
    generic = _ratio(fast_ms, fast_bicycle_ms)
    textbook = _ratio(textbook_ms, fast_ms)
    measured = f"fast {_fmt(fast_ms, '.2f')} ms"
    share = None
    if worse is not None and n_compared:
        share = 100.0 * len(worse) / n_compared
    if worse is None or not n_compared:
        worse_note = "textbook not run or unavailable"
    elif worse:
        worse_note = f"{len(worse)} of {n_compared}: {_problem_list(worse)}"
    else:
        worse_note = f"none of {n_compared}"
    return [
        target(
            f"generic fast / fast_bicycle median solve time <= {GENERIC_OVER_HAND_MAX:g} "
            f"({where}, side by side)",
            generic,
            GENERIC_OVER_HAND_MAX,
            "<=",
            "x",
            f"{measured}, fast_bicycle {_fmt(fast_bicycle_ms, '.2f')} ms",
        ),
        target(
            f"textbook ({TEXTBOOK}) / fast median solve time >= {TEXTBOOK_OVER_FAST_MIN:g} "
            f"({where}, side by side)",
            textbook,
            TEXTBOOK_OVER_FAST_MIN,
            ">=",
            "x",
            f"{measured}, textbook {_fmt(textbook_ms, '.1f')} ms",
        ),
        target(
            f"fast median solve <= {LARGE_NS_MEDIAN_MAX_MS:g} ms at Ns={LARGE_NS}",
            fast_large_ns_ms,
            LARGE_NS_MEDIAN_MAX_MS,
            "<=",
            "ms",
        ),
        target(
            f"problems where fast ends > {GAP_TOL:g} (relative) above the textbook "
            f"<= {WORSE_SHARE_MAX_PCT:g}%",
            share,
            WORSE_SHARE_MAX_PCT,
            "<=",
            "%",
            worse_note,
        ),
    ]


def _get(d: dict | None, key: str) -> Any:
    return None if d is None else d.get(key)


def large_ns_median(results: dict[str, Any], name: str = "fast") -> float | None:
    """``name``'s median solve time [ms] at ``Ns`` = :data:`LARGE_NS` in the sweep."""
    for row in results.get("sweep", {}).get("results", []):
        if row["n_scenarios"] == LARGE_NS and name in row["summary"]:
            return row["summary"][name]["solve_ms_median"]
    return None


def _closed_loop_targets(closed: dict[str, Any]) -> list[dict[str, Any]]:
    """The fast solver's latency, its speed over csnlp and its violations (closed loop)."""
    fast = closed.get("summary", {}).get("fast")
    problem = closed.get("problem", {})
    where = f"N={problem.get('horizon')}, Ns={problem.get('n_scenarios')}"
    fast_note = "" if fast else "fast solver unavailable"
    alone = (closed.get("alone") or {}).get("fast")

    def latency_note(key: str) -> str:
        if not fast:
            return fast_note
        if alone:
            return f"warm-started solves; the fast solvers alone: {_fmt(alone.get(key))} ms"
        return "warm-started solves"

    speed = closed.get("speedup", {})
    return [
        target(
            f"fast median solve <= {FAST_MEDIAN_MAX_MS:g} ms ({where}, closed loop, side by side)",
            _get(fast, "solve_ms_median"),
            FAST_MEDIAN_MAX_MS,
            "<=",
            "ms",
            latency_note("solve_ms_median"),
        ),
        target(
            f"fast p95 solve <= {FAST_P95_MAX_MS:g} ms ({where}, side by side)",
            _get(fast, "solve_ms_p95"),
            FAST_P95_MAX_MS,
            "<=",
            "ms",
            latency_note("solve_ms_p95"),
        ),
        target(
            "csnlp / fast median solve time > 1",
            _get(speed.get("csnlp"), "median_ratio"),
            1.0,
            ">",
            "x",
            fast_note or ("" if "csnlp" in speed else "csnlp not run or unavailable"),
        ),
        target(
            f"fast max violation <= {VIOLATION_TOL:g} where the reference needs no slack",
            _get(fast, "max_violation_no_slack"),
            VIOLATION_TOL,
            "<=",
            "",
            (
                f"reference {closed.get('reference')}; {_get(fast, 'n_no_slack')} problems"
                if fast
                else fast_note
            ),
        ),
    ]


def _filter_and_episode_targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The particle filter's step and update at 7000 particles, a whole episode."""
    pf_rows = results.get("particle_filter", {}).get("results", [])
    pf7000 = next((r for r in pf_rows if r["n_particles"] == 7000), None)
    targets = [
        target(
            f"PF {what}, 7000 particles, median <= {PF_STEP_MAX_MS:g} ms",
            _get(pf7000, key),
            PF_STEP_MAX_MS,
            "<=",
            "ms",
        )
        for what, key in (
            ("step (transition + update)", "step_ms_median"),
            ("update alone", "update_ms_median"),
        )
    ]
    episode = results.get("episode")
    targets.append(
        target(
            f"whole paper episode, scenario agent, <= {EPISODE_MAX_S:g} s wall",
            _get(episode, "episode_s"),
            EPISODE_MAX_S,
            "<=",
            "s",
            "" if episode is None else f"solver {episode['solver']}, {episode['steps']} steps",
        )
    )
    return targets


def evaluate_targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    """PASS/FAIL of every target, from the measurements in a benchmark result.

    The issue's speed targets first (:func:`speed_targets`), then the fast solver's
    latency, csnlp, violations, the particle filter and the episode.
    """
    closed = results.get("closed_loop", {})
    summary = closed.get("summary", {})
    fast = summary.get("fast")
    problem = closed.get("problem", {})
    compared = closed.get("reference") == TEXTBOOK and fast is not None
    targets = speed_targets(
        _get(fast, "solve_ms_median"),
        _get(summary.get("fast_bicycle"), "solve_ms_median"),
        _get(summary.get(TEXTBOOK), "solve_ms_median"),
        large_ns_median(results),
        fast.get("worse_than_reference") if compared else None,
        fast.get("n_reference_ok") if compared else None,
        f"N={problem.get('horizon')}, Ns={problem.get('n_scenarios')}",
    )
    return targets + _closed_loop_targets(closed) + _filter_and_episode_targets(results)


# --------------------------------------------------------------------------- text


def _fmt(x: Any, spec: str = ".1f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def _objective_column(s: dict[str, Any], name: str, reference: str | None) -> str:
    if name == reference:
        return "reference"
    if "n_worse" not in s:
        return "-"
    return f"higher on {s['n_worse']}, lower on {s['n_better']} of {s['n_compared']}"


def speed_rows(results: dict[str, Any]) -> list[tuple[str, str, str, str, str]]:
    """Rows ``(solver, median, p95, x fast, objective vs reference)`` of the speed table."""
    closed = results.get("closed_loop", {})
    rows = []
    for name in SPEED_TABLE_SOLVERS:
        info = closed.get("solvers", {}).get(name)
        if info is None:
            continue
        if not info["available"]:
            rows.append((name, "-", "-", "-", f"unavailable: {info['reason']}"))
            continue
        s = closed["summary"][name]
        ratio = "1" if name == "fast" else _fmt(_get(closed["speedup"].get(name), "median_ratio"))
        rows.append(
            (
                name,
                _fmt(s["solve_ms_median"], ".2f"),
                _fmt(s["solve_ms_p95"], ".2f"),
                ratio,
                _objective_column(s, name, closed.get("reference")),
            )
        )
    for name, s in (closed.get("alone") or {}).items():
        rows.append(
            (
                f"{name}, alone",
                _fmt(s["solve_ms_median"], ".2f"),
                _fmt(s["solve_ms_p95"], ".2f"),
                "",
                "",
            )
        )
    large = large_ns_median(results)
    if large is not None:
        rows.append((f"fast, Ns={LARGE_NS} (sweep)", _fmt(large, ".2f"), "", "", ""))
    return rows


def _speed_title(results: dict[str, Any]) -> str:
    closed = results.get("closed_loop", {})
    p = closed.get("problem", {})
    seeds = results.get("meta", {}).get("seeds")
    return (
        f"N = {p.get('horizon')}, Ns = {p.get('n_scenarios')}, {closed.get('n_problems')} "
        f"closed-loop problems of seeds {seeds}, warm-started, side by side"
    )


def _ratio_line(results: dict[str, Any]) -> str:
    summary = results.get("closed_loop", {}).get("summary", {})
    med = {name: _get(s, "solve_ms_median") for name, s in summary.items()}
    generic = _ratio(med.get("fast"), med.get("fast_bicycle"))
    textbook = _ratio(med.get(TEXTBOOK), med.get("fast"))
    return (
        f"generic fast / fast_bicycle: {_fmt(generic, '.2f')}x; "
        f"textbook / fast: {_fmt(textbook, '.0f')}x (medians)"
    )


def format_speed_table(results: dict[str, Any]) -> str:
    """The speed table (every solver side by side, the Ns=1000 row, the two ratios)."""
    head = f"{'solver':<28}{'median':>9}{'p95':>9}{'x fast':>8}  objective vs reference"
    lines = [f"Speed ({_speed_title(results)})", head, f"{'':<28}{'[ms]':>9}{'[ms]':>9}"]
    lines.append("-" * len(head))
    for name, median, p95_, ratio, objective in speed_rows(results):
        lines.append(f"{name:<28}{median:>9}{p95_:>9}{ratio:>8}  {objective}")
    lines.append(_ratio_line(results))
    return "\n".join(lines)


def format_markdown(results: dict[str, Any]) -> str:
    """The speed table and the targets as Markdown (e.g. for the README)."""
    lines = [
        f"| solver ({_speed_title(results)}) | median [ms] | p95 [ms] | x fast (median) "
        "| objective vs reference |",
        "|---|---|---|---|---|",
    ]
    for name, median, p95_, ratio, objective in speed_rows(results):
        lines.append(f"| {name} | {median} | {p95_} | {ratio} | {objective} |")
    lines += ["", _ratio_line(results) + ".", ""]
    for t in results.get("targets", []):
        lines.append(f"- {_target_line(t)}")
    return "\n".join(lines) + "\n"


def _target_line(t: dict[str, Any]) -> str:
    verdict = {True: "PASS", False: "FAIL", None: "SKIP"}[t["passed"]]
    if t["passed"] is None:
        measured = "not measured"
    else:
        unit = f" {t['unit']}" if t["unit"] and t["unit"] not in ("x", "%") else t["unit"]
        measured = f"measured {_fmt(t['value'], '.3g')}{unit}"
    note = f"  ({t['note']})" if t["note"] else ""
    return f"{verdict}  {t['target']}: {measured}{note}"


def _timing_columns(s: dict[str, Any]) -> str:
    """Median, p95, max, wall median [ms], iterations and successes of a timing summary."""
    iters = f"{_fmt(s['iterations_median'], '.0f')}/{_fmt(s['iterations_max'], '.0f')}"
    return (
        f"{_fmt(s['solve_ms_median']):>9}{_fmt(s['solve_ms_p95']):>9}"
        f"{_fmt(s['solve_ms_max']):>9}{_fmt(s['wall_ms_median']):>10}{iters:>8}"
        f"{s['n_success']:>4}/{s['n_problems']:<3}"
    )


def _closed_loop_lines(results: dict[str, Any]) -> list[str]:
    closed = results["closed_loop"]
    meta = results.get("meta", {})
    lines = [
        f"Closed-loop problems in detail (<= {meta.get('max_steps')} steps per seed, recorded "
        f"with the {meta.get('recording_solver')} solver; objective reference: "
        f"{closed['reference']})"
    ]
    head = (
        f"{'solver':<24}{'build':>7}{'median':>9}{'p95':>9}{'max':>9}{'wall med':>10}"
        f"{'iters':>8}{'ok':>8}{'|gap| med':>11}{'|gap| max':>11}{'viol@0':>10}"
    )
    lines += [head, f"{'':<24}{'[s]':>7}{'[ms]':>9}{'[ms]':>9}{'[ms]':>9}{'[ms]':>10}"]
    lines.append("-" * len(head))
    for name, info in closed["solvers"].items():
        if not info["available"]:
            lines.append(f"{name:<24}unavailable: {info['reason']}")
            continue
        s = closed["summary"][name]
        lines.append(
            f"{name:<24}{_fmt(s['build_time_s'], '.2f'):>7}{_timing_columns(s)}"
            f"{_fmt(s.get('rel_gap_abs_median'), '.1e'):>11}"
            f"{_fmt(s.get('rel_gap_abs_max'), '.1e'):>11}"
            f"{_fmt(s.get('max_violation_no_slack'), '.1e'):>10}"
        )
    for name, s in (closed.get("alone") or {}).items():
        lines.append(
            f"{name + ' (alone)':<24}{'':>7}{_timing_columns(s)}  plans differ from side by "
            f"side by <= {_fmt(s['plan_difference_max'], '.1e')}"
        )
    lines.append(
        "gap: relative objective gap to the reference where both succeed; viol@0: largest "
        f"scenario violation where the reference needs no slack (<= {NO_SLACK_TOL:g}); "
        "(alone): the same closed loop again without IPOPT or csnlp in between. Times and "
        "iterations: warm-started solves; each closed loop's first problem is apart: "
        + ", ".join(
            f"{name} cold max {_fmt(s.get('cold_solve_ms_max'))} ms"
            for name, s in closed["summary"].items()
        )
        + "."
    )
    for name, s in closed["summary"].items():
        if s.get("n_worse") or s.get("n_better"):
            lines.append(
                f"  {name}: objective above the reference by > {GAP_TOL:g} on "
                f"{s['n_worse']} problems, below on {s['n_better']} "
                f"(signed rel gap {_fmt(s['rel_gap_min'], '.1e')} .. "
                f"{_fmt(s['rel_gap_max'], '.1e')})"
            )
        if s.get("n_restarted"):
            lines.append(
                f"    re-solved from the {closed['reference']}'s solution: signed gap max "
                f"{_fmt(s.get('restart_rel_gap_max'), '.1e')}, |gap| max "
                f"{_fmt(s['restart_rel_gap_abs_max'], '.1e')} on those "
                f"{s['n_restarted']} problems"
            )
        if s.get("n_better"):
            lines.append(
                f"    lower plans that are local optima of the full problem (no lower "
                f"objective found next to them): {s.get('n_better_certified', 0)} of "
                f"{s['n_better']}"
            )
    return lines


def _sweep_lines(sweep: dict[str, Any]) -> list[str]:
    lines = [
        f"Scenario sweep (N={sweep['horizon']}, {sweep['n_anchors']} closed-loop anchors, "
        "warm-started; median / p95 [ms], successes)"
    ]
    names: list[str] = []
    for row in sweep["results"]:
        names += [n for n in row["solvers"] if n not in names]
    head = f"{'Ns':>6}" + "".join(f"{n:>24}" for n in names) + f"{'|gap| max fast':>16}"
    lines += [head, "-" * len(head)]
    for row in sweep["results"]:
        cells = []
        for name in names:
            s = row["summary"].get(name)
            if s is None:
                available = row["solvers"].get(name, {}).get("available", True)
                cells.append(f"{'-' if available else 'unavailable':>24}")
                continue
            cell = (
                f"{_fmt(s['solve_ms_median'])} / {_fmt(s['solve_ms_p95'])}"
                f"  {s['n_success']}/{s['n_problems']}"
            )
            cells.append(f"{cell:>24}")
        gap = _get(row["summary"].get("fast"), "rel_gap_abs_max")
        lines.append(f"{row['n_scenarios']:>6}" + "".join(cells) + f"{_fmt(gap, '.1e'):>16}")
    return lines


def format_report(results: dict[str, Any]) -> str:
    """The printed report: speed table, closed-loop details, sweep, filter, episode, targets."""
    lines = []
    if results.get("closed_loop"):
        lines += [format_speed_table(results), ""]
        lines += _closed_loop_lines(results) + [""]
    if results.get("sweep"):
        lines += _sweep_lines(results["sweep"]) + [""]
    pf = results.get("particle_filter")
    if pf:
        lines.append(f"Particle filter ({pf['n_steps']} steps per size)")
        head = f"{'particles':>10}{'step med':>10}{'p95':>9}{'update med':>12}{'predict med':>13}"
        lines += [head, f"{'':>10}{'[ms]':>10}{'[ms]':>9}{'[ms]':>12}{'[ms]':>13}"]
        lines.append("-" * len(head))
        for r in pf["results"]:
            lines.append(
                f"{r['n_particles']:>10}{_fmt(r['step_ms_median'], '.3f'):>10}"
                f"{_fmt(r['step_ms_p95'], '.3f'):>9}{_fmt(r['update_ms_median'], '.3f'):>12}"
                f"{_fmt(r['predict_ms_median'], '.3f'):>13}"
            )
        lines.append("")
    ep = results.get("episode")
    if ep:
        lines.append(
            f"Episode (seed {ep['seed']}, scenario agent, {ep['solver']} solver): "
            f"{ep['episode_s']:.2f} s wall for {ep['steps']} steps (setup {ep['setup_s']:.2f} s), "
            f"goal reached: {ep['reached_goal']}, solver successes {ep['solver_successes']}/"
            f"{ep['steps']}; per step median {ep['step_ms_median']:.1f} ms "
            f"(solve {ep['solve_ms_median']:.1f} ms, p95 {ep['solve_ms_p95']:.1f}, "
            f"max {ep['solve_ms_max']:.1f}; estimate {ep['estimate_ms_median']:.1f} ms)"
        )
        lines.append("")
    lines.append("Targets")
    lines += [f"  {_target_line(t)}" for t in results.get("targets", [])]
    return "\n".join(lines)


# --------------------------------------------------------------------------- JSON


def json_ready(obj: Any) -> Any:
    """Plain JSON data: NumPy scalars and arrays converted, NaN and inf written as null."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


__all__ = [
    "evaluate_targets",
    "format_markdown",
    "format_report",
    "format_speed_table",
    "json_ready",
    "speed_targets",
    "target",
]
