"""The augmented latent-force model: bicycle state stacked with the GP's latent state.

``xbar = [p_x, p_y, v, psi, z_1 .. z_p]``; the latent force ``w = H z`` is added to
the acceleration. One step (paper eq. DiscAugSys, with the GP part discretised
exactly by default):

    x_{k+1} = x_k + f(x_k, u_k, H z_k) dt + e_k,    e_k ~ N(0, diag(process_std^2))
    z_{k+1} = A z_k + eta_k,                        eta_k ~ N(0, Q)

The simulator, the particle filter and the MPC agents all build on this class, so
there is one model of the world. Agents get it from the *known* structure and
hyperparameters in the config, never from the env's hidden state.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lfm_env.config import DisturbanceConfig, EnvConfig
from lfm_env.gp import StateSpaceKernel
from lfm_env.vehicle import euler_step


def psd_factor(cov: np.ndarray) -> np.ndarray:
    """A matrix ``S`` with ``S S^T = cov`` for a symmetric PSD ``cov`` (rank-deficient ok)."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    return vecs * np.sqrt(np.clip(vals, 0.0, None))


@dataclass(frozen=True, eq=False)
class LatentForceModel:
    """Discrete-time augmented model of the case study, built from an :class:`EnvConfig`."""

    config: EnvConfig
    disturbance: DisturbanceConfig | None = None  # the GP to model; None: config.disturbance
    kernel: StateSpaceKernel = field(init=False)
    A: np.ndarray = field(init=False)  # (p, p) latent transition
    Q: np.ndarray = field(init=False)  # (p, p) latent process noise covariance
    Q_factor: np.ndarray = field(init=False)  # (p, p) with Q_factor Q_factor^T = Q
    H: np.ndarray = field(init=False)  # (p,) latent force read-out, w = H z
    process_std: np.ndarray = field(init=False)  # (4,) per-step std on [p_x, p_y, v, psi]
    # Single-precision copies the particle transition scales its float32 noise with.
    _process_std_col: np.ndarray = field(init=False, repr=False)  # (4, 1)
    _q_factor32: np.ndarray = field(init=False, repr=False)  # (p, p)

    def __post_init__(self) -> None:
        d = self.disturbance or self.config.disturbance
        kernel = d.make_kernel()
        A, Q = kernel.discretize(self.config.dt, method=d.discretization)
        object.__setattr__(self, "kernel", kernel)
        object.__setattr__(self, "A", np.asarray(A, dtype=float))
        object.__setattr__(self, "Q", np.asarray(Q, dtype=float))
        object.__setattr__(self, "Q_factor", psd_factor(np.asarray(Q, dtype=float)))
        object.__setattr__(self, "H", np.asarray(kernel.H, dtype=float).reshape(-1))
        object.__setattr__(self, "process_std", self.config.process_noise_std_rad)
        std_col = np.asarray(self.process_std, dtype=np.float32).reshape(4, 1)
        object.__setattr__(self, "_process_std_col", std_col)
        object.__setattr__(self, "_q_factor32", self.Q_factor.astype(np.float32))

    @property
    def latent_dim(self) -> int:
        """Dimension ``p`` of the latent state ``z``."""
        return int(self.A.shape[0])

    @property
    def state_dim(self) -> int:
        """Dimension ``4 + p`` of the augmented state."""
        return 4 + self.latent_dim

    @property
    def dt(self) -> float:
        """Sampling time [s]."""
        return self.config.dt

    def latent_force(self, z: np.ndarray) -> np.ndarray:
        """``w = H z`` [m/s^2] for latent states of shape ``(..., p)``."""
        return np.asarray(z) @ self.H

    def stationary_latent_covariance(self) -> np.ndarray:
        """Stationary covariance of the latent state (of the chosen discretisation)."""
        if (self.disturbance or self.config.disturbance).discretization == "exact":
            return np.asarray(self.kernel.Pinf, dtype=float)
        import scipy.linalg

        return scipy.linalg.solve_discrete_lyapunov(self.A, self.Q)

    def physical_step(
        self, x: np.ndarray, u: np.ndarray, w: np.ndarray | float, axis: int = -1
    ) -> np.ndarray:
        """Noise-free Euler step of the bicycle with latent force ``w``.

        ``x`` holds ``[p_x, p_y, v, psi]`` along ``axis`` (shape ``(..., 4)`` by default,
        ``(4, n)`` with ``axis=0``); see :func:`lfm_env.vehicle.euler_step`.
        """
        return euler_step(x, u, self.config.dt, w, self.config.vehicle_length, axis)

    def transition(
        self, particles: np.ndarray, u: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """Propagate augmented states ``(n, 4 + p)`` one step, with process noise.

        This is the bootstrap particle filter's proposal: all particles at once.
        """
        n, d = particles.shape
        # Component-major (d, n) working copy: contiguous rows make the elementwise model
        # several times faster than strided columns of the row-major particle array.
        X = np.ascontiguousarray(particles.T)
        z = X[4:]
        # One draw for all components; single precision is ample for noise samples and
        # halves the generator's cost, the largest part of a 7000-particle step.
        noise = rng.standard_normal((d, n), dtype=np.float32)
        out = np.empty((d, n))
        out[:4] = self.physical_step(X[:4], u, self.H @ z, axis=0)
        out[:4] += noise[:4] * self._process_std_col
        np.matmul(self.A, z, out=out[4:])
        out[4:] += self._q_factor32 @ noise[4:]
        return np.ascontiguousarray(out.T)

    def mean_latent_forecast(self, z: np.ndarray, horizon: int) -> np.ndarray:
        """Mean forecast of the latent force ``(..., horizon)`` from latent states ``(..., p)``.

        Element ``k`` is ``H A^k z``, the force acting during step ``k`` (``k = 0`` uses ``z``).
        """
        z = np.asarray(z, dtype=float)
        out = np.empty(z.shape[:-1] + (horizon,))
        zk = z
        for k in range(horizon):
            out[..., k] = zk @ self.H
            zk = zk @ self.A.T
        return out

    def sample_latent_forecasts(
        self, z0: np.ndarray, horizon: int, rng: np.random.Generator
    ) -> np.ndarray:
        """Sampled latent-force sequences ``(Ns, horizon)`` from latent states ``z0`` ``(Ns, p)``.

        The scenario draws of the paper: each row is one draw of the latent process noise
        over the horizon, started from its own ``z0`` row. Element ``k`` acts during step ``k``.
        """
        z = np.array(z0, dtype=float, copy=True)
        ns = z.shape[0]
        out = np.empty((ns, horizon))
        for k in range(horizon):
            out[:, k] = z @ self.H
            z = z @ self.A.T + rng.standard_normal((ns, self.latent_dim)) @ self.Q_factor.T
        return out
