"""The planar quadrotor in a gust: its system, env and scene."""
