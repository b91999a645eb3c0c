"""Which agents an evaluation runs: registered names, factories and ``"module:attribute"``.

:func:`experiments.evaluation.run.evaluate`, :func:`~experiments.evaluation.run.run_episode` and
``lfm-evaluate --agents`` take agent specs of three kinds:

* a registered name (``"scenario"``: :data:`controllers.agents.registry.AGENT_REGISTRY`),
  built by :func:`controllers.agents.registry.make_agent` (the oracle also gets the env);
* a factory: a callable called once per episode as ``factory(config)`` with the resolved
  :class:`~controllers.config.ExperimentConfig` (its ``env`` section is the world, its
  ``agents`` section the settings) and returning an agent
  (:class:`controllers.agents.protocol.Agent`: ``reset(seed=None)`` and ``act(obs)``). An agent
  class whose constructor takes the config is such a factory. The env is not given:
  agents never read the hidden truth. An agent object (not a class) is also accepted and
  used as it is, reset before every episode;
* a text ``"module:attribute"`` (``"mypkg.agents:ProportionalAgent"``): the module is
  imported as Python finds it or, if Python finds it nowhere, from the working folder, last
  (:func:`lfm_env.working_folder.import_named`: a file there never shadows an installed or
  standard module), and its attribute is a factory or an agent, as above.

Each agent is named, for the table's ``agent`` column, its files (``<name>__seed<S>``)
and its seed (:func:`experiments.evaluation.run.agent_seed`), by the ``name`` attribute of
its factory (or agent), else by the text ``module.attribute`` of a ``"module:attribute"``
spec, else by the factory's qualified name (without ``<locals>``; a lambda is
``lambda``). Names are 1 to 100 letters, digits or
``._+-`` (valid file names everywhere), unique in a run, and a user agent may not take
a registered agent's name.

Process pools (``jobs > 1``) send the spec to spawned workers with :mod:`pickle`, so a
factory must be importable by reference (a top-level function or class of a module, or
``"module:attribute"``); a lambda or a local function is refused with an error naming
the agent. Dask sends it with ``cloudpickle``; workers of a remote cluster need the
factory's module installed.
"""

from __future__ import annotations

import dataclasses
import pickle
import re
import sys
from collections.abc import Iterable
from typing import Any

from controllers.agents.protocol import Agent, is_agent
from controllers.agents.registry import AGENT_REGISTRY
from controllers.config import ExperimentConfig
from lfm_env import working_folder

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._+-]{0,99}")
_SPEC_TEXT = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_][\w.]*")


class AgentSpecError(ValueError):
    """An agent spec that cannot be resolved or does not give an agent (names the spec)."""


@dataclasses.dataclass(frozen=True)
class OwnAgentSpec:
    """A user agent to run: its name and how to get it (a registered agent is its name).

    Attributes:
        name: the agent's name in the table and in file names.
        target: a ``"module:attribute"`` text, a factory (``factory(config) -> agent``)
            or an agent object.
        text: how the user gave it (for error messages).
    """

    name: str
    target: Any
    text: str

    def build(self, config: ExperimentConfig) -> Agent:
        """A new agent for one episode (the agent object itself for an object spec).

        Raises:
            AgentSpecError: naming the spec, if it cannot be imported, its factory
                raises, or it gives something without ``reset`` and ``act``.
        """
        obj = _import(self.text) if isinstance(self.target, str) else self.target
        if is_agent(obj):
            return obj
        try:
            agent = obj(config)
        except Exception as exc:
            raise AgentSpecError(
                f"agent {self.text!r}: calling it with the config raised {_one_line(exc)} "
                "(a factory is called as factory(config) with the ExperimentConfig)"
            ) from exc
        if not is_agent(agent):
            raise AgentSpecError(
                f"agent {self.text!r}: its factory returned a {type(agent).__name__}, "
                "which has no reset(seed=None) and act(obs) (controllers.agents.protocol.Agent)"
            )
        return agent


def _one_line(exc: BaseException) -> str:
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _import(text: str) -> Any:
    """The attribute ``"module:attribute"`` names (a dotted attribute path is followed)."""
    module_name, _, attr = text.partition(":")
    try:
        module = working_folder.import_named(module_name)
    except Exception as exc:  # ImportError, or an error while running the module
        raise AgentSpecError(
            f"agent {text!r}: cannot import module {module_name!r} ({_one_line(exc)})"
        ) from exc
    obj: Any = module
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise AgentSpecError(
                f"agent {text!r}: module {module_name!r} has no attribute {attr!r}"
            ) from None
    if not (callable(obj) or is_agent(obj)):
        raise AgentSpecError(
            f"agent {text!r}: {attr!r} is a {type(obj).__name__}, neither an agent factory "
            "(a callable taking the config) nor an agent (reset and act)"
        )
    return obj


def _default_name(obj: Any, text: str | None) -> str:
    """``obj.name``, else the ``module.attribute`` text, else the qualified name."""
    own = getattr(obj, "name", None)
    if isinstance(own, str):
        return own
    if text is not None:
        return text.replace(":", ".")
    source = obj if callable(obj) and not is_agent(obj) else type(obj)
    qualname = getattr(source, "__qualname__", type(source).__name__)
    qualname = qualname.replace(".<locals>", "").replace("<lambda>", "lambda")
    return re.sub(r"[^A-Za-z0-9._+-]", "_", qualname)


def resolve_agent(spec: Any) -> str | OwnAgentSpec:
    """One agent spec resolved: a registered name as itself, anything else an
    :class:`OwnAgentSpec` (the module of a ``"module:attribute"`` text is imported).

    Raises:
        AgentSpecError: (a ``ValueError``) one line naming the spec, for an unknown
            name, a module or attribute that cannot be imported, an object that is
            neither a factory nor an agent, or a bad name.
    """
    if isinstance(spec, str):
        text = spec.strip()
        if text in AGENT_REGISTRY:
            return text
        if ":" not in text:
            raise AgentSpecError(
                f"unknown agent(s) [{text!r}]; choose from {sorted(AGENT_REGISTRY)} or give "
                "'module:attribute' of an agent factory"
            )
        if not _SPEC_TEXT.fullmatch(text):
            raise AgentSpecError(
                f"agent {text!r}: expected 'module:attribute', e.g. 'mypkg.agents:MyAgent'"
            )
        obj, target = _import(text), text
        name = _default_name(obj, text)
    elif is_agent(spec) or callable(spec):
        obj, target, text = spec, spec, _describe(spec)
        name = _default_name(obj, None)
    else:
        raise AgentSpecError(
            f"unknown agent {str(spec)!r} (a {type(spec).__name__}); choose from "
            f"{sorted(AGENT_REGISTRY)}, or give a factory (config -> agent), an agent, or "
            "'module:attribute'"
        )
    if not _NAME.fullmatch(name):
        raise AgentSpecError(
            f"agent {text!r}: its name {name!r} must be 1 to 100 letters, digits or ._+- "
            "(it names the agent's files); set a valid `name` attribute"
        )
    if name in AGENT_REGISTRY:
        raise AgentSpecError(
            f"agent {text!r}: its name {name!r} is a registered agent's; give your agent "
            "another `name` attribute"
        )
    return OwnAgentSpec(name=name, target=target, text=text)


def _describe(obj: Any) -> str:
    """A short text naming a factory or agent object in error messages."""
    source = obj if callable(obj) and not is_agent(obj) else type(obj)
    module = getattr(source, "__module__", None) or "?"
    return f"{module}:{getattr(source, '__qualname__', type(source).__name__)}"


def agent_name(agent: str | OwnAgentSpec) -> str:
    """The name of a resolved agent (a registered name is its own name)."""
    return agent if isinstance(agent, str) else agent.name


def resolve_agents(agents: Any) -> list[str | OwnAgentSpec]:
    """Agent specs resolved (:func:`resolve_agent`), each name once.

    Args:
        agents: one spec, a comma list of names and ``module:attribute`` texts, or a
            sequence of specs of any kind.

    Raises:
        AgentSpecError: (a ``ValueError``) for an empty list, a bad spec, or two
            agents of one name.
    """
    known = sorted(AGENT_REGISTRY)
    if isinstance(agents, str):
        items: list[Any] = agents.split(",")
    elif is_agent(agents) or (callable(agents) and not isinstance(agents, Iterable)):
        items = [agents]
    elif isinstance(agents, Iterable):
        items = list(agents)
    else:
        raise AgentSpecError(f"agents {agents!r}: give a list of agents; choose from {known}")
    if not items or any(isinstance(a, str) and not a.strip() for a in items):
        raise AgentSpecError(f"agents {agents!r}: give at least one agent; choose from {known}")
    unknown = [a.strip() for a in items if isinstance(a, str) and ":" not in a]
    unknown = [a for a in unknown if a not in AGENT_REGISTRY]
    if unknown:
        raise AgentSpecError(
            f"unknown agent(s) {unknown}; choose from {known} or give 'module:attribute' "
            "of an agent factory"
        )
    resolved = [resolve_agent(a) for a in items]
    names = [agent_name(a) for a in resolved]
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise AgentSpecError(
            f"agents {names}: each agent may appear only once ({twice} twice); give "
            "distinct `name` attributes"
        )
    return resolved


def check_agent(agent: str | OwnAgentSpec, config: ExperimentConfig) -> None:
    """Build a user agent once, so a bad factory fails before any episode runs.

    Registered agents are checked by :func:`controllers.agents.registry.check_agent_config`
    (without building a solver).

    Raises:
        AgentSpecError: naming the spec (see :meth:`OwnAgentSpec.build`).
    """
    if isinstance(agent, OwnAgentSpec):
        agent.build(config)


def sendable_problem(agent: str | OwnAgentSpec) -> str | None:
    """Why ``agent`` should not be sent to a fresh worker process that does not import the
    main script (a serial run's worker), else ``None``: an agent object (used as it is, in
    this process), a factory that does not pickle, or one that comes from ``__main__``."""
    if not isinstance(agent, OwnAgentSpec) or isinstance(agent.target, str):
        return None
    if is_agent(agent.target):  # used as it is: its own state stays in this process
        return f"agent {agent.text!r} is an agent object (run in this process, as it is)"
    module = getattr(agent.target, "__module__", None) or type(agent.target).__module__
    if module in ("__main__", "__mp_main__"):
        return f"agent {agent.text!r} is defined in the main script"
    try:
        pickle.dumps(agent)
    except Exception as exc:
        return f"agent {agent.text!r} cannot be pickled ({_one_line(exc)})"
    return None


def check_picklable(agent: str | OwnAgentSpec, how: str) -> None:
    """Refuse a user agent that cannot travel to the workers of ``how``.

    Args:
        agent: a resolved agent.
        how: ``"pool"`` (spawned processes: :mod:`pickle`, by reference) or ``"dask"``
            (``cloudpickle``, which also sends lambdas and ``__main__`` code by value).

    Raises:
        AgentSpecError: naming the agent and why.
    """
    if not isinstance(agent, OwnAgentSpec) or isinstance(agent.target, str):
        return
    if how == "dask":
        import cloudpickle

        dumps = cloudpickle.dumps
    else:
        dumps = pickle.dumps
    try:
        dumps(agent)
    except Exception as exc:
        raise AgentSpecError(
            f"agent {agent.text!r}: cannot be sent to worker processes ({_one_line(exc)}); "
            "define the factory at the top level of an importable module and pass it or "
            "'module:attribute', or run with jobs=1"
        ) from exc
    module = getattr(agent.target, "__module__", None) or type(agent.target).__module__
    main = sys.modules.get("__main__")
    if how == "pool" and module == "__main__" and not getattr(main, "__file__", None):
        raise AgentSpecError(
            f"agent {agent.text!r}: defined in an interactive session, which spawned "
            "workers cannot import; put it in a module and pass 'module:attribute', or "
            "run with jobs=1"
        )


__all__ = [
    "OwnAgentSpec",
    "AgentSpecError",
    "agent_name",
    "check_agent",
    "check_picklable",
    "resolve_agent",
    "resolve_agents",
    "sendable_problem",
]
