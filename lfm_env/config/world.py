"""What every world's config shares: the latent force's section and the world mixin.

:class:`LatentForceConfig` describes the latent force (a stationary GP in state-space form);
:class:`WorldConfig` derives, the same way for every world, the model, the reward's cost and
the SI vectors from a world's ``env`` section. Each world defines its own section in its
folder (``lfm_env/worlds/<world>/config.py``) and registers it
(:mod:`lfm_env.worlds.registry`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lfm_env.config.loading import (
    ConfigError,
    FieldChecker,
    from_dict,
    show_value,
    to_dict,
    to_dict_fields,
)

#: Longest episode [steps]: 100000 steps are hours of solves, and the recorded trajectory
#: (a few arrays of this length) stays within megabytes.
MAX_STEPS = 100_000

MATERN_NUS = (0.5, 1.5, 2.5, 3.5)
DISCRETIZATIONS = ("exact", "euler_maruyama")
KERNELS = ("matern", "squared_exponential", "periodic")
STARTS = ("stationary", "zero")


@dataclass(frozen=True)
class LatentForceConfig:
    """The latent force: a stationary GP in time, in state-space form.

    ``kernel`` picks the covariance: ``matern`` (exact in state space; the paper's),
    ``squared_exponential`` (Taylor approximation of order ``order``) or ``periodic``
    (``sigma^2 exp(-2 sin^2(pi tau / period) / lengthscale^2)``, cosine series with
    ``harmonics`` terms; its lengthscale is dimensionless).
    """

    kernel: str = "matern"  # one of KERNELS
    nu: float = 2.5  # Matern smoothness, a half-integer in MATERN_NUS
    variance: float = 4.0  # sigma^2 [(m/s^2)^2]
    lengthscale: float = 4.0  # [s] (dimensionless for the periodic kernel)
    order: int = 6  # Taylor order of the squared-exponential approximation, 1..12
    period: float = 10.0  # [s] of the periodic kernel
    harmonics: int = 6  # cosine-series terms of the periodic kernel
    discretization: str = "exact"  # "exact" (expm) or "euler_maruyama" (the published code)
    start: str = "stationary"  # "stationary" (z0 ~ N(0, Pinf)) or "zero" (the published code)

    def __post_init__(self) -> None:
        c = FieldChecker(self)
        c("kernel", self.kernel in KERNELS, f"one of {KERNELS}")
        c("nu", self.nu in MATERN_NUS, f"one of {list(MATERN_NUS)}")
        c.positive("variance", "lengthscale", "period")
        # Shorter lengthscales overflow lambda^(2 nu + 1) in the state-space model.
        c("lengthscale", self.lengthscale >= 1.0e-6, ">= 1.0e-6 s")
        c("order", 1 <= self.order <= 12, "an integer in [1, 12]")
        c("harmonics", 1 <= self.harmonics <= 100, "an integer in [1, 100]")
        c("discretization", self.discretization in DISCRETIZATIONS, f"one of {DISCRETIZATIONS}")
        c("start", self.start in STARTS, f"one of {STARTS}")
        if self.kernel != "matern":
            try:  # the approximations know their own limits (e.g. too few harmonics)
                self.make_kernel()
            except ValueError as exc:
                raise ConfigError(f"kernel={self.kernel!r}: {exc}") from None

    def make_kernel(self):
        """The state-space kernel (:mod:`lfm_env.gp`) these settings describe."""
        from lfm_env import gp

        if self.kernel == "squared_exponential":
            return gp.squared_exponential(self.variance, self.lengthscale, order=self.order)
        if self.kernel == "periodic":
            return gp.periodic(
                self.variance, self.lengthscale, self.period, harmonics=self.harmonics
            )
        return gp.matern(self.nu, self.variance, self.lengthscale)


class _RegisteredEnvId:
    """``ENV_ID`` of a world config (class or instance): its registered id
    (:func:`lfm_env.worlds.registry.env_id_of`)."""

    def __get__(self, obj: Any, cls: type) -> str:
        from lfm_env.worlds.registry import env_id_of

        return env_id_of(cls)


class WorldConfig:
    """What every world's ``env`` section gives the rest of the project (a mixin).

    A world config is a frozen dataclass with at least the fields ``dt`` [s],
    ``initial_state``, ``goal_state``, ``Q``, ``R``, ``measurement_noise_std``,
    ``process_noise_diffusion`` (vectors over the state in config units),
    ``max_steps`` and ``latent_force``; it names the states it gives in degrees
    (:attr:`ANGLE_STATES`, converted to radians here) and builds its system
    (:meth:`make_system`). Its env is the registered world's (:attr:`ENV_ID`). Everything
    else (the model, the cost, the SI vectors) is derived here the same way for every world.
    """

    ENV_ID = _RegisteredEnvId()  # the Gymnasium id of the world's env (from the registry)
    ANGLE_STATES: tuple[int, ...] = ()  # state indices given in degrees (deg/s) in configs
    RENAMED_KEYS = {"disturbance": "latent_force"}  # old name -> new (read with a warning)

    def make_system(self):  # pragma: no cover - every world defines it
        raise NotImplementedError

    def state_from_config(self, values: Any) -> np.ndarray:
        """A state vector given in config units (angles in degrees) in SI units [rad]."""
        out = np.array(tuple(values), dtype=float)
        for i in self.ANGLE_STATES:
            out[i] = math.radians(out[i])
        return out

    @property
    def initial_state_rad(self) -> np.ndarray:
        """Start state in SI units."""
        return self.state_from_config(self.initial_state)

    @property
    def goal_state_rad(self) -> np.ndarray:
        """Goal state of the cost in SI units."""
        return self.state_from_config(self.goal_state)

    @property
    def measurement_std_rad(self) -> np.ndarray:
        """Std of the full-state measurement noise in SI units."""
        return self.state_from_config(self.measurement_noise_std)

    @property
    def process_noise_std_rad(self) -> np.ndarray:
        """Per-step process noise std on the physical states in SI units."""
        return self.state_from_config(self.process_noise_diffusion) * math.sqrt(self.dt)

    def make_model(self, latent_force: LatentForceConfig | None = None, system: Any = None):
        """The latent-force model of this world, or of another belief about its force.

        Args:
            latent_force: the GP to model; ``None`` for this config's (the hidden truth's).
            system: the system to stack it on; ``None`` builds :meth:`make_system`.
        """
        from lfm_env.model import LatentForceModel

        d = self.latent_force if latent_force is None else latent_force
        return LatentForceModel(
            self.make_system() if system is None else system,
            kernel=d.make_kernel(),
            dt=self.dt,
            process_noise_std=self.process_noise_std_rad,
            discretization=d.discretization,
        )

    def make_cost(self):
        """The reward's cost: ``Q``, ``R`` on the goal state (no separate terminal weight)."""
        from lfm_env.cost import QuadraticCost

        return QuadraticCost(Q=self.Q, R=self.R, x_goal=self.goal_state_rad)

    def replace(self, **changes: Any):
        """A copy with some fields changed (validated like any config)."""
        cls = type(self)
        return from_dict(cls, {**to_dict(self), **to_dict_fields(changes)}, prefix="env")


def check_latent_step(
    config: WorldConfig,
    latent_force: LatentForceConfig | None = None,
    where: str = "env.latent_force",
) -> WorldConfig:
    """Refuse a latent-force model whose Euler-Maruyama step diverges; returns ``config``.

    The Euler step ``z+ = (I + F dt) z`` of a Matern model has the single eigenvalue
    ``1 - lambda dt`` with ``lambda = sqrt(2 nu) / lengthscale``: it is stable only for
    ``lambda dt < 2``, i.e. ``lengthscale > sqrt(2 nu) dt / 2``; beyond, the simulated
    force grows without bound (1e19 m/s^2 within 30 s). The exact discretisation is
    stable for every lengthscale. The env and the agents call this before simulating;
    :func:`load_env_config` does not, so such a config can still be read.

    Args:
        config: the world; its ``dt`` and, by default, its latent force.
        latent_force: another model of the force at the same ``dt`` (the agents' belief).
        where: the config section of that model, for the message.

    Raises:
        ConfigError: naming ``<where>.lengthscale`` and its lower bound.
    """
    d = config.latent_force if latent_force is None else latent_force
    if d.discretization == "euler_maruyama" and d.kernel == "matern":
        bound = math.sqrt(2.0 * d.nu) * config.dt / 2.0
        if not d.lengthscale > bound:
            raise ConfigError(
                f"{where}.lengthscale={show_value(d.lengthscale)}: must be > sqrt(2 nu) dt / 2"
                f" = {bound:.6g} s with discretization 'euler_maruyama' (its step diverges"
                " otherwise); use discretization 'exact' or a smaller dt"
            )
    elif d.discretization == "euler_maruyama":
        F = np.asarray(d.make_kernel().F)
        radius = float(np.max(np.abs(np.linalg.eigvals(np.eye(len(F)) + F * config.dt))))
        if radius >= 1.0:
            raise ConfigError(
                f"{where}.discretization='euler_maruyama': its step diverges for the "
                f"{d.kernel} kernel at dt={config.dt} (spectral radius {radius:.4g} >= 1); "
                "use discretization 'exact'"
            )
    return config


def check_goal_and_start(
    c: FieldChecker, config: Any, excess: Callable[[Any, Any], Any], goal_rule: str, region: str
) -> None:
    """The goal and the start's position inside the x bounds ``[x_min, x_max]`` and inside the
    region where ``excess(x, y)`` is 0 (the track's band, the tunnel): what a goal-reaching
    world's config checks last (``c`` raises at the first failure).

    Args:
        c: the config's checker.
        config: the world config (its ``goal``, ``initial_state``, ``x_min``, ``x_max``).
        excess: how far [m] a position lies outside the region.
        goal_rule: what the goal must be, for the message (e.g. ``on the track (...)``).
        region: the region's name in the start's message (``a position inside the <region>
            and the x bounds``).
    """
    gx, gy = config.goal
    inside_x = f"inside x bounds [{config.x_min}, {config.x_max}]"
    c("goal", config.x_min <= gx <= config.x_max, inside_x)
    c("goal", float(excess(gx, gy)) == 0.0, goal_rule)
    x0, y0 = config.initial_state[:2]
    c(
        "initial_state",
        config.x_min <= x0 <= config.x_max and float(excess(x0, y0)) == 0.0,
        f"a position inside the {region} and the x bounds",
    )


__all__ = [
    "DISCRETIZATIONS",
    "KERNELS",
    "MATERN_NUS",
    "MAX_STEPS",
    "STARTS",
    "LatentForceConfig",
    "WorldConfig",
    "check_goal_and_start",
    "check_latent_step",
]
