"""The latent-force model: any :class:`ControlSystem` stacked with a state-space GP.

The augmented state is ``xbar = [x, z]`` with the system's physical state ``x`` (``nx``)
and the GP's latent state ``z`` (``p``); the latent force ``w = H z`` (``nw`` components)
enters the system's right-hand side. One step (paper eq. DiscAugSys; the GP part is
discretised exactly by default, or by Euler-Maruyama as in the published code)::

    x_{k+1} = x_k + f(x_k, u_k, H z_k) dt + e_k,    e_k ~ N(0, diag(process_noise_std^2))
    z_{k+1} = A z_k + eta_k,                        eta_k ~ N(0, Q)

The simulator, the particle filter and the MPC agents all build on this class, so there
is one model of the world. Agents build theirs from the *known* structure and
hyperparameters, never from the env's hidden state.

A force with several components takes one kernel per component (independent GPs, stacked
block-diagonally): ``LatentForceModel(system, kernel=[k_x, k_y], ...)`` for a system with
two ``force_names``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg

from lfm_env.gp import StateSpaceKernel
from lfm_env.system import ControlSystem

DISCRETIZATIONS = ("exact", "euler_maruyama")
DRIFT_PRECISIONS = ("single", "double")  # of the drift in the particle transition


def psd_factor(cov: np.ndarray) -> np.ndarray:
    """A matrix ``S`` with ``S S^T = cov`` for a symmetric PSD ``cov`` (rank-deficient ok)."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    return vecs * np.sqrt(np.clip(vals, 0.0, None))


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class LatentForceModel:
    """Discrete-time augmented model of a system and its latent force.

    Args:
        system: the physics (:class:`~lfm_env.system.ControlSystem`).
        kernel: the GP of the force: one :class:`~lfm_env.gp.StateSpaceKernel` per force
            component (a single kernel for a one-component force).
        dt: sampling time [s]; one Euler step of the physics per sample.
        process_noise_std: per-step std of the physical process noise ``(nx,)``, in the
            states' units; ``None`` for none.
        discretization: ``"exact"`` (matrix exponential) or ``"euler_maruyama"`` for the GP.
        drift_precision: precision of the physics' drift ``f(x, u, w)`` in the particle
            :meth:`transition`: ``"single"`` (default; the state update itself stays in
            double precision) or ``"double"``. Single precision makes the drift's
            transcendental functions several times faster (the bicycle's drift for 7000
            particles: 144 -> 29 us). Its error comes from rounding the states and ``f``
            to about 6e-8 relative: for the case studies about 1e-7 of ``|x| + |f dt|``
            per step, four orders of magnitude below their process noise. Use
            ``"double"`` for a system whose drift is sensitive to the last digits of a
            large state (e.g. ``sin`` of a position of many kilometres). Simulation,
            solvers and :meth:`physical_step` always use double precision.
    """

    system: ControlSystem
    kernel: Any
    dt: float
    process_noise_std: Any = None
    discretization: str = "exact"
    drift_precision: str = "single"
    kernels: tuple[StateSpaceKernel, ...] = field(init=False)
    A: np.ndarray = field(init=False)  # (p, p) latent transition
    Q: np.ndarray = field(init=False)  # (p, p) latent process noise covariance
    Q_factor: np.ndarray = field(init=False)  # (p, p) with Q_factor Q_factor^T = Q
    H: np.ndarray = field(init=False)  # (nw, p) read-out, w = H z
    process_std: np.ndarray = field(init=False)  # (nx,) per-step std of the physical noise
    # Single-precision copies the particle transition scales its float32 noise with.
    _process_std_col: np.ndarray = field(init=False, repr=False)
    _q_factor32: np.ndarray = field(init=False, repr=False)
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        system = self.system
        if not isinstance(system, ControlSystem):
            raise ValueError(f"LatentForceModel.system must be a ControlSystem, got {system!r}")
        kernels = self.kernel if isinstance(self.kernel, Sequence) else (self.kernel,)
        kernels = tuple(kernels)
        if not all(isinstance(k, StateSpaceKernel) for k in kernels):
            raise ValueError("LatentForceModel.kernel: expected lfm_env.gp kernels")
        if len(kernels) != system.nw:
            raise ValueError(
                f"LatentForceModel.kernel: {len(kernels)} kernel(s) for a system with "
                f"{system.nw} force component(s) {system.force_names}; give one per component"
            )
        if not (isinstance(self.dt, (int, float)) and np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"LatentForceModel.dt={self.dt!r}: must be finite and > 0 s")
        if self.discretization not in DISCRETIZATIONS:
            raise ValueError(
                f"LatentForceModel.discretization={self.discretization!r}: one of {DISCRETIZATIONS}"
            )
        if self.drift_precision not in DRIFT_PRECISIONS:
            raise ValueError(
                f"LatentForceModel.drift_precision={self.drift_precision!r}: one of "
                f"{DRIFT_PRECISIONS}"
            )
        blocks = [k.discretize(self.dt, method=self.discretization) for k in kernels]
        A = scipy.linalg.block_diag(*[np.asarray(a, dtype=float) for a, _ in blocks])
        Q = scipy.linalg.block_diag(*[np.asarray(q, dtype=float) for _, q in blocks])
        H = scipy.linalg.block_diag(*[np.asarray(k.H, dtype=float).reshape(1, -1) for k in kernels])
        std = np.zeros(system.nx) if self.process_noise_std is None else self.process_noise_std
        std = np.asarray(std, dtype=float).reshape(-1)
        if std.shape != (system.nx,) or not np.all(np.isfinite(std)) or np.any(std < 0):
            raise ValueError(
                f"LatentForceModel.process_noise_std={self.process_noise_std!r}: must be "
                f"{system.nx} finite numbers >= 0 (one per state {system.state_labels})"
            )
        object.__setattr__(self, "kernels", kernels)
        object.__setattr__(self, "A", _frozen(A))
        object.__setattr__(self, "Q", _frozen(Q))
        object.__setattr__(self, "Q_factor", _frozen(psd_factor(Q)))
        object.__setattr__(self, "H", _frozen(H))
        object.__setattr__(self, "process_std", _frozen(std))
        object.__setattr__(self, "_process_std_col", std.astype(np.float32).reshape(-1, 1))
        object.__setattr__(self, "_q_factor32", self.Q_factor.astype(np.float32))

    # ------------------------------------------------------------------ dimensions

    @property
    def nx(self) -> int:
        """Number of physical states."""
        return self.system.nx

    @property
    def nw(self) -> int:
        """Number of latent-force components."""
        return self.system.nw

    @property
    def latent_dim(self) -> int:
        """Dimension ``p`` of the latent state ``z``."""
        return int(self.A.shape[0])

    @property
    def state_dim(self) -> int:
        """Dimension ``nx + p`` of the augmented state."""
        return self.nx + self.latent_dim

    # ------------------------------------------------------------------ latent force

    def latent_force(self, z: np.ndarray) -> np.ndarray:
        """``w = H z`` ``(..., nw)`` for latent states ``(..., p)``, in the force's units."""
        z = np.asarray(z)
        if self.nw == 1:  # a dot product per state: the same rounding as a 1-D read-out
            return (z @ self.H[0])[..., None]
        return z @ self.H.T

    def stationary_latent_covariance(self) -> np.ndarray:
        """Stationary covariance of the latent state (of the chosen discretisation)."""
        if self.discretization == "exact":
            return scipy.linalg.block_diag(*[np.asarray(k.Pinf, dtype=float) for k in self.kernels])
        return scipy.linalg.solve_discrete_lyapunov(self.A, self.Q)

    def mean_latent_forecast(self, z: np.ndarray, horizon: int) -> np.ndarray:
        """Mean forecast of the force ``(..., horizon, nw)`` from latent states ``(..., p)``.

        Element ``k`` is ``H A^k z``, the force acting during step ``k`` (``k = 0`` uses ``z``).
        """
        z = np.asarray(z, dtype=float)
        out = np.empty(z.shape[:-1] + (horizon, self.nw))
        zk = z
        for k in range(horizon):
            out[..., k, :] = self.latent_force(zk)
            zk = zk @ self.A.T
        return out

    def sample_latent_forecasts(
        self, z0: np.ndarray, horizon: int, rng: np.random.Generator
    ) -> np.ndarray:
        """Sampled forces ``(Ns, horizon, nw)`` from latent states ``z0`` ``(Ns, p)``.

        The scenario draws of the paper: each row is one draw of the latent process noise
        over the horizon, started from its own ``z0`` row. Element ``k`` acts during step
        ``k``.
        """
        z = np.array(z0, dtype=float, copy=True)
        ns = z.shape[0]
        out = np.empty((ns, horizon, self.nw))
        for k in range(horizon):
            out[:, k, :] = self.latent_force(z)
            z = z @ self.A.T + rng.standard_normal((ns, self.latent_dim)) @ self.Q_factor.T
        return out

    # ------------------------------------------------------------------ physics

    @property
    def force_enters_affinely(self) -> bool:
        """Whether ``f(x, u, w) = f0(x, u) + G(x, u) w`` (checked on the CasADi expression).

        Then, given the physical path, the latent state is linear-Gaussian: the case of the
        Rao-Blackwellised particle filter (:mod:`controllers.estimators.rbpf`).
        """
        if "affine" not in self._cache:
            import casadi as ca

            x, u, w = (
                ca.SX.sym(n, k) for n, k in (("x", self.nx), ("u", self.system.nu), ("w", self.nw))
            )
            f = self.system.casadi_rhs()(x, u, w)
            self._cache["affine"] = not ca.depends_on(ca.jacobian(f, w), w)
        return self._cache["affine"]

    @property
    def force_gain_is_constant(self) -> bool:
        """Whether ``G = df/dw`` depends on nothing (the force adds to fixed states).

        Then every particle of the Rao-Blackwellised filter shares one latent covariance.
        """
        if "constant_gain" not in self._cache:
            import casadi as ca

            x, u, w = self._symbols()
            J = ca.jacobian(self.system.casadi_rhs()(x, u, w), w)
            constant = not (ca.depends_on(J, x) or ca.depends_on(J, u) or ca.depends_on(J, w))
            self._cache["constant_gain"] = constant
        return self._cache["constant_gain"]

    def _symbols(self):
        import casadi as ca

        return ca.SX.sym("x", self.nx), ca.SX.sym("u", self.system.nu), ca.SX.sym("w", self.nw)

    def force_gain(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``G(x, u) = df/dw`` ``(..., nx, nw)`` of a force that enters affinely.

        Exact for such a force: column ``j`` is ``f(x, u, e_j) - f(x, u, 0)``.

        Raises:
            ValueError: the force does not enter affinely (:attr:`force_enters_affinely`).
        """
        if not self.force_enters_affinely:
            raise ValueError(
                f"system {self.system.name!r}: the force does not enter f(x, u, w) affinely "
                "(df/dw depends on w), so it has no constant gain"
            )
        x = np.asarray(x, dtype=float)
        base = np.asarray(self.system.rhs(x, u, np.zeros(self.nw)))
        cols = [np.asarray(self.system.rhs(x, u, e)) - base for e in np.eye(self.nw)]
        return np.stack(cols, axis=-1)

    def physical_step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Noise-free Euler step ``x + dt f(x, u, w)`` of physical states ``(..., nx)``."""
        return self.system.euler_step(x, u, w, self.dt)

    def transition(
        self, particles: np.ndarray, u: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """Propagate augmented states ``(n, nx + p)`` one step, with process noise.

        This is the bootstrap particle filter's proposal: all particles at once. The result
        ``(n, nx + p)`` is column-major (the transpose of a component-major buffer): the
        filter keeps that layout, so neither this step nor the next one copies it across.
        """
        n, d = particles.shape
        nx = self.nx
        # Component-major (d, n): contiguous rows make the elementwise model several times
        # faster than strided columns of a row-major particle array (free when the particles
        # are the column-major result of the previous step).
        X = np.ascontiguousarray(particles.T)
        z = X[nx:]
        # One draw for all components; single precision is ample for noise samples and
        # halves the generator's cost, the largest part of a 7000-particle step.
        noise = rng.standard_normal((d, n), dtype=np.float32)
        out = np.empty((d, n))
        # The system's functions take components on the last axis: transposed views of
        # the component-major rows (its stack() returns a view of a component-major buffer).
        w = self.latent_force(z.T)
        if self.drift_precision == "single":
            x32 = X[:nx].astype(np.float32)
            u32 = np.asarray(u, dtype=np.float32)
            dx = self.system.rhs(x32.T, u32, w.astype(np.float32)).T
        else:
            dx = self.system.rhs(X[:nx].T, u, w).T
        np.multiply(dx, self.dt, out=out[:nx])
        out[:nx] += X[:nx]
        out[:nx] += noise[:nx] * self._process_std_col
        np.matmul(self.A, z, out=out[nx:])
        out[nx:] += self._q_factor32 @ noise[nx:]
        return out.T


__all__ = ["DISCRETIZATIONS", "DRIFT_PRECISIONS", "LatentForceModel", "psd_factor"]
