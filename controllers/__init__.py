"""Agents for the SineTrack latent-force world: particle filter, scenario MPC, baselines."""
