"""The squared-exponential kernel as a Taylor-series state-space approximation
(:class:`SquaredExponential`, :func:`squared_exponential`)."""

from __future__ import annotations

import functools
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

#: Largest Taylor order accepted by :class:`SquaredExponential`. With balancing the
#: construction still works beyond it, but the covariance error is already < 3e-5 of
#: the variance at 12 while cond(Pinf) grows 5-10x per order (~4e3 at 12, ~2e5 at 16),
#: which the Kalman filter's covariance updates pay for in lost digits.
SE_MAX_ORDER = 12

#: :meth:`SquaredExponential.discretize` refuses a step whose ``Q = Pinf - A Pinf A^T``
#: carries a larger estimated relative rounding error than this.
SE_DISCRETIZATION_RTOL = 1e-6


def _stable_spectral_factor(coeffs: Any) -> np.ndarray:
    """Stable spectral factor of a spectral-density denominator ``P(w^2)``.

    With ``P(w^2) = sum_n c_n w^(2n)`` (``c_N > 0``, ``P > 0`` on the real axis), the
    polynomial ``P(-s^2)`` in ``s = i w`` has ``2N`` roots in ``+-`` pairs; the monic
    ``G(s)`` built from the ``N`` roots with negative real part satisfies
    ``P(w^2) = c_N |G(i w)|^2``, so ``1 / G`` is the transfer function of a stable SDE.

    Args:
        coeffs: ``[c_0, ..., c_N]``, coefficient of ``w^(2n)`` at index ``n``.

    Returns:
        ``G``'s real coefficients, highest power first (``G[0] == 1``), length ``N + 1``.

    Raises:
        ValueError: if ``P(-s^2)`` has roots on (or numerically at) the imaginary axis,
            i.e. no stable factor of order ``N`` exists.
    """
    c = np.asarray(coeffs, dtype=float)
    order = c.size - 1
    poly_s = np.zeros(2 * order + 1)
    for n in range(order + 1):
        # w^(2n) = (-s^2)^n; np.roots wants the highest power first.
        poly_s[2 * order - 2 * n] = (-1) ** n * c[n]
    roots = np.roots(poly_s)
    scale = max(1.0, float(np.abs(roots).max()))
    stable = roots[roots.real < -1e-9 * scale]
    if stable.size != order:
        raise ValueError(
            f"spectral density denominator of order {order} has {order - stable.size} root "
            f"pair(s) on the imaginary axis: no stable state-space model (F not stable)"
        )
    return np.real(np.poly(stable))


@functools.cache
def _se_unit_model(
    order: int,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Balanced order-``order`` SE model for unit variance and lengthscale.

    Returns:
        ``(F1, L1, q1, H1, P1)`` as read-only arrays (``q1`` a float), ``H1 = e_1``.

    Raises:
        ValueError: if the spectral factor or its Lyapunov solution is not usable.
    """
    # S(w) = sqrt(2 pi) exp(-w^2/2) ~ sqrt(2 pi) / sum_n (w^2/2)^n / n! (Hartikainen &
    # Sarkka 2010): the denominator is the order-N Taylor polynomial of exp(w^2/2).
    coeffs = [1.0 / (2.0**n * math.factorial(n)) for n in range(order + 1)]
    g = _stable_spectral_factor(coeffs)
    F = np.diag(np.ones(order - 1), k=1)
    F[-1, :] = -g[1:][::-1]
    # P = c_N |G|^2, so S = sqrt(2 pi) / (c_N |G|^2) = q / |G|^2.
    q = math.sqrt(2.0 * math.pi) * 2.0**order * math.factorial(order)
    # The companion matrix's entries span many orders of magnitude (cond(F) ~ 2e3 at
    # order 6, 7e7 at 12); a diagonal similarity z' = T^-1 z fixes that. matrix_balance
    # uses powers of two, so rescaling T to T[0, 0] = 1 is exact and keeps H = e_1.
    _, T = scipy.linalg.matrix_balance(F, permute=False, separate=False)
    t = np.diag(T) / T[0, 0]
    F_b = F * t[None, :] / t[:, None]
    L_b = np.zeros((order, 1))
    L_b[-1, 0] = 1.0 / t[-1]
    H_b = np.zeros((1, order))
    H_b[0, 0] = 1.0
    max_re = float(np.linalg.eigvals(F_b).real.max())
    if not max_re < 0.0:
        raise ValueError(f"order={order}: F is not stable (max real eigenvalue {max_re:.3g})")
    P = scipy.linalg.solve_continuous_lyapunov(F_b, -q * (L_b @ L_b.T))
    P = 0.5 * (P + P.T)
    if not np.linalg.eigvalsh(P).min() > 0.0:
        raise ValueError(f"order={order}: stationary covariance is not positive definite")
    arrays = (F_b, L_b, H_b, P)
    for arr in arrays:
        arr.flags.writeable = False
    return F_b, L_b, q, H_b, P


class SquaredExponential(StateSpaceKernel):
    """Squared-exponential kernel, approximated by an order-``N`` stable SDE.

    The exact kernel ``k(tau) = sigma^2 exp(-tau^2 / (2 l^2))`` has spectral density
    ``S(w) = sigma^2 sqrt(2 pi) l exp(-w^2 l^2 / 2)``, which is not rational.
    Hartikainen & Sarkka (2010) replace ``exp(x)`` in ``1 / exp(x)`` by its order-``N``
    Taylor polynomial; the stable spectral factor of that polynomial gives an ``N``-state
    companion-form model, here balanced (diagonal similarity, ``H = e_1`` kept) and
    time-scaled from the unit-lengthscale model: ``F = F1 / l``, ``Qc = sigma^2 q1 / l``,
    ``Pinf = sigma^2 P1``.

    Accuracy measured (``max |k_ss - k| / sigma^2`` over ``tau`` in ``[0, 5 l]``; the
    maximum sits at ``tau = 0``, i.e. the approximation's variance is slightly too large):

    ======  =======  ======  ======  ======  ======  ======  ======  ======
    order   2        3       4       5       6       8       10      12
    error   1.4e-1   4.5e-2  1.7e-2  7.0e-3  3.0e-3  6.0e-4  1.3e-4  2.9e-5
    ======  =======  ======  ======  ======  ======  ======  ======  ======

    :meth:`covariance` is the exact closed form; :meth:`state_space_covariance` is
    the approximation's. The state is a scaled basis of ``[w, w', ..., w^(N-1)]``
    with ``w = z[0]``.

    Attributes:
        variance: ``sigma^2`` [unit of w, squared].
        lengthscale: ``l`` [s].
        order: Taylor order ``N`` = state dimension, in ``[1, SE_MAX_ORDER]``.
    """

    variance: float
    lengthscale: float
    order: int

    def __init__(self, variance: float, lengthscale: float, order: int = 6) -> None:
        """Build the balanced SDE matrices.

        Args:
            variance: ``sigma^2`` > 0 [unit of w, squared].
            lengthscale: ``l`` > 0 [s].
            order: Taylor order ``N``, an integer in ``[1, SE_MAX_ORDER]``.

        Raises:
            ValueError: naming the offending field and its allowed values, or if the
                order's spectral factor is not stable.
        """
        self.variance = _check_positive(variance, "variance")
        self.lengthscale = _check_positive(lengthscale, "lengthscale")
        self.order = _check_int(order, "order", 1, SE_MAX_ORDER)
        F1, L1, q1, H1, P1 = _se_unit_model(self.order)
        # w(t) = sigma w1(t / l): time scaling divides F by l and the white-noise
        # intensity by l, and the output scaling multiplies Qc and Pinf by sigma^2.
        super().__init__(
            F1 / self.lengthscale,
            L1,
            np.array([[self.variance * q1 / self.lengthscale]]),
            H1,
            self.variance * P1,
        )

    def __repr__(self) -> str:
        return (
            f"SquaredExponential(variance={self.variance:g}, "
            f"lengthscale={self.lengthscale:g}, order={self.order})"
        )

    @property
    def hyperparameters(self) -> dict[str, float]:
        """``{"variance": sigma^2, "lengthscale": l}``; ``order`` is structural."""
        return {"variance": self.variance, "lengthscale": self.lengthscale}

    def with_hyperparameters(self, **hyperparameters: float) -> SquaredExponential:
        """Same order with some of ``variance``, ``lengthscale`` replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return SquaredExponential(**{**self.hyperparameters, **hyperparameters}, order=self.order)

    def covariance(self, tau: Any) -> np.ndarray:
        """Exact squared-exponential covariance ``sigma^2 exp(-tau^2 / (2 l^2))``.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        tau_arr = np.asarray(tau, dtype=float)
        return self.variance * np.exp(-0.5 * (tau_arr / self.lengthscale) ** 2)

    def discretize(self, dt: float, method: str = "exact") -> tuple[np.ndarray, np.ndarray]:
        """Discrete transition as :meth:`StateSpaceKernel.discretize`, with a conditioning check.

        For ``dt << l`` the exact ``Q = Pinf - A Pinf A^T`` is a difference of nearly
        equal matrices (``|Q| / |Pinf| ~ 0.7 dt / l`` at order 6), so its relative
        rounding error is about ``N eps |Pinf| / |Q|``.

        Raises:
            ValueError: as the base class, or if that error estimate exceeds
                ``SE_DISCRETIZATION_RTOL`` (``dt / l`` below ~2e-9 at order 6) or ``A``
                is not finite.
        """
        A, Q = super().discretize(dt, method)
        if method == "exact":
            if not np.all(np.isfinite(A)):
                raise ValueError(f"dt={dt!r}: expm(F dt) overflowed for {self!r}")
            q_norm = float(np.linalg.norm(Q))
            rel_err = (
                self.state_dim * np.finfo(float).eps * float(np.linalg.norm(self.Pinf)) / q_norm
                if q_norm > 0.0
                else math.inf
            )
            if rel_err > SE_DISCRETIZATION_RTOL:
                raise ValueError(
                    f"dt={dt!r} [s] is too small for lengthscale={self.lengthscale:g} [s] at "
                    f"order {self.order}: Q = Pinf - A Pinf A^T has relative rounding error "
                    f"~{rel_err:.1e} > {SE_DISCRETIZATION_RTOL:g} (dt / lengthscale = "
                    f"{float(dt) / self.lengthscale:.1e}); use a longer step or merge samples"
                )
        return A, Q


def squared_exponential(variance: float, lengthscale: float, order: int = 6) -> SquaredExponential:
    """Squared-exponential state-space approximation; see :class:`SquaredExponential`.

    Args:
        variance: ``sigma^2`` > 0 [unit of w, squared].
        lengthscale: ``l`` > 0 [s].
        order: Taylor order ``N`` in ``[1, SE_MAX_ORDER]`` (6: covariance within 0.3 %
            of the variance).

    Returns:
        The frozen :class:`SquaredExponential` kernel.
    """
    return SquaredExponential(variance, lengthscale, order)
