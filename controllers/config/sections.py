"""The ``agents:`` and ``evaluation:`` sections of a config, typed and checked.

:class:`AgentConfig` is the ``agents:`` section (with :class:`RobustConfig`, its ``robust:``
part), :class:`EvaluationConfig` the ``evaluation:`` section (how a run goes: the episode
time limit). The memory estimates here refuse settings that would not fit before anything
is built. A whole config joins them to the world's ``env:`` section
(:mod:`controllers.config.experiment`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from controllers.estimators.estimator import ESTIMATORS
from controllers.problem import PREDICTIONS
from controllers.solvers import SOLVER_SPECS, SOLVERS
from controllers.solvers.fast.options import MAX_THREADS
from lfm_env.config import ConfigError, FieldChecker, LatentForceConfig

RESAMPLING = ("systematic", "stratified", "residual", "multinomial")
SCENARIO_INITIAL_STATES = ("estimate", "particles")
#: How many SQP iterations an agent's control step spends (AgentConfig.iterations).
ITERATIONS = ("converged", "rti")
MAX_SCENARIOS = 100_000
MAX_ITER = 2**31 - 1
FAST_MAX_HORIZON = SOLVER_SPECS["fast"].max_horizon  # longest horizon of the fast solver
MAX_SOLVE_TIME = 3600.0  # [s] largest agents.max_solve_time
CONTROL_PERIOD = "control_period"  # agents.deadline: the world's dt

#: Memory budget [bytes] of an agent's filter and, separately, of its scenario problem:
#: settings whose estimate (below) exceeds it are refused before anything is built.
MEMORY_BUDGET = 2 * 1024**3
#: Arrays of the particles' size alive at once in a filter step (particles, proposals,
#: resampled copies, temporaries): 1e6 particles of 7 states took 447 MB, 8 x 56 MB.
FILTER_COPIES = 8
#: Copies of the condensed sensitivities ``(nx + ng) x N x Ns x N nu`` alive at once in a
#: solve (the fast SQP's linearisation and its QP rows).
PROBLEM_COPIES = 2


def _gb(n_bytes: float) -> str:
    return f"{n_bytes / 1024**3:.3g} GB"


def filter_memory(n_particles: int, state_dim: int, latent_dim: int, estimator: str) -> float:
    """Estimated peak memory [bytes] of a filter: ``n_particles x d x 8 bytes x``
    :data:`FILTER_COPIES`, ``d`` the filter's state dimension (plus the latent covariance
    of each particle, ``latent_dim^2``, for the Rao-Blackwellised filter; the UKF keeps no
    particles)."""
    if estimator == "ukf":
        return 8.0 * FILTER_COPIES * (state_dim + 1) ** 2
    per_particle = state_dim + (latent_dim**2 if estimator == "rbpf" else 0)
    return 8.0 * FILTER_COPIES * float(n_particles) * per_particle


def problem_memory(horizon: int, n_scenarios: int, nx: int, ng: int, nu: int) -> float:
    """Estimated peak memory [bytes] of a scenario problem and its solve: the condensed
    sensitivities of the ``nx`` states and ``ng`` constraints at ``N`` steps of ``Ns``
    scenarios to the ``N nu`` inputs, 8 bytes each, times :data:`PROBLEM_COPIES`."""
    return 8.0 * PROBLEM_COPIES * horizon * float(n_scenarios) * (nx + ng) * horizon * nu


def check_filter_memory(
    model: Any, n_particles: int, estimator: str, field_name: str = "agents.n_particles"
) -> None:
    """Refuse a filter whose estimate (:func:`filter_memory`) exceeds :data:`MEMORY_BUDGET`.

    Raises:
        ConfigError: naming ``field_name`` and the largest particle count within budget.
    """
    need = filter_memory(n_particles, model.state_dim, model.latent_dim, estimator)
    if need > MEMORY_BUDGET:
        largest = int(n_particles * MEMORY_BUDGET / need)
        raise ConfigError(
            f"{field_name}={n_particles}: the {estimator} filter of {model.state_dim} states "
            f"would need about {_gb(need)} (n_particles x {model.state_dim} x 8 bytes x "
            f"{FILTER_COPIES}), over the budget of {_gb(MEMORY_BUDGET)}; must be <= {largest}"
        )


def check_problem_memory(model: Any, horizon: int, n_scenarios: int) -> None:
    """Refuse a scenario problem whose estimate (:func:`problem_memory`) exceeds
    :data:`MEMORY_BUDGET`.

    Raises:
        ConfigError: naming ``agents.horizon`` and the scenario count.
    """
    system = model.system
    need = problem_memory(horizon, n_scenarios, system.nx, system.ng, system.nu)
    if need > MEMORY_BUDGET:
        raise ConfigError(
            f"agents.horizon={horizon} with {n_scenarios} scenarios: the scenario problem "
            f"would need about {_gb(need)} ((nx + ng) x N x Ns x N nu x 8 bytes x "
            f"{PROBLEM_COPIES}), over the budget of {_gb(MEMORY_BUDGET)}; lower "
            "agents.horizon or the scenario count"
        )


def check_backoff(c: FieldChecker, backoff: tuple[float, ...]) -> None:
    c("backoff", len(backoff) >= 1, "one number, or one per constraint group")
    c("backoff", all(0.0 <= k <= 10.0 for k in backoff), "in [0, 10] standard deviations")


FORECASTS = ("sampled", "mean")


@dataclass(frozen=True)
class RobustConfig:
    """The ``robust`` agent: the combination that carried the estimate's uncertainty best
    in our measurements (docs/agents.md, "The robust agent"); the ``agents.robust`` section.

    Its other settings (horizon, weights, solver, ...) are the ``agents`` section's.
    """

    estimator: str = "ukf"  # one of ESTIMATORS (the UKF needs no affine force)
    n_particles: int = 1000  # particles of a particle-filter estimator
    # k estimate stds per constraint group (the sine track: track, x, speed), or one for all
    backoff: tuple[float, ...] = (2.0,)
    forecast: str = "mean"  # "mean": the force's mean forecast, one scenario; "sampled"
    n_scenarios: int | None = None  # with "sampled": Ns, null for agents.n_scenarios
    scenario_initial_states: str = "estimate"  # with "sampled": "estimate" or "particles"

    def __post_init__(self) -> None:
        c = FieldChecker(self)
        c("estimator", self.estimator in ESTIMATORS, f"one of {ESTIMATORS}")
        c("n_particles", 1 <= self.n_particles <= 10_000_000, "an integer in [1, 1e7]")
        check_backoff(c, self.backoff)
        c("forecast", self.forecast in FORECASTS, f"one of {FORECASTS}")
        c(
            "n_scenarios",
            self.n_scenarios is None or 1 <= self.n_scenarios <= MAX_SCENARIOS,
            "null or an integer in [1, 100000]",
        )
        c(
            "scenario_initial_states",
            self.scenario_initial_states in SCENARIO_INITIAL_STATES,
            f"one of {SCENARIO_INITIAL_STATES}",
        )


@dataclass(frozen=True)
class AgentConfig:
    """Settings shared by the MPC agents (paper values by default).

    The agents' *model* of the world (dynamics, bounds, GP hyperparameters, noise levels)
    is the ``env`` section: it is the known structure the paper gives the controller.
    The agents' cost is the world's own by default: ``Q``, ``R`` and ``goal_state`` left out
    (``None``) are the ``env`` section's, ``Qf`` is ``Q``; a whole config resolves them
    (:class:`~controllers.config.ExperimentConfig`, whose ``agents`` hold the values used).
    Vectors over the state (``Q``, ``Qf``, ``goal_state``) have one entry per state of the
    system and are given in the config's units (the sine track's heading in degrees, as
    in the ``env`` section); ``R`` has one entry per input. Their lengths are checked
    against the world's when the config is resolved.
    """

    RENAMED_KEYS = {"disturbance": "latent_force"}  # old name -> new (read with a warning)

    horizon: int = 7  # N, prediction steps
    n_scenarios: int | None = 150  # Ns; null to derive it from violation_level/confidence
    violation_level: float | None = None  # epsilon of the Campi-Garatti bound, in (0, 1)
    confidence: float | None = None  # beta of the Campi-Garatti bound, in (0, 1)
    estimator: str = "bootstrap"  # one of controllers.estimators.estimator.ESTIMATORS
    n_particles: int = 7000  # particle filter size (bootstrap and rbpf)
    resampling: str = "systematic"  # one of RESAMPLING
    ess_threshold: float | None = None  # null: resample every step (paper); else in (0, 1]
    # The agents' cost, null for the world's own (its env.Q, env.R, env.goal_state; Qf: Q):
    Q: tuple[float, ...] | None = None  # stage weights on x - x_g (diagonal)
    Qf: tuple[float, ...] | None = None  # terminal weights (diagonal)
    R: tuple[float, ...] | None = None  # input weights (diagonal), e.g. on [a, delta (rad)]
    goal_state: tuple[float, ...] | None = None  # e.g. [m, m, m/s, deg]
    slack_penalty: float = 1.0e4  # exact L1 penalty per unit of state-constraint slack
    # One of controllers.solvers.SOLVERS: "fast_c", the fast SQP with its loop compiled (the
    # Python loop, "fast", with a one-line notice where no C compiler works).
    solver: str = "fast_c"
    # Solver iteration limit per step (the fast SQP's per start; its own default too: long
    # horizons need it, see FastSolverOptions.max_iter).
    max_iter: int = 150
    # Wall-clock limit of one solve [s]: a solve that reaches it stops; the agent applies the
    # plan reached if it is usable (below its warm start, MPCSolution.usable), else falls
    # back (the previous plan, else the system's fallback input), as on any failed solve.
    max_solve_time: float = 10.0
    # Wall-clock budget of one control step's compute (estimator + solve) for real-time
    # runs: null (the default: no budget, the run stays deterministic; steps longer than
    # the control period are only counted, episodes.csv's deadline_misses), "control_period"
    # (the world's dt) or a number of seconds. With a budget the solve gets what the
    # estimator left of it and stops there: the agent applies the best usable plan reached,
    # else its previous plan shifted, else the system's fallback input, each counted.
    deadline: float | str | None = None
    # Threads of the fast solver's C library (FastSolverOptions.threads): it pays
    # for many scenarios (Ns >= 500; 0.6x the solve time at Ns = 5000 with two) when the
    # agent has the cores to itself; keep 1 under lfm-evaluate --jobs, whose processes take
    # the cores already.
    solver_threads: int = 1
    scenario_initial_states: str = "estimate"  # "estimate" (paper) or "particles" (its remark)
    # The scenarios' prediction: "open_loop" (one shared input sequence, the paper's) or
    # "feedback" (u = v + K (x - r) per scenario, a TV-LQR law of the cost along the previous
    # plan; docs/feedback.md says when it pays).
    prediction: str = "open_loop"
    # SQP iterations per control step: "converged" (every solve to its tolerances, max_iter
    # per start) or "rti" (real-time iterations: after a converged first solve, each step
    # takes rti_iterations SQP iterations from the plan shifted by one step, without extra
    # starts; a step whose plan is not usable or has more slack than the shifted plan's is
    # solved again to convergence). The fast solvers only; docs/solvers.md says what it gives up.
    iterations: str = "converged"
    rti_iterations: int = 1
    # Constraint back-off of the filtering agents: each state constraint g_j is tightened
    # by k * sqrt(dg_j' Sigma_x dg_j), k estimate stds along its gradient: one k for all,
    # or one per constraint group of the system (the sine track: track, x, speed).
    backoff: tuple[float, ...] = (0.0,)
    # The robust agent's own settings (see RobustConfig).
    robust: RobustConfig = field(default_factory=RobustConfig)
    # The agents' belief about the latent force. null: the env section's, known a priori
    # (the paper); set it to learned hyperparameters (see lfm-calibrate).
    latent_force: LatentForceConfig | None = None
    # The "rl" agent's saved policy: a .zip written by lfm-train (its observation
    # normalisation beside it); null when no RL agent is run. Relative to the working dir.
    rl_policy: str | None = None

    def __post_init__(self) -> None:
        c = FieldChecker(self)
        c("rl_policy", self.rl_policy is None or self.rl_policy != "", "null or a file path")
        c("horizon", self.horizon >= 1, "an integer >= 1")
        c("horizon", self.horizon <= 200, "<= 200")
        # A solver's practical horizon (SolverSpec.max_horizon; the fast SQP's iterations
        # outgrow any solve limit beyond 40) is enforced up front.
        spec = SOLVER_SPECS.get(self.solver)
        longest = spec.max_horizon if spec is not None else None
        c(
            "horizon",
            longest is None or self.horizon <= longest,
            f"<= {longest} with solver {self.solver!r} (its iterations outgrow any "
            "solve-time limit beyond); use solver 'ipopt' for longer horizons",
        )
        if self.n_scenarios is None:
            c(
                "n_scenarios",
                self.violation_level is not None and self.confidence is not None,
                "an integer >= 1, or null with violation_level and confidence set",
            )
        else:
            c("n_scenarios", 1 <= self.n_scenarios <= MAX_SCENARIOS, "an integer in [1, 100000]")
        for name in ("violation_level", "confidence"):
            v = getattr(self, name)
            c(name, v is None or 0.0 < v < 1.0, "null or in (0, 1)")
        c("n_particles", 1 <= self.n_particles <= 10_000_000, "an integer in [1, 1e7]")
        c("resampling", self.resampling in RESAMPLING, f"one of {RESAMPLING}")
        c("estimator", self.estimator in ESTIMATORS, f"one of {ESTIMATORS}")
        c(
            "ess_threshold",
            self.ess_threshold is None or 0.0 < self.ess_threshold <= 1.0,
            "null or in (0, 1]",
        )
        c.non_negative(*(n for n in ("Q", "Qf", "R") if getattr(self, n) is not None))
        c.positive("slack_penalty")
        check_backoff(c, self.backoff)
        c("solver", self.solver in SOLVERS, f"one of {SOLVERS}")
        # IPOPT's iteration counter is a C int: larger values wrap around or are refused.
        c("max_iter", 1 <= self.max_iter <= MAX_ITER, f"an integer in [1, {MAX_ITER}]")
        c(
            "max_solve_time",
            0.0 < self.max_solve_time <= MAX_SOLVE_TIME,
            f"in (0, {MAX_SOLVE_TIME:g}] s",
        )
        d = self.deadline
        c(
            "deadline",
            d is None
            or d == CONTROL_PERIOD
            or (
                isinstance(d, (int, float)) and not isinstance(d, bool) and 0 < d <= MAX_SOLVE_TIME
            ),
            f"null (no budget), {CONTROL_PERIOD!r} or seconds in (0, {MAX_SOLVE_TIME:g}]",
        )
        c(
            "solver_threads",
            1 <= self.solver_threads <= MAX_THREADS,
            f"an integer in [1, {MAX_THREADS}]",
        )
        c(
            "solver_threads",
            self.solver_threads == 1 or (spec is not None and spec.threaded),
            f"1 with solver {self.solver!r} (only the fast solver's C library has threads)",
        )
        c(
            "scenario_initial_states",
            self.scenario_initial_states in SCENARIO_INITIAL_STATES,
            f"one of {SCENARIO_INITIAL_STATES}",
        )
        c("prediction", self.prediction in PREDICTIONS, f"one of {PREDICTIONS}")
        c("iterations", self.iterations in ITERATIONS, f"one of {ITERATIONS}")
        c(
            "iterations",
            self.iterations == "converged" or (spec is not None and spec.real_time),
            f"'converged' with solver {self.solver!r} (real-time iterations need a solver "
            "that takes an iteration limit per solve: 'fast' or 'fast_c')",
        )
        ok = isinstance(self.rti_iterations, int) and not isinstance(self.rti_iterations, bool)
        c(
            "rti_iterations",
            ok and 1 <= self.rti_iterations <= self.max_iter,
            "an int in [1, max_iter]",
        )

    def deadline_seconds(self, dt: float) -> float | None:
        """The step budget [s] of :attr:`deadline` for a world of control period ``dt`` [s];
        ``None`` without one."""
        if self.deadline is None:
            return None
        return float(dt) if self.deadline == CONTROL_PERIOD else float(self.deadline)

    def check_scenario_count(self, n_inputs: int) -> None:
        """Raise ``ConfigError`` if the Campi-Garatti count of a system with ``n_inputs``
        inputs (``nu N`` decision variables) exceeds :data:`MAX_SCENARIOS`."""
        if self.n_scenarios is not None:
            return
        # The bound decreases in Ns, so checking it at the largest count suffices.
        from scipy import optimize, stats

        d = n_inputs * self.horizon

        def excess(eps: float) -> float:
            return stats.binom.cdf(d - 1, MAX_SCENARIOS, eps) - self.confidence

        if excess(self.violation_level) > 0.0:
            least = optimize.brentq(excess, self.violation_level, 1.0 - 1e-9)
            least *= 1.001  # shown rounded to 4 digits: round up, so that it is admissible
            raise ConfigError(
                f"agents.violation_level={self.violation_level!r}: must be >= {least:.4g} with "
                f"confidence={self.confidence} and horizon={self.horizon} for {n_inputs} inputs"
                f" (the Campi-Garatti scenario count must stay <= {MAX_SCENARIOS})"
            )

    def scenario_count(self, n_inputs: int) -> int:
        """``n_scenarios``, or the Campi-Garatti count for ``n_inputs N`` decision variables."""
        if self.n_scenarios is not None:
            return self.n_scenarios
        from controllers.scenario_count import campi_garatti_scenarios

        return campi_garatti_scenarios(
            self.violation_level, self.confidence, n_inputs * self.horizon
        )


#: Default and largest ``evaluation.episode_timeout`` [s].
DEFAULT_EPISODE_TIMEOUT = 600.0
MAX_EPISODE_TIMEOUT = 30 * 24 * 3600.0


@dataclass(frozen=True)
class EvaluationConfig:
    """How an evaluation runs: the ``evaluation:`` section of a config file.

    A run setting, not a property of the episodes: it is not part of
    :meth:`ExperimentConfig.to_dict` (so neither of a results folder's ``config.yaml`` nor
    of its config hash), and configs that differ only here compare equal.
    """

    # Wall-clock limit of one episode [s]: an episode that runs longer ends as an error row
    # naming the limit (lfm-evaluate --episode-timeout overrides it); null: no limit.
    episode_timeout: float | None = DEFAULT_EPISODE_TIMEOUT

    def __post_init__(self) -> None:
        c = FieldChecker(self)
        c(
            "episode_timeout",
            self.episode_timeout is None or 0.0 < self.episode_timeout <= MAX_EPISODE_TIMEOUT,
            f"null (no limit) or in (0, {MAX_EPISODE_TIMEOUT:g}] s",
        )


__all__ = [
    "DEFAULT_EPISODE_TIMEOUT",
    "FAST_MAX_HORIZON",
    "MEMORY_BUDGET",
    "AgentConfig",
    "EvaluationConfig",
    "RobustConfig",
    "check_filter_memory",
    "check_problem_memory",
    "filter_memory",
    "problem_memory",
]
