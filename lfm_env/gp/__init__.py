"""State-space Gaussian processes in time.

Kernels are in :mod:`.kernels`, the Kalman likelihood in :mod:`.likelihood`, fitting in
:mod:`.inference`.

This layer knows no system: a kernel gives ``F, L, Qc, H, Pinf`` and their discretisation;
:mod:`lfm_env.model` stacks it onto a controlled system.
"""

from lfm_env.gp.inference import FitInfo, fit
from lfm_env.gp.kernels import (
    DISCRETIZATION_METHODS,
    SE_MAX_ORDER,
    START_MODES,
    Matern,
    Periodic,
    ProductKernel,
    SquaredExponential,
    StateSpaceKernel,
    SumKernel,
    matern,
    periodic,
    squared_exponential,
)
from lfm_env.gp.likelihood import log_marginal_likelihood, log_marginal_likelihood_and_grad

__all__ = [
    "DISCRETIZATION_METHODS",
    "SE_MAX_ORDER",
    "START_MODES",
    "FitInfo",
    "Matern",
    "Periodic",
    "ProductKernel",
    "SquaredExponential",
    "StateSpaceKernel",
    "SumKernel",
    "fit",
    "log_marginal_likelihood",
    "log_marginal_likelihood_and_grad",
    "matern",
    "periodic",
    "squared_exponential",
]
