"""Unscented Kalman filter on the augmented state of a latent-force model.

The cheap Gaussian baseline of the estimators: one mean and covariance of ``[x, z]``. The
prediction passes ``2 d + 1`` sigma points (``d = nx + p``) through the model's noise-free
step (:meth:`LatentForceModel.physical_step` and ``z+ = A z``) and adds the process noise
covariance ``diag(Sigma_x, Q)``; the measurement ``y = x + e`` is linear, so the update is
the Kalman filter's. On a linear model the unscented transform is exact and the filter is the
Kalman filter.

Sigma points follow Van der Merwe's scaled form with ``alpha = 1``, ``beta = 2``,
``kappa = 0``: ``mean +- sqrt(d) S_j`` with ``S S' = P`` and weights ``1 / (2 d)`` (the centre
point has weight 0 for the mean and 2 for the covariance). With ``alpha = 1`` no weight is
negative, so the predicted covariance stays positive semi-definite.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.estimators.particle_filter import measurement_noise_covariance
from lfm_env.model import LatentForceModel, psd_factor

_BETA = 2.0  # prior knowledge of a Gaussian distribution (optimal for one)


@dataclass(frozen=True)
class KalmanUpdateInfo:
    """Record of one :meth:`UnscentedKalmanFilter.update`.

    Attributes:
        nis: normalised innovation squared ``r' S^-1 r`` of the measurement.
        degenerate: the measurement was not finite and was skipped.
    """

    nis: float
    degenerate: bool


class UnscentedKalmanFilter:
    """UKF over ``[x, z]`` with the full-state measurement ``y = x + e``.

    Args:
        model: the latent-force model.
        measurement_std: std of the measurement noise ``(nx,)`` (> 0).
        mean: initial mean of ``[x, z]`` ``(nx + p,)``.
        covariance: initial covariance ``(nx + p, nx + p)``.
    """

    def __init__(
        self, model: LatentForceModel, measurement_std: Any, mean: Any, covariance: Any
    ) -> None:
        self.model = model
        self.nx, self.d = model.nx, model.state_dim
        self._R = measurement_noise_covariance(measurement_std, self.nx)
        q = np.zeros((self.d, self.d))
        q[: self.nx, : self.nx] = np.diag(model.process_std**2)
        q[self.nx :, self.nx :] = model.Q
        self._process_cov = q
        self.reset(mean, covariance)

    def reset(self, mean: Any, covariance: Any) -> None:
        """Restart from a new Gaussian of ``[x, z]``."""
        mean = np.array(mean, dtype=float).reshape(-1)
        cov = np.array(covariance, dtype=float)
        if mean.shape != (self.d,) or cov.shape != (self.d, self.d):
            raise ValueError(
                f"mean/covariance: expected ({self.d},) and ({self.d}, {self.d}), got "
                f"{mean.shape} and {cov.shape}"
            )
        self._mean, self._cov = mean, 0.5 * (cov + cov.T)

    # ------------------------------------------------------------------ the step

    def _step_points(self, points: np.ndarray, u: Any) -> np.ndarray:
        m, nx = self.model, self.nx
        x, z = points[:, :nx], points[:, nx:]
        x_next = m.physical_step(x, np.asarray(u, dtype=float), m.latent_force(z))
        return np.concatenate([x_next, z @ m.A.T], axis=1)

    def predict(self, u: Any) -> None:
        """Propagate the Gaussian through one step with the input ``u``."""
        d = self.d
        spread = np.sqrt(d) * psd_factor(self._cov).T  # rows: sqrt(d) S_j
        points = np.concatenate([self._mean[None], self._mean + spread, self._mean - spread])
        moved = self._step_points(points, u)
        w = 1.0 / (2 * d)
        mean = w * moved[1:].sum(axis=0)  # the centre point's mean weight is 0
        centred = moved - mean
        cov = w * centred[1:].T @ centred[1:] + _BETA * np.outer(centred[0], centred[0])
        self._mean = mean
        self._cov = 0.5 * (cov + cov.T) + self._process_cov

    def update(self, y: Any) -> KalmanUpdateInfo:
        """Kalman update with the measurement ``y`` ``(nx,)``; a non-finite one is skipped."""
        y = np.asarray(y, dtype=float).reshape(-1)
        nx = self.nx
        if y.shape != (nx,) or not np.all(np.isfinite(y)):
            return KalmanUpdateInfo(nis=float("nan"), degenerate=True)
        r = y - self._mean[:nx]
        S = self._cov[:nx, :nx] + self._R
        gain = np.linalg.solve(S, self._cov[:nx, :]).T  # P H' S^-1, (d, nx)
        self._mean = self._mean + gain @ r
        cov = self._cov - gain @ S @ gain.T
        self._cov = 0.5 * (cov + cov.T)
        return KalmanUpdateInfo(nis=float(r @ np.linalg.solve(S, r)), degenerate=False)

    def step(self, u: Any, y: Any) -> KalmanUpdateInfo:
        """:meth:`predict` with ``u``, then :meth:`update` with ``y``."""
        self.predict(u)
        return self.update(y)

    # ------------------------------------------------------------------ estimates

    @property
    def mean(self) -> np.ndarray:
        """Mean of ``[x, z]``."""
        return self._mean.copy()

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of ``[x, z]``."""
        return self._cov.copy()

    @property
    def std(self) -> np.ndarray:
        """Marginal standard deviations of ``[x, z]``."""
        return np.sqrt(np.maximum(np.diag(self._cov), 0.0))

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` Gaussian draws of ``[x, z]`` ``(n, nx + p)``."""
        return self._mean + rng.standard_normal((n, self.d)) @ psd_factor(self._cov).T

    def innovation_nis(self, y: Any) -> float:
        """``r' (P_xx + R)^-1 r`` of a measurement against the current (predicted) estimate."""
        r = np.asarray(y, dtype=float) - self._mean[: self.nx]
        return float(r @ np.linalg.solve(self._cov[: self.nx, : self.nx] + self._R, r))


__all__ = ["KalmanUpdateInfo", "UnscentedKalmanFilter"]
