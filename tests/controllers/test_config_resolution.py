"""A config is resolved once, at the edge: following it from ``make_agent`` (or ``evaluate``)
to the solver meets the resolver once, and every layer below takes the typed config.

The calls are counted with :func:`sys.setprofile` on the real functions (nothing replaced):
the resolver (:func:`controllers.config.load_config`), the reader of a whole config
(:func:`~controllers.config.read_document`), the world's reader of its section
(:func:`lfm_env.worlds.registry.load_env_config`) and the YAML reader
(:func:`lfm_env.config.loading.load_yaml`).
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from controllers.agents import make_agent
from controllers.config import load_config, read_document
from experiments.evaluation import evaluate
from lfm_env.config.loading import load_yaml
from lfm_env.worlds.registry import load_env_config

READERS = (load_config, read_document, load_env_config, load_yaml)


@contextmanager
def counting(functions: tuple[Callable, ...] = READERS) -> Iterator[Counter]:
    """Count the calls of ``functions`` (by name) in this thread while the block runs."""
    codes = {f.__code__: f.__name__ for f in functions}
    calls: Counter = Counter({name: 0 for name in codes.values()})

    def profile(frame, event, arg):
        if event == "call" and frame.f_code in codes:
            calls[codes[frame.f_code]] += 1

    previous = sys.getprofile()
    sys.setprofile(profile)
    try:
        yield calls
    finally:
        sys.setprofile(previous)


def test_make_agent_meets_the_resolver_once_from_a_preset_to_the_solver():
    with counting() as calls:
        agent = make_agent("scenario", "quick")
    assert agent.solver is not None and agent.problem.n_scenarios == 20  # built to the solver
    assert calls == {"load_config": 1, "read_document": 1, "load_env_config": 1, "load_yaml": 1}


def test_a_typed_config_is_not_read_again():
    config = load_config("quick")
    with counting() as calls:
        make_agent("robust", config)
    assert calls == {"load_config": 0, "read_document": 0, "load_env_config": 0, "load_yaml": 0}


def test_evaluate_reads_its_config_once_for_every_agent_and_episode():
    source = {"base": "quick", "env": {"max_steps": 3}}
    with counting() as calls:
        rows = evaluate(["nominal", "pf"], [0, 1], source, progress=False)
    assert len(rows) == 4 and not any(r["error"] for r in rows)
    # One read of the dict and of its base file; each episode's agent gets the typed config
    # (each episode's env takes the world's config object: its section is not read again).
    assert (calls["load_config"], calls["read_document"], calls["load_yaml"]) == (1, 1, 1)


def test_the_count_sees_every_call():
    """The counter itself: two resolutions are two."""
    with counting() as calls:
        load_config("quick")
        load_config("paper", ["agents.horizon=5"])
    assert calls == {"load_config": 2, "read_document": 2, "load_env_config": 2, "load_yaml": 2}
