"""The control objective: a quadratic cost on the distance to a goal state.

:class:`QuadraticCost` is read by the env (its reward is minus the stage cost), the scenario
problem and every solver; written once for NumPy and CasADi.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from lfm_env.validation import frozen_vector
from lfm_env.xp import is_symbolic

if TYPE_CHECKING:
    from lfm_env.system import ControlSystem


def _weight(value: Any, n: int, name: str) -> np.ndarray:
    """A PSD weight matrix from a diagonal (``n`` numbers) or a full ``(n, n)`` matrix."""
    arr = np.asarray(value, dtype=float)
    if arr.shape == (n,):
        arr = np.diag(arr)
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)):
        raise ValueError(
            f"QuadraticCost.{name}: must be {n} finite numbers or an ({n}, {n}) matrix"
        )
    if not np.allclose(arr, arr.T, rtol=0.0, atol=1e-12 * (1.0 + np.abs(arr).max())):
        raise ValueError(f"QuadraticCost.{name}: must be symmetric")
    if np.linalg.eigvalsh(arr)[0] < -1e-12 * (1.0 + np.abs(arr).max()):
        raise ValueError(f"QuadraticCost.{name}: must be positive semi-definite")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class QuadraticCost:
    """Stage cost ``(x - x_g)' Q (x - x_g) + u' R u`` and terminal ``(x - x_g)' Qf (x - x_g)``.

    Args:
        Q: state weights, a diagonal (``nx`` numbers) or an ``(nx, nx)`` PSD matrix, in
            1/(state unit)^2.
        R: input weights, a diagonal or an ``(nu, nu)`` PSD matrix.
        Qf: terminal state weights; ``None`` for ``Q``.
        x_goal: the goal state ``(nx,)`` in the states' units; ``None`` for zeros.
    """

    Q: Any
    R: Any
    Qf: Any = None
    x_goal: Any = None

    def __post_init__(self) -> None:
        q = np.asarray(self.Q, dtype=float)
        nx = q.shape[0] if q.ndim >= 1 else -1
        nu = np.asarray(self.R, dtype=float).shape[0] if np.ndim(self.R) >= 1 else -1
        if nx < 1 or nu < 1:
            raise ValueError("QuadraticCost: Q and R must be vectors or square matrices")
        object.__setattr__(self, "Q", _weight(self.Q, nx, "Q"))
        object.__setattr__(self, "R", _weight(self.R, nu, "R"))
        object.__setattr__(self, "Qf", _weight(self.Q if self.Qf is None else self.Qf, nx, "Qf"))
        goal = np.zeros(nx) if self.x_goal is None else self.x_goal
        object.__setattr__(self, "x_goal", frozen_vector(goal, nx, "QuadraticCost.x_goal"))
        if not np.all(np.isfinite(self.x_goal)):
            raise ValueError("QuadraticCost.x_goal must be finite")

    @property
    def nx(self) -> int:
        return int(self.Q.shape[0])

    @property
    def nu(self) -> int:
        return int(self.R.shape[0])

    @property
    def diagonal(self) -> bool:
        """True when ``Q``, ``R`` and ``Qf`` are diagonal (solvers take a cheaper path)."""
        return all(
            np.count_nonzero(m - np.diag(np.diag(m))) == 0 for m in (self.Q, self.R, self.Qf)
        )

    def check_system(self, system: ControlSystem) -> None:
        """Raise ``ValueError`` unless the dimensions fit ``system``."""
        if (self.nx, self.nu) != (system.nx, system.nu):
            raise ValueError(
                f"QuadraticCost has nx={self.nx}, nu={self.nu}; system {system.name!r} has "
                f"nx={system.nx} states {system.state_labels} and nu={system.nu} inputs"
            )

    def _form(self, M: np.ndarray, e: Any) -> Any:
        if is_symbolic(e):
            return ca.bilin(ca.DM(M), e, e)
        e = np.asarray(e, dtype=float)
        if np.count_nonzero(M - np.diag(np.diag(M))) == 0:
            d = np.diag(M)
            return e @ (d * e) if e.ndim == 1 else np.einsum("...i,i,...i->...", e, d, e)
        return np.einsum("...i,ij,...j->...", e, M, e)

    def state_cost(self, x: Any) -> Any:
        """``(x - x_g)' Q (x - x_g)`` (NumPy ``(...)`` or a CasADi scalar)."""
        return self._form(self.Q, x - (ca.DM(self.x_goal) if is_symbolic(x) else self.x_goal))

    def terminal_cost(self, x: Any) -> Any:
        """``(x - x_g)' Qf (x - x_g)``."""
        return self._form(self.Qf, x - (ca.DM(self.x_goal) if is_symbolic(x) else self.x_goal))

    def input_cost(self, u: Any) -> Any:
        """``u' R u``."""
        return self._form(self.R, u)

    def stage_cost(self, x: Any, u: Any) -> Any:
        """``(x - x_g)' Q (x - x_g) + u' R u``: minus the env's reward."""
        return self.state_cost(x) + self.input_cost(u)


__all__ = ["QuadraticCost"]
