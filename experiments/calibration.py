"""Learning the latent force's hyperparameters from calibration episodes, on any world
(``docs/evaluation.md``).

The nominal MPC drives the world; the force moves the states ``S`` through its gain ``G``
(:meth:`~lfm_env.model.LatentForceModel.force_gain`). Their Euler step, linearised about
each measurement, is a linear-Gaussian model ::

    x_S[k+1] = x_S[k] + dt (f0_S(y_k, u_k) + J_SS (x_S[k] - y_S[k])) + dt G_S w_k + e_k
    y_S[k]   = x_S[k] + n_k

(the other states' measurement noise added to the process noise), whose Kalman likelihood
(:func:`lfm_env.gp.likelihood.driven_log_likelihood`) is maximised over the force's
``variance`` and ``lengthscale`` (:func:`lfm_env.gp.inference.fit_driven`).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from controllers.config import ExperimentConfig, load_config
from lfm_env.config import LatentForceConfig, WorldConfig, to_dict

LEARNABLE = ("variance", "lengthscale")
#: The box of the learned values [the force's unit squared], [s]: wide, and the start
#: (variance 1, lengthscale 1 s) borrows nothing from the truth.
BOUNDS = {"variance": (1e-4, 1e4), "lengthscale": (1e-2, 1e3)}


@dataclass
class CalibrationRecord:
    """Measured states and applied inputs of one calibration episode."""

    measured: np.ndarray  # (T+1, nx) observations [the states' SI units] at samples 0..T
    inputs: np.ndarray  # (T, nu) applied inputs during steps 0..T-1
    true_latent_force: np.ndarray | None = None  # (T, nw) true w, kept only for reporting


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
    states: tuple[str, ...] = ()  # the measured states the force drives (the fit's data)


def record_calibration_episodes(
    config: ExperimentConfig, seeds: range | list[int] = range(5), agent: str = "nominal"
) -> list[CalibrationRecord]:
    """Run calibration episodes with ``agent`` (``"nominal"`` needs no force model) on ``seeds``
    and record states and inputs.
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the envs)
    from controllers.agents import make_agent

    records = []
    for seed in seeds:
        env = gym.make(config.env_id, config=config.env)
        ctrl = make_agent(agent, config)
        obs, info = env.reset(seed=int(seed))
        ctrl.reset(seed=int(seed) + 7919)
        measured, inputs, forces = [obs], [], []
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(ctrl.act(obs))
            measured.append(obs)
            inputs.append(info["applied_action"])
            forces.append(np.atleast_1d(info["latent_force"]))
            done = terminated or truncated
        env.close()
        records.append(
            CalibrationRecord(
                np.array(measured, dtype=float),
                np.array(inputs, dtype=float).reshape(len(inputs), -1),
                np.array(forces, dtype=float).reshape(len(forces), -1),
            )
        )
    return records


def _drift_jacobian(model: Any, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``df0/dx`` ``(T, nx, nx)`` of the force-free drift at each row of ``x``, ``u``."""
    import casadi as ca

    system = model.system
    xs, us = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu)
    f0 = system.casadi_rhs()(xs, us, ca.DM.zeros(system.nw))
    jac = ca.Function("df0_dx", [xs, us], [ca.jacobian(f0, xs)]).map(len(x))
    out = np.asarray(jac(x.T, u.T), dtype=float)  # (nx, T nx): the blocks side by side
    return out.reshape(system.nx, len(x), system.nx).transpose(1, 0, 2)


def forced_states(model: Any, records: list[CalibrationRecord]) -> np.ndarray:
    """Indices of the states the force moves at some recorded step (``G`` not zero there).

    Raises:
        ValueError: when the force does not enter the system affinely, or moves no state.
    """
    if not model.force_enters_affinely:
        raise ValueError(
            f"system {model.system.name!r}: lfm-calibrate needs a force that enters "
            "f(x, u, w) affinely (f0(x, u) + G(x, u) w)"
        )
    moved = np.zeros(model.nx, dtype=bool)
    for rec in records:
        G = model.force_gain(rec.measured[:-1], rec.inputs)  # (T, nx, nw)
        moved |= np.any(G != 0.0, axis=(0, 2))
    if not moved.any():
        raise ValueError("the latent force moves no state on the recorded steps: nothing to fit")
    return np.flatnonzero(moved)


def force_observations(
    model: Any, record: CalibrationRecord, measurement_std: Any, states: np.ndarray
) -> dict[str, np.ndarray]:
    """The data of one episode for :func:`lfm_env.gp.likelihood.driven_log_likelihood`:
    the measured ``states`` with the known part, transition, force gain and noise of each
    step, from the model linearised about the measurements (see the module docstring)."""
    y, u = record.measured, record.inputs
    x = y[:-1]
    dt = model.dt
    S = np.asarray(states)
    O = np.setdiff1d(np.arange(model.nx), S)  # noqa: E741 (the other states)
    f0 = np.asarray(model.system.rhs(x, u, np.zeros(model.nw)), dtype=float)  # (T, nx)
    G = model.force_gain(x, u)  # (T, nx, 1): a world's force has one component
    J = _drift_jacobian(model, x, u)
    J_SS, J_SO = J[:, S][:, :, S], J[:, S][:, :, O]
    r = np.asarray(measurement_std, dtype=float) ** 2
    process = np.diag(np.asarray(model.process_std, dtype=float)[S] ** 2)
    spread = dt**2 * np.einsum("kio,o,kjo->kij", J_SO, r[O], J_SO)
    return {
        "measured": y[:, S],
        "offset": dt * (f0[:, S] - np.einsum("kij,kj->ki", J_SS, x[:, S])),
        "transition": np.eye(len(S)) + dt * J_SS,
        "gain": dt * G[:, S, 0],
        "measurement_variance": r[S],
        "process_covariance": process + spread,
    }


def fit_latent_force(
    records: list[CalibrationRecord],
    env_config: WorldConfig,
    initial: LatentForceConfig | None = None,
) -> CalibrationResult:
    """Maximum-likelihood ``variance`` and ``lengthscale`` of the latent force of any world,
    from ``records`` of the world ``env_config``; the kernel family from ``initial`` (default:
    the world's, started at variance 1 and lengthscale 1 s).
    """
    from lfm_env.gp.inference import fit_driven

    if not records:
        raise ValueError("records: need at least one calibration episode")
    base = initial or dataclasses.replace(env_config.latent_force, variance=1.0, lengthscale=1.0)
    model = env_config.make_model(base)
    states = forced_states(model, records)
    std = env_config.measurement_std_rad
    episodes = [force_observations(model, rec, std, states) for rec in records]
    fitted = fit_driven(base.make_kernel(), model.dt, episodes, LEARNABLE, BOUNDS)
    info = fitted.fit_info
    learned = dataclasses.replace(base, **{k: info.hyperparameters[k] for k in LEARNABLE})
    names = model.system.state_names
    return CalibrationResult(
        latent_force=learned,
        log_likelihood=info.log_likelihood,
        true={k: float(getattr(env_config.latent_force, k)) for k in LEARNABLE},
        n_episodes=len(records),
        n_samples=int(sum(len(r.inputs) for r in records)),
        success=info.success,
        message=info.message,
        std_errors=dict(info.std_errors),
        states=tuple(names[i] for i in states),
    )


def calibrate(
    config: ExperimentConfig | str | os.PathLike | None = None, seeds: range | list[int] = range(5)
) -> CalibrationResult:
    """Calibration episodes (env ``seeds``) under the nominal MPC, then a maximum-likelihood fit;
    ``config`` as for :func:`~controllers.config.load_config`.
    """
    config = load_config(config)
    return fit_latent_force(record_calibration_episodes(config, seeds), config.env)


def write_learned_config(
    config: ExperimentConfig, result: CalibrationResult, path: str | os.PathLike
) -> None:
    """Write the resolved ``config`` with ``agents.latent_force`` set to the learned values."""
    import yaml

    data = config.to_dict()
    data["agents"]["latent_force"] = to_dict(result.latent_force)
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
            yaml.safe_dump(data, fh, sort_keys=False)
        os.replace(tmp, target)
    except BaseException:  # disk full, Ctrl-C: leave no temporary file behind
        Path(tmp).unlink(missing_ok=True)
        raise
