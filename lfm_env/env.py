"""The SineTrack Gymnasium environment: a bicycle on a sine track under a hidden GP force."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lfm_env.config import EnvConfig, check_latent_step, load_env_config
from lfm_env.model import LatentForceModel, psd_factor
from lfm_env.validation import real_vector

_LATENT_CHUNK = 64  # latent path is drawn in chunks so previews never change the episode


def segment_point_distance(p0: np.ndarray, p1: np.ndarray, q: np.ndarray) -> float:
    """Distance [m] from point ``q`` to the segment ``p0 -> p1`` (all shape ``(2,)``)."""
    d = p1 - p0
    dd = float(d @ d)
    t = 0.0 if dd == 0.0 else float(np.clip((q - p0) @ d / dd, 0.0, 1.0))
    return float(np.linalg.norm(p0 + t * d - q))


class SineTrackEnv(gym.Env):
    """A kinematic-bicycle car on a sinusoidal track, pushed by a hidden Matern latent force.

    ## Description
    The case study of "Model Predictive Control of Nonlinear Latent Force Models: A
    Scenario-Based Approach" (ICRA 2021). A car with kinematic-bicycle dynamics must drive
    along the track ``|p_y - 3 sin(0.2 p_x)| <= 1 m`` from ``[0, 0]`` to the goal
    ``[62.83, 0]``. An unmeasured disturbance ``w(t)``, a Gaussian process with a Matern
    5/2 covariance (``sigma^2 = 4``, lengthscale 4 s), acts on the acceleration:
    ``dv/dt = a + w``. The GP is simulated exactly through its state-space form.

    ## Action Space
    ``Box([-a_max, -delta_max], [a_max, delta_max], (2,), float64)``: acceleration
    ``a`` [m/s^2] and steering angle ``delta`` [rad]; by default ``|a| <= 5``,
    ``|delta| <= 25 deg``. Out-of-range actions are clipped to the box (the applied
    action is in ``info["applied_action"]``); non-finite actions, a wrong shape or a
    dtype that is not real numbers (text, objects, complex) raise ``ValueError``.

    ## Observation Space
    The physical state plus Gaussian measurement noise; the latent force is hidden.

    | Num | Observation | Unit | Noise std (default) |
    |-----|-------------|------|---------------------|
    | 0   | ``p_x`` position | m | 0.15 |
    | 1   | ``p_y`` position | m | 0.15 |
    | 2   | ``v`` speed | m/s | 0.15 |
    | 3   | ``psi`` heading | rad | 0.5 deg |

    ``Box(-max_float, max_float, (4,), float64)``.

    ## Rewards
    Minus the paper's stage cost on the true state before the step and the applied
    action: ``-[(x - x_g)^T Q (x - x_g) + u^T R u]`` with ``Q = diag(2, 2, 1, 0)``,
    ``R = diag(0.5, 10)``, ``x_g = [62.83, 0, 4 m/s, 0]``.

    ## Starting State
    True state ``[0, 0, 1 m/s, 45 deg]``; the latent state is drawn from the GP's
    stationary distribution (or zero, ``disturbance.start: zero``). The first
    observation is the noisy start state.

    ## Episode End
    * ``terminated`` with ``info["is_success"] = True`` when the segment travelled in
      the step passes within ``goal_radius`` (1 m) of the goal, so a fast car cannot
      jump over the goal disc.
    * ``terminated`` with failure when the car leaves the safety box: farther than
      ``safety_margin`` (10 m) outside the track band or the x bounds.
    * ``truncated`` after ``max_steps`` (150 steps, 30 s).
    Constraint violations (track, speed, x bounds) are recorded in ``info``, not enforced.

    ## Info
    ``true_state`` (4,), ``disturbance`` (``w`` [m/s^2] acting during the step just
    taken; at reset, the one that will act next), ``latent_state`` (z), ``track_excess``
    [m], ``speed_excess`` [m/s], ``x_excess`` [m] (each 0 inside the bounds),
    ``is_success``, ``failure``, ``applied_action``, ``time`` [s].

    ## Arguments
    ``gym.make("lfm_env/SineTrack-v0", config=None, render_mode=None,
    screen_size=(600, 300), scaling=25.0, follow=True)``: ``config`` is a YAML path, a
    dict (whole file or its ``env`` section) or an :class:`~lfm_env.config.EnvConfig`;
    ``scaling`` is pixels per metre; ``follow`` centres the view on the car (else the
    whole track is shown). ``reset(options=...)`` accepts ``initial_state``
    (``[m, m, m/s, rad]``) and ``latent_state`` overrides.

    ## Version History
    * v0: initial version.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 5}

    def __init__(
        self,
        config: Any = None,
        render_mode: str | None = None,
        screen_size: tuple[int, int] = (600, 300),
        scaling: float = 25.0,
        follow: bool = True,
    ) -> None:
        self.config: EnvConfig = check_latent_step(load_env_config(config))
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode={render_mode!r}: must be None or one of "
                f"{self.metadata['render_modes']}"
            )
        self.render_mode = render_mode
        self.screen_size = (int(screen_size[0]), int(screen_size[1]))
        self.scaling = float(scaling)
        self.follow = bool(follow)
        self.model = LatentForceModel(self.config)
        self.track = self.config.track
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / self.config.dt))}

        high = np.array([self.config.accel_max, self.config.steer_max])
        self.action_space = spaces.Box(-high, high, shape=(2,), dtype=np.float64)
        # Finite (but never binding) bounds: Gaussian noise has unbounded support.
        big = np.finfo(np.float64).max
        self.observation_space = spaces.Box(-big, big, shape=(4,), dtype=np.float64)

        self._Q = np.asarray(self.config.Q, dtype=float)
        self._R = np.asarray(self.config.R, dtype=float)
        self._x_goal = self.config.goal_state_rad
        self._goal = np.asarray(self.config.goal, dtype=float)
        self._meas_std = self.config.measurement_std_rad

        self._state = np.zeros(4)
        self._latent: np.ndarray = np.zeros((0, self.model.latent_dim))
        self._latent_rng: np.random.Generator | None = None
        self._noise_rng: np.random.Generator | None = None
        self._steps = 0
        self._viewer = None
        self._scene = None

    # ------------------------------------------------------------------ truth helpers

    @property
    def true_state(self) -> np.ndarray:
        """The hidden true physical state ``[m, m, m/s, rad]`` (a copy; for the oracle)."""
        return self._state.copy()

    @property
    def true_latent_state(self) -> np.ndarray:
        """The hidden latent state ``z`` acting in the next step (a copy)."""
        return self._latent_at(self._steps).copy()

    def preview_disturbance(self, n_steps: int) -> np.ndarray:
        """The true latent force of the next ``n_steps`` steps ``[m/s^2]`` (oracle only).

        Element ``k`` acts during step ``k`` from now. Reading it never changes the episode:
        the latent path is drawn from its own generator in fixed chunks.
        """
        if n_steps < 0:
            raise ValueError(f"n_steps={n_steps}: must be >= 0")
        return np.array([self._latent_at(self._steps + k) @ self.model.H for k in range(n_steps)])

    def _latent_at(self, k: int) -> np.ndarray:
        if self._latent_rng is None:
            raise gym.error.ResetNeeded("call reset() before using the environment")
        while k >= len(self._latent):
            m = self.model
            start = self._latent[-1]
            eta = self._latent_rng.standard_normal((_LATENT_CHUNK, m.latent_dim)) @ m.Q_factor.T
            chunk = np.empty((_LATENT_CHUNK, m.latent_dim))
            z = start
            for i in range(_LATENT_CHUNK):
                z = m.A @ z + eta[i]
                chunk[i] = z
            self._latent = np.concatenate([self._latent, chunk])
        return self._latent[k]

    # ------------------------------------------------------------------ Gymnasium API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"initial_state", "latent_state"}
        if unknown:
            raise ValueError(
                f"unknown reset option(s) {sorted(unknown)}; allowed: initial_state, latent_state"
            )
        # Independent streams: the hidden force does not depend on how much noise was drawn.
        latent_seed, noise_seed = self.np_random.integers(0, 2**63 - 1, size=2)
        self._latent_rng = np.random.default_rng(int(latent_seed))
        self._noise_rng = np.random.default_rng(int(noise_seed))

        m = self.model
        if "latent_state" in options:
            z0 = self._vector_option(options["latent_state"], m.latent_dim, "latent_state")
        elif self.config.disturbance.start == "stationary":
            z0 = psd_factor(m.stationary_latent_covariance()) @ self._latent_rng.standard_normal(
                m.latent_dim
            )
        else:
            z0 = np.zeros(m.latent_dim)
        self._latent = z0.reshape(1, -1).copy()
        if "initial_state" in options:
            self._state = self._vector_option(options["initial_state"], 4, "initial_state")
        else:
            self._state = self.config.initial_state_rad.copy()
        self._steps = 0
        self._sync_scene()
        if self.render_mode == "human":
            self.render()
        return self._observe(), self._info(success=False, failure=False, action=np.zeros(2))

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._noise_rng is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        u = self._check_action(action)
        x = self._state
        w = float(self._latent_at(self._steps) @ self.model.H)
        e = x - self._x_goal
        reward = -float(e @ (self._Q * e) + u @ (self._R * u))

        x_next = self.model.physical_step(x, u, w)
        x_next = x_next + self._noise_rng.standard_normal(4) * self.model.process_std
        self._state = x_next
        self._steps += 1

        success = segment_point_distance(x[:2], x_next[:2], self._goal) <= self.config.goal_radius
        failure = (not success) and self._outside_safety_box(x_next)
        terminated = bool(success or failure)
        truncated = bool(not terminated and self._steps >= self.config.max_steps)
        self._sync_scene()
        if self.render_mode == "human":
            self.render()
        info = self._info(success=success, failure=failure, action=u, w=w)
        return self._observe(), reward, terminated, truncated, info

    def _check_action(self, action: Any) -> np.ndarray:
        u = real_vector(action, 2, "action", "[a m/s^2, delta rad]")
        return np.clip(u, self.action_space.low, self.action_space.high)

    @staticmethod
    def _vector_option(value: Any, n: int, name: str) -> np.ndarray:
        v = np.asarray(value, dtype=float)
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            raise ValueError(f"reset option {name}={value!r}: must be {n} finite numbers")
        return v.copy()

    def _outside_safety_box(self, x: np.ndarray) -> bool:
        margin = self.config.safety_margin
        far_off_track = float(self.track.track_excess(x[0], x[1])) > margin
        far_off_x = float(self.track.x_excess(x[0])) > margin
        return bool(far_off_track or far_off_x or not np.all(np.isfinite(x)))

    def _observe(self) -> np.ndarray:
        noise = self._noise_rng.standard_normal(4) * self._meas_std
        return (self._state + noise).astype(np.float64)

    def _info(self, success: bool, failure: bool, action: np.ndarray, w: float | None = None):
        x = self._state
        z = self._latent_at(self._steps)
        if w is None:  # at reset: the force that acts in the first step
            w = float(z @ self.model.H)
        speed_excess = max(self.config.speed_min - x[2], x[2] - self.config.speed_max, 0.0)
        return {
            "true_state": x.copy(),
            "disturbance": float(w),
            "latent_state": z.copy(),
            "track_excess": float(self.track.track_excess(x[0], x[1])),
            "speed_excess": float(speed_excess),
            "x_excess": float(self.track.x_excess(x[0])),
            "is_success": bool(success),
            "failure": bool(failure),
            "applied_action": np.asarray(action, dtype=float).copy(),
            "time": self._steps * self.config.dt,
        }

    # ------------------------------------------------------------------ rendering

    def _sync_scene(self) -> None:
        if self._scene is not None:
            self._scene.update(self._state)

    def render(self) -> np.ndarray | None:
        """Draw the road and the car at its true pose with highway-env's viewer.

        ``rgb_array`` returns an ``(H, W, 3)`` uint8 frame and works without a display.
        """
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='rgb_array' or "
                "'human' to gym.make"
            )
            return None
        from lfm_env.rendering import TrackScene

        if self._scene is None:
            self._scene = TrackScene(
                self.track,
                self.config,
                screen_size=self.screen_size,
                scaling=self.scaling,
                follow=self.follow,
                offscreen=self.render_mode == "rgb_array",
            )
            self._scene.update(self._state)
        frame = self._scene.draw(goal=self._goal, goal_radius=self.config.goal_radius)
        return frame if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self._scene is not None:
            self._scene.close()
            self._scene = None
