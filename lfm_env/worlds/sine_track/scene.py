"""Rendering of the SineTrack world with highway-env's road graphics and viewer.

:class:`TrackScene` is the scene of :class:`lfm_env.worlds.sine_track.env.SineTrackEnv` (see
:class:`lfm_env.env.Scene`) and of the experiment layer's videos. It builds a highway-env
``Road`` holding one ``SineLane`` with the track's geometry and a ``Vehicle`` placed at the
car's true pose, and draws them with highway-env's ``EnvViewer``. Nothing here feeds back
into the dynamics.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from lfm_env.worlds.sine_track.config import SineTrackConfig
from lfm_env.worlds.sine_track.system import SineTrack


@contextmanager
def offscreen_video_driver(offscreen: bool) -> Iterator[None]:
    """Initialise pygame's display with SDL's ``offscreen`` video driver while inside.

    Offscreen frames need no display; without a driver named, SDL probes Wayland and X11
    first and prints ``error: XDG_RUNTIME_DIR is invalid or not set`` on a headless machine.
    A driver the user chose (``SDL_VIDEODRIVER``) or an already initialised display is left
    alone, so a failing real window still reports its error. The variable is restored on
    exit (SDL reads it only when the display initialises).

    Args:
        offscreen: whether the frames are drawn without a window; ``False`` does nothing.
    """
    import pygame

    if not offscreen or "SDL_VIDEODRIVER" in os.environ or pygame.display.get_init():
        yield
        return
    os.environ["SDL_VIDEODRIVER"] = "offscreen"
    try:
        yield
    finally:
        os.environ.pop("SDL_VIDEODRIVER", None)


class TrackScene:
    """A highway-env road with the sine lane and the car, drawn by ``EnvViewer``.

    Args:
        track: the track geometry.
        config: the world (the car's drawn length is ``config.vehicle_length`` [m]).
        screen_size: ``(width, height)`` [px].
        scaling: pixels per metre when following the car.
        follow: centre the view on the car; else fit the whole track.
        offscreen: draw without a window (``rgb_array``).
        goal: goal position ``(2,)`` [m] drawn as a circle by :meth:`draw`; ``None`` for none.
        goal_radius: radius [m] of that circle.
    """

    def __init__(
        self,
        track: SineTrack,
        config: SineTrackConfig,
        screen_size: tuple[int, int] = (600, 300),
        scaling: float = 25.0,
        follow: bool = True,
        offscreen: bool = True,
        goal: np.ndarray | None = None,
        goal_radius: float = 1.0,
    ) -> None:
        from highway_env.road.road import Road, RoadNetwork
        from highway_env.vehicle.kinematics import Vehicle

        class _Car(Vehicle):
            LENGTH = config.vehicle_length  # [m] drawn at the model's true size
            WIDTH = 0.5 * config.vehicle_length

        network = RoadNetwork()
        network.add_lane("start", "goal", track.make_lane())
        self.road = Road(network=network, np_random=np.random.default_rng(0), record_history=True)
        self.vehicle = _Car(self.road, position=[0.0, 0.0], heading=0.0, speed=0.0)
        self.road.vehicles.append(self.vehicle)
        self.track = track
        self.follow = follow
        self.goal = None if goal is None else np.asarray(goal, dtype=float)
        self.goal_radius = float(goal_radius)
        width, height = screen_size
        if not follow:
            # Fit the whole track: the scale is set by the longer extent.
            span_x = track.x_max - track.x_min + 4.0
            span_y = 2.0 * (track.amplitude + track.half_width) + 4.0
            scaling = min(width / span_x, height / span_y)
        # EnvViewer reads its settings from an env-like object's ``config`` dict.
        self.config = {
            "offscreen_rendering": offscreen,
            "screen_width": width,
            "screen_height": height,
            "scaling": scaling,
            "centering_position": [0.5, 0.5],
            "render_agent": True,
            "real_time_rendering": False,
            "simulation_frequency": max(1, round(1.0 / config.dt)),
            "show_trajectories": False,
        }
        self.observation_type = None
        self.action_type = None
        self._viewer = None

    def update(self, state: np.ndarray) -> None:
        """Place the drawn car at the true pose ``[p_x, p_y, v, psi]``."""
        self.vehicle.position = np.array(state[:2], dtype=float)
        self.vehicle.heading = float(state[3])
        self.vehicle.speed = float(state[2])

    def _window_centre(self) -> np.ndarray:
        if self.follow:
            return self.vehicle.position
        return np.array([0.5 * (self.track.x_min + self.track.x_max), 0.0])

    def draw(self, goal: np.ndarray | None = None, goal_radius: float | None = None) -> np.ndarray:
        """Draw the scene; returns an ``(H, W, 3)`` uint8 RGB frame with +y up.

        Args:
            goal: goal position ``(2,)`` [m] drawn as a circle; the constructor's by default
                (none when neither is given).
            goal_radius: its radius [m]; the constructor's by default.
        """
        goal = self.goal if goal is None else np.asarray(goal, dtype=float)
        goal_radius = self.goal_radius if goal_radius is None else float(goal_radius)
        import pygame
        from highway_env.envs.common.graphics import EnvViewer
        from highway_env.road.graphics import LaneGraphics

        if self._viewer is None:
            with offscreen_video_driver(self.config["offscreen_rendering"]):
                self._viewer = EnvViewer(self, config=self.config)
            # highway-env disables drawing under SDL_VIDEODRIVER=dummy, but its offscreen
            # surfaces draw fine without a display; keep it on so frames are never blank.
            self._viewer.enabled = True
        viewer = self._viewer
        viewer.observer_vehicle = None
        viewer.window_position = self._window_centre  # type: ignore[method-assign]
        # highway-env draws lane lines as chords 4.33 m apart, too coarse for a 31 m
        # wavelength; draw them every 0.25 m for this call only.
        saved = LaneGraphics.STRIPE_SPACING, LaneGraphics.STRIPE_LENGTH
        LaneGraphics.STRIPE_SPACING = LaneGraphics.STRIPE_LENGTH = 0.25
        try:
            viewer.display()
        finally:
            LaneGraphics.STRIPE_SPACING, LaneGraphics.STRIPE_LENGTH = saved
        surface = viewer.sim_surface
        if goal is not None:
            pygame.draw.circle(
                surface,
                (40, 170, 60),
                surface.vec2pix(goal),
                max(2, surface.pix(goal_radius)),
                width=2,
            )
        if not viewer.offscreen:
            viewer.screen.blit(surface, (0, 0))
            pygame.display.flip()
        # pygame's screen y axis points down; flip so +y is up, as in the plots.
        return np.ascontiguousarray(viewer.get_image()[::-1])

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
