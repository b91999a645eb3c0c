"""A generic Gymnasium environment over any latent-force model.

:class:`LatentForceEnv` simulates a :class:`~lfm_env.system.ControlSystem` pushed by a
hidden Gaussian-process force (a :class:`~lfm_env.model.LatentForceModel`, the truth) and
rewards a :class:`~lfm_env.cost.QuadraticCost`. It holds the state, the randomness and
the Gymnasium protocol only: the physics, the constraints and the cost come from the
model and the cost objects. A case study subclasses it to say when an episode succeeds or
fails and how to draw the scene (:class:`lfm_env.worlds.sine_track.env.SineTrackEnv`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lfm_env.config.loading import show_value
from lfm_env.cost import QuadraticCost
from lfm_env.model import LatentForceModel, psd_factor
from lfm_env.system import split_unit
from lfm_env.validation import real_vector

LATENT_STARTS = ("stationary", "zero")
_LATENT_CHUNK = 64  # latent path is drawn in chunks so previews never change the episode

#: How far the measurement noise reaches [its standard deviations]: NumPy's normal draws
#: (the ziggurat of ``Generator.standard_normal``, float64) never exceed 13.71 in magnitude
#: (3.654 plus the tail's ``-log(2**-53) / 3.654``), so ``state +- 14 std`` holds every
#: observation of a state.
NOISE_REACH = 14.0
#: The largest finite float32: the bound of a state nothing else bounds.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def observation_bounds(
    state_low: Any, state_high: Any, measurement_std: Any
) -> tuple[np.ndarray, np.ndarray]:
    """The observation space's bounds: the state's range widened by the noise's reach.

    ``state_low - NOISE_REACH std`` and ``state_high + NOISE_REACH std``, rounded outward to
    float32-representable numbers (so a float32 copy of the space holds the same values);
    an unbounded side (``-inf``, ``inf``) or one beyond float32's range is ``-+FLOAT32_MAX``.

    Returns:
        ``(low, high)``, float64 arrays of float32-representable numbers.
    """
    std = np.asarray(measurement_std, dtype=float)
    low = np.asarray(state_low, dtype=float) - NOISE_REACH * std
    high = np.asarray(state_high, dtype=float) + NOISE_REACH * std
    low = np.clip(np.nan_to_num(low, nan=-FLOAT32_MAX, neginf=-FLOAT32_MAX), -FLOAT32_MAX, None)
    high = np.clip(np.nan_to_num(high, nan=FLOAT32_MAX, posinf=FLOAT32_MAX), None, FLOAT32_MAX)
    with np.errstate(over="ignore"):  # nextafter of +-FLOAT32_MAX, then not taken
        low32, high32 = low.astype(np.float32), high.astype(np.float32)
        low32 = np.where(low32 > low, np.nextafter(low32, np.float32(-np.inf)), low32)
        high32 = np.where(high32 < high, np.nextafter(high32, np.float32(np.inf)), high32)
    return low32.astype(np.float64), high32.astype(np.float64)


class Scene(Protocol):
    """What :meth:`LatentForceEnv.render` draws with (made by the env's scene factory)."""

    def update(self, state: np.ndarray) -> None:
        """Place the drawing at the true physical state ``(nx,)``."""

    def draw(self) -> np.ndarray:
        """Draw; returns an ``(H, W, 3)`` uint8 RGB frame."""

    def close(self) -> None:
        """Release windows and surfaces."""


def _labelled(labels: tuple[str, ...]) -> str:
    """``"[a m/s^2, delta rad]"`` from labels ``("a [m/s^2]", "delta [rad]")``."""
    parts = [" ".join(p for p in split_unit(label) if p) for label in labels]
    return "[" + ", ".join(parts) + "]"


def has_display() -> bool:
    """Whether a window can open: on Linux, ``DISPLAY``, ``WAYLAND_DISPLAY`` or a video driver
    the user chose (``SDL_VIDEODRIVER``) is set; elsewhere always."""
    if not sys.platform.startswith("linux"):
        return True
    return any(os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"))


class LatentForceEnv(gym.Env):
    """A controlled system pushed by a hidden latent force, observed with noise.

    ## Description
    The true physical state ``x`` (``nx`` states) moves by one Euler step of the system's
    right-hand side per sample, ``x+ = x + dt f(x, u, w) + e`` with process noise ``e ~
    N(0, diag(model.process_std^2))`` (:meth:`LatentForceModel.physical_step`). The latent
    force ``w = H z`` (``nw`` components) is a Gaussian process in time, simulated in
    state-space form, ``z+ = A z + eta``; it is hidden from the agent. The path of ``z`` is
    drawn in chunks from a generator of its own, so reading it ahead
    (:meth:`preview_latent_force`, for an oracle) never changes the episode.

    ## Action Space
    ``Box(system.input_lower, system.input_upper, (nu,), float32)`` in the inputs' units.
    Actions of any real dtype are accepted and used in float64 (a float64 action is not
    rounded to float32); out-of-range actions are clipped to the system's bounds (the
    applied action is in ``info["applied_action"]``); non-finite actions, a wrong shape or
    a dtype that is not real numbers (text, objects, complex) raise ``ValueError``.

    ## Observation Space
    The physical state plus Gaussian measurement noise of std ``measurement_std``, in the
    states' units (``system.state_names``); the latent force is hidden.
    ``Box(low, high, (nx,), float64)`` with finite bounds that hold
    (:func:`observation_bounds`): the range ``state_bounds`` keeps each state in, widened
    by the noise's reach (:data:`NOISE_REACH` stds, beyond anything NumPy's normal
    generator draws), as float32-representable numbers; a state without a range gets
    ``+-FLOAT32_MAX``. An observation is clipped into the box, which changes it only when
    the state itself left its range (by more than the range's own slack: the step that
    ends an episode in a failure). The observations stay float64: rounding them to float32
    changes the MPC agents' closed-loop episodes (docs/environment.md, "Gymnasium
    conventions"); RL code casts them to float32 itself.

    ## Rewards
    Minus the stage cost on the true state before the step and the applied action:
    ``-[(x - x_g)^T Q (x - x_g) + u^T R u]`` (:meth:`QuadraticCost.stage_cost`).

    ## Starting State
    The true state ``initial_state``; the latent state drawn from the GP's stationary
    distribution (``latent_start="stationary"``) or zero (``"zero"``). The first
    observation is the noisy start state.

    ## Episode End
    * ``terminated`` with ``info["is_success"]`` when :meth:`_is_success` holds for the
      step just taken (never, unless a subclass says so);
    * ``terminated`` with ``info["failure"]`` when :meth:`_is_failure` holds for the new
      state (by default: a state that is not finite);
    * after ``terminated``, :meth:`step` raises ``gymnasium.error.ResetNeeded`` until
      :meth:`reset` (Gymnasium's rule: when an episode ends, ``reset()`` is necessary; the
      state would otherwise go on accumulating reward past its end);
    * the env never truncates: the time limit is Gymnasium's ``TimeLimit`` wrapper, applied
      by ``gym.make`` with ``max_steps`` steps unless ``max_episode_steps`` is given
      (:class:`lfm_env.wrappers.ConfigTimeLimit`); a directly constructed env runs until
      it terminates, so wrap it in ``TimeLimit(env, env.max_steps)``.
    State constraints are recorded in ``info``, not enforced.

    ## Info
    ``true_state`` (nx,), ``latent_force`` (the force ``w`` acting during the step just
    taken, at reset the one that acts next; a float when ``nw == 1``, else ``(nw,)``),
    ``latent_state`` (z), ``<group>_excess`` for each of ``system.constraint_groups`` (the
    largest excess ``max(g, 0)`` in the group, in its unit), ``constraint_excess`` (ng,) in
    ``system.constraint_names`` order, ``violated_groups`` (the number of constraint groups
    violated by the new state, dimensionless, 0 when every constraint holds: the safe-RL
    constraint cost), ``is_success``, ``failure``, ``applied_action``, ``time`` [s].

    ## Arguments
    ``LatentForceEnv(model, cost, initial_state, measurement_std, max_steps=200,
    latent_start="stationary", render_mode=None, scene_factory=None, state_bounds=None)``:
    ``model`` is the truth (its ``system`` the physics), ``cost`` the reward's cost,
    ``initial_state`` ``(nx,)`` and ``measurement_std`` ``(nx,)`` in the states' units;
    ``max_steps`` is the episode length the registered time limit uses (the env itself does
    not truncate). ``scene_factory(env)`` returns a :class:`Scene` for rendering (or a
    subclass overrides :meth:`_make_scene`). ``state_bounds`` is ``(low, high)``, each
    ``(nx,)`` in the states' units: the range the episode keeps each state in (``-inf`` /
    ``inf`` for none; ``None``: no state has one), which sets the observation space.
    ``render_mode="human"`` needs a display: on Linux without ``DISPLAY`` or
    ``WAYLAND_DISPLAY`` (nor ``SDL_VIDEODRIVER``) it is refused and not offered in
    ``metadata["render_modes"]``.
    ``reset(options=...)`` accepts a dict with ``initial_state`` ``(nx,)`` and
    ``latent_state`` ``(p,)`` overrides (anything but a dict or ``None`` is a ``TypeError``
    naming ``options``).

    ## Subclassing
    Override :meth:`_is_success` (the task's goal), :meth:`_is_failure` (e.g. a safety box)
    and :meth:`_make_scene` (the drawing).
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 5}
    #: The case study's settings (a world's config, e.g. a
    #: :class:`~lfm_env.worlds.sine_track.config.SineTrackConfig`); ``None`` here.
    config: Any = None

    def __init__(
        self,
        model: LatentForceModel,
        cost: QuadraticCost,
        initial_state: Any,
        measurement_std: Any,
        max_steps: int = 200,
        latent_start: str = "stationary",
        render_mode: str | None = None,
        scene_factory: Callable[[LatentForceEnv], Scene] | None = None,
        state_bounds: tuple[Any, Any] | None = None,
    ) -> None:
        if not isinstance(model, LatentForceModel):
            raise ValueError(f"model must be a LatentForceModel, got {type(model).__name__}")
        if not isinstance(cost, QuadraticCost):
            raise ValueError(f"cost must be a QuadraticCost, got {type(cost).__name__}")
        system = model.system
        cost.check_system(system)
        states = _labelled(system.state_names)
        self.model = model
        self.system = system
        self.cost = cost
        self.initial_state = real_vector(initial_state, system.nx, "initial_state", states)
        std = real_vector(measurement_std, system.nx, "measurement_std", states)
        if np.any(std < 0.0):
            raise ValueError(f"measurement_std={std.tolist()}: must be >= 0")
        self.measurement_std = std
        if (
            not isinstance(max_steps, (int, np.integer))
            or isinstance(max_steps, bool)
            or max_steps < 1
        ):
            raise ValueError(f"max_steps={max_steps!r}: must be an integer >= 1")
        self.max_steps = int(max_steps)
        if latent_start not in LATENT_STARTS:
            raise ValueError(f"latent_start={latent_start!r}: must be one of {LATENT_STARTS}")
        self.latent_start = latent_start
        draws = (
            scene_factory is not None or type(self)._make_scene is not LatentForceEnv._make_scene
        )
        if render_mode is not None and not draws:
            raise ValueError(
                f"render_mode={render_mode!r}: this env has no scene to draw; pass "
                "scene_factory or override _make_scene"
            )
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode={render_mode!r}: must be None or one of "
                f"{self.metadata['render_modes']}"
            )
        if render_mode == "human" and not has_display():
            raise ValueError(
                "render_mode='human': no display (neither DISPLAY nor WAYLAND_DISPLAY is set);"
                " use render_mode='rgb_array' for frames"
            )
        self.render_mode = render_mode
        self._scene_factory = scene_factory
        modes = [m for m in self.metadata["render_modes"] if m != "human" or has_display()]
        self.metadata = {
            **self.metadata,
            "render_modes": modes if draws else [],
            "render_fps": max(1, round(1.0 / model.dt)),
        }

        # float32 as RL libraries expect; actions are read and clipped in float64 against
        # the system's exact bounds, so float64 actions are never rounded.
        self.action_space = spaces.Box(
            system.input_lower.astype(np.float32),
            system.input_upper.astype(np.float32),
            shape=(system.nu,),
            dtype=np.float32,
        )
        # Finite bounds that hold: the states' range plus the noise's reach (float32 numbers).
        if state_bounds is None:
            state_bounds = (np.full(system.nx, -np.inf), np.full(system.nx, np.inf))
        lo = real_vector(np.nan_to_num(state_bounds[0], neginf=-FLOAT32_MAX), system.nx,
                         "state_bounds[0]", states)  # fmt: skip
        hi = real_vector(np.nan_to_num(state_bounds[1], posinf=FLOAT32_MAX), system.nx,
                         "state_bounds[1]", states)  # fmt: skip
        if np.any(lo > hi):
            raise ValueError(f"state_bounds: low {lo.tolist()} must be <= high {hi.tolist()}")
        low, high = observation_bounds(lo, hi, std)
        self.observation_space = spaces.Box(low, high, shape=(system.nx,), dtype=np.float64)

        self._action_layout = _labelled(system.input_names)
        self._state = np.zeros(system.nx)
        self._latent: np.ndarray = np.zeros((0, model.latent_dim))
        self._latent_rng: np.random.Generator | None = None
        self._noise_rng: np.random.Generator | None = None
        self._steps = 0
        self._terminated = False  # the episode ended (step refuses until reset)
        self._scene: Scene | None = None

    # ------------------------------------------------------------------ hidden truth

    @property
    def true_state(self) -> np.ndarray:
        """The hidden true physical state ``(nx,)`` (a copy; for the oracle and metrics)."""
        return self._state.copy()

    @property
    def true_latent_state(self) -> np.ndarray:
        """The hidden latent state ``z`` ``(p,)`` acting in the next step (a copy)."""
        return self._latent_at(self._steps).copy()

    def preview_latent_force(self, n_steps: int) -> np.ndarray:
        """The true latent force of the next ``n_steps`` steps ``(n_steps, nw)`` (oracle only).

        Row ``k`` acts during step ``k`` from now, in the force's units. Reading it never
        changes the episode: the latent path is drawn from its own generator in fixed chunks.
        """
        if n_steps < 0:
            raise ValueError(f"n_steps={n_steps}: must be >= 0")
        out = np.empty((n_steps, self.model.nw))
        for k in range(n_steps):
            out[k] = self.model.latent_force(self._latent_at(self._steps + k))
        return out

    def _latent_at(self, k: int) -> np.ndarray:
        if self._latent_rng is None:
            raise gym.error.ResetNeeded("call reset() before using the environment")
        m = self.model
        while k >= len(self._latent):
            eta = self._latent_rng.standard_normal((_LATENT_CHUNK, m.latent_dim)) @ m.Q_factor.T
            chunk = np.empty((_LATENT_CHUNK, m.latent_dim))
            z = self._latent[-1]
            for i in range(_LATENT_CHUNK):
                z = m.A @ z + eta[i]
                chunk[i] = z
            self._latent = np.concatenate([self._latent, chunk])
        return self._latent[k]

    # ------------------------------------------------------------------ task hooks

    def _is_success(self, state: np.ndarray, next_state: np.ndarray) -> bool:
        """Whether the step from ``state`` to ``next_state`` reached the task's goal."""
        return False

    def _is_failure(self, state: np.ndarray) -> bool:
        """Whether ``state`` ends the episode as a failure (by default: not finite)."""
        return not bool(np.all(np.isfinite(state)))

    def _make_scene(self) -> Scene:
        """The drawing used by :meth:`render` (made on the first call)."""
        if self._scene_factory is None:
            raise NotImplementedError(f"{type(self).__name__} has no scene to draw")
        return self._scene_factory(self)

    # ------------------------------------------------------------------ Gymnasium API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if options is not None and not isinstance(options, Mapping):
            raise TypeError(
                f"reset(options={show_value(options)}): options must be a dict (keys "
                "initial_state, latent_state) or None"
            )
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
        p = m.latent_dim
        if "latent_state" in options:
            z0 = real_vector(options["latent_state"], p, "reset option latent_state")
        elif self.latent_start == "stationary":
            z0 = psd_factor(m.stationary_latent_covariance()) @ self._latent_rng.standard_normal(p)
        else:
            z0 = np.zeros(p)
        self._latent = z0.reshape(1, -1).copy()
        if "initial_state" in options:
            self._state = real_vector(
                options["initial_state"],
                self.system.nx,
                "reset option initial_state",
                _labelled(self.system.state_names),
            )
        else:
            self._state = self.initial_state.copy()
        self._steps = 0
        self._terminated = False
        self._sync_scene()
        if self.render_mode == "human":
            self.render()
        info = self._info(success=False, failure=False, action=np.zeros(self.system.nu))
        return self._observe(), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._noise_rng is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        if self._terminated:
            raise gym.error.ResetNeeded(
                "step() after the episode terminated (info['is_success'] or "
                "info['failure']): call reset() first (Gymnasium: after terminated=True, "
                "reset() is necessary)"
            )
        u = self._check_action(action)
        x = self._state
        w = self.model.latent_force(self._latent_at(self._steps))
        reward = -float(self.cost.stage_cost(x, u))

        x_next = self.model.physical_step(x, u, w)
        x_next = x_next + self._noise_rng.standard_normal(self.system.nx) * self.model.process_std
        self._state = x_next
        self._steps += 1

        success = bool(self._is_success(x, x_next))
        failure = (not success) and bool(self._is_failure(x_next))
        terminated = bool(success or failure)
        self._terminated = terminated
        truncated = False  # the time limit is the TimeLimit wrapper's (gym.make)
        self._sync_scene()
        if self.render_mode == "human":
            self.render()
        info = self._info(success=success, failure=failure, action=u, w=w)
        return self._observe(), reward, terminated, truncated, info

    def _check_action(self, action: Any) -> np.ndarray:
        u = real_vector(action, self.system.nu, "action", self._action_layout)
        return np.clip(u, self.system.input_lower, self.system.input_upper)

    def _observe(self) -> np.ndarray:
        noise = self._noise_rng.standard_normal(self.system.nx) * self.measurement_std
        y = (self._state + noise).astype(np.float64)
        # Inside the box unless the state left its range (the step that ends an episode).
        return np.clip(y, self.observation_space.low, self.observation_space.high)

    def _info(
        self, success: bool, failure: bool, action: np.ndarray, w: np.ndarray | None = None
    ) -> dict[str, Any]:
        x = self._state
        z = self._latent_at(self._steps)
        if w is None:  # at reset: the force that acts in the first step
            w = self.model.latent_force(z)
        excess = self.system.constraint_excess(x)
        info: dict[str, Any] = {
            "true_state": x.copy(),
            "latent_force": float(w[0]) if self.model.nw == 1 else np.array(w, dtype=float),
            "latent_state": z.copy(),
        }
        violated = 0
        for group, idx in self.system.constraint_groups.items():
            info[f"{group}_excess"] = float(np.max(excess[list(idx)]))
            violated += info[f"{group}_excess"] > 0.0
        info.update(
            constraint_excess=excess,
            violated_groups=float(violated),
            is_success=bool(success),
            failure=bool(failure),
            applied_action=np.asarray(action, dtype=float).copy(),
            time=self._steps * self.model.dt,
        )
        return info

    # ------------------------------------------------------------------ rendering

    def make_scene(self) -> Scene:
        """A new drawing of this env's world, independent of the env's own.

        Replays use it to draw saved states: ``scene.update(x); frame = scene.draw()``.
        The size and options are the env's (e.g. ``screen_size``); close it when done.
        """
        return self._make_scene()

    def _sync_scene(self) -> None:
        if self._scene is not None:
            self._scene.update(self._state)

    def render(self) -> np.ndarray | None:
        """Draw the true state with the env's scene.

        ``rgb_array`` returns an ``(H, W, 3)`` uint8 frame; ``human`` shows it in a window.
        """
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='rgb_array' or "
                "'human' to gym.make"
            )
            return None
        if self._scene is None:
            self._scene = self._make_scene()
            self._scene.update(self._state)
        frame = self._scene.draw()
        return frame if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self._scene is not None:
            self._scene.close()
            self._scene = None


__all__ = [
    "FLOAT32_MAX",
    "LATENT_STARTS",
    "NOISE_REACH",
    "LatentForceEnv",
    "Scene",
    "has_display",
    "observation_bounds",
]
