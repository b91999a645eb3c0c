"""The scenario problem condensed onto the shared inputs, with derivatives from the model.

The latent forces ``W`` do not depend on the inputs, so every scenario's states are
explicit functions of the ``N nu`` shared inputs. :class:`CondensedModel` evaluates, for
all scenarios at once:

* the rollout through the model's own NumPy step (:meth:`LatentForceModel.physical_step`),
  the constraint values ``g(x_k)`` and the exact-penalty merit (equal to
  :meth:`ScenarioProblem.objective` up to rounding);
* forward sensitivities ``S_k = d x_k / d u`` from the step Jacobians ``A_k, B_k``;
* the cost gradient and the exact Hessian of the Lagrangian with respect to ``u`` by one
  second-order adjoint sweep (``H = 2 R + sum_k S~_k' M_k S~_k`` with ``M_k`` the Hessian of
  ``lambda_{k+1}' F + l_k + mu_k' g`` in ``(x_k, u_k)``).

Every derivative comes from the system's CasADi expressions (step Jacobian, Hessian of
``lambda' F``, constraint Jacobian and Hessian). Three backends evaluate them (the
attribute :attr:`CondensedModel.backend`; chosen by the ``backend`` argument or the
environment variable ``LFM_BACKEND`` = ``auto`` (default), ``c``, ``numpy`` or ``vm``):

* ``"compiled-c"``: the whole per-iteration work (rollout, sensitivities, gradient,
  Hessian) in one C library generated from those expressions, compiled once per system
  and compiler and cached on disk (:mod:`controllers.solvers.fast.codegen.build`); the
  default when a C compiler is found;
* ``"numpy-lanes"``: NumPy condensing, the pointwise derivatives generated as NumPy code
  evaluated on all ``Ns N`` points per call (:mod:`controllers.solvers.fast.lanes`); the
  fallback when no compiler is found or compilation fails (:attr:`backend_error` says why;
  a one-line warning on stderr says so once per process);
* ``"casadi-vm"``: the same NumPy condensing with the pointwise functions in CasADi's
  virtual machine (slow; used when the lanes lack an operation, or when asked for).

It also finds structure the solver exploits: constraints whose condensed Jacobian
``d g_j(x_k) / d u`` is the same constant for every scenario, step input and force (the
bicycle's speed bounds: ``v_k = v_0 + dt sum (a_j + w_j)``). For those only the extreme
scenario matters at every step, whatever ``u`` is: one exact linear row per step
(:func:`~controllers.solvers.fast.screening.shared_linear_constraints`). Its results are the
containers of :mod:`controllers.solvers.fast.iterate`.
"""

from __future__ import annotations

import math
import os
import sys
from collections import deque

import casadi as ca
import numpy as np

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.codegen.build import (
    CodegenUnavailable,
    address,
    build_library,
    notice,
    ptr,
)
from controllers.solvers.fast.codegen.source import constraint_jacobian_pattern
from controllers.solvers.fast.iterate import Linearisation, Rollout
from controllers.solvers.fast.lanes import LaneFunction
from controllers.solvers.fast.screening import (
    screen_rows,
    shared_linear_constraints,
    worst_rows,
)

BACKEND_ENV = "LFM_BACKEND"
BACKENDS = ("auto", "c", "numpy", "vm")


def _references(arrays: tuple[np.ndarray, ...]) -> int:
    """The largest ``sys.getrefcount`` of ``arrays``' members, seen from here."""
    return max(sys.getrefcount(a) for a in arrays)


# _references of a pair that only its tuple refers to (measured: interpreters count
# differently): a pooled rollout pair at this count is free for reuse.
_POOLED = _references((np.empty(0), np.empty(0)))


class CondensedModel:
    """Merit, sensitivities, gradient and Lagrangian Hessian of a problem over its inputs.

    Args:
        problem: the scenario problem (its model's system gives every expression).
        backend: ``"auto"`` (compiled C if a compiler is there, else NumPy lanes),
            ``"c"`` (compiled C or :class:`CodegenUnavailable`), ``"numpy"``
            or ``"vm"``; ``None`` reads ``$LFM_BACKEND`` (default ``"auto"``).

    A model serves one call at a time: its rollout arrays and the Hessian's scratch are its
    own and reused between calls (like the solver that holds it, give each thread its own).

    Attributes:
        backend: ``"compiled-c"``, ``"numpy-lanes"`` or ``"casadi-vm"``.
        compile_time: [s] building the C library in this constructor (generation, and
            compilation unless cached; 0 for the other backends).
        cache_hit: the C library came from the disk cache or this process (no compiler run).
        vector_math: how the C library's rollout, linearisation and Hessian evaluate the
            system's functions over the scenarios: 2 in
            vectorised loops with libmvec's vector sine, cosine, exp, log and pow; 1
            vectorised loops with scalar math; 0 one call per scenario (``codegen.inline``;
            0 without a C library).
        requested_backend: the ``backend`` asked for (``"auto"``, ``"c"``, ``"numpy"``, ``"vm"``).
        backend_error: why the C library is not used under ``"auto"`` (``None`` if it is).

    Raises:
        ValueError: on an unknown ``backend``.
        CodegenUnavailable: for ``backend="c"`` when no C library can be built.
    """

    def __init__(self, problem: ScenarioProblem, backend: str | None = None) -> None:
        self.problem = problem
        system, cost = problem.system, problem.cost
        n, nx, nu, nw, ng = problem.horizon, problem.nx, problem.nu, problem.nw, problem.ng
        self.n, self.nx, self.nu, self.nw, self.ng = n, nx, nu, nw, ng
        self.n_u = n * nu
        # A feedback prediction (ScenarioProblem.prediction): the inputs are the nominal
        # inputs v, each scenario applies v_k + K_k (x_k - r_k) under the law of set_law, and
        # the rows of G are the state constraints, then each input's upper and lower row
        # (n_rows of them); S has nxs rows per scenario and step (the state's, then the
        # applied input's). The C library of the closed-loop step (build_library's feedback)
        # does the work; there is no NumPy path for it.
        self.feedback = problem.prediction == "feedback"
        self.n_rows = ng + 2 * nu if self.feedback else ng
        self.nxs = nx + nu if self.feedback else nx
        self.lower = np.tile(problem.input_lower, n)
        self.upper = np.tile(problem.input_upper, n)
        choice = backend if backend is not None else (os.environ.get(BACKEND_ENV) or "auto")
        if choice not in BACKENDS:
            source = "backend" if backend is not None else f"${BACKEND_ENV}"
            raise ValueError(f"CondensedModel {source}={choice!r}: must be one of {BACKENDS}")
        self.requested_backend = choice

        # --- the C library ---
        self._lib = None
        # Threads of the C library's rollout, linearisation and Hessian: the scenarios in this
        # many contiguous chunks, one per thread (results equal to rounding for every
        # count; 1 is the serial sweep). See codegen/c/driver.c.
        self.threads = 1
        self.compile_time, self.cache_hit, self.backend_error = 0.0, False, None
        if choice in ("auto", "c"):
            try:
                built = build_library(system, problem.dt, self.feedback)
            except CodegenUnavailable as err:
                if choice == "c":
                    raise
                self.backend_error = str(err)
                notice(
                    f"the fast solver's C library is not available ({err}); the fast solver "
                    "uses its NumPy backend in this process (slower)"
                )
            else:
                self._lib, self.compile_time, self.cache_hit = (
                    built.lib,
                    built.build_time,
                    built.cache_hit,
                )
        if self.feedback and self._lib is None:
            raise CodegenUnavailable(
                "a feedback prediction in the condensed SQP needs the C library"
                + (f" ({self.backend_error})" if self.backend_error else f" (backend={choice!r})")
            )
        # The C library runs its chunks in threads (compiled with OpenMP).
        self.openmp = self._lib is not None and bool(self._lib.lfm_openmp())
        # Its loops over scenarios (rollout, linearisation, Hessian): 2 vectorised with
        # glibc's vector math (libmvec), 1 vectorisable without it, 0 one call per scenario.
        self.vector_math = int(self._lib.lfm_vector_math()) if self._lib is not None else 0

        # --- the generated derivative functions, evaluated on all points at once ---
        x, u, w = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("w", nw)
        lam, mu = ca.SX.sym("lam", nx), ca.SX.sym("mu", max(ng, 1))
        F = system.casadi_step(problem.dt)(x, u, w)
        z = ca.vertcat(x, u)
        vm = choice == "vm"
        self._step_jac = LaneFunction(
            ca.Function("step_jac", [x, u, w], [ca.jacobian(F, z)]), vm=vm
        )
        hess_F = ca.hessian(ca.dot(lam, F), z)[0]
        self._step_hess = LaneFunction(ca.Function("step_hess", [x, u, w, lam], [hess_F]), vm=vm)
        g = system.casadi_constraints()(x)
        lanes = [self._step_jac, self._step_hess]
        if ng:
            self._con_jac = LaneFunction(ca.Function("con_jac", [x], [ca.jacobian(g, x)]), vm=vm)
            hess_g = ca.hessian(ca.dot(mu, g), x)[0]
            self._con_hess = LaneFunction(ca.Function("con_hess", [x, mu], [hess_g]), vm=vm)
            lanes += [self._con_jac, self._con_hess]
        # The states each constraint depends on (for picking extreme scenarios; the compiled
        # library stores these entries of the constraint Jacobians, at _jg_index row-major).
        self.depends = constraint_jacobian_pattern(system)  # constraint j depends on state m
        self._jg_index = np.flatnonzero(self.depends)
        if self._lib is not None:
            self.backend = "compiled-c"
        elif all(f.backend == "numpy" for f in lanes):
            self.backend = "numpy-lanes"
        else:
            self.backend = "casadi-vm"

        # --- structure: constraints that are one exact linear row per step ---
        if self.feedback:  # (the law makes every row depend on the scenario: none)
            self.shared, self.shared_rows = np.zeros(0, dtype=int), np.zeros((0, n, n * nu))
            self._feedback_tables()
        else:
            self.shared, self.shared_rows = shared_linear_constraints(problem)
        self.screened = np.array(
            [j for j in range(self.n_rows) if j not in set(self.shared)], dtype=int
        )
        self._screened_c = np.ascontiguousarray(self.screened, dtype=np.int64)
        self._depends_c = np.ascontiguousarray(self.depends, dtype=np.uint8)
        self._screens_all = self.screened.size == self.n_rows

        # --- cost weights ---
        self._goal = np.ascontiguousarray(cost.x_goal, dtype=float)
        self._diagonal = cost.diagonal
        weights = np.stack([cost.Q] * (n - 1) + [cost.Qf])  # (N, nx, nx) for steps 1..N
        self._w_state = np.ascontiguousarray(weights, dtype=float)
        # The C library's constant arguments, and the addresses of the arrays a solve passes at
        # every call (its x0 and forces; :meth:`_held`).
        self._weights_p = (ptr(self._goal), ptr(self._w_state))
        self._held_ptrs: dict[int, tuple[np.ndarray, int]] = {}
        self._scratch = np.empty(0)  # the compiled Hessian's (_hessian_scratch)
        self._rollouts: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=8)
        self._w_diag = np.stack([np.diag(m) for m in weights])  # (N, nx)
        self._R2 = 2.0 * cost.R
        self._r_diag = np.tile(np.diag(cost.R), n)
        self._law_rows: np.ndarray | None = None  # (N, ND) the feedback law's data rows

    def _feedback_tables(self) -> None:
        """The row structure of a feedback prediction: which states each row depends on (an
        input row none: the screening picks its scenarios by value) and where each stored
        Jacobian entry sits in the ``(n_rows, nxs)`` Jacobian of a point (the state
        constraints' entries, then one per input row, on its input)."""
        nx, nu, ng, nxs = self.nx, self.nu, self.ng, self.nxs
        pattern = constraint_jacobian_pattern(self.problem.system)
        self.depends = np.zeros((self.n_rows, nx), dtype=bool)
        self.depends[:ng] = pattern
        rows, cols = np.nonzero(pattern)
        inputs = [(ng + side * nu + q) * nxs + nx + q for side in (0, 1) for q in range(nu)]
        self._jg_index = np.concatenate([rows * nxs + cols, inputs]).astype(int)

    def set_law(self, K: np.ndarray, r: np.ndarray, active: np.ndarray) -> None:
        """The law of the next evaluations (a feedback prediction): gains ``K`` ``(N, nu, nx)``,
        reference states ``r`` ``(N, nx)``; ``active`` ``(N,)`` says whether each step's input
        rows count (not where they repeat hard bounds of ``v_k``: ``K_k = 0``)."""
        n, nu, nx = self.n, self.nu, self.nx
        ndf = nu + nu * nx + nx
        rows = np.zeros((n, ndf + nu * nu + 1))
        rows[:, nu : nu + nu * nx] = np.asarray(K, dtype=float).reshape(n, nu * nx)
        rows[:, nu + nu * nx : ndf] = r
        rows[:, ndf : ndf + nu * nu] = np.asarray(self.problem.cost.R, dtype=float).ravel()
        rows[:, -1] = np.asarray(active, dtype=float)
        self._law_rows = rows

    def _data(self, u: np.ndarray) -> np.ndarray:
        """What the C library reads as the inputs: ``u`` itself, or with feedback the law's
        data rows ``(N, ND)`` with ``u`` as the nominal inputs (one buffer, rewritten)."""
        if not self.feedback:
            return u
        if self._law_rows is None:
            raise ValueError("CondensedModel.set_law: a feedback prediction needs its law first")
        self._law_rows[:, : self.nu] = u.reshape(self.n, self.nu)
        return self._law_rows

    def __getstate__(self) -> dict:
        # The loaded library and the generated code are rebuilt (from the disk cache).
        return {"problem": self.problem, "backend": self.requested_backend}

    def __setstate__(self, state: dict) -> None:
        CondensedModel.__init__(self, state["problem"], backend=state["backend"])

    @staticmethod
    def _strides(W: np.ndarray, axes: tuple[int, int, int]) -> tuple[int, int, int]:
        """Element strides of ``W`` along (force component, step, scenario) = ``axes``."""
        if W.dtype != np.float64:
            raise ValueError(f"W: must be float64, got {W.dtype}")
        return tuple(W.strides[a] // W.itemsize for a in axes)

    def _rollout_arrays(self, ns: int) -> tuple[np.ndarray, np.ndarray]:
        """``X`` ``(N + 1, nx, Ns)`` and ``G`` ``(n_rows, N, Ns)`` for a compiled rollout.

        A pair of the last few is reused once nothing else refers to either array any more
        (no rollout, view or caller holds them: CPython's reference count), so their pages
        are mapped already; fresh ones cost about 230 page faults per rollout at Ns = 5000.
        """
        for pair in self._rollouts:
            if pair[0].shape[2] == ns and _references(pair) <= _POOLED:
                return pair[0], pair[1]  # (a new tuple: holding it holds the arrays)
        pair = (np.empty((self.n + 1, self.nx, ns)), np.empty((self.n_rows, self.n, ns)))
        self._rollouts.append(pair)
        return pair[0], pair[1]

    def _hessian_scratch(self, ns: int) -> int:
        """The address of the compiled Hessian's scratch for ``ns`` scenarios (kept, so its
        pages are not faulted in again at every call)."""
        size = int(self._lib.lfm_hessian_scratch(ns))
        if self._scratch.size < size:
            self._scratch = np.empty(size)
        return ptr(self._scratch)

    def _held(self, a: np.ndarray) -> int:
        """``ptr(a)`` of an array passed again and again (a solve's initial states and
        forces), remembered by identity; the few arrays remembered are kept referenced, so
        their ids cannot be reused by other arrays meanwhile."""
        entry = self._held_ptrs.get(id(a))
        if entry is not None and entry[0] is a:
            return entry[1]
        if len(self._held_ptrs) >= 8:
            self._held_ptrs.clear()
        addr = ptr(a)
        self._held_ptrs[id(a)] = (a, addr)
        return addr

    # ------------------------------------------------------------------ evaluation

    def state_cost0(self, x0: np.ndarray) -> float:
        """The constant stage cost of the initial states ``x0`` ``(Ns, nx)``, averaged."""
        return float(np.mean(self.problem.cost.state_cost(x0)))

    def input_cost(self, u: np.ndarray) -> float:
        if self._diagonal:
            return float(self._r_diag @ (u * u))
        uk = u.reshape(self.n, self.nu)
        return float(np.einsum("ka,ab,kb->", uk, self.problem.cost.R, uk))

    def evaluate(
        self,
        x0T: np.ndarray,
        W: np.ndarray,
        u: np.ndarray,
        cost0: float,
        backoff: np.ndarray | None = None,
    ) -> Rollout:
        """Rollout of all scenarios and the exact-penalty merit.

        Args:
            x0T: initial states ``(nx, Ns)`` (component-major).
            W: forces ``(N, Ns, nw)``.
            u: flattened inputs ``(N nu,)``.
            cost0: :meth:`state_cost0` of the initial states.
            backoff: constraint tightening ``(ng, N, 1)`` added to every scenario's values.
        """
        p, model = self.problem, self.problem.model
        n, nu, ns = self.n, self.nu, x0T.shape[1]
        if self._lib is not None:
            X, G = self._rollout_arrays(ns)
            u = np.ascontiguousarray(u, dtype=float)
            sa, sk, si = self._strides(W, (2, 0, 1))
            x0c = np.ascontiguousarray(x0T, dtype=float)
            c_sum = np.zeros(1)  # the state cost summed over scenarios
            out = (ptr(X), ptr(G), ptr(c_sum))
            x0p, Wp = self._held(x0c), self._held(W)
            data = ptr(self._data(u))
            call = (n, ns, x0p, Wp, sa, sk, si, data, *self._weights_p, *out, self.threads)
            if self._lib.lfm_rollout(*call):
                X[:], G[:], c_sum[:] = np.nan, np.nan, np.nan
        else:
            X = np.empty((n + 1, self.nx, ns))
            X[0] = x0T
            uk = u.reshape(n, nu)
            for k in range(n):
                X[k + 1] = model.physical_step(X[k].T, uk[k], W[k]).T
            if self.ng:
                G = np.ascontiguousarray(
                    np.moveaxis(p.system.constraint_values(X[1:].transpose(0, 2, 1)), -1, 0)
                )
        if self.n_rows:
            if backoff is not None:
                G[: self.ng] += backoff
            slack = float(np.maximum(G.max(axis=2), 0.0).sum())
        else:
            G = np.zeros((0, n, ns))
            slack = 0.0
        if self._lib is not None:
            cost = float(c_sum[0])
        else:
            e = X[1:] - self._goal[None, :, None]
            if self._diagonal:
                cost = float(np.einsum("km,kmi,kmi->", self._w_diag, e, e))
            else:
                cost = float(np.einsum("kmi,kmn,kni->", e, self._w_state, e))
        # (with feedback the rollout's cost has each scenario's input cost)
        inputs = 0.0 if self.feedback else self.input_cost(u)
        merit = cost0 + cost / ns + inputs + p.slack_penalty * slack
        merit = merit if math.isfinite(merit) else math.inf
        return Rollout(u=u, X=X, G=G, slack=slack, merit=merit)

    @staticmethod
    def _lanes(a: np.ndarray) -> np.ndarray:
        """``(K, m, Ns)`` per-step data as ``(m, K, Ns)`` evaluation points."""
        return a.transpose(1, 0, 2)

    def _input_lanes(self, u: np.ndarray) -> np.ndarray:
        """The inputs ``(N nu,)`` as points ``(nu, N, 1)``: the same for every scenario."""
        return u.reshape(self.n, self.nu).T[:, :, None]

    def linearise(
        self, ro: Rollout, W_lanes: np.ndarray, recycle: Linearisation | None = None
    ) -> Linearisation:
        """Step Jacobians, sensitivities, constraint Jacobians and the cost gradient.

        ``recycle``: a linearisation the caller no longer needs; the C library writes
        the new one into its arrays (same sizes), which are then no longer its.
        Allocating them anew each iteration cost page faults: at Ns = 5000 a fresh 9 MB
        ``S`` took about 1000 faults per call and doubled the C library's time.
        """
        if self._lib is not None:
            return self._linearise_c(ro, W_lanes, recycle)
        n, nx, nu, n_u = self.n, self.nx, self.nu, self.n_u
        X = ro.X
        ns = X.shape[2]
        (J,) = self._step_jac(self._lanes(X[:n]), self._input_lanes(ro.u), W_lanes)
        # Dense column-major (nx, nx + nu) per point -> (N, Ns, nx, nx + nu).
        J = J.reshape(nx + nu, nx, n, ns).transpose(2, 3, 1, 0)
        A = np.ascontiguousarray(J[..., :nx])
        S = np.zeros((n, ns, nx, n_u))
        # --- forward sensitivities: S_{k+1} = A_k S_k + B_k E_k (S_0 = 0; causal columns) ---
        S[0, :, :, :nu] = J[0, :, :, nx:]
        for k in range(1, n):
            cols = k * nu
            np.matmul(A[k], S[k - 1, :, :, :cols], out=S[k, :, :, :cols])
            S[k, :, :, cols : cols + nu] = J[k, :, :, nx:]
        if self.ng:
            (Jg,) = self._con_jac(self._lanes(X[1:]))
            Jg = Jg.reshape(nx, self.ng, n, ns).transpose(2, 3, 1, 0)  # (N, Ns, ng, nx)
        else:
            Jg = np.zeros((n, ns, 0, nx))
        grad = (ro.u.reshape(n, nu) @ self._R2).ravel()  # d(u' R u)/du, R symmetric
        grad += S.reshape(-1, n_u).T @ self.state_gradient(X).ravel()
        return Linearisation(ro=ro, A=A, S=S, Jg=Jg, grad=grad)

    def state_gradient(self, X: np.ndarray) -> np.ndarray:
        """``d cost / d x_k`` of steps 1..N, ``(N, Ns, nx)``."""
        ns = X.shape[2]
        e = X[1:] - self._goal[None, :, None]  # (N, nx, Ns)
        if self._diagonal:
            g = self._w_diag[:, :, None] * e
        else:
            g = np.einsum("kmn,kni->kmi", self._w_state, e)
        return (2.0 / ns) * g.transpose(0, 2, 1)

    def hessian(self, lin: Linearisation, mu: np.ndarray, W_lanes: np.ndarray) -> np.ndarray:
        """Exact Hessian of the Lagrangian w.r.t. ``u`` ``(N nu, N nu)``.

        ``mu`` ``(ng, N, Ns)`` are the multipliers of the scenario rows (zero for rows that
        are not in the QP and for the shared linear rows, whose condensed curvature is zero).
        """
        if self._lib is not None:
            return self._hessian_c(lin, mu, W_lanes)
        n, nx, nu, n_u = self.n, self.nx, self.nu, self.n_u
        X, S, A, Jg = lin.ro.X, lin.sensitivities(), lin.A, lin.constraint_jacobians()
        ns = X.shape[2]
        # --- adjoint sweep: lambda_k = dl_k/dx_k + Jg_k' mu_k + A_k' lambda_{k+1} ---
        lam = self.state_gradient(X)  # (N, Ns, nx): dl/dx of steps 1..N
        has_mu = self.ng > 0 and bool(mu.any())
        if has_mu:
            mu_k = np.ascontiguousarray(mu.transpose(1, 2, 0))  # (N, Ns, ng)
            lam += np.matmul(mu_k[:, :, None, :], Jg)[:, :, 0, :]
        for k in range(n - 2, -1, -1):  # lam[k] = lambda at step k + 1
            lam[k] += np.matmul(lam[k + 1][:, None, :], A[k + 1])[:, 0, :]
        lam_lanes = lam.transpose(2, 0, 1)  # lambda_{k+1} for step k, (nx, N, Ns)
        u_lanes = self._input_lanes(lin.ro.u)
        (M,) = self._step_hess(self._lanes(X[:n]), u_lanes, W_lanes, lam_lanes)
        nz = nx + nu
        M = M.reshape(nz, nz, n, ns).transpose(2, 3, 1, 0)  # (N, Ns, nz, nz), step k
        # --- state curvature at steps 1..N: cost, dynamics (steps 1..N-1), constraints ---
        Mxx = np.empty((n, ns, nx, nx))
        Mxx[:] = (2.0 / ns) * self._w_state[:, None]
        Mxx[: n - 1] += M[1:, :, :nx, :nx]
        if has_mu:
            (Hg,) = self._con_hess(self._lanes(X[1:]), mu)
            Mxx += Hg.reshape(nx, nx, n, ns).transpose(2, 3, 1, 0)
        # S_k has nonzero columns for the inputs of the steps before k only (causality):
        # each step adds to the leading block of H alone.
        H = np.zeros((n_u, n_u))
        for k in range(n):
            cols = (k + 1) * nu
            Sk = np.ascontiguousarray(S[k, :, :, :cols])
            T = np.matmul(Mxx[k], Sk)
            H[:cols, :cols] += Sk.reshape(-1, cols).T @ T.reshape(-1, cols)
        # --- cross terms of the dynamics (S_0 = 0: step 0 has none) and input curvature ---
        if n > 1:
            Mxu = np.ascontiguousarray(M[1:, :, :nx, nx:]).reshape(n - 1, ns * nx, nu)
            Sk = S[: n - 1].reshape(n - 1, ns * nx, n_u)
            cross = np.matmul(Sk.transpose(0, 2, 1), Mxu)  # (N-1, N nu, nu)
            for k in range(1, n):
                blk = slice(k * nu, (k + 1) * nu)
                H[:, blk] += cross[k - 1]
                H[blk, :] += cross[k - 1].T
        uu = M[:, :, nx:, nx:].sum(axis=1)  # (N, nu, nu)
        for k in range(n):
            blk = slice(k * nu, (k + 1) * nu)
            H[blk, blk] += uu[k] + self._R2
        return 0.5 * (H + H.T)

    def _linearise_c(
        self, ro: Rollout, W_lanes: np.ndarray, recycle: Linearisation | None
    ) -> Linearisation:
        """:meth:`linearise` by the C library."""
        n, nu, n_u = self.n, self.nu, self.n_u
        X = np.ascontiguousarray(ro.X, dtype=float)
        u = np.ascontiguousarray(ro.u, dtype=float)
        ns = X.shape[2]
        size = ns * self.nxs * nu * n * (n + 1) // 2  # of S, causally packed
        if recycle is not None and recycle.packed and recycle.S.size == size:
            S, Jg = recycle.S, recycle.Jg  # every entry is written below
        else:
            S = np.empty(size)
            Jg = np.empty((n, ns, self._jg_index.size))
        grad = np.empty(n_u)
        sa, sk, si = self._strides(W_lanes, (0, 1, 2))
        args = (*self._weights_p, 2.0 / ns)
        out = (ptr(S), ptr(Jg), ptr(grad))
        Wp = self._held(W_lanes)
        data = ptr(self._data(u))
        call = (n, ns, ptr(X), Wp, sa, sk, si, data, *args, *out, self.threads)
        if self._lib.lfm_linearise(*call):
            grad[:] = np.nan
        if not self.feedback:  # (with feedback the scenarios' input costs are in grad)
            grad += (u.reshape(n, nu) @ self._R2).ravel()  # d(u' R u)/du, R symmetric
        rows = self.nxs if self.feedback else 0
        return Linearisation(
            ro=ro, A=None, S=S, Jg=Jg, grad=grad, packed=True, jg_index=self._jg_index, rows=rows
        )

    def _hessian_c(self, lin: Linearisation, mu: np.ndarray, W_lanes: np.ndarray) -> np.ndarray:
        """:meth:`hessian` by the C library."""
        n, nu, n_u = self.n, self.nu, self.n_u
        X, ns = lin.ro.X, lin.ro.X.shape[2]
        has_mu = self.n_rows > 0 and bool(mu.any())
        mu_c = np.ascontiguousarray(mu, dtype=float) if has_mu else None
        H = np.empty((n_u, n_u))
        sa, sk, si = self._strides(W_lanes, (0, 1, 2))
        u = ptr(self._data(np.ascontiguousarray(lin.ro.u, dtype=float)))
        data = (u, ptr(lin.S), ptr(lin.Jg), ptr(mu_c))
        weights = (*self._weights_p, 2.0 / ns)
        Wp = self._held(W_lanes)
        carry = self._hessian_scratch(ns)
        call = (n, ns, ptr(X), Wp, sa, sk, si, *data, *weights, ptr(H), carry, self.threads)
        if self._lib.lfm_hessian(*call):
            H[:] = np.nan
        for k in range(n):
            blk = slice(k * nu, (k + 1) * nu)
            H[blk, blk] += self._R2
        return H

    def rows(self, lin: Linearisation, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Jacobian rows ``(r, N nu)`` and values ``(r,)`` of scenario rows ``(j, k, i)``.

        ``k`` indexes steps ``1..N`` from 0.
        """
        j, k, i = pos[:, 0], pos[:, 1], pos[:, 2]
        if lin.packed:
            pos_c = np.ascontiguousarray(pos, dtype=np.int64)
            jac = np.empty((pos.shape[0], self.n_u))
            ns = lin.ro.X.shape[2]
            self._lib.lfm_rows(
                self.n, ns, ptr(lin.S), ptr(lin.Jg), pos.shape[0], address(pos_c), ptr(jac)
            )
        else:
            jac = np.einsum("rm,rmn->rn", lin.Jg[k, i, j], lin.S[k, i])
        return jac, lin.ro.G[j, k, i]

    def screen(self, ro: Rollout, margin: float, keep: int) -> np.ndarray:
        """The scenario rows ``(r, 3)`` of ``(constraint, step from 0, scenario)`` a QP at
        ``ro`` starts with (:func:`~controllers.solvers.fast.screening.screen_rows` of the
        screened constraints; ``margin`` in the constraints' unit, ``keep`` rows per group
        by value)."""
        nsc = self.screened.size
        if self._lib is not None and nsc:
            ns = ro.X.shape[2]
            cap = nsc * self.n * min(ns, keep + 1 + 2 * self.nx)
            out = np.empty((cap, 3), dtype=np.int64)
            args = (ptr(ro.G), ptr(ro.X), address(self._depends_c), float(margin), int(keep))
            r = self._lib.lfm_screen(
                self.n, ns, nsc, address(self._screened_c), *args, address(out), cap
            )
            if r >= 0:
                return out[:r]
        # No C library, or it ran out of memory: the reference gives the same rows.
        return screen_rows(ro.G, ro.X, self.screened, self.depends, margin, keep)

    def violated_rows(
        self,
        lin: Linearisation,
        d: np.ndarray,
        s_pos: np.ndarray,
        pos: np.ndarray,
        tol: float,
        keep: int,
    ) -> np.ndarray:
        """Scenario rows ``(r, 3)`` not in ``pos`` that the QP step ``d`` violates to first
        order by more than ``tol``, with the QP's slack ``s_pos`` ``(ng, N)`` of every
        (constraint, step) group: up to ``keep`` of the largest per group
        (:func:`~controllers.solvers.fast.screening.worst_rows`)."""
        nsc = self.screened.size
        if nsc == 0:
            return np.empty((0, 3), dtype=int)
        if self._lib is not None and lin.packed:
            ns = lin.ro.X.shape[2]
            cap = nsc * self.n * min(ns, keep)
            out = np.empty((cap, 3), dtype=np.int64)
            d = np.ascontiguousarray(d, dtype=float)
            s_pos = np.ascontiguousarray(s_pos, dtype=float)
            pos_c = np.ascontiguousarray(pos, dtype=np.int64)
            data = (ptr(lin.S), ptr(lin.Jg), ptr(lin.ro.G), ptr(d), ptr(s_pos))
            r = self._lib.lfm_violated(
                self.n,
                ns,
                nsc,
                address(self._screened_c),
                *data,
                pos_c.shape[0],
                address(pos_c),
                float(tol),
                int(keep),
                address(out),
                cap,
            )
            if r >= 0:
                return out[:r]
        # No C library, or it ran out of memory: the reference gives the same rows.
        viol = self.linearised_values(lin, d)
        viol -= s_pos[self.screened][:, :, None]
        return worst_rows(viol, self.screened, pos, tol, keep)

    def linearised_values(self, lin: Linearisation, d: np.ndarray) -> np.ndarray:
        """``g + (dg/du) d`` of every screened scenario row, ``(n_screened, N, Ns)``."""
        if self._lib is not None and self.n_rows:
            d = np.ascontiguousarray(d, dtype=float)
            G = lin.ro.G  # (n_rows, N, Ns), C-contiguous (built by evaluate)
            values = np.empty(G.shape)
            data = (ptr(lin.S), ptr(lin.Jg), ptr(G), ptr(d))
            self._lib.lfm_linear_change(self.n, G.shape[2], *data, ptr(values))
            return values if self._screens_all else values[self.screened]
        S = lin.sensitivities()
        Sd = (S.reshape(-1, self.n_u) @ d).reshape(S.shape[:3] + (1,))  # (N, Ns, nx, 1)
        change = np.matmul(lin.constraint_jacobians(), Sd)[..., 0]  # (N, Ns, ng)
        return lin.ro.G[self.screened] + change[:, :, self.screened].transpose(2, 0, 1)


__all__ = ["BACKENDS", "BACKEND_ENV", "CondensedModel"]
