"""The worlds of the case studies, one folder each (system, env, scene), and what they
share (:mod:`lfm_env.worlds.goal`).

The envs and systems are imported on first use (``from lfm_env.worlds import SineTrackEnv``),
so that a world's config can import the shared config layer without a cycle.
"""

from __future__ import annotations

from lfm_env.lazy import lazy_attributes

_EXPORTS = {
    "Corridor": "lfm_env.worlds.quadrotor.system",
    "QuadrotorGustEnv": "lfm_env.worlds.quadrotor.env",
    "SineTrack": "lfm_env.worlds.sine_track.system",
    "SineTrackEnv": "lfm_env.worlds.sine_track.env",
    "quadrotor_gust_system": "lfm_env.worlds.quadrotor.system",
    "sine_track_system": "lfm_env.worlds.sine_track.system",
}


__getattr__ = lazy_attributes(__name__, _EXPORTS)


__all__ = sorted(_EXPORTS)
