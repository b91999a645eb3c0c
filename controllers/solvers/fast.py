"""Fast default solver of the scenario MPC problem: a condensed exact-Hessian SQP.

:class:`FastScenarioSolver` minimises exactly :func:`controllers.problem.objective`
(the scenario-averaged quadratic cost plus the exact L1 penalty on the ``6 N`` shared
slacks) over the shared inputs ``u`` ``(N, 2)``, like the IPOPT reference
(:class:`controllers.solvers.ipopt.IpoptScenarioSolver`), but exploits the structure of the problem:

* **Condensing.** The latent forces ``W`` do not depend on ``u``, so every scenario's
  states are explicit functions of the ``2 N`` inputs. Rollouts, forward sensitivities
  ``dx_k / du`` and adjoints are vectorised over scenarios in NumPy (a Python loop over
  the ``N`` steps only).
* **Exact Hessian.** The Hessian of the Lagrangian with respect to ``u`` is assembled from
  the forward sensitivities and one adjoint sweep (second-order adjoint of the Euler
  recursion), including the curvature of the dynamics and of the track constraints
  weighted by the QP multipliers. When it is indefinite, ``sigma J_A' J_A`` of the
  constraints predicted active is added (which leaves the QP step on that active set
  unchanged), and only if that fails are small eigenvalues raised to a floor. Near a
  regular solution the SQP therefore converges quadratically.
* **Exact speed constraints.** The speed is linear in ``u``:
  ``v_k^(i) = v_0^(i) + dt sum_{j<k} (a_j + W[i, j])``, so at every step only the fastest
  and the slowest scenario matter, whatever ``u`` is: ``2 N`` exact linear rows.
* **Screened position rows with check-and-add.** The track and ``p_x`` rows of the QP
  are limited to the few scenarios closest to the current maximum of each
  ``(kind, step)``. After each QP solve the linearisation of *every* scenario row is
  checked at the QP step; violated rows are added and the QP re-solved. Adding
  constraints that the optimum already satisfies does not change a QP's solution, so the
  accepted step is exactly the step of the full (unscreened) QP.
* **Exact penalty inside the QP.** Each ``(kind, step)`` has one slack variable with cost
  ``slack_penalty``, shared by all its rows, as in the NLP. The QP is dense and small
  (``2 N`` input steps, ``2 N`` speed slacks and one slack per position group in use);
  its rows sit in fixed slots (one per speed bound and step, a few per position group,
  sorted by value) so that qpOASES' hot start from the previous QP's active set is
  meaningful. It is called through a CasADi ``FunctionBuffer``, which avoids the per-call
  conversion of NumPy arrays (hundreds of microseconds otherwise).
* **Globalisation.** Backtracking Armijo line search on the exact-penalty merit function
  (the objective of :mod:`controllers.problem`, evaluated on all scenarios), with a
  second-order correction against the Maratos effect. It stops when the next Newton step
  is predicted below ``final_step_tol`` (from the last step and its contraction), so a
  warm re-solve of a solved problem takes one iteration.

* **Extra starts.** The problem is not convex (left or right loops near the goal,
  bang-bang steering when the band cannot hold the scenarios). When the plan steers hard,
  the SQP also starts from the mirrored plan (and, with slack, from straight wheels), drops
  an extra start once its local model cannot beat the best plan or it heads for that same
  plan, and keeps the best.

The result is a KKT point of the full scenario problem: started from a local optimum that
IPOPT found, it stays there up to solver tolerances. From other starts the two may end in
different local optima; the extra starts make the fast solver's the lower one on most
problems where they differ (see ``lfm-benchmark``). Problems dominated by the
penalty (scenarios spread so widely that the track band cannot hold them: several
position slacks positive at once) are degenerate: there convergence is only linear and
may take tens of iterations (IPOPT needs many too).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem

N_KINDS = 6  # constraint kinds per step: track upper/lower, x lower/upper, speed lower/upper
N_POSITION_KINDS = 4  # the first four kinds depend on the position only
QP_SOLVERS = ("qpoases",)
RESTARTS = ("mirror", "straight")
# Sign of d g / d(track-upper or p_x) of the position kinds: track lower is -(track upper),
# x lower is -p_x, x upper is +p_x.
_POSITION_SIGN = np.array([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class FastSolverOptions:
    """Settings of :class:`FastScenarioSolver`; the defaults suit the paper's problem."""

    max_iter: int = 50  # SQP iterations per start
    tol: float = 1e-10  # relative predicted decrease below which a failed line search is OK
    step_tol: float = 1e-8  # [m/s^2, rad] input step that counts as converged
    final_step_tol: float = 1e-6  # [m/s^2, rad] predicted next step that counts as converged
    screen_margin: float = 0.5  # [m] rows within this of activity enter the QP at once
    screen_rows: int = 4  # QP row slots per (position kind, step); grows when needed
    add_tol: float = 1e-9  # [m] linearised violation of a missing row that adds it
    max_qp_rounds: int = 20  # check-and-add rounds per SQP iteration
    armijo: float = 1e-4  # sufficient-decrease fraction of the predicted decrease
    backtrack: float = 0.5  # step shrink factor of the line search
    min_step: float = 1e-8  # smallest line-search step before giving up
    hessian_floor: float = 1e-3  # smallest Hessian eigenvalue [per (m/s^2)^2 or rad^2]
    slack_regularisation: float = 1e-8  # quadratic weight on the QP slacks (strict convexity)
    second_order_correction: bool = True  # against the Maratos effect
    damping_init: float = 1.0  # first Levenberg-Marquardt damping after heavy backtracking
    damping_threshold: float = 0.1  # line-search step below which the damping grows
    qp_solver: str = "qpoases"  # one of QP_SOLVERS
    # Extra starts against local optima (see FastScenarioSolver.solve): any of RESTARTS.
    restarts: tuple[str, ...] = ("mirror", "straight")
    restart_threshold: float = 0.35  # fraction of the steering bound that calls for them
    restart_probe: int = 1  # SQP iterations an extra start runs before it may be given up
    restart_optimism: float = 2.0  # multiple of the model's predicted decrease it may still get
    restart_margin: float = 0.0  # relative margin added to the merit an extra start must beat
    restart_same_tol: float = 0.05  # [m/s^2, rad] an extra start this close to the best: same

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise ValueError(
                    f"FastSolverOptions.{name}={getattr(self, name)!r}: must be {allowed}"
                )

        for name in ("max_iter", "screen_rows", "max_qp_rounds", "restart_probe"):
            value = getattr(self, name)
            check(name, isinstance(value, int) and value >= 1, "an int >= 1")
        for name in (
            "tol",
            "step_tol",
            "final_step_tol",
            "screen_margin",
            "add_tol",
            "min_step",
            "hessian_floor",
            "slack_regularisation",
            "damping_init",
            "restart_optimism",
            "restart_same_tol",
        ):
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and math.isfinite(value) and value > 0
            check(name, ok, "finite and > 0")
        check("armijo", 0 < self.armijo < 0.5, "in (0, 0.5)")
        check("backtrack", 0 < self.backtrack < 1, "in (0, 1)")
        check("damping_threshold", 0 < self.damping_threshold <= 1, "in (0, 1]")
        check("qp_solver", self.qp_solver in QP_SOLVERS, f"one of {QP_SOLVERS}")
        if isinstance(self.restarts, list):
            object.__setattr__(self, "restarts", tuple(self.restarts))
        ok = isinstance(self.restarts, tuple) and all(r in RESTARTS for r in self.restarts)
        check("restarts", ok, f"a tuple of names from {RESTARTS}")
        margin = self.restart_margin
        ok = isinstance(margin, (int, float)) and math.isfinite(margin) and margin >= 0
        check("restart_margin", ok, "finite and >= 0")
        value = self.restart_threshold
        ok = isinstance(value, (int, float)) and 0 < value <= 1
        check("restart_threshold", ok, "in (0, 1]")


@dataclass
class _Rollout:
    """States, constraint values and merit of all scenarios under one input sequence.

    States are stored per component, ``X[m]`` ``(N+1, Ns)`` for ``m`` in
    ``(p_x, p_y, v, psi)``.
    """

    u: np.ndarray  # (2N,) flattened inputs [a_0, delta_0, a_1, ...]
    X: np.ndarray  # (4, N+1, Ns)
    cos_th: np.ndarray  # (N, Ns) cos(psi_k + alpha_k)
    sin_th: np.ndarray  # (N, Ns)
    g_pos: np.ndarray  # (4, N, Ns) position constraint values of steps 1..N [m]
    g_speed: np.ndarray  # (2, N) speed-lower/upper values of the extreme scenarios [m/s]
    slack: float  # sum of the minimal slacks
    merit: float  # exact-penalty objective (inf if not finite)


@dataclass
class _Linearisation:
    """First-order information at a rollout, w.r.t. the flattened inputs ``u`` ``(2N,)``."""

    ro: _Rollout
    S: np.ndarray  # (3, N, Ns, 2N) d(p_x, p_y, psi)_k / du at steps 1..N
    s_v: np.ndarray  # (N+1, 2N) d v_k / du, the same for every scenario
    slope: np.ndarray  # (N, Ns) track centre-line slope at p_x of steps 1..N
    grad: np.ndarray  # (2N,) gradient of the cost


@dataclass
class _QPStep:
    """Solution of one SQP subproblem."""

    d: np.ndarray  # (2N,) input step [m/s^2, rad]
    slack_sum: float  # sum of the QP's slacks
    pos: np.ndarray  # (r, 3) position rows (kind, step, scenario) in the QP
    lam: np.ndarray  # (r,) their multipliers
    qp: _SlotQP  # the QP object (for a second-order correction)
    row: np.ndarray  # (r,) their row slots in it
    s_pos: np.ndarray  # (4, N) slack of each position (kind, step) group
    s_speed: np.ndarray  # (2N,) slack of each speed row, ordered (step, lower/upper)
    lam_speed: np.ndarray  # (2N,) multipliers of the speed rows


class _SlotQP:
    """The SQP's QP ``min 1/2 z'Hz + g'z  s.t.  A z <= uba, lbx <= z <= ubx`` in fixed slots.

    ``z = [d (2N), s_speed (2N), s_pos (P)]``: the input step, one slack per (step, speed
    bound), and ``P`` slack slots for the position (kind, step) groups that have rows.
    Rows ``[J_r, -e_slack] z <= -g_r``: first one per (step, speed bound), then ``K``
    row slots per position slack slot, filled by decreasing value. Unused slots are zero
    rows with ``uba = +inf`` (their slack stays at zero). Only the Jacobian part of ``A``
    changes between calls, so qpOASES can hot-start from the previous active set. The
    CasADi conic is evaluated through a ``FunctionBuffer`` on persistent NumPy arrays.
    """

    def __init__(
        self,
        horizon: int,
        groups: int,
        slots: int,
        solver: str,
        slack_penalty: float,
        slack_reg: float,
    ) -> None:
        n = horizon
        self.horizon, self.groups, self.slots = n, groups, slots
        self.n_u, self.n_speed = 2 * n, 2 * n
        self.n_var = 4 * n + groups
        self.capacity = self.n_speed + groups * slots
        nv, cap, nu = self.n_var, self.capacity, self.n_u
        opts: dict[str, Any] = {"error_on_fail": False}
        if solver == "qpoases":
            opts["printLevel"] = "none"
        with _silenced_stdout():  # qpOASES prints a banner whenever a memory is created
            self._conic = ca.conic(
                "fast_sqp_qp",
                solver,
                {"h": ca.Sparsity.dense(nv, nv), "a": ca.Sparsity.dense(cap, nv)},
                opts,
            )
            self._buffer, self._evaluate = self._conic.buffer()
        # Dense inputs are column-major nonzeros; H is symmetric, A is viewed transposed.
        self._h = np.zeros(nv * nv)
        self.H = self._h.reshape(nv, nv)
        self.H[np.arange(nu, nv), np.arange(nu, nv)] = slack_reg
        self._a = np.zeros(cap * nv)
        self.A = self._a.reshape(nv, cap).T
        self.A[np.arange(self.n_speed), nu + np.arange(self.n_speed)] = -1.0
        for q in range(groups):
            first = self.n_speed + q * slots
            self.A[first : first + slots, nu + self.n_speed + q] = -1.0
        self.g = np.zeros(nv)
        self.g[nu:] = slack_penalty
        self.lba = np.full(cap, -np.inf)
        self.uba = np.full(cap, np.inf)
        self.lbx = np.zeros(nv)
        self.ubx = np.full(nv, np.inf)
        self.x = np.zeros(nv)
        self.lam_a = np.zeros(cap)
        outputs = {"x": self.x, "cost": np.zeros(1), "lam_a": self.lam_a, "lam_x": np.zeros(nv)}
        inputs = {
            "h": self._h,
            "g": self.g,
            "a": self._a,
            "lba": self.lba,
            "uba": self.uba,
            "lbx": self.lbx,
            "ubx": self.ubx,
        }
        self._keep = []  # the buffer holds raw pointers: keep every array alive
        for i, name in enumerate(self._conic.name_in()):
            arr = inputs.get(name)
            if arr is None:
                arr = np.zeros(self._conic.nnz_in(i))
            self._keep.append(arr)
            self._buffer.set_arg(i, memoryview(arr))
        for i, name in enumerate(self._conic.name_out()):
            arr = outputs.get(name, np.zeros(self._conic.nnz_out(i)))
            self._keep.append(arr)
            self._buffer.set_res(i, memoryview(arr))

    @staticmethod
    def layout(pos: np.ndarray, values: np.ndarray, horizon: int) -> tuple[np.ndarray, ...]:
        """Group slot and rank of each position row ``(kind, step, scenario)``.

        Returns ``(groups, slot_group, rank)``: the sorted group ids ``kind * N + step`` in
        use, the slack slot of each row and its rank by decreasing value in its group.
        """
        group = pos[:, 0] * horizon + pos[:, 1]
        groups, slot_group = np.unique(group, return_inverse=True)
        order = np.lexsort((-values, group))
        g_sorted = group[order]
        rank = np.empty(group.size, dtype=int)
        rank[order] = np.arange(g_sorted.size) - np.searchsorted(g_sorted, g_sorted, side="left")
        return groups, slot_group, rank

    def set_problem(
        self,
        H: np.ndarray,
        grad: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        a_speed: np.ndarray,
        g_speed: np.ndarray,
    ) -> None:
        """Hessian, gradient, step bounds and the speed rows (all ``2 N`` of them)."""
        nu, ns = self.n_u, self.n_speed
        self.H[:nu, :nu] = H
        self.g[:nu] = grad
        self.lbx[:nu] = lower
        self.ubx[:nu] = upper
        self.A[:ns, :nu] = a_speed
        self.uba[:ns] = -g_speed

    def set_position_rows(self, row: np.ndarray, a_pos: np.ndarray, g_pos: np.ndarray) -> None:
        """Fill the given row slots; every other position slot becomes an inactive zero row."""
        nu, ns = self.n_u, self.n_speed
        self.A[ns:, :nu] = 0.0
        self.uba[ns:] = np.inf
        self.A[row, :nu] = a_pos
        self.uba[row] = -g_pos

    def set_position_bounds(self, row: np.ndarray, g_pos: np.ndarray) -> None:
        """Change only the constant terms of the given rows (second-order correction)."""
        self.uba[row] = -g_pos

    def solve(self) -> tuple[np.ndarray, np.ndarray, bool]:
        """Solve from the previous active set: ``(z, row multipliers >= 0, success)``."""
        self._evaluate()
        ok = self._buffer.ret() == 0 and bool(np.all(np.isfinite(self.x)))
        return self.x.copy(), np.maximum(self.lam_a, 0.0), ok


@contextlib.contextmanager
def _silenced_stdout() -> Iterator[None]:
    """Send the process' C-level stdout to /dev/null (for chatty native libraries)."""
    sys.stdout.flush()
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # no real stdout (e.g. some notebooks)
        yield
        return
    saved = os.dup(fd)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), fd)
            yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


class FastScenarioSolver:
    """Condensed exact-Hessian SQP solver of a :class:`ScenarioProblem`.

    Same interface and result semantics as :class:`controllers.solvers.ipopt.IpoptScenarioSolver`:
    build once, call :meth:`solve` at every step; the previous solution shifted by one
    step is the default initial guess.

    Args:
        problem: the problem data (horizon, scenario count, weights, bounds, track).
        **options: fields of :class:`FastSolverOptions` (e.g. ``max_iter=30``).

    Raises:
        ValueError: on an unknown or out-of-range option.
    """

    def __init__(self, problem: ScenarioProblem, **options: Any) -> None:
        unknown = set(options) - set(FastSolverOptions.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown FastScenarioSolver options: {sorted(unknown)}")
        self.problem = problem
        self.options = FastSolverOptions(**options)
        n = problem.horizon
        self._n_u = 2 * n
        self._lower = np.tile(problem.input_lower, n)
        self._upper = np.tile(problem.input_upper, n)
        self._q = np.asarray(problem.Q, dtype=float)
        self._r = np.tile(np.asarray(problem.R, dtype=float), n)
        self._goal = np.asarray(problem.x_goal, dtype=float)
        # Weight of each state component at steps 1..N (the x_0 term is a constant).
        qf = np.asarray(problem.Qf, dtype=float)
        self._w_state = np.vstack([np.tile(self._q, (n - 1, 1)), qf[None]])  # (N, 4)
        # d v_k / d u: the accelerations of the earlier steps times dt, for every scenario.
        steps = np.arange(n + 1)
        self._strictly_later = (steps[:, None] > np.arange(n)[None, :]).astype(float)  # (N+1, N)
        self._s_v = np.zeros((n + 1, 2 * n))
        self._s_v[:, 0::2] = problem.dt * self._strictly_later
        self._qps: dict[tuple[int, int], _SlotQP] = {}
        self._prev_u: np.ndarray | None = None

    # ------------------------------------------------------------------ public API

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from zero inputs."""
        self._prev_u = None

    def __getstate__(self) -> dict[str, Any]:
        # The QP objects hold raw buffers of a CasADi function: rebuild them after
        # unpickling (e.g. in a worker process) instead of pickling them.
        state = self.__dict__.copy()
        state["_qps"] = {}
        return state

    def solve(
        self, x0: np.ndarray, W: np.ndarray, u_guess: np.ndarray | None = None
    ) -> MPCSolution:
        """Solve the scenario problem for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state ``[p_x, p_y, v, psi]`` [m, m, m/s, rad], shape ``(4,)`` or
                ``(Ns, 4)``.
            W: latent force [m/s^2] of each scenario and step, shape ``(Ns, N)``.
            u_guess: initial input sequence ``(N, 2)`` [m/s^2, rad]; by default the
                previous solution shifted by one step (zeros on the first solve).

        Returns:
            The solution: ``u`` inside the input bounds; ``objective``, ``slack`` and
            ``predicted`` those of :mod:`controllers.problem` (``objective``,
            ``minimal_slack`` summed, ``rollout``) for ``u``, computed by the solver's own
            vectorised rollout (equal up to rounding); ``solve_time`` the wall time of the
            whole call; ``extra`` counts QP solves, QP rows, merit evaluations and
            second-order corrections, and ``extra["restarts"]`` maps each extra start
            tried to ``"kept"`` or the status it ended with; ``iterations`` counts the
            iterations of every start. A solve that does not converge does not raise: it
            returns the best iterate (the merit decreases monotonically) with
            ``success=False``.

        Extra starts: the problem is not convex. Near the goal the plan turns a loop
        (the goal speed is not zero), and left and right loops are separate local optima;
        when a disturbance beyond the actuator limits pushes the car off the band, the
        steering becomes bang-bang with many local optima. So when the first plan steers
        beyond ``restart_threshold`` of the steering bound, the SQP also starts from that
        plan with its steering negated (``"mirror"``) and, if the plan needs slack, with
        the wheels straight (``"straight"``). After ``restart_probe`` iterations an extra
        start is abandoned as soon as its merit plus ``restart_optimism`` times the
        decrease its local model predicts still lies above the best plan so far; the plan
        with the lowest objective is returned (a failed start never replaces a successful
        one); an extra start that comes within ``restart_same_tol`` of the best plan is
        stopped too (it is heading for the same optimum).

        Raises:
            ValueError: on wrongly shaped or non-finite ``x0``, ``W`` or ``u_guess``.
        """
        t_start = time.perf_counter()
        problem, n = self.problem, self.problem.horizon
        x0, W = problem.check_data(x0, W)
        if u_guess is not None:
            u_guess = np.asarray(u_guess, dtype=float)
            if u_guess.shape != (n, 2) or not np.all(np.isfinite(u_guess)):
                raise ValueError(
                    f"u_guess has shape {u_guess.shape} or non-finite entries; "
                    f"expected finite (horizon, 2) = {(n, 2)}"
                )
            u0 = u_guess.ravel()
        elif self._prev_u is not None:
            u0 = np.concatenate([self._prev_u[1:], self._prev_u[-1:]]).ravel()
        else:
            u0 = np.zeros(2 * n)
        u0 = np.clip(u0, self._lower, self._upper)

        x0 = np.ascontiguousarray(x0)
        ro, status, success, iterations, extra = self._sqp(x0, W, u0)
        extra["restarts"] = {}
        for name in self._restart_names(ro):
            # The problem is not convex: try another start, abandon it once it cannot
            # plausibly beat the best plan so far, and keep the better plan.
            u_alt = self._restart_guess(name, ro.u)
            bar = ro.merit + self.options.restart_margin * abs(ro.merit)
            ro2, status2, success2, iterations2, extra2 = self._sqp(x0, W, u_alt, bar, ro.u)
            iterations += iterations2
            for key in ("qp_solves", "soc_steps", "merit_evals"):
                extra[key] += extra2[key]
            extra["qp_rows"] = max(extra["qp_rows"], extra2["qp_rows"])
            better = ro2.merit < ro.merit - 1e-12 * (1.0 + abs(ro.merit))
            keep = better and (success2 or not success)
            extra["restarts"][name] = "kept" if keep else status2.lower()
            if keep:
                ro, status, success = ro2, status2, success2

        # The iterates stay inside the input bounds (clipped steps), and the rollout of the
        # last one gives the prediction, slack and objective (those of mpc_problem, up to
        # rounding).
        u = ro.u.reshape(n, 2).copy()
        self._prev_u = u.copy()
        return MPCSolution(
            u=u,
            objective=ro.merit,
            slack=ro.slack,
            status=status,
            success=success,
            solve_time=time.perf_counter() - t_start,
            iterations=iterations,
            predicted=np.ascontiguousarray(ro.X.transpose(2, 1, 0)),
            extra=extra,
        )

    def _restart_names(self, ro: _Rollout) -> list[str]:
        """The extra starts worth trying after a first plan ``ro`` (see :meth:`solve`)."""
        opt = self.options
        delta = ro.u[1::2]
        frac = opt.restart_threshold - 1e-6
        lower, upper = frac * self._lower[1::2], frac * self._upper[1::2]
        hard = bool(np.any((delta <= lower) | (delta >= upper)))
        names = []
        if "mirror" in opt.restarts and hard:
            names.append("mirror")
        if "straight" in opt.restarts and hard and ro.slack > opt.add_tol:
            names.append("straight")
        return names

    def _restart_guess(self, name: str, u: np.ndarray) -> np.ndarray:
        """Initial guess of the extra start ``name`` from the plan ``u`` ``(2N,)``."""
        guess = u.copy()
        if name == "mirror":  # the same manoeuvre, turning the other way
            guess[1::2] *= -1.0
        else:  # "straight": the same accelerations, wheels straight
            guess[1::2] = 0.0
        return np.clip(guess, self._lower, self._upper)

    # ------------------------------------------------------------------ model pieces

    def _steering_terms(self, u: np.ndarray) -> tuple[np.ndarray, ...]:
        """Slip ``alpha(delta)``, yaw gain ``c(delta) = sin(alpha) / (l/2)`` and derivatives.

        All ``(N,)``; ``alpha = atan(0.5 tan(delta))`` is smooth for ``|delta| < pi/2``.
        """
        delta = u[1::2]
        t = np.tan(delta)
        den = 1.0 + 0.25 * t * t
        alpha = np.arctan(0.5 * t)
        alpha_p = 0.5 * (1.0 + t * t) / den
        alpha_pp = 0.75 * t * (1.0 + t * t) / (den * den)
        gain = 2.0 / self.problem.vehicle_length
        sa, ca_ = np.sin(alpha), np.cos(alpha)
        c = gain * sa
        c_p = gain * ca_ * alpha_p
        c_pp = gain * (ca_ * alpha_pp - sa * alpha_p * alpha_p)
        return alpha, alpha_p, alpha_pp, c, c_p, c_pp

    def _evaluate(self, x0: np.ndarray, W: np.ndarray, u: np.ndarray, cost0: float) -> _Rollout:
        """Rollout of all scenarios and the exact-penalty merit (= ``mpc_problem.objective``).

        ``cost0`` is the constant stage cost of ``x_0``. The Euler steps are those of
        :func:`lfm_env.vehicle.euler_step` (the same up to rounding).
        """
        p = self.problem
        n, ns, dt = p.horizon, x0.shape[0], p.dt
        alpha, _, _, c, _, _ = self._steering_terms(u)
        X = np.empty((4, n + 1, ns))
        px, py, v, psi = X
        cos_th = np.empty((n, ns))
        sin_th = np.empty((n, ns))
        X[:, 0] = x0.T
        # The speed does not depend on the heading: one cumulative sum for all steps.
        np.cumsum(dt * (u[0::2, None] + W.T), axis=0, out=v[1:])
        v[1:] += v[0]
        dtv = dt * v[:n]
        for k in range(n):
            th = psi[k] + alpha[k]
            np.cos(th, out=cos_th[k])
            np.sin(th, out=sin_th[k])
            np.multiply(dtv[k], cos_th[k], out=px[k + 1])
            px[k + 1] += px[k]
            np.multiply(dtv[k], sin_th[k], out=py[k + 1])
            py[k + 1] += py[k]
            np.multiply(dtv[k], c[k], out=psi[k + 1])
            psi[k + 1] += psi[k]

        track = p.track
        g_pos = np.empty((N_POSITION_KINDS, n, ns))
        np.subtract(
            py[1:], track.amplitude * np.sin(track.pulsation * px[1:] + track.phase), g_pos[0]
        )
        np.negative(g_pos[0], out=g_pos[1])
        g_pos[:2] -= track.half_width
        np.subtract(track.x_min, px[1:], out=g_pos[2])
        np.subtract(px[1:], track.x_max, out=g_pos[3])
        g_speed = np.stack([p.speed_min - v[1:].min(axis=1), v[1:].max(axis=1) - p.speed_max])
        slack = float(np.maximum(g_pos.max(axis=2), 0.0).sum() + np.maximum(g_speed, 0.0).sum())

        e = X[:, 1:] - self._goal[:, None, None]
        cost = cost0 + float(np.einsum("mk,mki,mki->", self._w_state.T, e, e)) / ns
        cost += float(self._r @ (u * u))
        merit = cost + p.slack_penalty * slack
        return _Rollout(
            u=u,
            X=X,
            cos_th=cos_th,
            sin_th=sin_th,
            g_pos=g_pos,
            g_speed=g_speed,
            slack=slack,
            merit=merit if math.isfinite(merit) else math.inf,
        )

    def _linearise(self, ro: _Rollout) -> _Linearisation:
        """Forward sensitivities, cost gradient and track slope at a rollout."""
        p = self.problem
        n, nu, dt = p.horizon, self._n_u, p.dt
        ns = ro.X.shape[2]
        px, py, v, psi = ro.X
        _, alpha_p, _, c, c_p, _ = self._steering_terms(ro.u)
        s_v = self._s_v

        # --- forward sensitivities d x_k / d u, vectorised over steps and scenarios ---
        S = np.empty((3, n, ns, nu))
        # Heading: psi_k = psi_0 + sum_{j<k} dt v_j c(delta_j). Its acceleration columns are
        # the same for every scenario; its steering column j is dt v_j c'(delta_j) (j < k).
        psi_a = np.cumsum((dt * c)[:, None] * s_v[:n, 0::2], axis=0)  # steps 1..N
        S[2, :, :, 0::2] = psi_a[:, None, :]
        S[2, :, :, 1::2] = self._strictly_later[1:, None, :] * ((dt * c_p)[:, None] * v[:n]).T
        # theta_k = psi_k + alpha(delta_k) for k = 0..N-1; psi_0 is fixed.
        heading = np.empty((n, ns, nu))
        heading[0] = 0.0
        heading[1:] = S[2, : n - 1]
        heading[np.arange(n), :, 2 * np.arange(n) + 1] = alpha_p[:, None]
        # p_x and p_y add dt v_k (cos, sin)(theta_k) per step: increments, then a running sum.
        dtv = dt * v[:n]
        np.multiply((-dtv * ro.sin_th)[:, :, None], heading, out=S[0])
        S[0] += (dt * ro.cos_th)[:, :, None] * s_v[:n, None, :]
        np.multiply((dtv * ro.cos_th)[:, :, None], heading, out=S[1])
        S[1] += (dt * ro.sin_th)[:, :, None] * s_v[:n, None, :]
        for k in range(1, n):
            S[:2, k] += S[:2, k - 1]

        # --- cost gradient: d cost / d x_k = (2 / Ns) W_k (x_k - x_g) ---
        wq = (2.0 / ns) * self._w_state
        g = self._goal
        residual = np.empty((3, n, ns))
        for row, m in enumerate((0, 1, 3)):
            np.multiply(wq[:, m : m + 1], ro.X[m, 1:] - g[m], out=residual[row])
        grad = 2.0 * self._r * ro.u + S.reshape(-1, nu).T @ residual.ravel()
        grad += s_v[1:].T @ (wq[:, 2] * (v[1:] - g[2]).sum(axis=1))

        track = p.track
        slope = track.amplitude * track.pulsation * np.cos(track.pulsation * px[1:] + track.phase)
        return _Linearisation(ro=ro, S=S, s_v=s_v, slope=slope, grad=grad)

    def _hessian(self, lin: _Linearisation, mu: np.ndarray) -> np.ndarray:
        """Exact Hessian of the Lagrangian w.r.t. ``u`` ``(2N, 2N)``.

        ``mu`` ``(4, N, Ns)`` are the multipliers of the position rows (zero for rows that
        are not in the QP). The speed rows are linear in ``u`` and add no curvature.
        Second-order adjoint: ``H = 2R + sum_k S_k' (d2 l_k) S_k + sum_k Z_k' M_k Z_k``
        with ``M_k`` the Hessian of ``lambda_{k+1}' F(x_k, u_k)`` in ``(v_k, psi_k, delta_k)``.
        """
        p = self.problem
        n, nu, dt = p.horizon, self._n_u, p.dt
        px, py, v, psi = lin.ro.X
        cos_th, sin_th = lin.ro.cos_th, lin.ro.sin_th
        ns = px.shape[1]
        _, alpha_p, alpha_pp, _, c_p, c_pp = self._steering_terms(lin.ro.u)
        wq = (2.0 / ns) * self._w_state
        g = self._goal

        # --- adjoint sweep: lambda_k = d l_k / d x_k + A_k' lambda_{k+1} ---
        # l_k is the stage cost plus the multiplier-weighted position constraints. Speed
        # adjoints never reach the position/heading adjoints nor the curvature, so only
        # (p_x, p_y, psi) are propagated.
        gpx = wq[:, 0:1] * (px[1:] - g[0])
        gpy = wq[:, 1:2] * (py[1:] - g[1])
        gpsi = wq[:, 3:4] * (psi[1:] - g[3])
        weight = np.empty((3, n, ns))  # curvature of l_k in (p_x, p_y, psi)
        weight[0] = wq[:, 0:1]
        weight[1] = wq[:, 1:2]
        weight[2] = wq[:, 3:4]
        if mu.any():
            track = p.track
            amp, om = track.amplitude, track.pulsation
            arg = om * px[1:] + track.phase
            mu_track = mu[0] - mu[1]  # track-upper minus track-lower multipliers
            gpx += mu[3] - mu[2] - (amp * om) * mu_track * np.cos(arg)
            gpy += mu_track
            weight[0] += (amp * om * om) * mu_track * np.sin(arg)
        # p_x and p_y enter linearly: their adjoints are sums of the later gradients.
        lam_x = np.cumsum(gpx[::-1], axis=0)[::-1]  # lam_x[k] = lambda_{k+1}
        lam_y = np.cumsum(gpy[::-1], axis=0)[::-1]
        proj = lam_x * cos_th + lam_y * sin_th  # lambda_{k+1} along theta_k, (N, Ns)
        proj_p = lam_y * cos_th - lam_x * sin_th  # its derivative in theta
        dtv = dt * v[:n]
        lam_psi = np.empty((n, ns))
        lam_psi[n - 1] = gpsi[n - 1]
        for k in range(n - 1, 0, -1):
            lam_psi[k - 1] = gpsi[k - 1] + lam_psi[k] + dtv[k] * proj_p[k]
        # Hessian M_k of lambda_{k+1}' F(x_k, u_k) in (v_k, psi_k, delta_k), per scenario:
        # M_vp = dt P', M_vd = dt (P' a' + l_psi c'), M_pp = -dt v P, M_pd = M_pp a',
        # M_dd = dt v (P' a'' - P a'^2 + l_psi c''), with P, P' = proj, proj_p.
        m_pp = -dtv * proj
        sums = np.stack([proj_p.sum(axis=1), lam_psi.sum(axis=1)])
        v_sums = np.einsum("ki,ski->sk", dtv, np.stack([proj_p, proj, lam_psi]))
        m_vd_sum = dt * (alpha_p * sums[0] + c_p * sums[1])
        m_dd_sum = alpha_pp * v_sums[0] - alpha_p * alpha_p * v_sums[1] + c_pp * v_sums[2]

        # --- Gauss-Newton part plus the state curvature of l_k and of the heading ---
        weight[2, : n - 1] += m_pp[1:]  # S_0 = 0, so m_pp[0] never contributes
        S = lin.S.reshape(-1, nu)
        H = S.T @ (weight.reshape(-1, 1) * S)
        H[np.diag_indices(nu)] += 2.0 * self._r
        H += lin.s_v[1:].T @ ((2.0 * self._w_state[:, 2:3]) * lin.s_v[1:])

        # --- cross terms of the dynamics curvature (psi_0 is fixed: step 0 has none) ---
        s_psi = lin.S[2, : n - 1]  # d psi_k / du, k = 1..N-1
        cross_vp, cross_pp = np.einsum("kin,ski->skn", s_psi, np.stack([proj_p[1:], m_pp[1:]]))
        cross = lin.s_v[1:n].T @ (dt * cross_vp)
        cross_d = m_vd_sum[:, None] * lin.s_v[:n]
        cross_d[1:] += alpha_p[1:, None] * cross_pp
        H += cross + cross.T
        H[:, 1::2] += cross_d.T
        H[1::2, :] += cross_d
        idx = np.arange(1, nu, 2)
        H[idx, idx] += m_dd_sum
        return H

    def _convexify(
        self,
        H: np.ndarray,
        lin: _Linearisation,
        active_pos: np.ndarray,
        active_speed: np.ndarray,
        active_bounds: np.ndarray,
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """A positive definite QP Hessian that leaves the Newton step unchanged if it can.

        The Lagrangian's Hessian is often indefinite although it is positive definite on
        the null space of the active constraints (second-order sufficiency). Adding
        ``sigma J_A' J_A`` for the constraints ``A`` predicted active (hard-active rows and
        input bounds of the previous QP) then makes it positive definite without changing
        the QP's solution on that active set: only its multipliers shift, by
        ``sigma J_A d``. If that is not enough, eigenvalues below ``hessian_floor`` are
        raised to it (clipping rather than mirroring keeps directions of negative
        curvature cheap for the QP; the line search decides how far to go).

        Returns:
            ``(H_qp, sigma, J_pos)`` with ``J_pos`` the Jacobian rows of ``active_pos``
            (``sigma = 0`` when no augmentation was used).
        """
        floor = self.options.hessian_floor
        w, V = np.linalg.eigh(H)
        j_pos = np.empty((0, self._n_u))
        if w[0] >= floor:
            return H, 0.0, j_pos
        rows = []
        if active_pos.shape[0]:
            j_pos = self._position_rows(lin, active_pos)[0]
            rows.append(j_pos)
        if active_speed.size:
            rows.append(lin.s_v[1:][active_speed // 2])
        if active_bounds.size:
            rows.append(np.eye(self._n_u)[active_bounds])
        if rows:
            J = np.vstack(rows)
            G = J.T @ J
            sigma = float(np.max(np.abs(w))) / max(float(np.max(np.diag(G))), 1e-12)
            for _ in range(4):
                H_aug = H + sigma * G
                w_aug, V_aug = np.linalg.eigh(H_aug)
                if w_aug[0] >= floor:
                    return H_aug, sigma, j_pos
                sigma *= 10.0
        return (V * np.maximum(w, floor)) @ V.T, 0.0, j_pos

    # ------------------------------------------------------------------ QP subproblem

    def _qp(self, groups: int, slots: int) -> _SlotQP:
        """The cached QP with room for ``groups`` position groups of ``slots`` rows each.

        Sizes are rounded up to powers of two, so a few QP objects serve every solve and
        each keeps its own hot-start information.
        """
        n = self.problem.horizon
        groups = min(max(4, 1 << (groups - 1).bit_length()), N_POSITION_KINDS * n)
        base = self.options.screen_rows
        while base < slots:
            base *= 2
        key = (groups, base)
        qp = self._qps.get(key)
        if qp is None:
            p, opt = self.problem, self.options
            qp = _SlotQP(n, groups, base, opt.qp_solver, p.slack_penalty, opt.slack_regularisation)
            self._qps[key] = qp
        return qp

    def _screen(self, ro: _Rollout) -> np.ndarray:
        """Initial position rows ``(r, 3)`` of ``(kind, step index, scenario)``.

        In every (kind, step) group whose largest value lies within ``screen_margin`` of
        activity: the ``screen_rows`` largest values within that margin, and the scenarios
        that are extreme in the group's value and in progress ``p_x``. Scenarios differ
        mostly in how far they get along similar paths, so a step that turns the vehicle
        can make the other end of that family the worst one.
        """
        opt = self.options
        n = ro.g_pos.shape[1]
        G = ro.g_pos.reshape(N_POSITION_KINDS * n, -1)
        ns = G.shape[1]
        # Only groups whose largest value is within the margin contribute: select them
        # first (usually a few of the 4 N), then rank within those alone.
        active = np.nonzero(G.max(axis=1) >= -opt.screen_margin)[0]
        if active.size == 0:
            return np.empty((0, 3), dtype=int)
        Ga = G[active]
        keep = min(opt.screen_rows, ns)
        top = np.argpartition(Ga, ns - keep, axis=1)[:, ns - keep :]
        near = np.take_along_axis(Ga, top, axis=1) >= -opt.screen_margin
        px = ro.X[0, 1:]
        step = active % n
        extremes = np.column_stack(
            [Ga.argmin(axis=1), px.argmax(axis=1)[step], px.argmin(axis=1)[step]]
        )
        sub, col = np.nonzero(near)
        flat = np.unique(
            np.concatenate(
                [active[sub] * ns + top[sub, col], np.repeat(active, 3) * ns + extremes.ravel()]
            )
        )
        group, scen = np.divmod(flat, ns)
        return np.column_stack([group // n, group % n, scen])

    def _position_rows(self, lin: _Linearisation, pos: np.ndarray) -> tuple[np.ndarray, ...]:
        """Jacobian rows ``(r, 2N)`` and values ``(r,)`` of position rows ``(kind, step, i)``."""
        kind, step, scen = pos[:, 0], pos[:, 1], pos[:, 2]
        d_px = lin.S[0, step, scen]
        d_track = lin.S[1, step, scen] - lin.slope[step, scen, None] * d_px
        jac = np.where((kind < 2)[:, None], d_track, d_px)
        return _POSITION_SIGN[kind, None] * jac, lin.ro.g_pos[kind, step, scen]

    def _missing_rows(
        self, lin: _Linearisation, d: np.ndarray, s_pos: np.ndarray, pos: np.ndarray
    ) -> np.ndarray:
        """Position rows of the full QP violated at the step ``(d, s_pos)``.

        Up to ``screen_rows`` of the worst per (kind, step) group, so that rows that are
        close together enter in one round.
        """
        n = self.problem.horizon
        lin_px = lin.S[0] @ d  # (N, Ns)
        lin_tr = lin.S[1] @ d - lin.slope * lin_px
        viol = lin.ro.g_pos + np.stack([lin_tr, -lin_tr, -lin_px, lin_px])
        viol -= s_pos[:, :, None]
        viol[pos[:, 0], pos[:, 1], pos[:, 2]] = -np.inf
        flat = viol.reshape(N_POSITION_KINDS * n, -1)
        bad = np.nonzero(flat.max(axis=1) > self.options.add_tol)[0]
        if bad.size == 0:
            return np.empty((0, 3), dtype=int)
        flat = flat[bad]
        ns = flat.shape[1]
        keep = min(self.options.screen_rows, ns)
        worst = np.argpartition(flat, ns - keep, axis=1)[:, ns - keep :]
        sub, col = np.nonzero(np.take_along_axis(flat, worst, axis=1) > self.options.add_tol)
        group = bad[sub]
        worst = worst[sub, col]
        return np.column_stack([group // n, group % n, worst])

    def _solve_qp(
        self, lin: _Linearisation, H: np.ndarray, u: np.ndarray, pos: np.ndarray, stats: dict
    ) -> _QPStep | None:
        """Step of the full QP by check-and-add over the position rows; None on failure."""
        n, nu = self.problem.horizon, self._n_u
        a_speed = np.empty((2 * n, nu))
        a_speed[0::2] = -lin.s_v[1:]
        a_speed[1::2] = lin.s_v[1:]
        g_speed = lin.ro.g_speed.T.ravel()
        for _ in range(self.options.max_qp_rounds):
            a_pos, g_pos = self._position_rows(lin, pos)
            groups, slot_group, rank = _SlotQP.layout(pos, g_pos, n)
            qp = self._qp(max(groups.size, 1), int(rank.max(initial=0)) + 1)
            row = qp.n_speed + slot_group * qp.slots + rank
            qp.set_problem(H, lin.grad, self._lower - u, self._upper - u, a_speed, g_speed)
            qp.set_position_rows(row, a_pos, g_pos)
            z, lam_all, ok = qp.solve()
            stats["qp_solves"] += 1
            if not ok:
                return None
            s_pos = np.zeros((N_POSITION_KINDS, n))
            s_pos.reshape(-1)[groups] = z[nu + 2 * n : nu + 2 * n + groups.size]
            missing = self._missing_rows(lin, z[:nu], s_pos, pos)
            if missing.shape[0] == 0:
                break
            pos = np.concatenate([pos, missing])
        stats["qp_rows"] = max(stats["qp_rows"], pos.shape[0])
        return _QPStep(
            d=z[:nu],
            slack_sum=float(z[nu:].sum()),
            pos=pos,
            lam=lam_all[row],
            qp=qp,
            row=row,
            s_pos=s_pos,
            s_speed=z[nu : nu + 2 * n],
            lam_speed=lam_all[: 2 * n],
        )

    def _newton_step(
        self,
        lin: _Linearisation,
        H: np.ndarray,
        u: np.ndarray,
        active_pos: np.ndarray,
        active_speed: np.ndarray,
        damping: float,
        stats: dict,
    ) -> tuple[_QPStep | None, np.ndarray]:
        """QP step with a convexified Hessian, and the position-row multipliers ``(4, N, Ns)``.

        A constraint predicted active whose row the QP leaves slack (or whose multiplier
        turns negative) would have bent the step through the augmentation: it is dropped
        and the QP re-solved. ``damping`` (Levenberg-Marquardt) is added to the Hessian.
        """
        n = self.problem.horizon
        mu = np.zeros((N_POSITION_KINDS, n, lin.ro.X.shape[2]))
        bounds = np.nonzero((u <= self._lower + 1e-12) | (u >= self._upper - 1e-12))[0]
        screened = self._screen(lin.ro)
        for attempt in range(4):
            if attempt == 3:  # give up predicting: plain eigenvalue clipping
                active_pos, active_speed, bounds = active_pos[:0], active_speed[:0], bounds[:0]
            H_qp, sigma, j_pos = self._convexify(H, lin, active_pos, active_speed, bounds)
            if damping > 0.0:
                H_qp = H_qp + damping * np.eye(self._n_u)
            step = self._solve_qp(lin, H_qp, u, screened, stats)
            if step is None:
                return None, mu
            mu[:] = 0.0
            mu[step.pos[:, 0], step.pos[:, 1], step.pos[:, 2]] = step.lam
            if sigma == 0.0:
                return step, mu
            d, tol = step.d, 1e-8
            idx = (active_pos[:, 0], active_pos[:, 1], active_pos[:, 2])
            lin_d = j_pos @ d
            lam = mu[idx] + sigma * lin_d  # multipliers of the un-augmented QP
            keep_pos = (lam >= -tol) & (
                lin.ro.g_pos[idx] + lin_d - step.s_pos[active_pos[:, 0], active_pos[:, 1]] >= -tol
            )
            mu[idx] = np.maximum(lam, 0.0)
            k, b = active_speed // 2, active_speed % 2
            v_d = np.where(b == 1, 1.0, -1.0) * (lin.s_v[k + 1] @ d)
            keep_speed = (step.lam_speed[active_speed] + sigma * v_d >= -tol) & (
                lin.ro.g_speed[b, k] + v_d - step.s_speed[active_speed] >= -tol
            )
            u_new = u[bounds] + d[bounds]
            keep_bounds = (u_new <= self._lower[bounds] + 1e-10) | (
                u_new >= self._upper[bounds] - 1e-10
            )
            if keep_pos.all() and keep_speed.all() and keep_bounds.all():
                return step, mu
            active_pos = active_pos[keep_pos]
            active_speed = active_speed[keep_speed]
            bounds = bounds[keep_bounds]
        return step, mu

    # ------------------------------------------------------------------ SQP

    def _sqp(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u0: np.ndarray,
        abandon_above: float = math.inf,
        rival: np.ndarray | None = None,
    ) -> tuple[_Rollout, str, bool, int, dict[str, Any]]:
        """SQP iterations from ``u0``: ``(final rollout, status, success, iterations, extra)``.

        ``abandon_above``: after ``restart_probe`` iterations, stop with status
        ``"Abandoned"`` when the merit plus ``restart_optimism`` times the directional
        derivative along the QP step (the local model's promise) is above this value.
        ``rival``: the best plan so far ``(2N,)``; stop with status ``"Duplicate"`` when an
        iterate comes within ``restart_same_tol`` of it (the same local optimum again).
        """
        p, opt = self.problem, self.options
        n, nu, rho = p.horizon, self._n_u, p.slack_penalty
        ns = x0.shape[0]
        mu = np.zeros((N_POSITION_KINDS, n, ns))
        active_pos = np.empty((0, 3), dtype=int)
        active_speed = np.empty(0, dtype=int)
        stats: dict[str, Any] = {"qp_solves": 0, "qp_rows": 0, "soc_steps": 0, "merit_evals": 1}
        e0 = x0 - self._goal
        cost0 = float(np.mean(e0 * e0 @ self._q))
        with np.errstate(all="ignore"):
            ro = self._evaluate(x0, W, u0, cost0)
        if not math.isfinite(ro.merit):
            return ro, "Invalid_Initial_Point", False, 0, stats
        status, success, iterations = "Maximum_Iterations_Exceeded", False, 0
        prev_step = math.inf  # size of the last accepted full step
        damping = 0.0  # Levenberg-Marquardt term: grows while the quadratic model is poor
        while iterations < opt.max_iter:
            iterations += 1
            u = ro.u
            with np.errstate(all="ignore"):
                lin = self._linearise(ro)
                H = self._hessian(lin, mu)
            if not (np.all(np.isfinite(H)) and np.all(np.isfinite(lin.grad))):
                status = "Invalid_Derivatives"
                break
            try:
                qp_step, mu = self._newton_step(lin, H, u, active_pos, active_speed, damping, stats)
            except np.linalg.LinAlgError:  # eigen-decomposition failed: keep the best iterate
                status = "Numerical_Error"
                break
            if qp_step is None:
                status = "QP_Failed"
                break
            d, pos = qp_step.d, qp_step.pos
            # Hard-active constraints of this QP: the prediction for the next convexification.
            hard = (mu[pos[:, 0], pos[:, 1], pos[:, 2]] > 1e-9) & (
                qp_step.s_pos[pos[:, 0], pos[:, 1]] <= 1e-9
            )
            active_pos = pos[hard]
            active_speed = np.nonzero((qp_step.lam_speed > 1e-9) & (qp_step.s_speed <= 1e-9))[0]
            if np.max(np.abs(d)) <= opt.step_tol:
                status, success = "Solve_Succeeded", True
                break
            # Upper bound of the merit's directional derivative along d (< 0 unless d = 0).
            D = float(lin.grad @ d) + rho * (qp_step.slack_sum - ro.slack)
            if (
                iterations >= opt.restart_probe
                and ro.merit + opt.restart_optimism * D > abandon_above
            ):
                # Even a multiple of the decrease the local model promises leaves this
                # start above the plan to beat: give it up.
                status = "Abandoned"
                break

            # --- line search on the exact-penalty merit, with second-order correction ---
            t = 1.0
            accepted = None
            while t >= opt.min_step:
                with np.errstate(all="ignore"):
                    trial = self._evaluate(
                        x0, W, np.clip(u + t * d, self._lower, self._upper), cost0
                    )
                stats["merit_evals"] += 1
                if trial.merit <= ro.merit + opt.armijo * t * D:
                    accepted = trial
                    break
                if t == 1.0 and opt.second_order_correction and trial.slack > ro.slack:
                    # The constraints' curvature made the full step infeasible: shift the
                    # rows by their second-order error and re-solve (Maratos effect).
                    a_pos, _ = self._position_rows(lin, pos)
                    g_try = trial.g_pos[pos[:, 0], pos[:, 1], pos[:, 2]]
                    qp_step.qp.set_position_bounds(qp_step.row, g_try - a_pos @ d)
                    z_soc, _, ok_soc = qp_step.qp.solve()
                    stats["qp_solves"] += 1
                    if ok_soc:
                        u_soc = np.clip(u + z_soc[:nu], self._lower, self._upper)
                        with np.errstate(all="ignore"):
                            soc = self._evaluate(x0, W, u_soc, cost0)
                        stats["merit_evals"] += 1
                        if soc.merit <= ro.merit + opt.armijo * D:
                            stats["soc_steps"] += 1
                            accepted = soc
                            break
                t *= opt.backtrack
            if accepted is None:
                # No decrease along a descent direction: converged up to rounding if the
                # predicted decrease is negligible, else a genuine failure.
                if -D <= 1e3 * opt.tol * (1.0 + abs(ro.merit)):
                    status, success = "Solve_Succeeded", True
                else:
                    status = "Line_Search_Failed"
                break
            step = float(np.max(np.abs(accepted.u - u)))
            slack_change = abs(accepted.slack - ro.slack)
            ro = accepted
            if rival is not None and np.max(np.abs(ro.u - rival)) <= opt.restart_same_tol:
                status = "Duplicate"
                break
            # Heavy backtracking means the quadratic model is poor this far out (negative
            # curvature, strongly curved constraints): damp the next steps, like a trust
            # region; full steps undo it, so the local convergence stays quadratic.
            if t < opt.damping_threshold:
                damping = max(10.0 * damping, opt.damping_init)
            elif t == 1.0:
                damping = 0.1 * damping if damping > 1e-3 * opt.damping_init else 0.0
            ratio = step / prev_step if math.isfinite(prev_step) else 1.0
            predicted_next = step * min(ratio, 1.0) if t == 1.0 else math.inf
            prev_step = step if t == 1.0 else math.inf
            if predicted_next <= opt.final_step_tol and (
                ro.slack <= opt.add_tol or slack_change <= opt.add_tol * (1.0 + ro.slack)
            ):
                status, success = "Solve_Succeeded", True
                break
        return ro, status, success, iterations, stats
