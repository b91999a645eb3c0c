"""The paper's case study as a Gymnasium env: a bicycle on a sine track under a hidden force."""

from __future__ import annotations

from typing import Any

import numpy as np

from lfm_env.worlds.goal import GoalReachingEnv
from lfm_env.worlds.sine_track.config import SineTrackConfig


class SineTrackEnv(GoalReachingEnv):
    """A kinematic-bicycle car on a sinusoidal track, pushed by a hidden Matern latent force.

    ## Description
    The case study of "Model Predictive Control of Nonlinear Latent Force Models: A
    Scenario-Based Approach" (ICRA 2021), the first instance of
    :class:`~lfm_env.env.LatentForceEnv`. A car with kinematic-bicycle dynamics
    (:func:`lfm_env.worlds.sine_track.system.sine_track_system`) must drive along the track
    ``|p_y - 3 sin(0.2 p_x)| <= 1 m`` from ``[0, 0]`` to the goal ``[62.83, 0]``. An
    unmeasured latent force ``w(t)``, a Gaussian process with a Matern 5/2 covariance
    (``sigma^2 = 4``, lengthscale 4 s), acts on the acceleration: ``dv/dt = a + w``. The GP
    is simulated exactly through its state-space form.

    ## Action Space
    ``Box([-a_max, -delta_max], [a_max, delta_max], (2,), float32)``: acceleration
    ``a`` [m/s^2] and steering angle ``delta`` [rad]; by default ``|a| <= 5``,
    ``|delta| <= 25 deg``. Actions are read in float64; out-of-range actions are clipped
    to the system's bounds (the applied action is in ``info["applied_action"]``);
    non-finite actions, a wrong shape or a dtype that is not real numbers (text, objects,
    complex) raise ``ValueError``.

    ## Observation Space
    The physical state plus Gaussian measurement noise; the latent force is hidden.

    | Num | Observation | Unit | Noise std (default) |
    |-----|-------------|------|---------------------|
    | 0   | ``p_x`` position | m | 0.15 |
    | 1   | ``p_y`` position | m | 0.15 |
    | 2   | ``v`` speed | m/s | 0.15 |
    | 3   | ``psi`` heading | rad | 0.5 deg |

    ``Box(low, high, (4,), float64)``: ``p_x`` within ``[x_min, x_max]`` and ``p_y`` within
    ``+-(track_amplitude + track_half_width)``, each widened by twice ``safety_margin`` (the
    safety box, and the step that leaves it) and by 14 noise stds; the speed and the heading
    have no bound of their own (``+-3.4e38``, float32's largest). Defaults:
    ``[-23.1, -26.1, -3.4e38, -3.4e38]`` to ``[92.1, 26.1, 3.4e38, 3.4e38]``.

    ## Rewards
    Minus the paper's stage cost on the true state before the step and the applied
    action: ``-[(x - x_g)^T Q (x - x_g) + u^T R u]`` with ``Q = diag(2, 2, 1, 0)``,
    ``R = diag(0.5, 10)``, ``x_g = [62.83, 0, 4 m/s, 0]`` (``SineTrackConfig.make_cost``).

    ## Starting State
    True state ``[0, 0, 1 m/s, 45 deg]``; the latent state is drawn from the GP's
    stationary distribution (or zero, ``latent_force.start: zero``). The first
    observation is the noisy start state.

    ## Episode End
    * ``terminated`` with ``info["is_success"] = True`` when the segment travelled in
      the step passes within ``goal_radius`` (1 m) of the goal, so a fast car cannot
      jump over the goal disc.
    * ``terminated`` with failure when the car leaves the safety box: farther than
      ``safety_margin`` (10 m) outside the track band or the x bounds, or a state that
      is not finite.
    * ``truncated`` by ``gym.make``'s time limit after ``max_steps`` (150 steps, 30 s), or
      ``max_episode_steps`` when given; the env itself never truncates.
    Constraint violations (track, speed, x bounds) are recorded in ``info``, not enforced.

    ## Info
    ``true_state`` (4,), ``latent_force`` (``w`` [m/s^2] acting during the step just
    taken; at reset, the one that will act next), ``latent_state`` (z), ``track_excess``
    [m], ``x_excess`` [m], ``speed_excess`` [m/s] (each 0 inside the bounds; the system's
    constraint groups), ``constraint_excess`` (6,) in the order track_left, track_right,
    x_min, x_max [m], speed_min, speed_max [m/s], ``cost`` (the number of violated
    constraint groups, 0 to 3), ``is_success``, ``failure``,
    ``applied_action``, ``time`` [s].

    ## Arguments
    ``gym.make("lfm_env/SineTrack-v0", config=None, render_mode=None,
    screen_size=(600, 300), scaling=25.0, follow=True)``: ``config`` is a YAML path, a
    dict (whole file or its ``env`` section) or a
    :class:`~lfm_env.worlds.sine_track.config.SineTrackConfig`;
    ``scaling`` is pixels per metre; ``follow`` centres the view on the car (else the
    whole track is shown). ``reset(options=...)`` accepts ``initial_state``
    (``[m, m, m/s, rad]``) and ``latent_state`` overrides. The env exposes ``config``,
    ``system``, ``model`` (the truth), ``cost`` and ``track``.

    ## Version History
    * v0: initial version (rebuilt on ``LatentForceEnv`` with the same episodes, bit for
      bit, and the added ``info["constraint_excess"]``); then Gymnasium's conventions: a
      float32 action space, an unbounded observation space, ``info["violated_groups"]`` and the time
      limit as a ``TimeLimit`` wrapper (same episodes); then finite observation bounds
      that hold (same episodes).
    """

    CONFIG = SineTrackConfig
    SAFETY_GROUPS = ("track", "x")

    def __init__(
        self,
        config: Any = None,
        render_mode: str | None = None,
        screen_size: tuple[int, int] = (600, 300),
        scaling: float = 25.0,
        follow: bool = True,
    ) -> None:
        self.screen_size = (int(screen_size[0]), int(screen_size[1]))
        self.scaling = float(scaling)
        self.follow = bool(follow)
        super().__init__(config, render_mode)
        self.track = self.config.track

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``p_x`` and ``p_y`` in the safety box widened once more by ``safety_margin`` (the
        step that leaves it); the speed and the heading are not bounded by it."""
        c, m = self.config, self.config.safety_margin
        y = abs(c.track_amplitude) + c.track_half_width + 2.0 * m
        inf = np.inf
        return (
            np.array([c.x_min - 2.0 * m, -y, -inf, -inf]),
            np.array([c.x_max + 2.0 * m, y, inf, inf]),
        )

    def _make_scene(self):
        """highway-env's road with the sine lane and the car (:class:`TrackScene`)."""
        from lfm_env.worlds.sine_track.scene import TrackScene

        return TrackScene(
            self.track,
            self.config,
            screen_size=self.screen_size,
            scaling=self.scaling,
            follow=self.follow,
            offscreen=self.render_mode == "rgb_array",
            goal=self._goal,
            goal_radius=self.config.goal_radius,
        )


__all__ = ["SineTrackEnv"]
