"""Control: estimators, the scenario problem, its solvers (one registry) and the agents."""

from controllers.agents import AGENT_LABELS, AGENTS, make_agent
from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood
from controllers.problem import MPCSolution, ScenarioProblem

__all__ = [
    "AGENTS",
    "AGENT_LABELS",
    "MPCSolution",
    "ParticleFilter",
    "ScenarioProblem",
    "gaussian_log_likelihood",
    "make_agent",
]
