"""The agents: the MPC agents over any model (:mod:`~controllers.agents.mpc`), the agent
that runs a trained policy (:mod:`~controllers.agents.rl`) and the face every agent has
(:mod:`~controllers.agents.protocol`)."""

from controllers.agents.mpc import (
    AGENT_LABELS,
    AGENTS,
    CertaintyEquivalentMPCAgent,
    MPCAgent,
    NominalMPCAgent,
    OracleMPCAgent,
    ParticleScenarioMPCAgent,
    RobustMPCAgent,
    ScenarioMPCAgent,
    check_agent_config,
    make_agent,
    needs_measurement_noise,
)
from controllers.agents.protocol import INFO_DEFAULTS, Agent, is_agent, last_info
from controllers.agents.rl import RLAgent

__all__ = [
    "AGENTS",
    "AGENT_LABELS",
    "INFO_DEFAULTS",
    "Agent",
    "CertaintyEquivalentMPCAgent",
    "MPCAgent",
    "NominalMPCAgent",
    "OracleMPCAgent",
    "ParticleScenarioMPCAgent",
    "RLAgent",
    "RobustMPCAgent",
    "ScenarioMPCAgent",
    "check_agent_config",
    "is_agent",
    "last_info",
    "make_agent",
    "needs_measurement_noise",
]
