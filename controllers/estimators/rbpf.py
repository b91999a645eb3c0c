"""Rao-Blackwellised (marginalised) particle filter for a latent-force model.

Particles carry only the physical state ``x``; each carries an exact Kalman filter over the
latent state ``z``. This is exact when the force enters the dynamics affinely,
``f(x, u, w) = f0(x, u) + G(x, u) w`` (:attr:`LatentForceModel.force_enters_affinely`):
given the physical path, the model is then linear-Gaussian in ``z`` (Schoen, Gustafsson and
Nordlund, "Marginalized particle filters for mixed linear/nonlinear state-space models",
IEEE TSP 2005). With the full-state measurement ``y = x + e`` the next physical state is
Gaussian given a particle and ``y``, so the filter is *fully adapted* (the optimal proposal;
Pitt and Shephard's auxiliary filter): for particle ``i`` with ``z_k ~ N(m_i, P_i)``::

    C_i = dt G(x_i, u) H,   mu_i = x_i + dt f0(x_i, u) + C_i m_i,   S_i = C_i P_i C_i' + Sigma_x
    weight_i  *= N(y_{k+1}; mu_i, S_i + R)             (the predictive likelihood; resample)
    x_i+      ~  N(x_i+ | mu_i, S_i) N(y_{k+1} | x_i+, R)   (Gaussian: the optimal proposal)
    m_i, P_i  <- Kalman update of z_k with the "measurement" x_i+ (matrix C_i, noise Sigma_x)
    m_i, P_i  <- A m_i, A P_i A' + Q                    (time update of z)

The weights depend on the particle before the move, not on the noise drawn for it, so far
fewer particles carry the same information as the bootstrap filter's. The estimate's moments
add the Kalman covariances to the spread of the particles.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from controllers.estimators.particle_filter import UpdateInfo, measurement_noise_covariance
from controllers.estimators.resampling import RESAMPLERS
from lfm_env.model import LatentForceModel

_JITTER = 1e-12  # [state units^2] keeps S_i invertible for states without process noise


def _apply(mats: np.ndarray, vecs: np.ndarray) -> np.ndarray:
    """``mats[i] @ vecs[i]`` for ``(n, a, b)`` matrices, or one ``(1, a, b)`` for all."""
    if mats.shape[0] == 1:
        return vecs @ mats[0].T
    return np.einsum("nij,nj->ni", mats, vecs)


class RaoBlackwellisedParticleFilter:
    """Particles over the physical state, a Kalman filter per particle over the latent one.

    Args:
        model: the latent-force model; its force must enter the dynamics affinely.
        measurement_std: std of the full-state measurement noise ``(nx,)`` (> 0).
        x_particles: initial physical states ``(n, nx)``.
        z_mean: initial latent mean ``(p,)`` (the same for every particle).
        z_cov: initial latent covariance ``(p, p)``.
        rng: the generator of the process noise and the resampling.
        resampling: one of the bootstrap filter's schemes.
        ess_threshold: ``None`` resamples every step; else a fraction in ``(0, 1]``.

    Raises:
        ValueError: the force does not enter affinely, or a shape is wrong.
    """

    def __init__(
        self,
        model: LatentForceModel,
        measurement_std: Any,
        x_particles: np.ndarray,
        z_mean: np.ndarray,
        z_cov: np.ndarray,
        rng: np.random.Generator,
        resampling: str = "systematic",
        ess_threshold: float | None = None,
    ) -> None:
        if not model.force_enters_affinely:
            raise ValueError(
                f"system {model.system.name!r}: the Rao-Blackwellised filter needs a force that "
                "enters f(x, u, w) affinely (df/dw must not depend on w); use the bootstrap "
                "filter"
            )
        if resampling not in RESAMPLERS:
            raise ValueError(f"resampling: {resampling!r} is not one of {sorted(RESAMPLERS)}")
        if ess_threshold is not None and not 0.0 < float(ess_threshold) <= 1.0:
            raise ValueError(f"ess_threshold: must be None or in (0, 1], got {ess_threshold!r}")
        self.model = model
        self.nx, self.p = model.nx, model.latent_dim
        self._R = measurement_noise_covariance(measurement_std, self.nx)
        self._sigma_x = np.diag(model.process_std**2) + _JITTER * np.eye(self.nx)
        self._rng = rng
        self._resample = RESAMPLERS[resampling]
        self._ess_threshold = ess_threshold
        self.reset(x_particles, z_mean, z_cov)

    def reset(self, x_particles: np.ndarray, z_mean: np.ndarray, z_cov: np.ndarray) -> None:
        """Restart from new physical particles ``(n, nx)`` and one latent Gaussian."""
        x = np.array(x_particles, dtype=float)
        if x.ndim != 2 or x.shape[1] != self.nx or not np.all(np.isfinite(x)):
            raise ValueError(f"x_particles: expected finite shape (n, {self.nx}), got {x.shape}")
        n, p = x.shape[0], self.p
        self._X = x
        self._M = np.array(np.broadcast_to(np.asarray(z_mean, dtype=float), (n, p)))
        # With a constant force gain every particle's latent covariance follows the same
        # Riccati recursion, so one (1, p, p) covariance serves them all.
        shared = 1 if self.model.force_gain_is_constant else n
        self._P = np.array(np.broadcast_to(np.asarray(z_cov, dtype=float), (shared, p, p)))
        self._log_w = np.full(n, -np.log(n))
        self._moments: tuple[np.ndarray, np.ndarray] | None = None
        self.n_degenerate = 0

    # ------------------------------------------------------------------ the step

    def step(self, u: Any, y: Any) -> UpdateInfo:
        """Move with the input ``u`` applied since the last sample and condition on ``y``.

        A measurement that no particle can explain (non-finite predictive likelihoods) is
        skipped: the particles move by their prior dynamics, and the record says so.
        """
        m = self.model
        X, M, P = self._X, self._M, self._P
        n, nx = X.shape
        shared = P.shape[0] == 1  # one latent covariance for all particles
        u = np.asarray(u, dtype=float)
        y = np.asarray(y, dtype=float).reshape(-1)
        f0 = np.asarray(m.system.rhs(X, u, np.zeros(m.nw)))
        # C: (n, nx, p), or (1, nx, p) shared when the gain is constant.
        C = m.dt * (m.force_gain(X[:1] if shared else X, u) @ m.H)
        Ct = C.transpose(0, 2, 1)
        mu = X + m.dt * f0 + _apply(C, M)
        PCt = P @ Ct  # (., p, nx)
        S = C @ PCt + self._sigma_x  # (., nx, nx): x_{k+1} | particle
        V = S + self._R  # (., nx, nx): y_{k+1} | particle
        r = y - mu
        # --- weights: the predictive likelihood N(y; mu_i, V_i) ---
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            L = np.linalg.cholesky(V)
            a = _apply(np.linalg.inv(L), r)
            log_det = np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)
            ll = -0.5 * np.einsum("ni,ni->n", a, a) - log_det
        lw = self._log_w + ll
        degenerate = not np.any(np.isfinite(lw))
        if degenerate:
            self.n_degenerate += 1
            ess, resampled, max_ll = 0.0, False, -np.inf
            x_new = mu + _apply(np.linalg.cholesky(S), self._rng.standard_normal((n, nx)))
        else:
            lw = np.where(np.isfinite(lw), lw, -np.inf)
            max_ll = float(np.max(ll[np.isfinite(ll)]))
            w = np.exp(lw - lw.max())
            w /= w.sum()
            ess = float(1.0 / np.dot(w, w))
            resampled = self._ess_threshold is None or ess < self._ess_threshold * n
            if resampled:
                idx = self._resample(w, self._rng)
                mu, r, M = mu[idx], r[idx], M[idx]
                if not shared:
                    S, C, PCt, P, V = S[idx], C[idx], PCt[idx], P[idx], V[idx]
                self._log_w = np.full(n, -np.log(n))
            else:
                self._log_w = np.log(w)
            # --- move: x_{k+1} | particle, y  ~  N(mu + S V^-1 r, S - S V^-1 S) ---
            gain = np.linalg.solve(V, S).transpose(0, 2, 1)  # S V^-1 (S, V symmetric)
            cov = S - gain @ S
            cov = 0.5 * (cov + cov.transpose(0, 2, 1)) + _JITTER * np.eye(nx)
            noise = self._rng.standard_normal((n, nx))
            x_new = mu + _apply(gain, r) + _apply(np.linalg.cholesky(cov), noise)
        # --- condition z_k on x_{k+1} (gain P C' S^-1), then its time update ---
        K = np.linalg.solve(S, PCt.transpose(0, 2, 1)).transpose(0, 2, 1)
        M = M + _apply(K, x_new - mu)
        P = P - K @ PCt.transpose(0, 2, 1)
        M = M @ m.A.T
        P = m.A @ P @ m.A.T + m.Q
        self._X, self._M, self._P = x_new, M, 0.5 * (P + P.transpose(0, 2, 1))
        self._moments = None
        return UpdateInfo(
            ess=ess, resampled=resampled, degenerate=degenerate, max_log_likelihood=max_ll
        )

    # ------------------------------------------------------------------ estimates

    @property
    def weights(self) -> np.ndarray:
        """Normalised particle weights ``(n,)``."""
        w = np.exp(self._log_w - self._log_w.max())
        return w / w.sum()

    def _compute(self) -> tuple[np.ndarray, np.ndarray]:
        if self._moments is None:
            w = self.weights
            aug = np.concatenate([self._X, self._M], axis=1)
            mean = w @ aug
            d = aug - mean
            cov = (d * w[:, None]).T @ d
            P = (
                self._P
                if self._P.shape[0] > 1
                else np.broadcast_to(self._P, (len(w),) + self._P.shape[1:])
            )
            cov[self.nx :, self.nx :] += np.einsum("n,nij->ij", w, P)
            self._moments = (mean, 0.5 * (cov + cov.T))
        return self._moments

    @property
    def mean(self) -> np.ndarray:
        """Mean of the augmented state ``[x, z]`` ``(nx + p,)``."""
        return self._compute()[0].copy()

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of ``[x, z]``: the particles' spread plus their Kalman covariances."""
        return self._compute()[1].copy()

    @property
    def std(self) -> np.ndarray:
        """Marginal standard deviations of ``[x, z]``."""
        return np.sqrt(np.maximum(np.diag(self._compute()[1]), 0.0))

    @property
    def physical_particles(self) -> np.ndarray:
        """The particles' physical states ``(n, nx)`` (a copy)."""
        return self._X.copy()

    @property
    def n_particles(self) -> int:
        return self._X.shape[0]

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` draws of the augmented state ``(n, nx + p)`` from the filter's mixture.

        A particle is drawn by weight, then its latent state from its Kalman Gaussian.
        """
        idx = rng.choice(self.n_particles, size=n, p=self.weights)
        vals, vecs = np.linalg.eigh(self._P if self._P.shape[0] == 1 else self._P[idx])
        factor = vecs * np.sqrt(np.clip(vals, 0.0, None))[:, None, :]
        z = self._M[idx] + _apply(factor, rng.standard_normal((n, self.p)))
        return np.concatenate([self._X[idx], z], axis=1)


__all__ = ["RaoBlackwellisedParticleFilter"]
