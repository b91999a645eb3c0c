"""The agents: the MPC agents over any model (:mod:`~controllers.agents.mpc`), the agent
that runs a trained policy (:mod:`~controllers.agents.rl`), a peer library's robust MPC
(:mod:`~controllers.agents.dompc`, do-mpc, the ``peers`` extra), the face every agent has
(:mod:`~controllers.agents.protocol`) and every agent's record, the registered ones and a
user's own, with :func:`make_agent` (:mod:`~controllers.agents.registry`)."""

from controllers.agents.dompc import DoMpcAgent
from controllers.agents.mpc import (
    CertaintyEquivalentMPCAgent,
    MPCAgent,
    NominalMPCAgent,
    OracleMPCAgent,
    ParticleScenarioMPCAgent,
    RobustMPCAgent,
    ScenarioMPCAgent,
)
from controllers.agents.protocol import INFO_DEFAULTS, Agent, is_agent, last_info
from controllers.agents.registry import (
    AGENT_REGISTRY,
    AgentSpec,
    AgentSpecError,
    agent_spec,
    check_agent_config,
    make_agent,
    needs_measurement_noise,
    register_agent,
    resolve_agent,
    resolve_agents,
)
from controllers.agents.rl import RLAgent

__all__ = [
    "AGENT_REGISTRY",
    "INFO_DEFAULTS",
    "Agent",
    "AgentSpec",
    "AgentSpecError",
    "CertaintyEquivalentMPCAgent",
    "DoMpcAgent",
    "MPCAgent",
    "NominalMPCAgent",
    "OracleMPCAgent",
    "ParticleScenarioMPCAgent",
    "RLAgent",
    "RobustMPCAgent",
    "ScenarioMPCAgent",
    "agent_spec",
    "check_agent_config",
    "is_agent",
    "last_info",
    "make_agent",
    "needs_measurement_noise",
    "register_agent",
    "resolve_agent",
    "resolve_agents",
]
