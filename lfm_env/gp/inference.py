"""Fitting a state-space GP's hyperparameters to data: maximum likelihood.

:func:`fit` maximises the Kalman likelihood of noisy samples of the GP itself
(:mod:`lfm_env.gp.likelihood`) over log-hyperparameters with L-BFGS-B; :func:`fit_driven`
that of measured states the GP drives as a latent force (the calibration of a latent
force model, ``lfm-calibrate``). The kernels themselves live in :mod:`lfm_env.gp.kernels`.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Iterable
from typing import Any

import numpy as np

from lfm_env.gp.kernels.base import StateSpaceKernel, _check_positive
from lfm_env.gp.likelihood import (
    _check_data,
    _kalman_log_likelihood,
    _log_likelihood_and_grad,
    driven_log_likelihood,
)

#: Objective value :func:`fit` reports where the model cannot be built (e.g. a periodic
#: lengthscale too small for its harmonics); L-BFGS-B's line search then backs off.
_FIT_PENALTY = 1e10


@dataclasses.dataclass(frozen=True)
class FitInfo:
    """What :func:`fit` found besides the kernel, stored as ``kernel.fit_info``.

    Attributes:
        noise_variance: measurement-noise variance used or learned [unit of y, squared].
        noise_variance_learned: whether ``noise_variance`` was optimised.
        log_likelihood: log marginal likelihood at the optimum [nats].
        hyperparameters: the fitted kernel's hyperparameters (fixed ones included).
        success: the optimiser's convergence flag.
        message: the optimiser's message.
        n_iterations: optimiser iterations.
        n_evaluations: likelihood-and-gradient evaluations.
    """

    noise_variance: float
    noise_variance_learned: bool
    log_likelihood: float
    hyperparameters: dict[str, float]
    success: bool
    message: str
    n_iterations: int
    n_evaluations: int


def fit(
    kernel: StateSpaceKernel,
    times: Any,
    values: Any,
    noise_variance: float | None = None,
    *,
    fixed: Iterable[str] = (),
    initial_noise_variance: float | None = None,
    log_bounds_width: float = math.log(1e4),
    max_iter: int = 500,
) -> StateSpaceKernel:
    """Maximum-likelihood hyperparameters of ``kernel`` for noisy samples ``values``.

    Maximises :func:`log_marginal_likelihood` over the logarithms of
    ``kernel.hyperparameters`` (minus ``fixed``) and, if ``noise_variance`` is None,
    of the noise variance, by L-BFGS-B with the sensitivity-equation gradient of
    :func:`log_marginal_likelihood_and_grad`. The starting point is ``kernel``'s own
    hyperparameters; each log-parameter is boxed to ``+- log_bounds_width`` around
    its start. Structural settings (Matern ``nu``, SE ``order``, periodic
    ``harmonics``) are kept. Where the model cannot be built (e.g. a periodic
    lengthscale too small for its harmonics) the objective is a large penalty.

    Args:
        kernel: starting kernel.
        times: sample times [s], 1-D, sorted non-decreasing.
        values: observations, same shape [unit of w]; subtract a known mean first.
        noise_variance: fixed measurement-noise variance > 0 [unit of w, squared], or
            None to learn it.
        fixed: hyperparameter names to keep at ``kernel``'s values (e.g. one factor's
            variance in a product, where only the product of variances is identifiable).
        initial_noise_variance: start for the learned noise variance; default
            ``0.1 * mean(values**2)``.
        log_bounds_width: half-width of each log-parameter's box [nats].
        max_iter: L-BFGS-B iteration limit.

    Returns:
        The fitted kernel (same class and structure); ``fitted.fit_info`` is a
        :class:`FitInfo` with the noise variance, log-likelihood and optimiser status.

    Raises:
        ValueError: on malformed data or names, or if the starting point itself is
            invalid.

    Warns:
        RuntimeWarning: if the optimiser reports no convergence (the best point is
            still returned, with ``fit_info.success = False``).
    """
    t, y = _check_data(times, values)
    hp = kernel.hyperparameters
    fixed_set = set(fixed)
    unknown = sorted(fixed_set - set(hp))
    if unknown:
        raise ValueError(f"fixed: unknown name(s) {unknown}; allowed: {', '.join(hp) or 'none'}")
    names = [name for name in hp if name not in fixed_set]
    learn_noise = noise_variance is None
    if learn_noise:
        if initial_noise_variance is None:
            scale = float(np.mean(y**2))
            r0 = 0.1 * scale if scale > 0.0 else 1.0
        else:
            r0 = _check_positive(initial_noise_variance, "initial_noise_variance")
    else:
        r0 = _check_positive(noise_variance, "noise_variance")
    width = _check_positive(log_bounds_width, "log_bounds_width")
    n = t.size

    def unpack(theta: np.ndarray) -> tuple[StateSpaceKernel, float]:
        params = np.exp(theta)
        k = kernel.with_hyperparameters(
            **{name: float(v) for name, v in zip(names, params[: len(names)], strict=True)}
        )
        return k, float(params[-1]) if learn_noise else r0

    n_eval = 0

    def objective(theta: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal n_eval
        n_eval += 1
        try:
            k, r = unpack(theta)
            ll, grad = _log_likelihood_and_grad(k, t, y, r, names, learn_noise)
        except (ValueError, np.linalg.LinAlgError):
            return _FIT_PENALTY, np.zeros_like(theta)
        if not (math.isfinite(ll) and np.all(np.isfinite(grad))):
            return _FIT_PENALTY, np.zeros_like(theta)
        # Per-sample scale keeps L-BFGS-B's absolute gradient tolerance meaningful.
        return -ll / n, -grad / n

    theta0 = np.log([hp[name] for name in names] + ([r0] if learn_noise else []))
    if theta0.size == 0:
        success, message, n_iter, theta = True, "nothing to fit", 0, theta0
    else:
        f0, _ = objective(theta0)
        if f0 >= _FIT_PENALTY:
            # Re-run outside the guard so the caller sees why.
            k0, r_0 = unpack(theta0)
            _log_likelihood_and_grad(k0, t, y, r_0, names, learn_noise)
            raise ValueError("fit: the starting hyperparameters give a non-finite likelihood")
        import scipy.optimize  # here, not at the top: 0.13 s of every import of the GP layer

        res = scipy.optimize.minimize(
            objective,
            theta0,
            jac=True,
            method="L-BFGS-B",
            bounds=[(th - width, th + width) for th in theta0],
            # Tighter than scipy's defaults: the gradient is accurate to ~1e-9, and the
            # per-sample scale would otherwise stop ~1e-5 nats/sample short of the optimum.
            options={"maxiter": int(max_iter), "ftol": 1e-13, "gtol": 1e-9},
        )
        success, message, n_iter, theta = bool(res.success), str(res.message), int(res.nit), res.x
        if not success:
            warnings.warn(
                f"fit: L-BFGS-B did not converge: {message}", RuntimeWarning, stacklevel=2
            )
    fitted, r_fit = unpack(np.asarray(theta, dtype=float))
    ll_fit, _ = _kalman_log_likelihood(fitted, t, y, r_fit)
    info = FitInfo(
        noise_variance=r_fit,
        noise_variance_learned=learn_noise,
        log_likelihood=ll_fit,
        hyperparameters=dict(fitted.hyperparameters),
        success=success,
        message=message,
        n_iterations=n_iter,
        n_evaluations=n_eval,
    )
    # Kernels are frozen; the fit record is attached once, on this fresh instance.
    object.__setattr__(fitted, "fit_info", info)
    return fitted


@dataclasses.dataclass(frozen=True)
class DrivenFitInfo:
    """What :func:`fit_driven` found besides the kernel, stored as ``kernel.fit_info``.

    Attributes:
        log_likelihood: the summed :func:`driven_log_likelihood` at the optimum [nats].
        hyperparameters: the fitted kernel's hyperparameters (fixed ones included).
        std_errors: per learned name, the standard error of its logarithm, from a
            central-difference Hessian of the log-likelihood (NaN where not positive).
        success: the optimiser's convergence flag.
        message: the optimiser's message.
        n_evaluations: likelihood evaluations of the optimiser.
    """

    log_likelihood: float
    hyperparameters: dict[str, float]
    std_errors: dict[str, float]
    success: bool
    message: str
    n_evaluations: int


def log_space_std_errors(f: Any, theta: np.ndarray, h: float = 1e-3) -> list[float]:
    """Standard errors of ``theta`` from a central-difference Hessian of the negative
    log-likelihood ``f`` at its minimum ``theta`` (NaN where the inverse is not positive)."""
    import scipy.linalg

    n = theta.size
    hess = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            ei, ej = np.eye(n)[i] * h, np.eye(n)[j] * h
            hess[i, j] = (
                f(theta + ei + ej) - f(theta + ei - ej) - f(theta - ei + ej) + f(theta - ei - ej)
            ) / (4 * h * h)
    try:
        cov = scipy.linalg.inv(0.5 * (hess + hess.T))
        return [float(np.sqrt(c)) if c > 0 else float("nan") for c in np.diag(cov)]
    except np.linalg.LinAlgError:
        return [float("nan")] * n


def fit_driven(
    kernel: StateSpaceKernel,
    dt: float,
    episodes: Iterable[dict[str, Any]],
    names: Iterable[str] = ("variance", "lengthscale"),
    bounds: dict[str, tuple[float, float]] | None = None,
) -> StateSpaceKernel:
    """Maximum-likelihood hyperparameters of a latent force from the states it drives.

    Maximises the sum over ``episodes`` of :func:`driven_log_likelihood` over the
    logarithms of ``names`` by L-BFGS-B, from ``kernel``'s own values (choose a start
    that borrows nothing from the truth). Where a kernel cannot be built the objective is
    a large penalty.

    Args:
        kernel: the starting kernel (its structure, e.g. Matern ``nu``, is kept).
        dt: step [s] between measurements.
        episodes: per episode the keyword arguments of :func:`driven_log_likelihood`
            besides ``kernel`` and ``dt`` (``measured``, ``offset``, ``gain``,
            ``measurement_variance``, ``process_covariance``, optionally ``transition``).
        names: the hyperparameters to learn (keys of ``kernel.hyperparameters``).
        bounds: per name, ``(low, high)`` of the value itself; default a factor 1e4 either
            side of the start.

    Returns:
        The fitted kernel; ``fitted.fit_info`` is a :class:`DrivenFitInfo`.

    Raises:
        ValueError: without episodes, or for a name the kernel does not have.
    """
    import scipy.optimize

    episodes = list(episodes)
    if not episodes:
        raise ValueError("episodes: need at least one calibration episode")
    names = list(names)
    hp = kernel.hyperparameters
    unknown = sorted(set(names) - set(hp))
    if unknown:
        raise ValueError(f"names: unknown {unknown}; allowed: {', '.join(hp) or 'none'}")
    bounds = dict(bounds or {})
    box = [
        tuple(math.log(b) for b in bounds[n]) if n in bounds else
        (math.log(hp[n]) - math.log(1e4), math.log(hp[n]) + math.log(1e4))
        for n in names
    ]  # fmt: skip

    def kernel_of(theta: np.ndarray) -> StateSpaceKernel:
        return kernel.with_hyperparameters(
            **{n: float(v) for n, v in zip(names, np.exp(theta), strict=True)}
        )

    def negative_ll(theta: np.ndarray) -> float:
        try:
            k = kernel_of(theta)
            return -sum(driven_log_likelihood(k, dt, **e) for e in episodes)
        except (ValueError, np.linalg.LinAlgError):
            return 1e12  # outside the kernel's usable range

    theta0 = np.log([hp[n] for n in names])
    res = scipy.optimize.minimize(negative_ll, theta0, method="L-BFGS-B", bounds=box)
    fitted = kernel_of(res.x)
    info = DrivenFitInfo(
        log_likelihood=-float(res.fun),
        hyperparameters=dict(fitted.hyperparameters),
        std_errors=dict(zip(names, log_space_std_errors(negative_ll, res.x), strict=True)),
        success=bool(res.success),
        message=str(res.message),
        n_evaluations=int(res.nfev),
    )
    object.__setattr__(fitted, "fit_info", info)
    return fitted


__all__ = ["DrivenFitInfo", "FitInfo", "fit", "fit_driven", "log_space_std_errors"]
