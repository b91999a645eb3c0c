"""State estimators of a latent-force model behind one face, chosen by name.

Every estimator tracks the augmented state ``[x, z]`` from full-state measurements
``y = x + e`` and gives its mean, covariance and standard deviations the same way, draws
from its distribution (the scenario starts of the uncertainty-aware agents) and a
normalised distance of each measurement to the estimate (the agents' divergence check):

* ``"bootstrap"``: the bootstrap particle filter of the paper over ``[x, z]``
  (:class:`~controllers.estimators.particle_filter.ParticleFilter`).
* ``"rbpf"``: the Rao-Blackwellised particle filter: particles over ``x``, a Kalman filter
  per particle over ``z`` (:mod:`controllers.estimators.rbpf`; the force must enter the
  dynamics affinely).
* ``"ukf"``: the unscented Kalman filter over ``[x, z]`` (:mod:`controllers.estimators.ukf`).

All start from the first measurement: ``x ~ N(y, R)`` and the latent state at the GP's
stationary distribution ``z ~ N(0, P_inf)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood
from controllers.estimators.rbpf import RaoBlackwellisedParticleFilter
from controllers.estimators.ukf import UnscentedKalmanFilter
from lfm_env.model import LatentForceModel, psd_factor

ESTIMATORS = ("bootstrap", "rbpf", "ukf")


@dataclass(frozen=True)
class EstimateInfo:
    """What one :meth:`StateEstimator.start` or ``step`` reports.

    Attributes:
        degenerate: the measurement was skipped (no particle explained it, or not finite).
        nis: normalised squared distance of the measurement to the estimate (particle
            filters: to the closest particle, in measurement-noise units; the UKF: the
            innovation's ``r' S^-1 r``); compare with a chi^2 quantile of ``nx`` dof.
    """

    degenerate: bool
    nis: float


class StateEstimator:
    """The common face; see the module docstring. Subclasses implement the four hooks."""

    name = ""

    def __init__(self, model: LatentForceModel, measurement_std: Any) -> None:
        self.model = model
        self.nx = model.nx
        self.measurement_std = np.asarray(measurement_std, dtype=float).reshape(-1)
        self.latent_prior_cov = model.stationary_latent_covariance()
        self._latent_prior_factor = psd_factor(self.latent_prior_cov)

    def start(self, y: np.ndarray, rng: np.random.Generator) -> EstimateInfo:
        """(Re)start from the first measurement ``y``, drawing with ``rng``."""
        raise NotImplementedError

    def step(self, u: np.ndarray, y: np.ndarray) -> EstimateInfo:
        """Predict with the input applied since the last sample, update with ``y``."""
        raise NotImplementedError

    # The estimates are the underlying filter's (``self.filter``, made by :meth:`start`).

    @property
    def mean(self) -> np.ndarray:
        """Mean of ``[x, z]`` ``(nx + p,)``."""
        return self.filter.mean

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of ``[x, z]``."""
        return self.filter.covariance

    @property
    def std(self) -> np.ndarray:
        """Marginal standard deviations of ``[x, z]``."""
        return self.filter.std

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` draws of ``[x, z]`` ``(n, nx + p)`` from the estimate's distribution."""
        return self.filter.sample(n, rng)


class _ParticleEstimator(StateEstimator):
    """What the two particle filters share: their settings, the physical prior around the
    first measurement and the distance of a measurement to the closest particle."""

    def __init__(
        self,
        model: LatentForceModel,
        measurement_std: Any,
        n_particles: int,
        resampling: str = "systematic",
        ess_threshold: float | None = None,
    ) -> None:
        super().__init__(model, measurement_std)
        self.n_particles = int(n_particles)
        self.resampling, self.ess_threshold = resampling, ess_threshold

    def _physical_prior(self, y: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        return y + rng.standard_normal((n, self.nx)) * self.measurement_std

    def _closest(self, y: np.ndarray, physical: np.ndarray) -> float:
        r = (physical - y) / self.measurement_std
        return float(np.min(np.einsum("ij,ij->i", r, r)))


class BootstrapEstimator(_ParticleEstimator):
    """The paper's bootstrap particle filter over ``[x, z]``."""

    name = "bootstrap"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._log_lik = gaussian_log_likelihood(self.measurement_std, np.arange(self.nx))
        self.filter: ParticleFilter | None = None

    def _prior(self, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        n, p = self.n_particles, self.model.latent_dim
        x = self._physical_prior(y, n, rng)
        z = rng.standard_normal((n, p)) @ self._latent_prior_factor.T
        return np.concatenate([x, z], axis=1)

    def start(self, y: np.ndarray, rng: np.random.Generator) -> EstimateInfo:
        if self.filter is None:
            self.filter = ParticleFilter(
                self.model.transition,
                self._log_lik,
                self._prior(y, rng),
                rng,
                resampling=self.resampling,
                ess_threshold=self.ess_threshold,
            )
        else:
            self.filter.reset(self._prior(y, rng))
        return EstimateInfo(False, self._closest(y, self.filter.particles[:, : self.nx]))

    def step(self, u: np.ndarray, y: np.ndarray) -> EstimateInfo:
        rec = self.filter.step(u, y)
        return EstimateInfo(
            bool(rec.degenerate), self._closest(y, self.filter.particles[:, : self.nx])
        )

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        idx = rng.choice(self.filter.n_particles, size=n, p=self.filter.weights)
        return self.filter.particles[idx]


class RBPFEstimator(_ParticleEstimator):
    """The Rao-Blackwellised particle filter (particles over ``x``, Kalman over ``z``)."""

    name = "rbpf"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        model = self.model
        if not model.force_enters_affinely:
            raise ValueError(
                f"estimator 'rbpf': the force of system {model.system.name!r} does not enter "
                "f(x, u, w) affinely; use 'bootstrap' or 'ukf'"
            )
        self.filter: RaoBlackwellisedParticleFilter | None = None

    def start(self, y: np.ndarray, rng: np.random.Generator) -> EstimateInfo:
        x = self._physical_prior(y, self.n_particles, rng)
        z0 = np.zeros(self.model.latent_dim)
        if self.filter is None:
            self.filter = RaoBlackwellisedParticleFilter(
                self.model,
                self.measurement_std,
                x,
                z0,
                self.latent_prior_cov,
                rng,
                resampling=self.resampling,
                ess_threshold=self.ess_threshold,
            )
        else:
            self.filter.reset(x, z0, self.latent_prior_cov)
        return EstimateInfo(False, self._closest(y, x))

    def step(self, u: np.ndarray, y: np.ndarray) -> EstimateInfo:
        rec = self.filter.step(u, y)
        return EstimateInfo(bool(rec.degenerate), self._closest(y, self.filter.physical_particles))


class UKFEstimator(StateEstimator):
    """The unscented Kalman filter over ``[x, z]`` (one Gaussian)."""

    name = "ukf"

    def __init__(self, model: LatentForceModel, measurement_std: Any, **_: Any) -> None:
        super().__init__(model, measurement_std)
        self.filter: UnscentedKalmanFilter | None = None

    def start(self, y: np.ndarray, rng: np.random.Generator) -> EstimateInfo:
        nx, p = self.nx, self.model.latent_dim
        mean = np.concatenate([y, np.zeros(p)])
        cov = np.zeros((nx + p, nx + p))
        cov[:nx, :nx] = np.diag(self.measurement_std**2)
        cov[nx:, nx:] = self.latent_prior_cov
        if self.filter is None:
            self.filter = UnscentedKalmanFilter(self.model, self.measurement_std, mean, cov)
        else:
            self.filter.reset(mean, cov)
        return EstimateInfo(False, 0.0)

    def step(self, u: np.ndarray, y: np.ndarray) -> EstimateInfo:
        rec = self.filter.step(u, y)
        return EstimateInfo(rec.degenerate, rec.nis if not rec.degenerate else 0.0)


_CLASSES = {"bootstrap": BootstrapEstimator, "rbpf": RBPFEstimator, "ukf": UKFEstimator}


def make_estimator(
    name: str,
    model: LatentForceModel,
    measurement_std: Any,
    n_particles: int = 7000,
    resampling: str = "systematic",
    ess_threshold: float | None = None,
) -> StateEstimator:
    """The estimator ``name`` (one of :data:`ESTIMATORS`) of ``model``.

    Args:
        name: ``"bootstrap"``, ``"rbpf"`` or ``"ukf"``.
        model: the agent's latent-force model.
        measurement_std: std of the full-state measurement noise ``(nx,)`` (> 0).
        n_particles, resampling, ess_threshold: the particle filters' settings (the UKF
            ignores them).
    """
    if name not in _CLASSES:
        raise ValueError(f"unknown estimator {name!r}; choose one of {ESTIMATORS}")
    return _CLASSES[name](
        model,
        measurement_std,
        n_particles=n_particles,
        resampling=resampling,
        ess_threshold=ess_threshold,
    )


__all__ = [
    "ESTIMATORS",
    "BootstrapEstimator",
    "EstimateInfo",
    "RBPFEstimator",
    "StateEstimator",
    "UKFEstimator",
    "make_estimator",
]
