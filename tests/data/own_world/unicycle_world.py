"""A world of one's own, defined outside the package: a unicycle on a lane, pushed by a
hidden force along its heading. The tests copy this file into a temporary folder and name
it in a config as ``env_id: <module>:Mine/Unicycle-v0`` (issue 35)."""

from dataclasses import dataclass, field

from lfm_env import register_world
from lfm_env.config import FieldChecker, LatentForceConfig, WorldConfig
from lfm_env.system import ControlSystem
from lfm_env.worlds.goal import GoalReachingEnv
from lfm_env.xp import xp


def rhs(x, u, w):
    px, py, v, theta = xp.unstack(x)
    a, omega = xp.unstack(u)
    (force,) = xp.unstack(w)
    return xp.stack([v * xp.cos(theta), v * xp.sin(theta), a + force, omega])


def lane(x):
    px, py, v, theta = xp.unstack(x)
    return xp.stack([py - 0.8, -py - 0.8, v - 2.0])


@dataclass(frozen=True)
class UnicycleConfig(WorldConfig):
    dt: float = 0.2
    initial_state: tuple[float, float, float, float] = (0.0, 0.0, 0.5, 0.0)
    goal: tuple[float, float] = (4.0, 0.0)
    goal_radius: float = 0.3
    goal_state: tuple[float, float, float, float] = (4.0, 0.0, 1.0, 0.0)
    Q: tuple[float, float, float, float] = (1.0, 2.0, 0.5, 0.1)
    R: tuple[float, float] = (0.1, 0.1)
    measurement_noise_std: tuple[float, float, float, float] = (0.02, 0.02, 0.05, 0.02)
    process_noise_diffusion: tuple[float, float, float, float] = (0.005, 0.005, 0.02, 0.01)
    max_steps: int = 40
    safety_margin: float = 2.0
    latent_force: LatentForceConfig = field(
        default_factory=lambda: LatentForceConfig(nu=1.5, variance=0.5, lengthscale=1.5)
    )

    def __post_init__(self):
        c = FieldChecker(self)
        c.positive("dt", "goal_radius", "max_steps", "safety_margin")

    def make_system(self):
        return ControlSystem(
            name="unicycle",
            state_names=("p_x [m]", "p_y [m]", "v [m/s]", "theta [rad]"),
            input_names=("a [m/s^2]", "omega [rad/s]"),
            rhs=rhs,
            input_lower=[-2.0, -1.5],
            input_upper=[2.0, 1.5],
            constraints=lane,
            constraint_names=("left [m]", "right [m]", "speed [m/s]"),
            constraint_groups={"lane": (0, 1), "speed": (2,)},
            force_names=("w [m/s^2]",),
        )


class UnicycleEnv(GoalReachingEnv):
    CONFIG = UnicycleConfig
    SAFETY_GROUPS = ("lane",)


register_world("Mine/Unicycle-v0", config=UnicycleConfig, env=UnicycleEnv)
