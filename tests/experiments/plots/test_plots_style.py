"""The shared figure toolkit (``experiments.plots.style``)."""

from __future__ import annotations


def test_registered_agents_keep_their_colours_and_others_get_a_stable_fallback():
    from controllers.agents.registry import AGENT_REGISTRY
    from experiments.plots.style import agent_colour

    assert {n: agent_colour(n) for n in AGENT_REGISTRY} == {
        n: s.colour for n, s in AGENT_REGISTRY.items()
    }
    assert agent_colour("rl") == "tab:olive"  # what its name got before it had a record
    assert agent_colour("my_agent") == agent_colour("my_agent") != ""
