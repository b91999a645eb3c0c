"""The columns of ``episodes.csv``: :data:`HEAD_COLUMNS`, the system's constraint-group columns
(:func:`group_columns`), :data:`TAIL_COLUMNS` (:func:`row_columns`); :data:`TIMING_COLUMNS`
differ between otherwise identical runs.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

#: Columns of every row before the constraint-group columns, in table order.
HEAD_COLUMNS: tuple[str, ...] = (
    "agent",  # agent name
    "seed",  # env seed
    "success",  # reached the goal
    "steps",  # steps taken
    "time_to_goal",  # [s], NaN without success
    "cost",  # sum of the true stage cost (= -reward) over the episode
)
#: Columns of every row after the constraint-group columns, in table order.
TAIL_COLUMNS: tuple[str, ...] = (
    "failure",  # the env ended the episode as a failure (e.g. left the safety box)
    "latent_rmse",  # [force unit] RMSE of the latent-force estimate; NaN without a filter
    "latent_coverage",  # fraction of steps with the true force in the 2-sigma band
    "solve_time_median",  # [s]
    "solve_time_p95",  # [s]
    "solve_time_max",  # [s]
    # [s] a step's compute, the wall time of the agent's act() (estimator + solve)
    "step_time_median",
    "step_time_max",  # [s]
    "deadline_misses",  # steps whose compute exceeded the control period dt
    "solver_failures",  # steps whose solve returned no usable plan (the agent fell back)
    "unconverged_solves",  # steps whose solve did not converge but gave a usable plan
    "fallback_steps",  # steps that applied a fallback action (previous plan or brake)
    # Steps whose solve agents.deadline stopped, by what the agent applied: the best usable
    # plan reached, its previous plan shifted, the system's fallback input (0 without one).
    "deadline_plans",
    "deadline_shifted",
    "deadline_fallbacks",
    "filter_resets",  # particle-filter restarts after divergence (filter agents)
    "slack_total",  # sum of the per-step constraint slack
    "wall_time",  # [s] whole episode, including building the agent
    "error",  # '' if the episode ran, else "ExceptionType: message"
)

#: Columns that measure time and so differ between otherwise identical runs.
TIMING_COLUMNS: tuple[str, ...] = (
    "solve_time_median",
    "solve_time_p95",
    "solve_time_max",
    "step_time_median",
    "step_time_max",
    "deadline_misses",
    "wall_time",
)

_STR_COLUMNS = ("agent", "error")
_INT_COLUMNS = (
    "seed",
    "steps",
    "solver_failures",
    "unconverged_solves",
    "fallback_steps",
    "deadline_misses",
    "deadline_plans",
    "deadline_shifted",
    "deadline_fallbacks",
    "filter_resets",
)
_BOOL_COLUMNS = ("success", "failure")
_FIXED_COLUMNS = HEAD_COLUMNS + TAIL_COLUMNS
_VIOLATION_SUFFIX = "_violation_steps"  # int columns of the constraint groups
_OVER = "_over_"  # {g}_violation_steps_over_{t}: the steps beyond tolerance t


def _group_names(system: Any) -> tuple[str, ...]:
    """The constraint-group names of a system (or of a sequence of names), in order."""
    groups = getattr(system, "constraint_groups", system)
    if isinstance(groups, str) or not isinstance(groups, Iterable):
        raise ValueError(
            f"{groups!r}: give a ControlSystem or a sequence of constraint-group names"
        )
    return tuple(str(g) for g in groups)


def tolerance_column(group: str, tolerance: float) -> str:
    """The column of a group's violation steps beyond ``tolerance`` [group unit].

    ``{group}_violation_steps_over_{tolerance:g}``, e.g. ``track_violation_steps_over_0.01``.
    """
    return f"{group}{_VIOLATION_SUFFIX}{_OVER}{float(tolerance):g}"


def tolerance_columns(system: Any) -> tuple[tuple[str, float, str], ...]:
    """``(group, tolerance, column)`` of every count beyond ``system.violation_tolerances`` [group
    unit], in the groups' and tolerances' order; empty for a sequence of group names.
    """
    tolerances = getattr(system, "violation_tolerances", None) or {}
    return tuple(
        (g, float(t), tolerance_column(g, t))
        for g in _group_names(system)
        for t in tolerances.get(g, ())
    )


def group_columns(system: Any) -> tuple[str, ...]:
    """Per constraint group ``g`` of ``system`` (or of a sequence of group names, then without
    tolerances): ``{g}_violation_steps`` (excess above 0), ``max_{g}_excess`` (constraint unit),
    then ``{g}_violation_steps_over_{t:g}`` per tolerance ``t``.
    """
    over: dict[str, list[str]] = {}
    for g, _, column in tolerance_columns(system):
        over.setdefault(g, []).append(column)
    return tuple(
        c
        for g in _group_names(system)
        for c in (f"{g}{_VIOLATION_SUFFIX}", f"max_{g}_excess", *over.get(g, ()))
    )


def row_columns(system: Any) -> tuple[str, ...]:
    """Columns of a row of an episode on ``system`` (or its group names), in table order."""
    return HEAD_COLUMNS + group_columns(system) + TAIL_COLUMNS


_GROUP_COLUMN = re.compile(
    rf"(?P<steps>.+){_VIOLATION_SUFFIX}|max_(?P<max>.+)_excess"
    rf"|(?P<over>.+){_VIOLATION_SUFFIX}{_OVER}(?P<tol>[0-9.eE+-]+)"
)


def _table_columns(rows: Iterable[dict[str, Any]]) -> tuple[str, ...]:
    """The columns of saved rows: the fixed ones around the group columns they hold (groups in
    first-seen order, tolerances increasing), other keys after.
    """
    seen: dict[str, None] = {}
    for row in rows:
        seen.update((k, None) for k in row if k not in _FIXED_COLUMNS)
    groups: dict[str, list[tuple[float, str]]] = {}
    for key in seen:
        m = _GROUP_COLUMN.fullmatch(key)
        if m is None:
            continue
        if m.group("over") is not None:
            try:
                tol = float(m.group("tol"))
            except ValueError:
                continue
            groups.setdefault(m.group("over"), []).append((tol, key))
        else:
            groups.setdefault(m.group("steps") or m.group("max"), [])
    ordered = []
    for g, over in groups.items():
        raw = (f"{g}{_VIOLATION_SUFFIX}", f"max_{g}_excess")
        ordered += [c for c in raw if c in seen] + [c for _, c in sorted(over)]
    ordered += [c for c in seen if c not in ordered]
    return HEAD_COLUMNS + tuple(ordered) + TAIL_COLUMNS


def _is_count_column(column: str) -> bool:
    """Integer columns of the constraint groups: raw and tolerance-aware violation steps."""
    return column.endswith(_VIOLATION_SUFFIX) or (
        (m := _GROUP_COLUMN.fullmatch(column)) is not None and m.group("over") is not None
    )


def violation_counts(trajectory: dict[str, np.ndarray], system: Any) -> dict[str, int]:
    """The raw and tolerance-aware violation steps of a trajectory's ``<group>_excess (T,)`` arrays
    (groups without one left out).
    """
    counts: dict[str, int] = {}
    for g in _group_names(system):
        if f"{g}_excess" in trajectory:
            excess = np.asarray(trajectory[f"{g}_excess"], dtype=float)
            counts[f"{g}{_VIOLATION_SUFFIX}"] = int(np.sum(excess > 0.0))
    for g, t, column in tolerance_columns(system):
        if f"{g}_excess" in trajectory:
            counts[column] = int(np.sum(np.asarray(trajectory[f"{g}_excess"], float) > t))
    return counts


def _metric_columns(columns: Sequence[str]) -> tuple[str, ...]:
    return tuple(c for c in columns if c not in ("agent", "seed", "wall_time", "error"))
