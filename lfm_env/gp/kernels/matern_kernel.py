"""Matern kernels with half-integer smoothness as exact SDEs (:class:`Matern`, :func:`matern`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.linalg
import scipy.special

from lfm_env.gp.kernels.base import (
    StateSpaceKernel,
    _check_hyperparameter_names,
    _check_positive,
)


def _is_positive_half_integer(nu: Any) -> bool:
    try:
        two_nu = 2.0 * float(nu)
    except (TypeError, ValueError):
        return False
    return (
        math.isfinite(two_nu) and two_nu > 0 and two_nu == round(two_nu) and round(two_nu) % 2 == 1
    )


class Matern(StateSpaceKernel):
    """Matern kernel with half-integer smoothness ``nu = p - 1/2`` as a ``p``-state SDE.

    With ``lambda = sqrt(2 nu) / lengthscale`` the state is ``z = [w, w', ..., w^(p-1)]``,
    ``F`` is the companion matrix of ``(s + lambda)^p``, ``L = e_p``, ``H = e_1``
    and ``Qc = q = 2 sigma^2 sqrt(pi) lambda^(2p-1) Gamma(p) / Gamma(p - 1/2)``.

    Attributes:
        nu: smoothness, a positive half-integer (0.5, 1.5, 2.5, ...).
        variance: ``sigma^2`` [unit of w, squared].
        lengthscale: ``l`` [s].
    """

    nu: float
    variance: float
    lengthscale: float

    def __init__(self, nu: float, variance: float, lengthscale: float) -> None:
        """Build the SDE matrices.

        Args:
            nu: smoothness, a positive half-integer (0.5, 1.5, 2.5, 3.5, ...).
            variance: ``sigma^2`` > 0 [unit of w, squared].
            lengthscale: ``l`` > 0 [s].

        Raises:
            ValueError: naming the offending field and its allowed values.
        """
        if isinstance(nu, bool) or not _is_positive_half_integer(nu):
            raise ValueError(
                f"nu={nu!r}: must be a positive half-integer (0.5, 1.5, 2.5, 3.5, ...)"
            )
        self.nu = float(nu)
        self.variance = _check_positive(variance, "variance")
        self.lengthscale = _check_positive(lengthscale, "lengthscale")

        p = int(round(self.nu + 0.5))
        lam = math.sqrt(2.0 * self.nu) / self.lengthscale
        binom = np.array([math.comb(p, j) for j in range(p)], dtype=float)
        F = np.diag(np.ones(p - 1), k=1)
        F[-1, :] = -binom * lam ** np.arange(p, 0, -1)
        L = np.zeros((p, 1))
        L[-1, 0] = 1.0
        H = np.zeros((1, p))
        H[0, 0] = 1.0
        # lgamma keeps the constant finite for large p, where Gamma(p) overflows.
        log_c = math.log(2.0 * math.sqrt(math.pi)) + math.lgamma(p) - math.lgamma(p - 0.5)
        c_unit = math.exp(log_c)
        q = self.variance * c_unit * lam ** (2 * p - 1)

        # Pinf entries span powers lambda^0 .. lambda^(2p-2); solving directly loses
        # the small ones to rounding for short lengthscales. With D = diag(lambda^i)
        # we have F = lambda D F1 D^-1 (F1 the lambda=1 companion matrix), so
        # Pinf = sigma^2 D P1 D with P1 the unit-variance, lambda=1 solution.
        F1 = np.diag(np.ones(p - 1), k=1)
        F1[-1, :] = -binom
        P1 = scipy.linalg.solve_continuous_lyapunov(F1, -c_unit * (L @ L.T))
        d = lam ** np.arange(p)
        Pinf = self.variance * (d[:, None] * P1 * d[None, :])

        super().__init__(F, L, np.array([[q]]), H, Pinf)

    @property
    def order(self) -> int:
        """Number of states ``p = nu + 1/2``."""
        return self.state_dim

    @property
    def hyperparameters(self) -> dict[str, float]:
        """``{"variance": sigma^2, "lengthscale": l}``; ``nu`` is structural, not learned."""
        return {"variance": self.variance, "lengthscale": self.lengthscale}

    def with_hyperparameters(self, **hyperparameters: float) -> Matern:
        """Matern kernel of the same ``nu`` with some of ``variance``, ``lengthscale`` replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return Matern(self.nu, **{**self.hyperparameters, **hyperparameters})

    def __repr__(self) -> str:
        return (
            f"Matern(nu={self.nu:g}, variance={self.variance:g}, lengthscale={self.lengthscale:g})"
        )

    def covariance(self, tau: Any) -> np.ndarray:
        """Closed-form Matern covariance at lags ``tau`` [s].

        For ``nu = p - 1/2`` and ``x = sqrt(2 nu) |tau| / l``::

            k = sigma^2 exp(-x) (p-1)!/(2p-2)! sum_{i=0}^{p-1} (p-1+i)!/(i!(p-1-i)!) (2x)^(p-1-i)

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        x = math.sqrt(2.0 * self.nu) * np.abs(np.asarray(tau, dtype=float)) / self.lengthscale
        p = self.state_dim
        poly = np.zeros_like(x)
        for i in range(p):
            coef = math.factorial(p - 1 + i) / (math.factorial(i) * math.factorial(p - 1 - i))
            poly = poly + coef * (2.0 * x) ** (p - 1 - i)
        scale = math.factorial(p - 1) / math.factorial(2 * p - 2)
        return self.variance * np.exp(-x) * scale * poly


def matern(nu: float, variance: float, lengthscale: float) -> Matern:
    """Matern state-space kernel; see :class:`Matern`.

    Args:
        nu: smoothness, a positive half-integer (0.5, 1.5, 2.5, 3.5, ...).
        variance: ``sigma^2`` > 0 [unit of w, squared].
        lengthscale: ``l`` > 0 [s].

    Returns:
        The frozen :class:`Matern` kernel.
    """
    return Matern(nu, variance, lengthscale)
