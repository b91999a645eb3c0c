"""Solvers of the scenario MPC problem."""
