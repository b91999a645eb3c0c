"""State-space (SDE) representation of temporal Gaussian processes.

A stationary GP ``w(t)`` in time with a rational spectral density is the output
``w = H z`` of the linear time-invariant SDE (Hartikainen & Sarkka 2010)::

    dz/dt = F z + L xi(t),    E[xi(t) xi(s)^T] = Qc delta(t - s),

started from (or run long enough to reach) its stationary covariance ``Pinf``,
which solves ``F Pinf + Pinf F^T + L Qc L^T = 0``. Time is in seconds [s]; the
output ``w`` carries the unit of the modelled quantity (in the case study the
latent force, [m/s^2]). For :class:`Matern` state component ``i`` carries that
unit per ``[s^i]`` (the ``i``-th time derivative of ``w``); the other kernels use
better-conditioned state bases, and only ``w = H z`` has a fixed meaning.

:class:`StateSpaceKernel` holds the matrices and does the generic work
(discretisation, sampling, covariance check); subclasses only build the matrices
from hyperparameters:

* :class:`Matern` (half-integer ``nu``, exact),
* :class:`SquaredExponential` (Taylor-series spectral approximation of order ``N``),
* :class:`Periodic` (truncated Bessel series of resonators),
* :class:`SumKernel` / :class:`ProductKernel`, made by ``k1 + k2`` and ``k1 * k2``.

Inference (likelihood and fitting) lives in :mod:`lfm_env.gp.inference`. One module per
family: :mod:`.base` (:class:`StateSpaceKernel`), :mod:`.matern_kernel`,
:mod:`.squared_exponential_kernel`, :mod:`.periodic_kernel` (sums and products in :mod:`.base`).
"""

from lfm_env.gp.kernels.base import (
    DISCRETIZATION_METHODS,
    START_MODES,
    ProductKernel,
    StateSpaceKernel,
    SumKernel,
)
from lfm_env.gp.kernels.matern_kernel import Matern, matern
from lfm_env.gp.kernels.periodic_kernel import Periodic, periodic
from lfm_env.gp.kernels.squared_exponential_kernel import (
    SE_DISCRETIZATION_RTOL,
    SE_MAX_ORDER,
    SquaredExponential,
    squared_exponential,
)

__all__ = [
    "DISCRETIZATION_METHODS",
    "SE_DISCRETIZATION_RTOL",
    "SE_MAX_ORDER",
    "START_MODES",
    "Matern",
    "Periodic",
    "ProductKernel",
    "SquaredExponential",
    "StateSpaceKernel",
    "SumKernel",
    "matern",
    "periodic",
    "squared_exponential",
]
