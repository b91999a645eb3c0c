"""The systems of the case studies, one module each, written with :mod:`lfm_env.system`."""

from lfm_env.systems.quadrotor import Corridor, quadrotor_gust_system
from lfm_env.systems.sine_track import SineTrack, sine_track_system

__all__ = ["Corridor", "SineTrack", "quadrotor_gust_system", "sine_track_system"]
