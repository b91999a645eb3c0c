"""Kept for old imports: the agent protocol lives in :mod:`controllers.agents.protocol`."""

from controllers.agents.protocol import (
    INFO_DEFAULTS,
    Agent,
    AgentInfo,
    SB3Policy,
    SB3Predict,
    is_agent,
    last_info,
)

__all__ = [
    "INFO_DEFAULTS",
    "Agent",
    "AgentInfo",
    "SB3Policy",
    "SB3Predict",
    "is_agent",
    "last_info",
]
