"""The agents, one :class:`AgentSpec` each: the registered ones, a user's own, and
:func:`make_agent`.

Everything the project knows about an agent lives in its record: how to build it, its labels
in help texts, tables and figures, its colour and its place in tables. The command lines, the
evaluation, the report and the plots read these records (as Gymnasium's ``gym.make`` reads an
``EnvSpec``); nothing else lists the agents.

A user's agent is any object with the agents' face (:class:`controllers.agents.protocol.Agent`)
and joins the same records, in three ways (:func:`resolve_agent`):

* a factory: a callable called once per episode as ``factory(config)`` with the resolved
  :class:`~controllers.config.ExperimentConfig` (its ``env`` section is the world, its
  ``agents`` section the settings) and returning an agent; an agent class whose constructor
  takes the config is such a factory. The env is not given: a user's agent never reads the
  hidden truth. An agent object (not a class) is used as it is, reset before every episode;
* a text ``"module:attribute"`` (``"mypkg.agents:ProportionalAgent"``): the module is
  imported as Python finds it or, if Python finds it nowhere, from the working folder, last
  (:func:`lfm_env.working_folder.import_named`: a file there never shadows an installed or
  standard module), and its attribute is a factory or an agent, as above;
* registered by name with :func:`register_agent` (from the user's own module, as a world is
  registered), with its labels and colour: then its name works as a registered agent's.

An agent is named, for the table's ``agent`` column, its files (``<name>__seed<S>``) and its
seed, by its record: a registered name, else the ``name`` attribute of its factory (or agent),
else the text ``module.attribute`` of a ``"module:attribute"`` spec, else the factory's
qualified name (without ``<locals>``; a lambda is ``lambda``). Names are 1 to 100 letters,
digits or ``._+-`` (valid file names everywhere), unique in a run, and a user's agent may not
take a registered agent's name.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from controllers.agents.dompc import MISSING_DO_MPC, DoMpcAgent, do_mpc_installed
from controllers.agents.mpc import (
    CertaintyEquivalentMPCAgent,
    NominalMPCAgent,
    OracleMPCAgent,
    ParticleScenarioMPCAgent,
    RobustMPCAgent,
    ScenarioMPCAgent,
)
from controllers.agents.protocol import Agent, is_agent
from controllers.agents.rl import RLAgent, check_rl_policy
from controllers.config import ExperimentConfig, load_config
from lfm_env.config import ConfigError
from lfm_env.validation import one_line
from lfm_env.working_folder import import_named

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._+-]{0,99}")
_SPEC_TEXT = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_][\w.]*")
#: The place in tables of an agent that gives none (after the project's agents).
USER_ORDER = 100


class AgentSpecError(ValueError):
    """An agent spec that cannot be resolved or does not give an agent (names the spec)."""


@dataclass(frozen=True)
class AgentSpec:
    """One agent: how to build it and how the experiment layer shows it.

    A registered agent of the project gives ``agent_class``, built as ``agent_class(model,
    cost, settings, measurement_std)`` from the config; a user's agent gives ``factory``.
    """

    name: str  # as in ``--agents`` and the results' ``agent`` column
    agent_class: type | None = None  # the project's agents: built from the config's parts
    factory: Any = None  # a user's: factory(config) -> agent, an agent, or "module:attribute"
    label: str = ""  # one line for help texts and the report's list of agents
    short_label: str = ""  # table headers and axis labels
    colour: str | None = None  # matplotlib colour in every figure (None: a fallback one)
    order: int = USER_ORDER  # place in tables and figures; equal orders sorted by name
    reads_truth: bool = False  # True: also gets the env (env=...), to read the hidden truth
    check: Callable[[ExperimentConfig], None] | None = None  # raises ConfigError; no solver
    # The agents-section settings it reads ("latent_force": it models the force with the
    # agents' belief); a report describes only the settings of the agents it holds.
    uses: tuple[str, ...] = ()
    text: str = ""  # how a user gave it (for messages); the name for the project's agents

    def __post_init__(self) -> None:
        object.__setattr__(self, "label", self.label or self.name)
        object.__setattr__(self, "short_label", self.short_label or self.label)
        object.__setattr__(self, "text", self.text or self.name)

    @property
    def needs_measurement_noise(self) -> bool:
        """Whether its estimator weighs measurements by their noise (every std must be > 0)."""
        return bool(getattr(self.agent_class, "needs_measurement_noise", False))

    def build(self, config: ExperimentConfig, env: Any = None) -> Agent:
        """A new agent for one episode (the agent object itself for an object spec).

        Args:
            config: the resolved config.
            env: the environment, given to an agent that reads the truth (the oracle) only.

        Raises:
            AgentSpecError: naming a user's spec, if it cannot be imported, its factory
                raises, or it gives something without ``reset`` and ``act``.
        """
        if self.agent_class is not None:
            args = (config.make_model(), config.make_cost(), config.agents, config.measurement_std)
            return self.agent_class(*args, env=env) if self.reads_truth else self.agent_class(*args)
        obj = _import(self.text) if isinstance(self.factory, str) else self.factory
        if is_agent(obj):
            return obj
        try:
            agent = obj(config)
        except Exception as exc:
            raise AgentSpecError(
                f"agent {self.text!r}: calling it with the config raised {one_line(exc)} "
                "(a factory is called as factory(config) with the ExperimentConfig)"
            ) from exc
        if not is_agent(agent):
            raise AgentSpecError(
                f"agent {self.text!r}: its factory returned a {type(agent).__name__}, "
                "which has no reset(seed=None) and act(obs) (controllers.agents.protocol.Agent)"
            )
        return agent

    def check_config(self, config: ExperimentConfig) -> None:
        """Raise if the agent cannot run on ``config``, before any episode.

        Cheap for the project's agents (no solver is built): every agent with an estimator
        (:attr:`needs_measurement_noise`) weighs measurements by their noise, which must not
        be zero, and ``check`` runs (``dompc`` needs do-mpc, ``rl`` its policy file). A user's
        agent is built once, so a bad factory fails early.

        Raises:
            ConfigError: naming the field; AgentSpecError: naming a user's spec.
        """
        if self.agent_class is None:
            self.build(config)
            return
        std = tuple(config.env.measurement_noise_std)
        if self.needs_measurement_noise and not all(s > 0.0 for s in std):
            states = config.make_system().state_names
            zero = [n for n, s in zip(states, std, strict=False) if not s > 0.0]
            raise ConfigError(
                f"env.measurement_noise_std={list(std)}: must be all > 0 (each in (0, inf)) "
                f"for the {self.name!r} agent (its estimator weighs each measurement by this "
                f"noise); zero for {zero}"
            )
        if self.check is not None:
            self.check(config)


def _check_rl_policy(config: ExperimentConfig) -> None:
    """The policy file must be there before the first episode."""
    check_rl_policy(config.agents.rl_policy)


def _check_do_mpc(config: ExperimentConfig) -> None:
    """do-mpc (the ``peers`` extra) must be installed; checked without importing it."""
    if not do_mpc_installed():
        raise ConfigError(MISSING_DO_MPC)


# Colours follow the paper's captions where it names them (true path green dashed,
# estimate red); each agent keeps its colour so plots can be compared.
_FILTER_USES = ("horizon", "solver", "prediction", "estimator", "n_particles")
_SPECS = (
    AgentSpec(
        "nominal",
        NominalMPCAgent,
        label="nominal MPC (w = 0)",
        short_label="nominal MPC",
        colour="tab:gray",
        order=0,
        uses=("horizon", "solver", "prediction"),
    ),
    AgentSpec(
        "pf",
        CertaintyEquivalentMPCAgent,
        label="PF + certainty-equivalent MPC",
        short_label="PF + CE MPC",
        colour="tab:orange",
        order=1,
        uses=(*_FILTER_USES, "latent_force"),
    ),
    AgentSpec(
        "scenario",
        ScenarioMPCAgent,
        label="PF + scenario MPC (paper)",
        short_label="scenario MPC (paper)",
        colour="tab:blue",
        order=2,
        uses=(*_FILTER_USES, "n_scenarios", "latent_force"),
    ),
    AgentSpec(
        "scenario_particles",
        ParticleScenarioMPCAgent,
        label="PF + scenario MPC, scenarios start from particles (paper's remark)",
        short_label="scenario MPC, particle starts",
        colour="tab:green",
        order=3,
        uses=(*_FILTER_USES, "n_scenarios", "latent_force"),
    ),
    AgentSpec(
        "robust",
        RobustMPCAgent,
        label="robust: estimator whose 2-sigma band covers + MPC with constraint back-off",
        short_label="robust MPC (back-off)",
        colour="tab:red",
        order=4,
        uses=("horizon", "solver", "prediction", "robust", "latent_force"),
    ),
    AgentSpec(
        "oracle",
        OracleMPCAgent,
        # Certainty-equivalent MPC on the truth: it knows what no estimator can, but it is
        # no upper bound (a short horizon and no margins can still lose to another agent).
        label="oracle MPC (certainty-equivalent MPC that reads the true state and force)",
        short_label="oracle (reads the truth)",
        colour="tab:purple",
        order=5,
        reads_truth=True,
        uses=("horizon", "solver", "prediction"),
    ),
    AgentSpec(
        "rl",
        RLAgent,
        label="RL baseline (a policy trained by lfm-train, agents.rl_policy)",
        short_label="RL baseline",
        colour="tab:olive",
        order=6,
        check=_check_rl_policy,
        uses=("rl_policy",),
    ),
    # A peer library's robust MPC, after the project's agents (room is left for more).
    AgentSpec(
        "dompc",
        DoMpcAgent,
        label="do-mpc multi-stage MPC (peer, UKF)",
        short_label="do-mpc multi-stage",
        colour="tab:brown",
        order=10,
        check=_check_do_mpc,
    ),
)

_REGISTERED: dict[str, AgentSpec] = {s.name: s for s in _SPECS}

#: The registered agents by name, in their order (read-only; :func:`register_agent` adds).
AGENT_REGISTRY: Mapping[str, AgentSpec] = MappingProxyType(_REGISTERED)


def register_agent(
    name: str,
    factory: Any,
    label: str = "",
    short_label: str = "",
    colour: str | None = None,
    order: int = USER_ORDER,
) -> AgentSpec:
    """Register a user's agent under ``name``: ``--agents name`` and every table then know it.

    Call it at the top level of your own module (as :func:`lfm_env.register_world`); a process
    that has not imported the module knows the agent as ``"module:attribute"`` only.

    Args:
        name: 1 to 100 letters, digits or ``._+-``, not a registered agent's.
        factory: ``factory(config) -> agent`` (an agent class taking the config), an agent, or
            ``"module:attribute"``.
        label, short_label, colour, order: how tables and figures show it.

    Raises:
        AgentSpecError: for a bad or taken name, or a factory that is neither callable nor
            an agent.
    """
    spec = AgentSpec(name, factory=factory, label=label, short_label=short_label,
                     colour=colour, order=order, text=name)  # fmt: skip
    known = _REGISTERED.get(name)
    if known is not None and known.factory is not None and known.factory == factory:
        return known  # the same agent registered again (its module imported anew)
    _check_user_spec(spec, callable(factory) or is_agent(factory) or isinstance(factory, str))
    _REGISTERED[name] = spec
    ordered = sorted(_REGISTERED.values(), key=lambda s: (s.order, s.name))
    _REGISTERED.clear()
    _REGISTERED.update((s.name, s) for s in ordered)
    return spec


def _check_user_spec(spec: AgentSpec, usable: bool) -> None:
    """A user's spec: a valid name that no registered agent has, and a usable target."""
    if not usable:
        raise AgentSpecError(
            f"agent {spec.text!r}: neither an agent factory (a callable taking the config) "
            "nor an agent (reset and act)"
        )
    if not isinstance(spec.name, str) or not _NAME.fullmatch(spec.name):
        raise AgentSpecError(
            f"agent {spec.text!r}: its name {spec.name!r} must be 1 to 100 letters, digits or "
            "._+- (it names the agent's files); set a valid `name` attribute"
        )
    if spec.name in AGENT_REGISTRY:
        raise AgentSpecError(
            f"agent {spec.text!r}: its name {spec.name!r} is a registered agent's; give your "
            "agent another `name` attribute"
        )


def agent_spec(name: str) -> AgentSpec:
    """The record of a registered agent.

    Raises:
        ValueError: naming the registered agents, for an unknown ``name``.
    """
    if name not in AGENT_REGISTRY:
        raise ValueError(f"unknown agent {name!r}; choose one of {list(AGENT_REGISTRY)}")
    return AGENT_REGISTRY[name]


def needs_measurement_noise(name: str) -> bool:
    """Whether the registered agent ``name`` weighs measurements by their noise (its
    estimator's likelihood), so every ``env.measurement_noise_std`` must be > 0."""
    return AGENT_REGISTRY[name].needs_measurement_noise


def check_agent_config(name: str, config: ExperimentConfig) -> ExperimentConfig:
    """Raise ``ConfigError`` if the registered agent ``name`` cannot run on this config
    (:meth:`AgentSpec.check_config`); returns it."""
    agent_spec(name).check_config(config)
    return config


def make_agent(
    name: str, config: ExperimentConfig | str | os.PathLike | None = None, env: Any = None
) -> Any:
    """Build a registered agent by name from a config.

    Args:
        name: one of :data:`AGENT_REGISTRY` (``"nominal"``, ``"pf"``, ``"scenario"``,
            ``"scenario_particles"``, ``"robust"``, ``"oracle"``, ``"rl"``, ``"dompc"``).
        config: an :class:`~controllers.config.ExperimentConfig`; a preset's name, a YAML
            path, a dict (whole file) or ``None`` (the paper's values) is resolved once by
            :func:`~controllers.config.load_config`. The ``env`` section is the agents'
            known model, the ``agents`` section their settings.
        env: the environment, only for the oracle (which reads the hidden truth).

    To use an agent on another system, build it directly:
    ``ScenarioMPCAgent(model, cost, AgentConfig(...), measurement_std=...)``.
    """
    spec = agent_spec(name)
    if env is not None and not spec.reads_truth:
        raise ValueError(f"agent {name!r} must not get env= (only the oracle reads the truth)")
    if not isinstance(config, ExperimentConfig):
        config = load_config(config)
    spec.check_config(config)
    return spec.build(config, env=env)


# --------------------------------------------------------------------------- a user's agents


def _import(text: str) -> Any:
    """The attribute ``"module:attribute"`` names (a dotted attribute path is followed)."""
    module_name, _, attr = text.partition(":")
    try:
        module = import_named(module_name)  # (the working folder too: that module, last)
    except Exception as exc:  # ImportError, or an error while running the module
        raise AgentSpecError(
            f"agent {text!r}: cannot import module {module_name!r} ({one_line(exc)})"
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


def _describe(obj: Any) -> str:
    """A short text naming a factory or agent object in error messages."""
    source = obj if callable(obj) and not is_agent(obj) else type(obj)
    module = getattr(source, "__module__", None) or "?"
    return f"{module}:{getattr(source, '__qualname__', type(source).__name__)}"


def _text_spec(text: str) -> AgentSpec:
    """The record of a name (registered) or a ``"module:attribute"`` text (imported now)."""
    if text in AGENT_REGISTRY:
        return AGENT_REGISTRY[text]
    if ":" not in text:
        raise AgentSpecError(
            f"unknown agent(s) [{text!r}]; choose from {sorted(AGENT_REGISTRY)} or give "
            "'module:attribute' of an agent factory"
        )
    if not _SPEC_TEXT.fullmatch(text):
        raise AgentSpecError(
            f"agent {text!r}: expected 'module:attribute', e.g. 'mypkg.agents:MyAgent'"
        )
    obj = _import(text)
    if isinstance(obj, AgentSpec):
        return obj
    for known in AGENT_REGISTRY.values():  # a registered agent named by its module
        if known.factory is not None and (known.factory is obj or known.factory == text):
            return known
    return AgentSpec(_default_name(obj, text), factory=text, text=text)


def resolve_agent(spec: Any) -> AgentSpec:
    """One agent spec as its record: a registered name gives the registered record; a
    factory, an agent object or a ``"module:attribute"`` text (its module imported) a
    user's record (:class:`AgentSpec` with ``factory``).

    Raises:
        AgentSpecError: (a ``ValueError``) one line naming the spec, for an unknown
            name, a module or attribute that cannot be imported, an object that is
            neither a factory nor an agent, or a bad name.
    """
    if isinstance(spec, AgentSpec):
        return spec
    if isinstance(spec, str):
        resolved = _text_spec(spec.strip())
        if AGENT_REGISTRY.get(resolved.name) is resolved:
            return resolved
    elif is_agent(spec) or callable(spec):
        resolved = AgentSpec(_default_name(spec, None), factory=spec, text=_describe(spec))
    else:
        raise AgentSpecError(
            f"unknown agent {str(spec)!r} (a {type(spec).__name__}); choose from "
            f"{sorted(AGENT_REGISTRY)}, or give a factory (config -> agent), an agent, or "
            "'module:attribute'"
        )
    _check_user_spec(resolved, True)
    return resolved


def _spec_items(agents: Any) -> list[Any]:
    """The items of an ``agents`` argument: one spec, a comma list or a sequence."""
    if isinstance(agents, str):
        return agents.split(",")
    if isinstance(agents, AgentSpec) or is_agent(agents):
        return [agents]
    if callable(agents) and not isinstance(agents, Iterable):
        return [agents]
    if isinstance(agents, Iterable):
        return list(agents)
    raise AgentSpecError(
        f"agents {agents!r}: give a list of agents; choose from {sorted(AGENT_REGISTRY)}"
    )


def resolve_agents(agents: Any) -> list[AgentSpec]:
    """Agent specs resolved (:func:`resolve_agent`), each name once.

    Args:
        agents: one spec, a comma list of names and ``module:attribute`` texts, or a
            sequence of specs of any kind.

    Raises:
        AgentSpecError: (a ``ValueError``) for an empty list, a bad spec, or two
            agents of one name.
    """
    known = sorted(AGENT_REGISTRY)
    items = _spec_items(agents)
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
    names = [a.name for a in resolved]
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise AgentSpecError(
            f"agents {names}: each agent may appear only once ({twice} twice); give "
            "distinct `name` attributes"
        )
    return resolved


__all__ = [
    "AGENT_REGISTRY",
    "AgentSpec",
    "AgentSpecError",
    "agent_spec",
    "check_agent_config",
    "make_agent",
    "needs_measurement_noise",
    "register_agent",
    "resolve_agent",
    "resolve_agents",
]
