"""How the report writes numbers (significant digits, estimates with intervals) and agents."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from controllers.agents.registry import AGENT_REGISTRY

if TYPE_CHECKING:
    from experiments.report.stats import Estimate


def fmt(value: float, digits: int = 3) -> str:
    """A number for a table: ``digits`` significant digits, thousands separated, "n/a"."""
    if value is None or not np.isfinite(value):
        return "n/a"
    if abs(value) >= 10**digits:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}"


def fmt_estimate(e: Estimate, n_total: int | None = None) -> str:
    """``mean [low, high]``, with ``(n=k)`` when fewer values than episodes were usable."""
    if e.n == 0:
        return "n/a"
    text = f"{fmt(e.mean)} [{fmt(e.low)}, {fmt(e.high)}]"
    if n_total is not None and e.n < n_total:
        text += f" (n={e.n})"
    return text


def agent_label(name: str, wrap: bool = False) -> str:
    """Short display label of an agent (its ``short_label``, else its name); ``wrap`` puts a
    parenthesised remark on its own line.
    """
    label = AGENT_REGISTRY[name].short_label if name in AGENT_REGISTRY else name
    return label.replace(" (", "\n(").replace(", ", ",\n") if wrap else label


def long_label(name: str) -> str:
    """The one-line label of an agent (a registered agent's ``label``, else its name)."""
    return AGENT_REGISTRY[name].label if name in AGENT_REGISTRY else name
