"""The RL baseline as an agent: a policy trained by ``lfm-train`` behind the agents' face.

:class:`RLAgent` (agent name ``"rl"``) loads the stable-baselines3 policy named by
``agents.rl_policy`` (``OUT/policy.zip`` of ``lfm-train``, with ``OUT/policy.npz``, the
observation normalisation, and ``OUT/policy.json``, the algorithm and the SHA-256 of the
other two, beside it: a set of files of two trainings is refused) and acts
like the MPC agents: ``reset(seed)``, ``act(obs)`` returning a float64 action in the
inputs' units, and ``last_info``. It reads the observation only (no hidden truth): the
policy sees :func:`policy_features` of it, the noisy state and the signed constraint values
``g(y)`` of the known system (the same features in training and here).

stable-baselines3 and torch are the ``rl`` extra (``pip install -e .[rl]``); they are
imported when a policy is loaded. A policy file is a pickle-based SB3 archive: load only
policies you trained yourself.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from controllers.config import AgentConfig
from lfm_env.config import ConfigError
from lfm_env.cost import QuadraticCost
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem
from lfm_env.validation import real_vector

ALGOS = ("ppo", "sac")


def policy_features(system: ControlSystem, y: np.ndarray) -> np.ndarray:
    """What the policy observes: ``[y, g(y)]``, shape ``(nx + ng,)``, float64.

    Args:
        system: the known system (its ``constraint_values``, ``g <= 0`` inside the bounds,
            in each constraint's unit).
        y: the observation ``(nx,)`` in the states' units.
    """
    y = np.asarray(y, dtype=float)
    g = np.asarray(system.constraint_values(y), dtype=float).reshape(-1)
    return np.concatenate([y, g])


def _policy_error(path: Any, problem: str) -> ConfigError:
    return ConfigError(
        f"agents.rl_policy={path!r}: {problem}; set it to the policy.zip written by lfm-train "
        "(e.g. lfm-train --out results/rl/ppo, then agents.rl_policy: results/rl/ppo/policy.zip)"
    )


def file_digest(path: Path) -> str:
    """The SHA-256 of a file's content (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def policy_set_problem(policy: Path, summary: dict[str, Any]) -> str | None:
    """Why the policy files of ``policy`` (its ``.zip`` and ``.npz``) are not the set its
    summary ``.json`` records (``summary["files"]``: each file's SHA-256, written by
    ``lfm-train`` with the set), else ``None``. A summary without ``files`` (written before
    sets were recorded) cannot be checked and passes."""
    files = summary.get("files")
    if files is None:
        return None
    if not isinstance(files, dict):
        return f"{policy.with_suffix('.json').name} holds no valid list of files"
    for name, recorded in sorted(files.items()):
        path = policy.with_suffix(Path(str(name)).suffix)
        try:
            actual = file_digest(path)
        except OSError as exc:
            return f"{path.name} cannot be read ({exc.strerror or exc})"
        if actual != recorded:
            return (
                f"{path.name} does not match {policy.with_suffix('.json').name} (its SHA-256 is "
                "not the one recorded with the set: the files of two trainings, as a training "
                "stopped while writing them, or a file copied from another run, leaves)"
            )
    return None


def check_rl_policy(path: str | None) -> tuple[Path, Path, Path]:
    """The policy, normalisation and summary files of ``agents.rl_policy``, or a ConfigError.

    Raises:
        ConfigError: naming ``agents.rl_policy`` when it is null, not a file, or the
            ``.npz``/``.json`` written beside it by ``lfm-train`` are missing.
    """
    if path is None:
        raise _policy_error(path, "the 'rl' agent needs a trained policy, got null")
    policy = Path(path)
    if not policy.is_file():
        raise _policy_error(path, "no such file")
    norm, summary = policy.with_suffix(".npz"), policy.with_suffix(".json")
    for extra in (norm, summary):
        if not extra.is_file():
            raise _policy_error(path, f"{extra.name} is missing beside it")
    return policy, norm, summary


class RLAgent:
    """A trained stable-baselines3 policy acting on the observation.

    Args:
        model: the agent's latent-force model (its ``system``: features, input bounds).
        cost: the control objective (unused: the policy was trained on it).
        settings: agent settings; ``settings.rl_policy`` is the policy's ``.zip``.
        measurement_std: unused (the policy was trained with the env's noise).

    Raises:
        ConfigError: naming ``agents.rl_policy`` if the policy is missing, unreadable or
            made for another system (its features or its actions have other sizes).
    """

    name = "rl"

    def __init__(
        self,
        model: LatentForceModel,
        cost: QuadraticCost | None = None,
        settings: AgentConfig | None = None,
        measurement_std: Any = None,
    ) -> None:
        self.model = model
        self.system = model.system
        self.settings = AgentConfig() if settings is None else settings
        path = self.settings.rl_policy
        policy, norm, summary = check_rl_policy(path)
        try:
            info = json.loads(summary.read_text())
            algo = info["algo"]
            stats = np.load(norm, allow_pickle=False)
            self._mean = np.asarray(stats["mean"], dtype=float)
            self._std = np.sqrt(np.asarray(stats["var"], dtype=float) + float(stats["epsilon"]))
            self._clip = float(stats["clip_obs"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise _policy_error(path, f"unreadable files beside it ({exc})") from None
        problem = policy_set_problem(policy, info)
        if problem is not None:
            raise _policy_error(path, f"{problem}; train it again (lfm-train --resume or --force)")
        if algo not in ALGOS:
            raise _policy_error(path, f"unknown algorithm {algo!r} in {summary.name}")
        trained_on = info.get("system", self.system.name)  # written by lfm-train
        if trained_on != self.system.name:
            raise _policy_error(
                path, f"trained on the {trained_on} system, this is {self.system.name}"
            )
        self.policy = _load(algo, policy, path)
        n_features = self.system.nx + self.system.ng
        shape = self.policy.observation_space.shape
        if shape != (n_features,) or self._mean.shape != (n_features,):
            raise _policy_error(
                path, f"made for {shape} features, this system has {n_features} (nx + ng)"
            )
        if self.policy.action_space.shape != (self.system.nu,):
            raise _policy_error(path, f"made for other actions than the system's {self.system.nu}")
        self.algo = algo
        self.last_info: dict[str, Any] = {}

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode (the policy acts deterministically; ``seed`` is unused)."""
        self.last_info = {}

    def act(self, obs: Any) -> np.ndarray:
        """The action ``(nu,)`` float64 in the inputs' units for an observation ``(nx,)``."""
        y = real_vector(obs, self.system.nx, "obs", f"{list(self.system.state_names)}")
        t0 = time.perf_counter()
        z = np.clip(
            (policy_features(self.system, y) - self._mean) / self._std, -self._clip, self._clip
        )
        a, _ = self.policy.predict(z.astype(np.float32), deterministic=True)
        a = np.clip(np.asarray(a, dtype=float).reshape(self.system.nu), -1.0, 1.0)
        low, high = self.system.input_lower, self.system.input_upper
        u = self.system.clip_input(low + 0.5 * (a + 1.0) * (high - low))
        self.last_info = {
            "estimate": y.copy(),
            "estimate_std": np.zeros(self.system.nx),
            "solve_time": time.perf_counter() - t0,
            "success": True,
            "policy_action": a,
        }
        return np.asarray(u, dtype=float)


def _load(algo: str, policy: Path, path: Any) -> Any:
    try:
        import torch
        from stable_baselines3 import PPO, SAC
    except ImportError as exc:
        raise ConfigError(
            f"agents.rl_policy={path!r}: the 'rl' agent needs the rl extra "
            f"(pip install -e '.[rl]'): {exc}"
        ) from None
    torch.set_num_threads(1)  # one core per episode process, as the MPC agents
    cls = {"ppo": PPO, "sac": SAC}[algo]
    try:
        return cls.load(policy, device="cpu")
    except Exception as exc:  # a damaged or foreign archive: one line naming the field
        raise _policy_error(path, f"cannot be loaded as {algo} ({type(exc).__name__})") from None


__all__ = ["RLAgent", "check_rl_policy", "file_digest", "policy_features", "policy_set_problem"]
