"""The registered agents: one :class:`AgentSpec` per agent, and :func:`make_agent`.

Everything the project knows about a registered agent lives in its record: the class that
builds it, its labels in help texts, tables and figures, its colour and its place in
tables. The command lines, the evaluation, the report and the plots read these records
(as Gymnasium's ``gym.make`` reads an ``EnvSpec``); nothing else lists the agents.

An agent of one's own needs no record: :func:`experiments.evaluation.run.evaluate` takes
any object with the agents' face (:class:`controllers.agents.protocol.Agent`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
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
from controllers.agents.rl import RLAgent, check_rl_policy
from controllers.config import ExperimentConfig, load_config
from lfm_env.config import ConfigError


@dataclass(frozen=True)
class AgentSpec:
    """One registered agent: how to build it and how the experiment layer shows it."""

    name: str  # the registered name, as in ``--agents`` and the results' ``agent`` column
    agent_class: type  # built as agent_class(model, cost, settings, measurement_std)
    label: str  # one line for help texts and the report's list of agents
    short_label: str  # table headers and axis labels
    colour: str  # matplotlib colour of the agent in every figure
    order: int  # place in tables and figures; other agents (a user's own) follow, sorted
    reads_truth: bool = False  # True: also gets the env (env=...), to read the hidden truth
    check: Callable[[ExperimentConfig], None] | None = None  # raises ConfigError; no solver
    # The agents-section settings it reads ("latent_force": it models the force with the
    # agents' belief); a report describes only the settings of the agents it holds.
    uses: tuple[str, ...] = ()

    @property
    def needs_measurement_noise(self) -> bool:
        """Whether its estimator weighs measurements by their noise (every std must be > 0)."""
        return bool(getattr(self.agent_class, "needs_measurement_noise", False))


def _check_rl_policy(config: ExperimentConfig) -> None:
    """The policy file must be there before the first episode."""
    check_rl_policy(config.agents.rl_policy)


def _check_do_mpc(config: ExperimentConfig) -> None:
    """do-mpc (the ``peers`` extra) must be installed; checked without importing it."""
    if not do_mpc_installed():
        raise ConfigError(MISSING_DO_MPC)


# Colours follow the paper's captions where it names them (true path green dashed,
# estimate red); each agent keeps its colour so plots can be compared.
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
        uses=("horizon", "solver", "prediction", "estimator", "n_particles", "latent_force"),
    ),
    AgentSpec(
        "scenario",
        ScenarioMPCAgent,
        label="PF + scenario MPC (paper)",
        short_label="scenario MPC (paper)",
        colour="tab:blue",
        order=2,
        uses=(
            "horizon",
            "solver",
            "prediction",
            "estimator",
            "n_particles",
            "n_scenarios",
            "latent_force",
        ),
    ),
    AgentSpec(
        "scenario_particles",
        ParticleScenarioMPCAgent,
        label="PF + scenario MPC, scenarios start from particles (paper's remark)",
        short_label="scenario MPC, particle starts",
        colour="tab:green",
        order=3,
        uses=(
            "horizon",
            "solver",
            "prediction",
            "estimator",
            "n_particles",
            "n_scenarios",
            "latent_force",
        ),
    ),
    AgentSpec(
        "robust",
        RobustMPCAgent,
        label="robust: calibrated estimator + MPC with constraint back-off",
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

#: The registered agents by name, in their order (read-only).
AGENT_REGISTRY: Mapping[str, AgentSpec] = MappingProxyType(
    {s.name: s for s in sorted(_SPECS, key=lambda s: s.order)}
)

#: Derived views, kept for old imports: name -> class, name -> label (read-only).
AGENTS: Mapping[str, type] = MappingProxyType({n: s.agent_class for n, s in AGENT_REGISTRY.items()})
AGENT_LABELS: Mapping[str, str] = MappingProxyType({n: s.label for n, s in AGENT_REGISTRY.items()})


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


def check_agent_config(name: str, config: Any = None) -> ExperimentConfig:
    """Raise ``ConfigError`` if agent ``name`` cannot run on this config; returns it resolved.

    Cheap (builds no solver), so :func:`experiments.evaluation.run.evaluate` calls it for every
    agent before the first episode. Every agent with an estimator (``pf``, ``scenario``,
    ``scenario_particles``, ``robust``, ``dompc``: :func:`needs_measurement_noise`) weighs
    measurements by their noise, which must not be zero. ``dompc`` needs do-mpc (the
    ``peers`` extra): without it, one line naming the extra.
    """
    spec = agent_spec(name)
    config = load_config(config)
    std = tuple(config.env.measurement_noise_std)
    if spec.needs_measurement_noise and not all(s > 0.0 for s in std):
        states = config.make_system().state_names
        zero = [n for n, s in zip(states, std, strict=False) if not s > 0.0]
        raise ConfigError(
            f"env.measurement_noise_std={list(std)}: must be all > 0 (each in (0, inf)) "
            f"for the {name!r} agent (its estimator weighs each measurement by this noise); "
            f"zero for {zero}"
        )
    if spec.check is not None:
        spec.check(config)
    return config


def make_agent(name: str, config: Any = None, env: Any = None) -> Any:
    """Build an agent by name from a config.

    Args:
        name: one of :data:`AGENT_REGISTRY` (``"nominal"``, ``"pf"``, ``"scenario"``,
            ``"scenario_particles"``, ``"robust"``, ``"oracle"``, ``"rl"``, ``"dompc"``).
        config: an :class:`~controllers.config.ExperimentConfig`, a YAML path, a dict
            (whole file), or ``None`` for the paper's values; the ``env`` section is the
            agents' known model, the ``agents`` section their settings.
        env: the environment, only for the oracle (which reads the hidden truth).

    To use an agent on another system, build it directly:
    ``ScenarioMPCAgent(model, cost, AgentConfig(...), measurement_std=...)``.
    """
    spec = agent_spec(name)
    if env is not None and not spec.reads_truth:
        raise ValueError(f"agent {name!r} must not get env= (only the oracle reads the truth)")
    config = check_agent_config(name, config)
    args = (config.make_model(), config.make_cost(), config.agents, config.measurement_std)
    if spec.reads_truth:
        return spec.agent_class(*args, env=env)
    return spec.agent_class(*args)


__all__ = [
    "AGENTS",
    "AGENT_LABELS",
    "AGENT_REGISTRY",
    "AgentSpec",
    "agent_spec",
    "check_agent_config",
    "make_agent",
    "needs_measurement_noise",
]
