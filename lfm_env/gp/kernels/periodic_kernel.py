"""The periodic kernel as a truncated Bessel series of resonators (:class:`Periodic`,
:func:`periodic`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.linalg
import scipy.special

from lfm_env.gp.kernels.base import (
    StateSpaceKernel,
    _check_hyperparameter_names,
    _check_int,
    _check_positive,
)


def _periodic_weights(lengthscale: float, harmonics: int) -> np.ndarray:
    """Bessel-series weights ``q_j^2 / sigma^2`` for ``j = 0 .. harmonics``.

    ``exp(z cos x) = I_0(z) + 2 sum_j I_j(z) cos(j x)`` with ``z = l^-2``, times
    ``exp(-z)``; ``ive`` is ``I_j(z) exp(-z)``, finite for any ``z``. They sum to 1 as
    ``harmonics -> oo``.
    """
    j = np.arange(harmonics + 1)
    return np.where(j == 0, 1.0, 2.0) * scipy.special.ive(j, lengthscale**-2)


def _periodic_tail(lengthscale: float, harmonics: int) -> float:
    """Truncation error ``sum_{j > harmonics} q_j^2 / sigma^2`` (= max_tau |k_J - k| / sigma^2)."""
    tail = 1.0 - float(_periodic_weights(lengthscale, harmonics).sum())
    if tail > 1e-8:
        return tail
    # 1 - sum only resolves ~1e-16; sum the tail terms (super-exponentially decaying
    # once j exceeds ~sqrt(z)) instead when it is small.
    z = lengthscale**-2
    j = np.arange(harmonics + 1, harmonics + 60 + int(30.0 * math.sqrt(z)))
    return float(2.0 * scipy.special.ive(j, z).sum())


class Periodic(StateSpaceKernel):
    """Periodic kernel as a sum of undamped resonators (Solin & Sarkka 2014).

    The exact kernel is ``k(tau) = sigma^2 exp(-2 sin^2(pi tau / T) / l^2)``; with
    ``z = l^-2`` it expands as ``sigma^2 sum_j q_j^2 cos(j w0 tau)``, ``w0 = 2 pi / T``,
    ``q_0^2 = I_0(z) / e^z``, ``q_j^2 = 2 I_j(z) / e^z``. Truncating at ``J`` harmonics
    gives ``J + 1`` two-state resonators: ``F`` block-diagonal ``[[0, -j w0], [j w0, 0]]``,
    ``L = I``, ``Qc = 0`` (the process is deterministic given its initial state, so
    ``Pinf = sigma^2 diag(q_j^2 I_2)`` is given, not solved), ``H = [1, 0, 1, 0, ...]``.

    The truncation error ``max_tau |k_J(tau) - k(tau)| = sigma^2 sum_{j > J} q_j^2`` (at
    ``tau = 0``) is exact and stored in :attr:`truncation_error`. With ``J = 6`` it is
    1.3e-6 at ``l = 1``, 7.7e-5 at 0.7, 2.0e-3 at 0.5 and 1.1e-2 at 0.4; with ``J = 10``
    it is 3.1e-6 at 0.5 and 2.0e-3 at 0.3.

    :meth:`covariance` is the exact closed form; :meth:`state_space_covariance` the
    truncated series (equal to ``H expm(F tau) Pinf H^T``).

    Attributes:
        variance: ``sigma^2`` [unit of w, squared].
        lengthscale: ``l`` [-], dimensionless (it scales ``sin(pi tau / T)``).
        period: ``T`` [s].
        harmonics: ``J``, number of harmonics above the constant term.
        max_truncation_error: largest accepted truncation error, relative to ``sigma^2``.
        truncation_error: this kernel's truncation error, relative to ``sigma^2``.
    """

    variance: float
    lengthscale: float
    period: float
    harmonics: int
    max_truncation_error: float
    truncation_error: float

    def __init__(
        self,
        variance: float,
        lengthscale: float,
        period: float,
        harmonics: int = 6,
        max_truncation_error: float = 1e-2,
    ) -> None:
        """Build the resonator matrices.

        Args:
            variance: ``sigma^2`` > 0 [unit of w, squared].
            lengthscale: ``l`` > 0 [-].
            period: ``T`` > 0 [s].
            harmonics: ``J`` >= 0.
            max_truncation_error: in ``(0, 1]``; the truncated series' largest
                covariance error, relative to ``sigma^2``, must not exceed it.

        Raises:
            ValueError: naming the offending field, or if ``lengthscale`` is too small
                for ``harmonics`` (the message says how many harmonics would do).
        """
        self.variance = _check_positive(variance, "variance")
        self.lengthscale = _check_positive(lengthscale, "lengthscale")
        self.period = _check_positive(period, "period")
        self.harmonics = _check_int(harmonics, "harmonics", 0)
        tol = _check_positive(max_truncation_error, "max_truncation_error")
        if tol > 1.0:
            raise ValueError(f"max_truncation_error={max_truncation_error!r}: must be in (0, 1]")
        self.max_truncation_error = tol
        self.truncation_error = _periodic_tail(self.lengthscale, self.harmonics)
        if self.truncation_error > tol:
            raise ValueError(
                f"lengthscale={self.lengthscale:g} is too small for harmonics={self.harmonics}: "
                f"truncation error {self.truncation_error:.2e} (relative to variance) > "
                f"max_truncation_error={tol:g}; use harmonics >= "
                f"{self._harmonics_needed(self.lengthscale, tol)} or a larger lengthscale"
            )
        weights = _periodic_weights(self.lengthscale, self.harmonics)
        w0 = 2.0 * math.pi / self.period
        p = 2 * (self.harmonics + 1)
        F = scipy.linalg.block_diag(
            *[np.array([[0.0, -j * w0], [j * w0, 0.0]]) for j in range(self.harmonics + 1)]
        )
        H = np.tile([1.0, 0.0], self.harmonics + 1)[None, :]
        Pinf = self.variance * np.diag(np.repeat(weights, 2))
        super().__init__(F, np.eye(p), np.zeros((p, p)), H, Pinf)

    @staticmethod
    def _harmonics_needed(lengthscale: float, tol: float) -> int:
        """Smallest ``J`` whose truncation error is <= ``tol``."""
        z = lengthscale**-2
        j_max = 60 + int(30.0 * math.sqrt(z))
        weights = np.where(np.arange(j_max + 1) == 0, 1.0, 2.0) * scipy.special.ive(
            np.arange(j_max + 1), z
        )
        tails = 1.0 - np.cumsum(weights)
        return int(np.argmax(tails <= tol)) if np.any(tails <= tol) else j_max

    def __repr__(self) -> str:
        return (
            f"Periodic(variance={self.variance:g}, lengthscale={self.lengthscale:g}, "
            f"period={self.period:g}, harmonics={self.harmonics})"
        )

    @property
    def hyperparameters(self) -> dict[str, float]:
        """``{"variance": sigma^2, "lengthscale": l, "period": T}``."""
        return {"variance": self.variance, "lengthscale": self.lengthscale, "period": self.period}

    def with_hyperparameters(self, **hyperparameters: float) -> Periodic:
        """Same ``harmonics`` and tolerance with some hyperparameters replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter, or if the new
                lengthscale is too small for ``harmonics``.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return Periodic(
            **{**self.hyperparameters, **hyperparameters},
            harmonics=self.harmonics,
            max_truncation_error=self.max_truncation_error,
        )

    def covariance(self, tau: Any) -> np.ndarray:
        """Exact periodic covariance ``sigma^2 exp(-2 sin^2(pi tau / T) / l^2)``.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        s = np.sin(math.pi * np.asarray(tau, dtype=float) / self.period)
        return self.variance * np.exp(-2.0 * s**2 / self.lengthscale**2)

    def state_space_covariance(self, tau: Any) -> np.ndarray:
        """Truncated series ``sigma^2 sum_{j <= J} q_j^2 cos(j w0 tau) = H e^{F tau} Pinf H^T``.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        tau_arr = np.asarray(tau, dtype=float)
        weights = np.diag(self.Pinf)[::2]
        w0 = 2.0 * math.pi / self.period
        j = np.arange(self.harmonics + 1)
        return np.cos(tau_arr[..., None] * (j * w0)) @ weights


def periodic(
    variance: float,
    lengthscale: float,
    period: float,
    harmonics: int = 6,
    *,
    max_truncation_error: float = 1e-2,
) -> Periodic:
    """Periodic state-space kernel; see :class:`Periodic`.

    Args:
        variance: ``sigma^2`` > 0 [unit of w, squared].
        lengthscale: ``l`` > 0 [-] (dimensionless).
        period: ``T`` > 0 [s].
        harmonics: ``J`` >= 0 (6: exact to 1e-6 of the variance for ``l >= 1``, to 2e-3
            for ``l >= 0.5``).
        max_truncation_error: accepted truncation error relative to ``sigma^2``.

    Returns:
        The frozen :class:`Periodic` kernel.
    """
    return Periodic(variance, lengthscale, period, harmonics, max_truncation_error)
