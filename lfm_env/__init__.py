"""The world of the case study: state-space GP, bicycle, track, and the SineTrack env."""

from gymnasium.envs.registration import register

register(
    id="lfm_env/SineTrack-v0",
    entry_point="lfm_env.env:SineTrackEnv",
    max_episode_steps=None,  # the env truncates itself after config.max_steps
)

__all__ = ["register"]
