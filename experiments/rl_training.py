"""RL baseline: train PPO or SAC (stable-baselines3) on the config's world through ``gym.make``
(``lfm-train``; ``docs/agents.md``): actions rescaled to ``[-1, 1]``, observations
:func:`~controllers.agents.rl.policy_features` normalised by ``VecNormalize``, the
:class:`TrainingReward`. Writes ``OUT/policy.zip``, ``policy.npz``, ``policy.json`` (as one
set, ``policy.json`` last with the others' SHA-256) and ``eval.yaml``; one run owns ``OUT``
at a time (:class:`~experiments.evaluation.storage.FolderLock`).
"""

from __future__ import annotations

import json
import math
import os
import secrets
import time
from collections import deque
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import lfm_env  # noqa: F401  (registers the envs)
from controllers.agents.rl import file_digest, policy_features, policy_set_problem
from controllers.config import ExperimentConfig, load_config
from experiments.evaluation.storage import FolderLock, ResultsFolderError

ALGOS = ("ppo", "sac")
MAX_TIMESTEPS = 10**9
POLICY_FILE = "policy.zip"
EVAL_CONFIG_FILE = "eval.yaml"  # beside the policy: the config that evaluates it
DEFAULT_N_ENVS = 8  # envs stepped in lockstep (the README's measured run)


class TrainingReward(gym.Wrapper):
    """The reward RL trains on: ``reward / scale - cost_weight * info["violated_groups"]``, and on a
    failure that once more for each step the time limit had left (``max_steps - t``).

    Args:
        env: the env (rewards are minus stage costs).
        scale: divisor of the env's reward, > 0 (the stage cost at the start state).
        cost_weight: weight per violated constraint group, >= 0.
        max_steps: the episode's time limit [steps], >= 1.
    """

    def __init__(self, env: gym.Env, scale: float, cost_weight: float, max_steps: int) -> None:
        super().__init__(env)
        if not (math.isfinite(scale) and scale > 0.0):
            raise ValueError(f"scale={scale!r}: must be > 0")
        if not (math.isfinite(cost_weight) and cost_weight >= 0.0):
            raise ValueError(f"cost_weight={cost_weight!r}: must be >= 0")
        self.scale = float(scale)
        self.cost_weight = float(cost_weight)
        self.max_steps = int(max_steps)
        self._t = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self._t = 0
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._t += 1
        r = float(reward) / self.scale - self.cost_weight * float(info["violated_groups"])
        if terminated and info.get("failure", False):
            r += r * max(0, self.max_steps - self._t)
        return obs, r, terminated, truncated, info


def reward_scale(config: ExperimentConfig) -> float:
    """The stage cost at the start state with no input (the training reward's divisor)."""
    cfg = config.env
    cost = cfg.make_cost()
    nu = cfg.make_model().system.nu
    return max(float(cost.stage_cost(np.asarray(cfg.initial_state_rad), np.zeros(nu))), 1e-9)


def make_training_env(config: ExperimentConfig, cost_weight: float = 1.0) -> gym.Env:
    """One training env: ``gym.make`` of the config's world, observed through
    :func:`~controllers.agents.rl.policy_features` of the agents' known system, actions in
    ``[-1, 1]``, the :class:`TrainingReward`, and SB3's ``Monitor`` (returns, lengths)."""
    from stable_baselines3.common.monitor import Monitor

    system = config.make_model().system  # the agents' model of the world, as the rl agent
    env = gym.make(config.env_id, config=config.env)
    n = system.nx + system.ng
    space = gym.spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64)
    env = gym.wrappers.TransformObservation(env, lambda y: policy_features(system, y), space)
    env = gym.wrappers.RescaleAction(env, np.float32(-1.0), np.float32(1.0))
    env = TrainingReward(env, reward_scale(config), cost_weight, env.spec.max_episode_steps)
    return Monitor(env, info_keywords=("is_success",))


class _Progress:
    """SB3 callback factory: a tqdm bar, a wall-clock budget and the last episodes' stats."""

    @staticmethod
    def make(total: int, minutes: float | None, show: bool) -> Any:
        from stable_baselines3.common.callbacks import BaseCallback
        from tqdm import tqdm

        class Callback(BaseCallback):
            def _on_training_start(self) -> None:
                self.t0 = time.perf_counter()
                self.returns: deque[float] = deque(maxlen=100)
                self.successes: deque[float] = deque(maxlen=100)
                self.bar = tqdm(total=total, unit="step", disable=not show, smoothing=0.05)

            def _on_step(self) -> bool:
                self.bar.update(self.training_env.num_envs)
                for info in self.locals.get("infos", ()):
                    if "episode" in info:
                        self.returns.append(float(info["episode"]["r"]))
                        self.successes.append(float(info.get("is_success", False)))
                if self.returns and self.n_calls % 200 == 0:
                    self.bar.set_postfix(
                        ret=f"{np.mean(self.returns):.1f}", success=f"{np.mean(self.successes):.2f}"
                    )
                elapsed = time.perf_counter() - self.t0
                return minutes is None or elapsed < 60.0 * minutes

            def _on_training_end(self) -> None:
                self.bar.close()

        return Callback()


def _algorithm(algo: str) -> Any:
    from stable_baselines3 import PPO, SAC

    return PPO if algo == "ppo" else SAC


def _make_model(algo: str, venv: Any, seed: int, timesteps: int) -> Any:
    """PPO (512 steps per env and update, minibatches of 256) or SAC (SB3's defaults, first
    update after 1000 steps); shorter for runs shorter than one such update (smoke tests)."""
    from stable_baselines3 import PPO, SAC

    if algo == "ppo":
        n_steps = max(8, min(512, -(-timesteps // venv.num_envs)))
        return PPO(
            "MlpPolicy",
            venv,
            n_steps=n_steps,
            batch_size=min(256, n_steps * venv.num_envs),
            n_epochs=10,
            gamma=0.99,
            gae_lambda=0.95,
            learning_rate=3e-4,
            seed=seed,
            device="cpu",
            verbose=0,
        )
    starts = min(1000, timesteps // 2)
    return SAC("MlpPolicy", venv, learning_starts=starts, seed=seed, device="cpu", verbose=0)


def train(
    config: ExperimentConfig | str | os.PathLike | dict | None = None,
    algo: str = "ppo",
    timesteps: int = 1_000_000,
    minutes: float | None = None,
    out: str | Path = "results/rl/ppo",
    seed: int = 0,
    n_envs: int = DEFAULT_N_ENVS,
    cost_weight: float = 1.0,
    progress: bool = True,
    resume: bool = False,
    force: bool = False,
) -> dict[str, Any]:
    """Train a policy and save it under ``out``; returns the run's summary (``policy.json``).

    Args:
        config: an :class:`~controllers.config.ExperimentConfig`, YAML path, dict or ``None``.
        algo: ``"ppo"`` or ``"sac"``.
        timesteps: env steps to train at most, >= 1 (summed over the envs).
        minutes: wall-clock budget [min] (> 0) that stops training earlier; ``None``: none.
        out: folder of ``policy.zip``, ``policy.npz``, ``policy.json`` and ``eval.yaml``.
        seed: seed of the networks, the sampling and the envs (env ``i`` gets ``seed + i``).
        n_envs: envs stepped in lockstep in this process, >= 1.
        cost_weight: training penalty per violated constraint group and step, >= 0.
        progress: show a tqdm progress bar.
        resume: train the policy in ``out`` ``timesteps`` more steps (same algorithm, world).
        force: replace a policy saved in ``out``.

    Raises:
        ValueError: naming the bad argument and its allowed range.
        ResultsFolderError: (a ``ValueError``) ``out`` in use (named), holding a policy
            without ``resume`` or ``force``, or ``resume`` without a matching policy.
    """
    check_training_arguments(algo, timesteps, minutes, n_envs, cost_weight)
    if resume and force:
        raise ValueError("resume and force exclude each other")
    cfg = load_config(config)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    hint = "wait for that training to end or choose another output folder"
    with FolderLock(out, "training folder", hint):
        previous = check_training_folder(out, cfg, algo, resume, force)
        return _train(
            cfg, algo, timesteps, minutes, out, seed, n_envs, cost_weight, progress, previous
        )


def check_training_folder(
    out: Path, cfg: ExperimentConfig, algo: str, resume: bool, force: bool
) -> dict[str, Any] | None:
    """The summary of the policy in ``out`` to resume (``None`` to start anew).

    Raises:
        ResultsFolderError: a policy without ``resume``/``force``, or ``resume`` without a
            matching one.
    """
    policy = out / POLICY_FILE
    if not policy.exists():
        if resume:
            raise ResultsFolderError(
                f"training folder {str(out)!r} holds no policy to resume ({POLICY_FILE}); "
                "run without --resume to train a new one"
            )
        return None
    if force:
        return None
    try:
        summary = json.loads(policy.with_suffix(".json").read_text())
        steps, trained = int(summary["timesteps"]), str(summary["algo"])
        world = (str(summary["env_id"]), str(summary["system"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if resume:
            raise ResultsFolderError(
                f"training folder {str(out)!r}: cannot resume, its policy.json is missing or "
                f"damaged ({type(exc).__name__}); pass --force to replace the policy"
            ) from exc
        steps, trained, world = None, None, None
    if not resume:
        what = "a policy" if steps is None else f"a {trained} policy trained for {steps} steps"
        raise ResultsFolderError(
            f"training folder {str(out)!r} already holds {what} ({POLICY_FILE}); pass "
            "--resume to train it further or --force to replace it"
        )
    problem = policy_set_problem(policy, summary)
    if problem is not None:
        raise ResultsFolderError(
            f"training folder {str(out)!r}: cannot resume, {problem}; pass --force to train a "
            "new policy in its place"
        )
    if trained != algo:
        raise ResultsFolderError(
            f"training folder {str(out)!r} holds a {trained} policy: resume it with "
            f"--algo {trained}"
        )
    here = (cfg.env_id, cfg.make_model().system.name)
    if world != here:
        raise ResultsFolderError(
            f"training folder {str(out)!r} holds a policy of the world {world[0]} "
            f"(system {world[1]}), not of this config's {here[0]} (system {here[1]})"
        )
    return summary


def _train(
    cfg: ExperimentConfig,
    algo: str,
    timesteps: int,
    minutes: float | None,
    out: Path,
    seed: int,
    n_envs: int,
    cost_weight: float,
    progress: bool,
    previous: dict[str, Any] | None,
) -> dict[str, Any]:
    """The training of :func:`train` (``out`` locked, checked); ``previous``: the summary
    of the policy in ``out`` to resume, or ``None``."""
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    venv = DummyVecEnv([lambda: make_training_env(cfg, cost_weight)] * n_envs)
    venv.seed(seed)
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=0.99)
    if previous is None:
        model = _make_model(algo, venv, seed, int(timesteps))
    else:
        model = _algorithm(algo).load(out / POLICY_FILE, env=venv, device="cpu")
        _restore_statistics(venv, out / "policy.npz", int(previous["timesteps"]))
    callback = _Progress.make(timesteps, minutes, progress)
    t0 = time.perf_counter()
    try:
        model.learn(
            total_timesteps=timesteps, callback=callback, reset_num_timesteps=previous is None
        )
    finally:  # Ctrl-C or an error: keep what was learnt
        summary = _save(model, venv, cfg, out, algo, seed, cost_weight, t0, callback, previous)
        write_eval_config(cfg, out)
        venv.close()
    return summary


def write_eval_config(config: ExperimentConfig, out: str | Path) -> Path:
    """Write ``OUT/eval.yaml`` (the training's resolved config, ``agents.rl_policy`` the absolute
    policy path, for ``lfm-evaluate --config OUT/eval.yaml --agents rl,...``); returns its path.
    """
    import yaml

    out = Path(out)
    data = config.to_dict()
    data["agents"]["rl_policy"] = str((out / POLICY_FILE).resolve())
    path = out / EVAL_CONFIG_FILE
    header = (
        "# Written by lfm-train: the config the policy beside this file was trained on, whose\n"
        "# rl agent runs it. Evaluate it next to the MPC agents on the same seeds:\n"
        f"#   lfm-evaluate --config {path} --agents rl,nominal,scenario\n"
    )
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(header + yaml.safe_dump(data, sort_keys=False))
    os.replace(tmp, path)
    return path


def _restore_statistics(venv: Any, path: Path, steps: int) -> None:
    """The observation (and reward) normalisation saved in ``policy.npz``, into ``venv``
    (a file of an older version, without its counts, counts ``steps``)."""
    with np.load(path, allow_pickle=False) as stats:
        venv.obs_rms.mean = np.array(stats["mean"], dtype=float)
        venv.obs_rms.var = np.array(stats["var"], dtype=float)
        venv.obs_rms.count = float(stats["count"]) if "count" in stats else float(steps)
        if "ret_var" in stats:
            venv.ret_rms.mean = np.array(stats["ret_mean"], dtype=float)
            venv.ret_rms.var = np.array(stats["ret_var"], dtype=float)
            venv.ret_rms.count = float(stats["ret_count"])


def check_training_arguments(
    algo: str, timesteps: int, minutes: float | None, n_envs: int, cost_weight: float
) -> None:
    """Raise ``ValueError`` naming the first argument of :func:`train` out of its range."""
    if algo not in ALGOS:
        raise ValueError(f"algo={algo!r}: must be one of {ALGOS}")
    if isinstance(timesteps, bool) or not 1 <= int(timesteps) <= MAX_TIMESTEPS:
        raise ValueError(f"timesteps={timesteps!r}: must be an integer in [1, {MAX_TIMESTEPS}]")
    if minutes is not None and not (math.isfinite(minutes) and minutes > 0.0):
        raise ValueError(f"minutes={minutes!r}: must be > 0 (or None for no budget)")
    if isinstance(n_envs, bool) or not 1 <= int(n_envs) <= 64:
        raise ValueError(f"n_envs={n_envs!r}: must be an integer in [1, 64]")
    if not (math.isfinite(cost_weight) and cost_weight >= 0.0):
        raise ValueError(f"cost_weight={cost_weight!r}: must be >= 0")


def _replace_set(out: Path, write: dict[str, Any], summary: dict[str, Any]) -> None:
    """Write the policy's files as one set: each to a temporary file in ``out``, then
    ``policy.json`` with the SHA-256 of the others (``summary["files"]``), then every file
    renamed into place, ``policy.json`` last. A run stopped at any moment leaves the previous
    set, or files the ``rl`` agent and ``--resume`` refuse by name, never a silent mix."""
    token = secrets.token_hex(4)
    temporary = {name: out / f".{name}.{token}.tmp" for name in (*write, "policy.json")}
    try:
        for name, writer in write.items():
            writer(temporary[name])
        summary["files"] = {name: file_digest(temporary[name]) for name in write}
        temporary["policy.json"].write_text(json.dumps(summary, indent=2) + "\n")
        for name, path in temporary.items():  # policy.json last (dicts keep order)
            os.replace(path, out / name)
    finally:
        for path in temporary.values():
            path.unlink(missing_ok=True)


def _save(
    model: Any,
    venv: Any,
    cfg: ExperimentConfig,
    out: Path,
    algo: str,
    seed: int,
    cost_weight: float,
    t0: float,
    callback: Any,
    previous: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``policy.zip``, ``policy.npz`` (observation normalisation) and ``policy.json``
    (with the other two's SHA-256) as one set (:func:`_replace_set`)."""
    rms = venv.obs_rms
    statistics = {
        "mean": rms.mean,
        "var": rms.var,
        "epsilon": np.float64(venv.epsilon),
        "clip_obs": np.float64(venv.clip_obs),
        "count": np.float64(rms.count),
        "ret_mean": np.asarray(venv.ret_rms.mean, dtype=float),
        "ret_var": np.asarray(venv.ret_rms.var, dtype=float),
        "ret_count": np.float64(venv.ret_rms.count),
    }

    def save_npz(path: Path) -> None:
        with open(path, "wb") as fh:
            np.savez(fh, **statistics)

    def save_zip(path: Path) -> None:
        with open(path, "wb") as fh:  # (a file object: SB3 adds no suffix)
            model.save(fh)

    earlier = 0.0 if previous is None else float(previous.get("wall_time_s") or 0.0)
    returns = list(getattr(callback, "returns", []))
    successes = list(getattr(callback, "successes", []))
    summary = {
        "algo": algo,
        "env_id": cfg.env_id,
        "system": cfg.make_model().system.name,  # the rl agent refuses another system
        "timesteps": int(model.num_timesteps),
        "wall_time_s": round(earlier + time.perf_counter() - t0, 1),
        "resumed_from": 0 if previous is None else int(previous["timesteps"]),
        "seed": int(seed),
        "n_envs": int(venv.num_envs),
        "cost_weight": float(cost_weight),
        "reward_scale": reward_scale(cfg),
        "last_episodes": len(returns),
        "last_training_return_mean": float(np.mean(returns)) if returns else None,
        "last_success_rate": float(np.mean(successes)) if successes else None,
        "n_features": int(rms.mean.shape[0]),
    }
    _replace_set(out, {POLICY_FILE: save_zip, "policy.npz": save_npz}, summary)
    return summary
