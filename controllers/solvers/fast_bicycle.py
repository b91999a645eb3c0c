"""The bicycle's derivatives written by hand: an optional cache of the generic fast solver.

:class:`BicycleFastSolver` is :class:`~controllers.solvers.fast.solver.FastScenarioSolver` (the
same SQP, QP, screening, globalisation and extra starts) with the rollout, sensitivities,
gradient and Lagrangian Hessian of the sine-track bicycle written out by hand
(:class:`BicycleCondensedModel`) instead of generated from the system definition. It
solves only problems of :func:`lfm_env.worlds.sine_track.system.sine_track_system` with diagonal
cost weights. ``lfm-benchmark`` times it beside the generic solver; it stays only while it
is measurably faster. Registered as ``"fast_bicycle"``.

What the hand-written form exploits (and the generic one cannot know): the speed is the
same linear function of ``u`` in every scenario (``v_k = v_0 + dt sum (a_j + w_j)``, one
cumulative sum), ``p_x``, ``p_y`` enter the dynamics linearly (their adjoints are running
sums), and the steering enters through ``alpha(delta)`` alone (its derivatives once per
step, not per scenario).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.condensed import CondensedModel, Rollout
from controllers.solvers.fast.solver import FastScenarioSolver
from lfm_env.worlds.sine_track.system import track_of

N_POSITION_KINDS = 4  # track left/right, x lower/upper: the constraints with scenario rows
# Sign of d g / d(track-left or p_x) of the position kinds: track right is -(track left),
# x lower is -p_x, x upper is +p_x.
_POSITION_SIGN = np.array([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class _Bicycle:
    """The numbers of a sine-track :class:`ScenarioProblem` the hand-written code needs."""

    horizon: int
    dt: float
    vehicle_length: float
    track: Any
    speed_min: float
    speed_max: float
    slack_penalty: float

    @classmethod
    def of(cls, problem: ScenarioProblem) -> _Bicycle:
        system = problem.system
        track = track_of(system)  # raises for any other system
        if not problem.cost.diagonal:
            raise ValueError("BicycleFastSolver needs diagonal cost weights")
        g = system.constraints
        return cls(
            horizon=problem.horizon,
            dt=problem.dt,
            vehicle_length=system.rhs.length,
            track=track,
            speed_min=g.speed_min,
            speed_max=g.speed_max,
            slack_penalty=problem.slack_penalty,
        )


@dataclass
class _BicycleRollout(Rollout):
    """A :class:`Rollout` with the bicycle's per-component states and headings."""

    Xc: np.ndarray = None  # (4, N+1, Ns) states per component (X is its transposed view)
    cos_th: np.ndarray = None  # (N, Ns) cos(psi_k + alpha_k)
    sin_th: np.ndarray = None  # (N, Ns)
    g_pos: np.ndarray = None  # (4, N, Ns) position constraint values of steps 1..N [m]


@dataclass
class _BicycleLinearisation:
    """First-order information at a rollout, w.r.t. the flattened inputs ``u`` ``(2N,)``."""

    ro: _BicycleRollout
    S: np.ndarray  # (3, N, Ns, 2N) d(p_x, p_y, psi)_k / du at steps 1..N
    s_v: np.ndarray  # (N+1, 2N) d v_k / du, the same for every scenario
    slope: np.ndarray  # (N, Ns) track centre-line slope at p_x of steps 1..N
    grad: np.ndarray  # (2N,) gradient of the cost


class BicycleCondensedModel(CondensedModel):
    """:class:`CondensedModel` of a sine-track problem with hand-written derivatives."""

    def __init__(self, problem: ScenarioProblem) -> None:
        super().__init__(problem)
        self.bicycle = _Bicycle.of(problem)
        self.backend = "hand_written"
        n, cost = problem.horizon, problem.cost
        self._rb = np.tile(np.diag(cost.R), n)
        # Weight of each state component at steps 1..N (the x_0 term is a constant).
        self._wb = np.vstack([np.tile(np.diag(cost.Q), (n - 1, 1)), np.diag(cost.Qf)[None]])
        # d v_k / d u: the accelerations of the earlier steps times dt, for every scenario.
        steps = np.arange(n + 1)
        self._strictly_later = (steps[:, None] > np.arange(n)[None, :]).astype(float)
        self._s_v = np.zeros((n + 1, 2 * n))
        self._s_v[:, 0::2] = problem.dt * self._strictly_later

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
        gain = 2.0 / self.bicycle.vehicle_length
        sa, ca_ = np.sin(alpha), np.cos(alpha)
        c = gain * sa
        c_p = gain * ca_ * alpha_p
        c_pp = gain * (ca_ * alpha_pp - sa * alpha_p * alpha_p)
        return alpha, alpha_p, alpha_pp, c, c_p, c_pp

    def evaluate(
        self,
        x0T: np.ndarray,
        W: np.ndarray,
        u: np.ndarray,
        cost0: float,
        backoff: np.ndarray | None = None,
    ) -> _BicycleRollout:
        """Rollout of all scenarios and the exact-penalty merit, by hand.

        Same arguments as :meth:`CondensedModel.evaluate`; the Euler steps are the
        bicycle's (:func:`lfm_env.worlds.sine_track.system.bicycle_rhs`), equal up to rounding.
        """
        p = self.bicycle
        n, ns, dt = p.horizon, x0T.shape[1], p.dt
        W = W[:, :, 0].T  # (Ns, N): the one force component
        alpha, _, _, c, _, _ = self._steering_terms(u)
        X = np.empty((4, n + 1, ns))
        px, py, v, psi = X
        cos_th = np.empty((n, ns))
        sin_th = np.empty((n, ns))
        X[:, 0] = x0T
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
        G = np.empty((6, n, ns))
        np.subtract(p.speed_min, v[1:], out=G[4])
        np.subtract(v[1:], p.speed_max, out=G[5])
        if backoff is not None:
            g_pos += backoff[:4]
            G[4:] += backoff[4:]
        G[:4] = g_pos
        g_speed = np.stack([G[4].max(axis=1), G[5].max(axis=1)])
        slack = float(np.maximum(g_pos.max(axis=2), 0.0).sum() + np.maximum(g_speed, 0.0).sum())

        e = X[:, 1:] - self._goal[:, None, None]
        cost = cost0 + float(np.einsum("mk,mki,mki->", self._wb.T, e, e)) / ns
        cost += float(self._rb @ (u * u))
        merit = cost + p.slack_penalty * slack
        return _BicycleRollout(
            u=u,
            X=X.transpose(1, 0, 2),
            G=G,
            Xc=X,
            cos_th=cos_th,
            sin_th=sin_th,
            g_pos=g_pos,
            slack=slack,
            merit=merit if math.isfinite(merit) else math.inf,
        )

    def linearise(
        self, ro: _BicycleRollout, W_lanes: np.ndarray, recycle: object = None
    ) -> _BicycleLinearisation:
        """Forward sensitivities, cost gradient and track slope at a rollout (``recycle``:
        accepted for the generic signature, unused: the arrays are built anew)."""
        p = self.bicycle
        n, nu, dt = p.horizon, self.n_u, p.dt
        ns = ro.Xc.shape[2]
        px, py, v, psi = ro.Xc
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
        wq = (2.0 / ns) * self._wb
        g = self._goal
        residual = np.empty((3, n, ns))
        for row, m in enumerate((0, 1, 3)):
            np.multiply(wq[:, m : m + 1], ro.Xc[m, 1:] - g[m], out=residual[row])
        grad = 2.0 * self._rb * ro.u + S.reshape(-1, nu).T @ residual.ravel()
        grad += s_v[1:].T @ (wq[:, 2] * (v[1:] - g[2]).sum(axis=1))

        track = p.track
        slope = track.amplitude * track.pulsation * np.cos(track.pulsation * px[1:] + track.phase)
        return _BicycleLinearisation(ro=ro, S=S, s_v=s_v, slope=slope, grad=grad)

    def hessian(
        self, lin: _BicycleLinearisation, mu: np.ndarray, W_lanes: np.ndarray
    ) -> np.ndarray:
        """Exact Hessian of the Lagrangian w.r.t. ``u`` ``(2N, 2N)``.

        ``mu`` ``(6, N, Ns)`` are the multipliers of the scenario rows (zero for rows that
        are not in the QP; the speed rows are shared linear rows, linear in ``u``, and add
        no curvature).
        Second-order adjoint: ``H = 2R + sum_k S_k' (d2 l_k) S_k + sum_k Z_k' M_k Z_k``
        with ``M_k`` the Hessian of ``lambda_{k+1}' F(x_k, u_k)`` in ``(v_k, psi_k, delta_k)``.
        """
        p = self.bicycle
        n, nu, dt = p.horizon, self.n_u, p.dt
        mu = mu[:N_POSITION_KINDS]
        px, py, v, psi = lin.ro.Xc
        cos_th, sin_th = lin.ro.cos_th, lin.ro.sin_th
        ns = px.shape[1]
        _, alpha_p, alpha_pp, _, c_p, c_pp = self._steering_terms(lin.ro.u)
        wq = (2.0 / ns) * self._wb
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
        H[np.diag_indices(nu)] += 2.0 * self._rb
        H += lin.s_v[1:].T @ ((2.0 * self._wb[:, 2:3]) * lin.s_v[1:])

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

    def rows(self, lin: _BicycleLinearisation, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Jacobian rows ``(r, 2N)`` and values ``(r,)`` of position rows ``(kind, step, i)``."""
        kind, step, scen = pos[:, 0], pos[:, 1], pos[:, 2]
        d_px = lin.S[0, step, scen]
        d_track = lin.S[1, step, scen] - lin.slope[step, scen, None] * d_px
        jac = np.where((kind < 2)[:, None], d_track, d_px)
        return _POSITION_SIGN[kind, None] * jac, lin.ro.G[kind, step, scen]

    def linearised_values(self, lin: _BicycleLinearisation, d: np.ndarray) -> np.ndarray:
        """``g + (dg/du) d`` of every position row, ``(4, N, Ns)``."""
        lin_px = lin.S[0] @ d  # (N, Ns)
        lin_tr = lin.S[1] @ d - lin.slope * lin_px
        return lin.ro.g_pos + np.stack([lin_tr, -lin_tr, -lin_px, lin_px])


class BicycleFastSolver(FastScenarioSolver):
    """:class:`FastScenarioSolver` on :class:`BicycleCondensedModel` (sine track only)."""

    model_class = BicycleCondensedModel


__all__ = ["BicycleCondensedModel", "BicycleFastSolver"]
