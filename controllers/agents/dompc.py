"""do-mpc's robust multi-stage MPC as an agent: a peer library next to the project's agents.

:class:`DoMpcAgent` (``"dompc"``) plans with `do-mpc <https://www.do-mpc.com>`_ (5.x), the most
used Python MPC library, built once from the project's own definitions: the model is the
system's Euler step (:meth:`ControlSystem.casadi_step`, exactly
:meth:`LatentForceModel.physical_step`), the cost the :class:`QuadraticCost`, the state
constraints the system's ``g(x) <= 0``, the input bounds the system's. Nothing of the
dynamics, the cost or a constraint is written again here. It estimates like the ``robust``
agent (``settings.robust``: the UKF by default) and hands do-mpc the estimate of the latent
force as the uncertain parameter of a scenario tree.

The formulation (one do-mpc ``MPC``, built in the constructor and re-solved every step):

* **Model** (``Model("discrete")``): ``x+ = x + dt f(x, u, w)`` with ``w = w_mean + w_offset``;
  ``w_mean`` is a time-varying parameter (``_tvp``), ``w_offset`` the uncertain parameter
  (``_p``).
* **Scenario tree** (``n_robust = 1``, ``open_loop = False``): ``2 nw + 1`` branches, the
  nominal one first: offsets ``0`` and ``+- spread * std_j`` along each force component ``j``
  (``std`` the estimator's std of the current force; ``spread = 2`` by default, a 95% band).
  The first input is shared; after the first step every branch has its own inputs (do-mpc's
  recourse). do-mpc holds a branch's parameter constant over the horizon.
* **Force along the horizon** (``force``): ``"forecast"`` (default) passes the force's mean
  forecast ``H A^k z_hat`` (``k = 0..N``) through ``w_mean``, so each branch is the forecast
  shifted by its constant offset; ``"constant"`` holds the current estimate ``H z_hat`` over
  the horizon (the textbook use of do-mpc's constant uncertain parameters).
* **Cost** (``set_objective``): ``lterm`` is the stage cost ``(x - x_g)' Q (x - x_g) + u' R u``
  (do-mpc's ``lterm`` may depend on the inputs), ``mterm`` the terminal cost; do-mpc weighs
  every branch ``1 / (2 nw + 1)``, so the objective is the branches' average, as the
  project's scenario average. ``set_rterm`` (the Delta-u penalty) is zero: the project's cost
  has none.
* **Constraints**: the input bounds hard (``bounds``); ``g`` of the *next* state,
  ``g(x + dt f(x, u, w)) <= eps`` (``set_nl_cons``, soft), so they bind ``x_1 .. x_N`` as in
  :class:`~controllers.problem.ScenarioProblem` (do-mpc evaluates a constraint at ``x_k``,
  ``k = 0..N-1``). The slacks ``eps >= 0`` are an exact L1 penalty of
  ``settings.slack_penalty / (2 nw + 1)`` per unit and branch: do-mpc adds a branch's slack
  penalty once per branch, so at the first step (one slack shared by the branches) it is
  exactly the project's ``slack_penalty * max_i g``, and later (one slack per branch) the
  branches' average excess instead of the project's largest one.
* **Solver**: do-mpc's IPOPT (``nlpsol_opts``: output off, ``max_iter`` and ``max_wall_time``
  from the settings, IPOPT's default ``tol`` 1e-8), warm-started by do-mpc from its previous
  solution (not shifted); an episode's first solve starts from every state at the estimate
  and every input at the middle of its bounds. The action is chosen as the project's agents
  choose it (:class:`~controllers.agents.mpc.PlanChoice`): a usable plan is applied (converged,
  or stopped early with a merit below its warm start's: the exact-penalty objective of the
  nominal branch's inputs rolled out along the nominal force), else the previous nominal plan
  shifted, else the system's fallback input.

The defaults were chosen on env seeds 1000..1019 (never on evaluation seeds). ``force``: the
forecast and the constant force differ little (paper: the same counts but on one seed, the
track steps > 1 cm -0.05 [-0.15, 0] per episode; quadrotor: corridor steps > 1 cm +0.40
[0.00, 0.85], cost -1.1 [-3.9, 0.7]); ``"forecast"`` is kept, as the model the ``pf`` and
``robust`` agents plan with. ``spread`` 1, 2, 3 gave 10.95, 7.70, 5.20 speed-violation steps
per paper episode (the force enters the acceleration), the same track steps (6.3 to 6.45 >
1 cm: those come from the state estimate's error, which do-mpc's tree does not carry) and
9.27, 9.35, 9.40 s to the goal; on the quadrotor 3.7, 2.7, 2.8 corridor steps > 1 cm.

How it differs from the project's scenario problem (:data:`APPROXIMATIONS`; read in
do-mpc 5.1.2's ``MPC._prepare_nlp``). Not expressible in do-mpc's multi-stage MPC: a force
that evolves randomly within a branch (a scenario's uncertain parameter is constant along the
horizon; the scenario agents' sampled paths would need ``n_robust = N``, ``3^N`` scenarios,
2,187 at ``N = 7``), one slack shared by all branches at a step after the first (do-mpc's
slacks are per scenario), and an uncertain initial state (every branch starts from one
``x0``: the estimate's mean; no back-off, where the ``robust`` agent backs its constraints
off by the estimate's spread). Equal weights are do-mpc's only ones (``1 / scenarios`` per
step), as here. Chosen, not forced: the inputs branch after the first step (do-mpc's default
recourse, ``open_loop = False``); ``open_loop = True`` would share one input sequence, as
the project's problem does.

do-mpc is an optional dependency (the ``peers`` extra); building the agent without it raises
:class:`ImportError` with :data:`MISSING_DO_MPC`.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import sys
import time
import warnings
from typing import Any

import numpy as np

from controllers.agents.estimation import EstimatorLoop
from controllers.agents.mpc import PlanChoice
from controllers.agents.protocol import SB3Predict
from controllers.config import AgentConfig, check_filter_memory
from controllers.estimators.estimator import make_estimator
from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from lfm_env.cost import QuadraticCost
from lfm_env.model import LatentForceModel
from lfm_env.validation import real_vector

#: The one-line error of building the agent without do-mpc.
MISSING_DO_MPC = "dompc needs do-mpc: pip install 'lfm-scenario-mpc[peers]'"

#: How the force runs along the horizon within a branch (see the module docstring).
FORCE_MODELS = ("forecast", "constant")

#: The approximations of the project's problem in do-mpc's formulation, for reports.
APPROXIMATIONS = (
    "force constant within a branch: forecast mean plus a constant offset (or held constant)",
    "2 nw + 1 branches at +- spread std of the current force; no future process noise",
    "inputs branch after the first step (n_robust = 1, recourse; open_loop would share them)",
    "equal branch weights 1 / (2 nw + 1)",
    "slack per branch after the first step: average excess, not the largest",
    "initial state is the estimate's mean: no physical-state uncertainty, no back-off",
)

# Warnings do-mpc 5.1 raises that are no concern of the agent: its optional ONNX and OPC UA
# features at import, and CasADi 3.8's notice on do-mpc's own np.any of a DM in setup().
_DO_MPC_WARNINGS = (
    (UserWarning, r"The (ONNX|opcua) feature is not available"),
    (FutureWarning, r"\s*casadi: a numpy function was called on a casadi value"),
)


@contextlib.contextmanager
def _quiet_do_mpc():
    with warnings.catch_warnings():
        for category, message in _DO_MPC_WARNINGS:
            warnings.filterwarnings("ignore", message=message, category=category)
        yield


def do_mpc_installed() -> bool:
    """Whether do-mpc can be imported, without importing it (which takes seconds)."""
    if "do_mpc" in sys.modules:
        return sys.modules["do_mpc"] is not None  # None: an import that is to fail
    return importlib.util.find_spec("do_mpc") is not None


def import_do_mpc() -> Any:
    """The ``do_mpc`` module, or :class:`ImportError` with the one line :data:`MISSING_DO_MPC`."""
    try:
        with _quiet_do_mpc():
            import do_mpc
    except ImportError:
        raise ImportError(MISSING_DO_MPC) from None
    return do_mpc


class DoMpcAgent(EstimatorLoop, PlanChoice, SB3Predict):
    """do-mpc's robust multi-stage MPC on the agent's estimate (see the module docstring).

    Same face as the project's agents (:class:`controllers.agents.protocol.Agent`,
    ``last_info`` with every key, stable-baselines3's ``predict``); built as they are.

    Args:
        model: the agent's latent-force model of the world.
        cost: the control objective.
        settings: the ``agents`` section: ``horizon``, ``slack_penalty``, ``max_iter`` and
            ``max_solve_time`` (IPOPT's ``max_iter`` and ``max_wall_time``), and the estimator of
            ``robust`` (``estimator``, ``n_particles``) with ``resampling`` and
            ``ess_threshold``.
        measurement_std: std of the noise of each observed state ``(nx,)``, all > 0.
        spread: the branches' offsets in stds of the current force estimate (> 0).
        force: ``"forecast"`` or ``"constant"`` (:data:`FORCE_MODELS`).

    Raises:
        ImportError: :data:`MISSING_DO_MPC` when do-mpc is not installed.
        ValueError: a measurement std that is not > 0, ``spread <= 0`` or an unknown ``force``.
    """

    name = "dompc"
    needs_measurement_noise = True  # its estimator weighs every measurement by its noise

    def __init__(
        self,
        model: LatentForceModel,
        cost: QuadraticCost,
        settings: AgentConfig | None = None,
        measurement_std: Any = None,
        *,
        spread: float = 2.0,
        force: str = "forecast",
    ) -> None:
        do_mpc = import_do_mpc()
        self.model, self.system, self.cost = model, model.system, cost
        self.settings = AgentConfig() if settings is None else settings
        nx = self.system.nx
        std = np.zeros(nx) if measurement_std is None else measurement_std
        self.measurement_std = real_vector(
            std, nx, "measurement_std", f"one per state {list(self.system.state_names)}"
        )
        if not np.all(self.measurement_std > 0.0):
            raise ValueError(
                f"measurement_std={self.measurement_std.tolist()}: must be all > 0 for the "
                f"{self.name!r} agent (its estimator weighs each measurement by this noise)"
            )
        if not (np.isfinite(spread) and spread > 0.0):
            raise ValueError(f"spread={spread!r}: must be a finite number > 0 (stds)")
        if force not in FORCE_MODELS:
            raise ValueError(f"force={force!r}: must be one of {FORCE_MODELS}")
        cost.check_system(self.system)
        self.spread, self.force = float(spread), force
        self.horizon = self.settings.horizon
        self.n_branches = 2 * self.system.nw + 1
        s, r = self.settings, self.settings.robust
        check_filter_memory(model, r.n_particles, r.estimator, "agents.robust.n_particles")
        self.estimator = make_estimator(
            r.estimator,
            model,
            self.measurement_std,
            n_particles=r.n_particles,
            resampling=s.resampling,
            ess_threshold=s.ess_threshold,
        )
        self.solver = self._build(do_mpc)
        # The merit a plan is judged by (usable: below its warm start's): the exact-penalty
        # objective of the nominal branch's inputs along the nominal force, rolled out.
        self._merit = ScenarioProblem(
            model, cost, horizon=self.horizon, n_scenarios=1, slack_penalty=s.slack_penalty
        )
        self.last_info: dict[str, Any] = {}
        self.rng = np.random.default_rng()
        self._init_estimator_loop()
        self._u_prev: np.ndarray | None = None
        self._plan: np.ndarray | None = None
        self._guess_needed = True

    # ------------------------------------------------------------------ do-mpc, built once

    def _build(self, do_mpc: Any) -> Any:
        system, dt, N = self.system, self.model.dt, self.horizon
        nx, nu, nw = system.nx, system.nu, system.nw
        with _quiet_do_mpc():
            m = do_mpc.model.Model("discrete", "SX")
            m.set_variable("_x", "x", shape=(nx, 1))
            m.set_variable("_u", "u", shape=(nu, 1))
            m.set_variable("_tvp", "w_mean", shape=(nw, 1))
            m.set_variable("_p", "w_offset", shape=(nw, 1))
            # The expressions must use the symbols the model holds once set up (set_rhs before
            # setup may use those set_variable returned; do-mpc substitutes them itself).
            x, u = m.x["x"], m.u["u"]
            step = system.casadi_step(dt)
            m.set_rhs("x", step(x, u, m.tvp["w_mean"] + m.p["w_offset"]))
            m.setup()
            x, u = m.x["x"], m.u["u"]
            x_next = step(x, u, m.tvp["w_mean"] + m.p["w_offset"])

            mpc = do_mpc.controller.MPC(m)
            st = mpc.settings
            st.n_horizon = N
            st.n_robust = 1
            st.open_loop = False  # do-mpc's default: inputs branch after the robust horizon
            st.t_step = dt
            st.store_full_solution = False
            st.store_lagr_multiplier = False
            st.store_solver_stats = []  # read from mpc.solver_stats (return_status is text)
            st.nlpsol_opts = {
                "ipopt.print_level": 0,
                "ipopt.sb": "yes",
                "print_time": 0,
                "ipopt.max_iter": int(self.settings.max_iter),
                "ipopt.max_wall_time": float(self.settings.max_solve_time),
            }
            mpc.set_objective(lterm=self.cost.stage_cost(x, u), mterm=self.cost.terminal_cost(x))
            mpc.set_rterm(u=0.0)  # no Delta-u penalty (the project's cost has none)
            mpc.bounds["lower", "_u", "u"] = system.input_lower
            mpc.bounds["upper", "_u", "u"] = system.input_upper
            if system.ng:
                mpc.set_nl_cons(
                    "g",
                    system.casadi_constraints()(x_next),
                    ub=0.0,
                    soft_constraint=True,
                    penalty_term_cons=float(self.settings.slack_penalty) / self.n_branches,
                )
            self._p = mpc.get_p_template(self.n_branches)
            mpc.set_p_fun(lambda t_now: self._p)
            self._tvp = mpc.get_tvp_template()
            mpc.set_tvp_fun(lambda t_now: self._tvp)
            mpc.setup()
        import casadi as ca

        self._objective = ca.Function("objective", [mpc.opt_x, mpc.opt_p], [mpc.nlp_obj])
        return mpc

    def branch_offsets(self, force_std: Any) -> np.ndarray:
        """The branches' force offsets ``(2 nw + 1, nw)``: 0, then ``+- spread std_j e_j``."""
        nw = self.system.nw
        std = np.asarray(force_std, dtype=float).reshape(nw)
        steps = self.spread * np.diag(std)
        return np.concatenate([np.zeros((1, nw)), np.stack([steps, -steps], 1).reshape(-1, nw)])

    def solve(self, x0: Any, W: Any, force_std: Any) -> MPCSolution:
        """One do-mpc solve from ``x0`` ``(nx,)`` with the force ``W`` along the horizon.

        Args:
            x0: the initial state.
            W: the force ``w_mean`` acting during steps ``0..N-1`` ``(N, nw)`` (or ``(N,)``
                with one component), e.g. the mean forecast.
            force_std: std of the current force ``(nw,)``: the branches' offsets.

        Returns:
            The nominal branch's inputs ``u`` ``(N, nu)`` (its first row is the action), the
            objective of do-mpc's NLP, the total slack, IPOPT's status, the wall time of
            ``make_step`` [s], and ``predicted`` ``(2 nw + 1, N+1, nx)`` (the nominal branch
            first); ``extra["branch_inputs"]`` ``(2 nw + 1, N, nu)``, ``extra["offsets"]``,
            and the merits ``extra["merit"]``, ``extra["start_merit"]`` of the plan and of its
            warm start (the exact-penalty objective of the nominal branch's inputs along
            ``W``): a plan stopped early is usable when its merit is below its warm start's.
        """
        mpc, N, nw = self.solver, self.horizon, self.system.nw
        x0 = np.asarray(x0, dtype=float).reshape(self.system.nx)
        W = np.asarray(W, dtype=float).reshape(N, nw)
        offsets = self.branch_offsets(force_std)
        for i, offset in enumerate(offsets):
            self._p["_p", i] = offset
        for k in range(N + 1):  # step N's value enters nothing (the terminal cost has no force)
            self._tvp["_tvp", k, "w_mean"] = W[min(k, N - 1)]
        if self._guess_needed or not np.all(np.isfinite(mpc.opt_x_num.cat.full())):
            mpc.x0 = x0
            mpc.u0 = 0.5 * (self.system.input_lower + self.system.input_upper)
            mpc.set_initial_guess()  # every state x0, every input the bounds' midpoint
            mpc.opt_x_num["_eps"] = 0.0
            self._guess_needed = False
        start = self._branches()[0][0]  # the warm start's nominal inputs (do-mpc's own guess)
        t0 = time.perf_counter()
        with _quiet_do_mpc():
            mpc.make_step(x0)
        solve_time = time.perf_counter() - t0
        stats = mpc.solver_stats
        U, X, slack = self._branches()
        success = bool(stats.get("success", False)) and bool(np.all(np.isfinite(U)))
        merit, start_merit = self._merits(x0, W, U[0], start, success)
        return MPCSolution(
            u=U[0].copy(),
            objective=float(self._objective(mpc.opt_x_num, mpc.opt_p_num)),
            slack=slack,
            status=str(stats.get("return_status", "")),
            success=success,
            solve_time=solve_time,
            iterations=int(stats.get("iter_count", 0)),
            predicted=X,
            extra={
                "branch_inputs": U,
                "offsets": offsets,
                "merit": merit,
                "start_merit": start_merit,
            },  # fmt: skip
            usable=is_usable(success, merit, start_merit),
        )

    def _merits(
        self, x0: np.ndarray, W: np.ndarray, u: np.ndarray, start: np.ndarray, success: bool
    ) -> tuple[float, float]:
        """The merits of the plan's and of the warm start's nominal inputs (NaN: not needed,
        the solve converged; or not finite)."""
        if success or not (np.all(np.isfinite(u)) and np.all(np.isfinite(start))):
            return math.nan, math.nan
        clip = self.system.clip_input
        return tuple(float(self._merit.objective(x0, W[None], clip(v))) for v in (u, start))

    def _branches(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The solution's inputs ``(S, N, nu)`` and states ``(S, N+1, nx)`` of every branch
        (the nominal one first) and its total slack.

        At step 0 only do-mpc's scenario 0 exists (its other slots are free variables of the
        NLP, in no constraint), so every branch starts from it; the slacks in use are the
        first step's shared one and one per branch after it.
        """
        opt, N, S = self.solver.opt_x_num_unscaled, self.horizon, self.n_branches

        def node(k: int, s: int) -> int:
            return 0 if k == 0 else s

        U = np.array(
            [[opt["_u", k, node(k, s)].full().ravel() for k in range(N)] for s in range(S)]
        )
        X = np.array(
            [[opt["_x", k, node(k, s), -1].full().ravel() for k in range(N + 1)] for s in range(S)]
        )
        slack = 0.0
        if self.system.ng:
            used = [opt["_eps", 0, 0]] + [opt["_eps", k, s] for k in range(1, N) for s in range(S)]
            slack = float(sum(np.maximum(e.full(), 0.0).sum() for e in used))
        return U, X, slack

    # ------------------------------------------------------------------ public face

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; ``seed`` fixes the agent's own randomness (its estimator's)."""
        self.rng = np.random.default_rng(seed)
        self._init_estimator_loop()
        self._u_prev = None
        self._plan = None
        self._guess_needed = True  # the episode's first solve starts from a fresh guess
        self.solver.reset_history()
        self.last_info = {}

    def act(self, obs: Any) -> np.ndarray:
        """The action ``(nu,)`` in the inputs' units for an observation ``(nx,)`` of the state."""
        nx, N = self.system.nx, self.horizon
        y = real_vector(obs, nx, "obs", f"{list(self.system.state_names)}")
        t0 = time.perf_counter()
        info = self._estimate(y)
        t_est = time.perf_counter() - t0
        mean = self.estimator.mean
        x_hat = mean[:nx]
        if self.force == "forecast":
            W = self.model.mean_latent_forecast(mean[nx:], N)
        else:
            W = np.broadcast_to(info["latent_force"], (N, self.system.nw))
        sol = self.solve(x_hat, W, info["latent_force_std"])
        self._x_hat = x_hat
        u, fallback = self._choose_action(sol)
        self._u_prev = u
        info.update(self._solve_info(sol, t_est, fallback, x_hat, W))
        info["branch_inputs"] = sol.extra["branch_inputs"]
        self.last_info = info
        return u

    # ------------------------------------------------------------------ internals

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        """Estimator step (:class:`~controllers.agents.estimation.EstimatorLoop`)."""
        return self._estimator_step(y)[0]


def make_dompc_agent(config: Any) -> DoMpcAgent:
    """An evaluation factory: the ``dompc`` agent of a resolved config (``factory(config)``)."""
    return DoMpcAgent(
        config.make_model(), config.make_cost(), config.agents, config.measurement_std
    )


make_dompc_agent.name = "dompc"  # the table's agent column


def make_dompc_constant_agent(config: Any) -> DoMpcAgent:
    """The ``dompc`` agent with the force held constant over the horizon (``force="constant"``)."""
    return DoMpcAgent(
        config.make_model(),
        config.make_cost(),
        config.agents,
        config.measurement_std,
        force="constant",
    )


make_dompc_constant_agent.name = "dompc_constant"


__all__ = [
    "APPROXIMATIONS",
    "FORCE_MODELS",
    "MISSING_DO_MPC",
    "DoMpcAgent",
    "do_mpc_installed",
    "import_do_mpc",
    "make_dompc_agent",
    "make_dompc_constant_agent",
]
