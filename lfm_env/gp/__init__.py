"""State-space Gaussian processes in time.

Kernels are in :mod:`.kernels`, the Kalman likelihood in :mod:`.likelihood`, fitting in
:mod:`.inference`.

This layer knows no system: a kernel gives ``F, L, Qc, H, Pinf`` and their discretisation;
:mod:`lfm_env.model` stacks it onto a controlled system.
"""

from lfm_env.gp.inference import DrivenFitInfo, FitInfo, fit, fit_driven
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
from lfm_env.gp.likelihood import (
    driven_log_likelihood,
    log_marginal_likelihood,
    log_marginal_likelihood_and_grad,
)

__all__ = [
    "DISCRETIZATION_METHODS",
    "SE_MAX_ORDER",
    "START_MODES",
    "DrivenFitInfo",
    "FitInfo",
    "Matern",
    "Periodic",
    "ProductKernel",
    "SquaredExponential",
    "StateSpaceKernel",
    "SumKernel",
    "driven_log_likelihood",
    "fit",
    "fit_driven",
    "log_marginal_likelihood",
    "log_marginal_likelihood_and_grad",
    "matern",
    "periodic",
    "squared_exponential",
]
