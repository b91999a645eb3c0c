"""The shared figure toolkit: agent colours, pyplot-free figures, time axes, units.

Every figure of the experiment layer is built with :func:`new_figure` (no pyplot, no global
state, nothing opens a window) and written with :func:`save_figure`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from controllers.agents.registry import AGENT_REGISTRY
from lfm_env.system import ControlSystem, split_unit

_FALLBACK_COLOURS = ("tab:brown", "tab:pink", "tab:olive", "tab:cyan")


def agent_colour(name: str) -> str:
    """A fixed colour per agent name: a registered agent's own
    (:class:`~controllers.agents.registry.AgentSpec`), else a stable fallback."""
    if name in AGENT_REGISTRY:
        return AGENT_REGISTRY[name].colour
    return _FALLBACK_COLOURS[sum(map(ord, name)) % len(_FALLBACK_COLOURS)]


def new_figure(width: float, height: float) -> Figure:
    """A pyplot-free figure of ``width`` x ``height`` inches with an Agg canvas."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Write ``fig`` as a PNG (or the format of the suffix) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def sample_times(n: int, dt: float) -> np.ndarray:
    """Times ``k dt`` [s] of ``n`` samples."""
    return np.arange(n) * dt


def _step_plot(ax, t: np.ndarray, values: np.ndarray, dt: float | None = None, **kwargs):
    """Draw per-step values held over ``[k dt, (k+1) dt)`` (zero-order hold)."""
    if len(values) == 0:
        return None
    if dt is None:
        dt = t[1] - t[0] if len(t) > 1 else 1.0
    tt = np.append(t, t[-1] + dt)
    vv = np.append(values, values[-1])
    return ax.step(tt, vv, where="post", **kwargs)


def unit_of(label: str) -> str:
    """The unit of a label ``"p_x [m]"`` (``"m"``); ``""`` when it has none."""
    return split_unit(label)[1]


def _joined_units(labels: Sequence[str]) -> str:
    """The distinct units of ``labels``, joined by ``", "`` (usually one)."""
    return ", ".join(u for u in dict.fromkeys(unit_of(x) for x in labels) if u)


def group_unit(system: ControlSystem, group: str) -> str:
    """The unit of a constraint group's excess: its constraints' unit (``"m"``)."""
    if group not in system.constraint_groups:
        raise ValueError(
            f"group {group!r}: not a constraint group of system {system.name!r}; "
            f"its groups are {list(system.constraint_groups)}"
        )
    return _joined_units([system.constraint_names[j] for j in system.constraint_groups[group]])


def force_unit(system: ControlSystem) -> str:
    """The unit of the latent force (of all its components; usually one)."""
    return _joined_units(system.force_names)
