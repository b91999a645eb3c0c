"""The case studies' Gymnasium environments, each a :class:`lfm_env.env.LatentForceEnv`."""

from lfm_env.envs.quadrotor_gust import QuadrotorGustEnv
from lfm_env.envs.sine_track import SineTrackEnv

__all__ = ["QuadrotorGustEnv", "SineTrackEnv"]
