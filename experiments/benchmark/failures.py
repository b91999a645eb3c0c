"""The benchmark's failed solves: what kind each is, and every one with its problem's id."""

from __future__ import annotations

from typing import Any

FAILURE_KINDS = (
    "QP_Failed",
    "Maximum_Iterations_Exceeded",
    "wall_time",
    "infeasible",
    "exception",
    "other",
)


def classify_failure(status: str) -> str:
    """The kind of a failed solve's status, one of :data:`FAILURE_KINDS`."""
    if status.startswith("raised"):
        return "exception"
    if "QP_Failed" in status:
        return "QP_Failed"
    if "Maximum_Iterations_Exceeded" in status:
        return "Maximum_Iterations_Exceeded"
    if "WallTime" in status or "wall time" in status.lower():
        return "wall_time"
    if "nfeasib" in status:
        return "infeasible"
    return "other"


def failures_of(
    records: dict[str, list[dict[str, Any]]], part: str, horizon: int, n_scenarios: int
) -> list[dict[str, Any]]:
    """Every failed solve of ``records``: ``[{"part", "solver", "seed", "step", "N", "Ns", "kind",
    "status"}]``, solver by solver in problem order.
    """
    out = []
    for name, recs in records.items():
        for r in recs:
            if r["success"]:
                continue
            out.append(
                {
                    "part": part,
                    "solver": name,
                    "seed": int(r["seed"]),
                    "step": int(r["step"]),
                    "N": int(horizon),
                    "Ns": int(n_scenarios),
                    "kind": classify_failure(str(r["status"])),
                    "status": str(r["status"]),
                }
            )
    return out
