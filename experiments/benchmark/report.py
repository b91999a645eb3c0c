"""The benchmark's report: :func:`format_report` (every table, failure and check),
:func:`format_markdown` (speed table and checks) and :func:`json_ready` (strict JSON).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from experiments.benchmark.checks import ANCHOR, LARGE_NS, TEXTBOOK, check_lines, large_ns_median
from experiments.benchmark.solvers import GAP_TOL, NO_SLACK_TOL, SOLVER_VARIANTS

SPEED_TABLE_SOLVERS = ("fast", "fast_c", ANCHOR, "ipopt", TEXTBOOK, "csnlp")


def _fmt(x: Any, spec: str = ".1f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def _get(d: dict | None, key: str) -> Any:
    return None if d is None else d.get(key)


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b <= 0:
        return None
    return a / b


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
    for name in ("fast", "fast_c", *SOLVER_VARIANTS):
        large = large_ns_median(results, name)
        if large is not None:
            rows.append((f"{name}, Ns={LARGE_NS} (sweep)", _fmt(large, ".2f"), "", "", ""))
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
    textbook = _ratio(med.get(TEXTBOOK), med.get("fast"))
    anchor = _ratio(med.get(ANCHOR), med.get("fast"))
    return (
        f"{ANCHOR} / fast: {_fmt(anchor, '.1f')}x; "
        f"textbook / fast: {_fmt(textbook, '.0f')}x (medians)"
    )


def _table_head(head: str, *units: str) -> list[str]:
    """A text table's column titles, the units line(s) under them, and a rule as wide."""
    return [head, *units, "-" * len(head)]


def format_speed_table(results: dict[str, Any]) -> str:
    """The speed table (every solver side by side, the Ns=1000 row, the two ratios)."""
    head = f"{'solver':<28}{'median':>9}{'p95':>9}{'x fast':>8}  objective vs reference"
    lines = [
        f"Speed ({_speed_title(results)})",
        *_table_head(head, f"{'':<28}{'[ms]':>9}{'[ms]':>9}"),
    ]
    for name, median, p95_, ratio, objective in speed_rows(results):
        lines.append(f"{name:<28}{median:>9}{p95_:>9}{ratio:>8}  {objective}")
    lines.append(_ratio_line(results))
    return "\n".join(lines)


def format_markdown(results: dict[str, Any]) -> str:
    """The speed table and the checks as Markdown (e.g. for docs/benchmark.md)."""
    lines = [
        f"| solver ({_speed_title(results)}) | median [ms] | p95 [ms] | x fast (median) "
        "| objective vs reference |",
        "|---|---|---|---|---|",
    ]
    for name, median, p95_, ratio, objective in speed_rows(results):
        lines.append(f"| {name} | {median} | {p95_} | {ratio} | {objective} |")
    lines += ["", _ratio_line(results) + ".", ""]
    lines += ["```text", *check_lines(results.get("checks", [])), "```"]
    if results.get("compiled"):
        from experiments.benchmark.compiled import compiled_lines

        lines += ["", "```text", *compiled_lines(results), "```"]
    return "\n".join(lines) + "\n"


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
    lines += _table_head(head, f"{'':<24}{'[s]':>7}{'[ms]':>9}{'[ms]':>9}{'[ms]':>9}{'[ms]':>10}")
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
    lines += _table_head(head)
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


def _horizon_lines(horizons: dict[str, Any]) -> list[str]:
    lines = [
        "Horizons (closed-loop problems recorded at each N, warm-started, side by side; "
        f"within: fast at most {GAP_TOL:g} (relative) above IPOPT's objective)"
    ]
    head = (
        f"{'N':>4}{'Ns':>6}{'problems':>10}{'fast med':>10}{'p95':>9}{'iters':>7}{'fails':>7}"
        f"{'ipopt med':>11}{'p95':>9}{'iters':>7}{'fails':>7}{'x fast':>8}{'within':>9}"
    )
    lines += _table_head(head, f"{'':>20}{'[ms]':>10}{'[ms]':>9}{'':>14}{'[ms]':>11}{'[ms]':>9}")
    for row in horizons.get("results", []):
        cells = []
        for name in ("fast", "ipopt"):
            s = row["summary"].get(name)
            if s is None:
                cells.append(f"{'-':>10}{'-':>9}{'-':>7}{'-':>7}" if name == "fast" else "")
                continue
            width = 10 if name == "fast" else 11
            cells.append(
                f"{_fmt(s['solve_ms_median'], '.2f'):>{width}}{_fmt(s['solve_ms_p95'], '.2f'):>9}"
                f"{_fmt(s['iterations_median'], '.0f'):>7}"
                f"{s['n_problems'] - s['n_success']:>7}"
            )
        ipopt, fast = row["summary"].get("ipopt"), row["summary"].get("fast")
        ratio = _ratio(_get(ipopt, "solve_ms_median"), _get(fast, "solve_ms_median"))
        agreement = row.get("agreement") or {}
        within = (
            f"{agreement['n_within']}/{agreement['n_compared']}"
            if agreement.get("n_compared")
            else "-"
        )
        lines.append(
            f"{row['horizon']:>4}{row['n_scenarios']:>6}{row['n_problems']:>10}"
            + "".join(cells)
            + f"{_fmt(ratio, '.0f'):>8}{within:>9}"
        )
    lines.append(
        "N at the config's horizon: the main comparison's problems (whole episodes); "
        "other N: the first steps of each seed's episode run at that N."
    )
    feasible = [row for row in horizons.get("results", []) if row.get("feasibility")]
    if feasible:
        lines.append(
            "Infeasible for every input (the least slack of the shared linear constraints "
            "over all inputs, an LP, is > 0; controllers.feasibility):"
        )
        for row in feasible:
            f = row["feasibility"]
            text = f"  N = {row['horizon']}: {f['n_infeasible']}/{f['n_problems']} problems"
            if f["n_infeasible"]:
                seeds = ", ".join(str(s) for s in f["seeds_infeasible"])
                text += (
                    f" (seeds {seeds}); least slack median {_fmt(f['bound_median'], '.3g')}, "
                    f"max {_fmt(f['bound_max'], '.3g')}; fast solver's slack / least slack "
                    f"{_fmt(f['slack_over_bound_median'], '.3f')} (median over those)"
                )
            lines.append(text)
    return lines


def _failure_lines(failures: list[dict[str, Any]]) -> list[str]:
    if not failures:
        return ["Failed solves: none (every solver, every part)"]
    kinds: dict[str, int] = {}
    for f in failures:
        kinds[f["kind"]] = kinds.get(f["kind"], 0) + 1
    lines = [
        f"Failed solves: {len(failures)} ("
        + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items()))
        + ")",
        f"{'part':<20}{'solver':<25}{'seed':>5}{'step':>6}{'N':>4}{'Ns':>6}"
        f"{'least slack':>13}  status",
    ]
    for f in failures:
        least = f.get("least_slack")
        lines.append(
            f"{f['part']:<20}{f['solver']:<25}{f['seed']:>5}{f['step']:>6}{f['N']:>4}"
            f"{f['Ns']:>6}{_fmt(least, '.3g'):>13}  {f['status'][:80]}"
        )
    lines.append(
        "least slack: the least total slack any input leaves on that problem (> 0: no input "
        "satisfies every scenario; '-': not computed)"
    )
    return lines


def _first_solve_lines(first: dict[str, Any]) -> list[str]:
    lines = [f"First solve of a freshly built {first['solver']} solver (build + first solve)"]
    for i, r in enumerate(first.get("results", [])):
        if "error" in r:
            lines.append(f"  build {i + 1}: unavailable: {r['error']}")
            continue
        extra = ", ".join(
            f"{k} {_fmt(v, '.2f') if isinstance(v, float) else v}"
            for k, v in r.items()
            if k not in ("build_s", "first_solve_ms", "total_s", "success")
        )
        lines.append(
            f"  build {i + 1}: build {r['build_s']:.2f} s, first solve "
            f"{r['first_solve_ms']:.1f} ms, total {r['total_s']:.2f} s, "
            f"success {r['success']}; {extra}"
        )
    return lines


def format_report(results: dict[str, Any]) -> str:
    """The printed report: speed table, closed-loop details, sweep, filter, episode, checks."""
    lines = []
    if results.get("closed_loop"):
        lines += [format_speed_table(results), ""]
        lines += _closed_loop_lines(results) + [""]
    if results.get("horizons"):
        lines += _horizon_lines(results["horizons"]) + [""]
    if results.get("sweep"):
        lines += _sweep_lines(results["sweep"]) + [""]
    if results.get("first_solve"):
        lines += _first_solve_lines(results["first_solve"]) + [""]
    pf = results.get("particle_filter")
    if pf:
        lines.append(f"Particle filter ({pf['n_steps']} steps per size)")
        head = (
            f"{'particles':>10}{'step med':>10}{'p95':>9}{'update med':>12}{'predict med':>13}"
            f"{'ziggurat step med':>19}"
        )
        units = f"{'':>10}{'[ms]':>10}{'[ms]':>9}{'[ms]':>12}{'[ms]':>13}{'[ms]':>19}"
        lines += _table_head(head, units)
        for r in pf["results"]:
            lines.append(
                f"{r['n_particles']:>10}{_fmt(r['step_ms_median'], '.3f'):>10}"
                f"{_fmt(r['step_ms_p95'], '.3f'):>9}{_fmt(r['update_ms_median'], '.3f'):>12}"
                f"{_fmt(r['predict_ms_median'], '.3f'):>13}"
                f"{_fmt(r.get('numpy_normals_step_ms_median'), '.3f'):>19}"
            )
        lines.append(
            "ziggurat: the same filter drawing its noise with NumPy's ziggurat (the filter "
            "before its Box-Muller draws), interleaved on the same measurements."
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
    if "failures" in results:
        lines += _failure_lines(results["failures"]) + [""]
    if results.get("compiled"):
        from experiments.benchmark.compiled import compiled_lines

        lines += compiled_lines(results) + [""]
    lines.append("Checks (lfm-benchmark --check fails on a FAIL; --threshold KEY=VALUE)")
    lines += [f"  {line}" for line in check_lines(results.get("checks", []))]
    return "\n".join(lines)


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
