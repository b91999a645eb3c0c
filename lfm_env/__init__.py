"""The world of the case study: state-space GP, bicycle, track, and the SineTrack env."""
