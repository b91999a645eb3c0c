"""Control: estimators, the scenario problem, its solvers (one registry), the agents, and the
controller's export as C (:mod:`controllers.export`; :func:`write_problem` writes a scenario
problem for the exported ``example``)."""

from controllers.agents import AGENT_REGISTRY, make_agent
from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood
from controllers.export.project import write_problem
from controllers.problem import MPCSolution, ScenarioProblem

__all__ = [
    "AGENT_REGISTRY",
    "MPCSolution",
    "ParticleFilter",
    "ScenarioProblem",
    "gaussian_log_likelihood",
    "make_agent",
    "write_problem",
]
