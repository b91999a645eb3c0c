"""Learning the latent force's hyperparameters from calibration episodes.

The paper gives the controller the GP's hyperparameters a priori and notes that, with
full-state feedback, they can be learned from measurements. Here a calibration run
drives the car with a simple controller (the nominal MPC, which needs no latent force
model), records the measured speeds and the applied accelerations, and maximises the
exact likelihood of the measured speeds under the model

    v_{k+1} = v_k + (a_k + H z_k) dt + e_k,   z_{k+1} = A z_k + eta_k,   y_k = v_k + n_k

with a Kalman filter on ``[v, z]``. This is the "w ~ dv/dt - a" idea with the
measurement noise kept in the model: differencing noisy speeds would give a
correlated (moving-average) noise that a white-noise GP likelihood ignores.
The other physical states carry no information about ``w`` and are left out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize

from lfm_env.config import LatentForceConfig, SineTrackConfig, load_env_config
from lfm_env.gp import StateSpaceKernel

LEARNABLE = ("variance", "lengthscale")


@dataclass
class SpeedRecord:
    """Measured speeds and applied accelerations of one calibration episode."""

    speed: np.ndarray  # (T+1,) measured speed [m/s] at samples 0..T
    accel: np.ndarray  # (T,) applied acceleration [m/s^2] during steps 0..T-1
    true_latent_force: np.ndarray | None = None  # (T,) true w, kept only for reporting


@dataclass
class CalibrationResult:
    """Learned hyperparameters and how the fit went."""

    latent_force: LatentForceConfig  # the learned kernel settings, usable as agents.latent_force
    log_likelihood: float  # of all records at the optimum
    true: dict[str, float]  # the env's (hidden) hyperparameters, for comparison only
    n_episodes: int
    n_samples: int
    success: bool
    message: str
    std_errors: dict[str, float] = field(default_factory=dict)  # in log-space, from the Hessian


def speed_log_likelihood(
    kernel: StateSpaceKernel,
    records: list[SpeedRecord],
    dt: float,
    measurement_std: float,
    process_std: float,
) -> float:
    """Exact log-likelihood [nats] of the measured speeds of ``records`` under ``kernel``.

    Args:
        kernel: the latent force's state-space kernel (hyperparameters to score).
        records: calibration episodes; each starts with the latent state stationary.
        dt: sampling time [s].
        measurement_std: std of the speed measurement [m/s].
        process_std: per-step std of the process noise on the speed [m/s].
    """
    A_z, Q_z = kernel.discretize(dt)
    H = np.asarray(kernel.H, dtype=float).reshape(-1)
    p = A_z.shape[0]
    A = np.zeros((p + 1, p + 1))
    A[0, 0] = 1.0
    A[0, 1:] = dt * H
    A[1:, 1:] = A_z
    Q = np.zeros((p + 1, p + 1))
    Q[0, 0] = process_std**2
    Q[1:, 1:] = Q_z
    r = measurement_std**2
    total = 0.0
    for rec in records:
        # Diffuse-ish prior on v (first measurement decides it), stationary on z.
        m = np.zeros(p + 1)
        m[0] = rec.speed[0]
        P = np.zeros((p + 1, p + 1))
        P[0, 0] = r
        P[1:, 1:] = kernel.Pinf
        for k in range(len(rec.accel)):
            m = A @ m
            m[0] += rec.accel[k] * dt
            P = A @ P @ A.T + Q
            s = P[0, 0] + r
            innov = rec.speed[k + 1] - m[0]
            total += -0.5 * (np.log(2.0 * np.pi * s) + innov * innov / s)
            gain = P[:, 0] / s
            m = m + gain * innov
            P = P - np.outer(gain, P[0, :])
            P = 0.5 * (P + P.T)
    return float(total)


def record_calibration_episodes(
    config: Any = None, seeds: range | list[int] = range(5), agent: str = "nominal"
) -> list[SpeedRecord]:
    """Run calibration episodes with a simple controller and record speeds and inputs.

    Args:
        config: the world (a path, dict or config); its ``agents`` section sets the controller.
        seeds: env seeds of the calibration episodes.
        agent: the controller; ``"nominal"`` needs no latent force model.
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the env)
    from controllers.agents import make_agent
    from controllers.config import load_config

    config = load_config(config)  # read and checked once for all episodes
    records = []
    for seed in seeds:
        env = gym.make("lfm_env/SineTrack-v0", config=config.env)
        ctrl = make_agent(agent, config)
        obs, info = env.reset(seed=int(seed))
        ctrl.reset(seed=int(seed) + 7919)
        speeds, accels, ws = [obs[2]], [], []
        done = False
        while not done:
            u = ctrl.act(obs)
            obs, _, terminated, truncated, info = env.step(u)
            speeds.append(obs[2])
            accels.append(info["applied_action"][0])
            ws.append(info["latent_force"])
            done = terminated or truncated
        env.close()
        records.append(SpeedRecord(np.array(speeds), np.array(accels), np.array(ws)))
    return records


def fit_latent_force(
    records: list[SpeedRecord],
    env_config: SineTrackConfig,
    initial: LatentForceConfig | None = None,
) -> CalibrationResult:
    """Maximum-likelihood ``variance`` and ``lengthscale`` of the latent force.

    The kernel family and its fixed settings (``nu``, ``order``, ``period``...) come from
    ``initial`` (default: the env's ``latent_force`` section, with a deliberately wrong
    start of variance 1 and lengthscale 1 s so nothing is borrowed from the truth).
    """
    if not records:
        raise ValueError("records: need at least one calibration episode")
    base = initial or dataclasses.replace(env_config.latent_force, variance=1.0, lengthscale=1.0)
    dt = env_config.dt
    meas_std = float(env_config.measurement_std_rad[2])
    proc_std = float(env_config.process_noise_std_rad[2])

    def kernel_of(theta: np.ndarray) -> StateSpaceKernel:
        variance, lengthscale = (float(v) for v in np.exp(theta))
        return dataclasses.replace(base, variance=variance, lengthscale=lengthscale).make_kernel()

    def negative_ll(theta: np.ndarray) -> float:
        try:
            return -speed_log_likelihood(kernel_of(theta), records, dt, meas_std, proc_std)
        except (ValueError, np.linalg.LinAlgError):
            return 1e12  # outside the kernel's usable range

    theta0 = np.log([base.variance, base.lengthscale])
    bounds = [(np.log(1e-4), np.log(1e4)), (np.log(1e-2), np.log(1e3))]
    res = scipy.optimize.minimize(negative_ll, theta0, method="L-BFGS-B", bounds=bounds)
    std_errors = _log_space_std_errors(negative_ll, res.x)
    learned = dataclasses.replace(
        base, variance=float(np.exp(res.x[0])), lengthscale=float(np.exp(res.x[1]))
    )
    true = {k: float(getattr(env_config.latent_force, k)) for k in LEARNABLE}
    return CalibrationResult(
        latent_force=learned,
        log_likelihood=-float(res.fun),
        true=true,
        n_episodes=len(records),
        n_samples=int(sum(len(r.accel) for r in records)),
        success=bool(res.success),
        message=str(res.message),
        std_errors=dict(zip(LEARNABLE, std_errors, strict=True)),
    )


def _log_space_std_errors(f, theta: np.ndarray, h: float = 1e-3) -> list[float]:
    """Standard errors from a central-difference Hessian of ``f`` (NaN if not PD)."""
    n = theta.size
    hess = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            ei, ej = np.eye(n)[i] * h, np.eye(n)[j] * h
            hess[i, j] = (
                f(theta + ei + ej) - f(theta + ei - ej) - f(theta - ei + ej) + f(theta - ei - ej)
            ) / (4 * h * h)
    try:
        cov = scipy.linalg.inv(0.5 * (hess + hess.T))
        return [float(np.sqrt(c)) if c > 0 else float("nan") for c in np.diag(cov)]
    except np.linalg.LinAlgError:
        return [float("nan")] * n


def calibrate(config: Any = None, seeds: range | list[int] = range(5)) -> CalibrationResult:
    """Calibration episodes under the nominal MPC, then a maximum-likelihood fit."""
    env_config = load_env_config(config)
    records = record_calibration_episodes(config, seeds)
    return fit_latent_force(records, env_config)


def write_learned_config(config: Any, result: CalibrationResult, path: str) -> None:
    """Write ``config`` (path or dict) with ``agents.latent_force`` set to the learned values."""
    import os
    import tempfile
    from pathlib import Path

    import yaml

    from lfm_env.config import load_yaml, read_section, to_dict

    if config is None:
        data: dict = {}
    elif isinstance(config, dict):
        data = dict(config)
    else:
        data = load_yaml(config)
    env = read_section(data, "env") or {}
    agents = dict(read_section(data, "agents") or {}) if ("agents" in data or "env" in data) else {}
    agents["latent_force"] = to_dict(result.latent_force)
    out = {"env": env, "agents": agents}
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    header = (
        f"# Learned by lfm-calibrate from {result.n_episodes} calibration episodes "
        f"({result.n_samples} samples).\n# The env keeps its own (hidden) latent force; "
        "the agents model the learned one.\n"
    )
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(header)
            yaml.safe_dump(out, fh, sort_keys=False)
        os.replace(tmp, target)
    except BaseException:  # disk full, Ctrl-C: leave no temporary file behind
        Path(tmp).unlink(missing_ok=True)
        raise
