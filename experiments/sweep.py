"""The risk trade-off: one ``agents`` setting swept over values, each evaluated against a
baseline agent on the same seeds (paired bootstrap differences). The folder's layout is
:mod:`experiments.report.sweep_summary`'s; every evaluation folder resumes as usual.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from controllers.agents.registry import AGENT_REGISTRY, resolve_agents
from controllers.config import ConfigError, ExperimentConfig, load_config
from controllers.config.experiment import split_values
from experiments.evaluation import run as evaluation
from experiments.evaluation.episode import check_seeds
from experiments.evaluation.storage import check_folder
from experiments.report.sweep_summary import (
    BASELINE_FOLDER,
    MANIFEST,
    SweepSummary,
    load_sweep,
    read_manifest,
    value_folder,
    write_sweep,
)

SECTION = "agents"  # the sweep varies agent settings only: the episodes stay the same


def config_with(config: ExperimentConfig, key: str, text: str) -> ExperimentConfig:
    """The config with one dotted key of ``agents`` (``"agents.robust.backoff"``) set to ``text``,
    read by the field's type (``"2"`` for a list field is ``[2.0]``; ``"null"`` None).

    Raises:
        ConfigError: naming the key: outside ``agents``, unknown, a section, or a bad value.
    """
    parts = key.split(".")
    if len(parts) < 2 or parts[0] != SECTION or not all(parts):
        raise ConfigError(
            f"--set {key}: give a dotted key of the agents section, e.g. agents.backoff or "
            "agents.robust.backoff (a sweep compares agents on the same episodes, so env "
            "settings are not swept)"
        )
    try:
        return load_config(config, [(key, text)])
    except ConfigError as exc:
        message = " ".join(str(exc).split())
        if message.startswith("--set "):  # the key itself: named already
            raise ConfigError(message) from None
        raise ConfigError(f"--set {key}={text}: {message}") from None


def parse_setting(
    text: str, config: ExperimentConfig
) -> tuple[str, list[str], list[ExperimentConfig]]:
    """``"agents.backoff=0,1,2"`` -> the key, the value texts and the config of each value.

    Raises:
        ConfigError: naming the key: malformed, repeated values, or refused by the config.
    """
    key, sep, values = str(text).partition("=")
    key = key.strip()
    if not sep or not key or not values.strip():
        raise ConfigError(f"--set {text!r}: expected KEY=V1,V2,... e.g. agents.backoff=0,1,2,3")
    texts = split_values(values)
    if any(not t for t in texts):
        raise ConfigError(f"--set {text!r}: a value of {key} is empty")
    if len(set(texts)) != len(texts):
        raise ConfigError(f"--set {text!r}: the values of {key} repeat")
    return key, texts, [config_with(config, key, t) for t in texts]


def _registered_agents(agents: Any) -> list[str]:
    """Registered agent names only: the sweep's manifest stores the agents by name."""
    specs = resolve_agents(agents)
    own = [s.text for s in specs if s.agent_class is None]
    if own:
        raise ValueError(
            f"agents {own}: only registered agents here; choose from {sorted(AGENT_REGISTRY)}"
        )
    return [s.name for s in specs]


def run_sweep(
    agent: str,
    setting: str,
    seeds: Iterable[int] | str,
    config: ExperimentConfig | str | os.PathLike | dict | None = None,
    out: str | os.PathLike = "results/sweep",
    baseline: str = "pf",
    jobs: int = 1,
    scheduler: str | None = None,
    dask_workers: int | None = None,
    progress: bool = True,
    retry_failed: bool = True,
    episode_timeout: float | None = None,
) -> SweepSummary:
    """Run the baseline and every value of ``setting``, then write ``sweep.md`` and ``.png``.

    Args:
        agent: the agent whose setting is swept (e.g. ``"robust"``).
        setting: ``"KEY=V1,V2,..."`` with a dotted key of the agents section.
        seeds: env seeds (integers >= 0) or a text such as ``"0:100"``.
        config: the base config (a path, a dict, an ``ExperimentConfig`` or ``None``).
        out: the sweep folder.
        baseline: the agent every value is compared with, run once on the base config.
        jobs, scheduler, dask_workers: how each evaluation runs (:func:`evaluate`).
        progress: progress bars (one per evaluation, labelled with its value).
        retry_failed: re-run saved episodes that raised an error.
        episode_timeout: wall-clock limit of one episode [s] (as :func:`evaluate`).

    Returns:
        The summary read back from the folder (:func:`load_sweep`).

    Raises:
        ValueError: bad agents, seeds or setting, or a folder of another sweep or config,
            before any episode runs.
    """
    (agent_name,) = _registered_agents([agent])
    (baseline_name,) = _registered_agents([baseline])
    seed_list = check_seeds(seeds)
    base = evaluation.resolve_config(config, [baseline_name])
    if episode_timeout is None:  # (the values' configs are built without the run settings)
        episode_timeout = base.evaluation.episode_timeout or 0
    key, texts, configs = parse_setting(setting, base)
    for cfg in configs:
        evaluation.resolve_config(cfg, [agent_name])
    out_path = Path(out).resolve()
    if out_path.exists() and not out_path.is_dir():
        raise evaluation.ResultsFolderError(f"sweep folder {str(out_path)!r} is a file")
    manifest = {
        "agent": agent_name,
        "baseline": baseline_name,
        "key": key,
        "values": texts,
        "seeds": seed_list,
    }
    old = read_manifest(out_path)
    if old is not None:
        differ = [k for k in ("agent", "baseline", "key") if old[k] != manifest[k]]
        if differ:
            shown = "; ".join(f"{k}: {old[k]!r} in the folder, {manifest[k]!r} now" for k in differ)
            raise evaluation.ResultsFolderError(
                f"sweep folder {str(out_path)!r} holds another sweep ({shown}); choose another "
                "output folder or delete this one"
            )
    runs = [(baseline_name, base, out_path / BASELINE_FOLDER, f"{baseline_name} (baseline)")]
    runs += [
        (agent_name, cfg, out_path / value_folder(key, t), f"{key}={t}")
        for t, cfg in zip(texts, configs, strict=True)
    ]
    for _, cfg, folder, _ in runs:  # every folder checked before the first episode
        check_folder(folder, cfg)
    out_path.mkdir(parents=True, exist_ok=True)
    (out_path / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    for name, cfg, folder, label in runs:
        evaluation.evaluate(
            [name],
            seed_list,
            cfg,
            out=folder,
            jobs=jobs,
            scheduler=scheduler,
            dask_workers=dask_workers,
            progress=progress,
            retry_failed=retry_failed,
            progress_label=label,
            episode_timeout=episode_timeout,
        )
    summary = load_sweep(out_path)
    write_sweep(summary)
    return summary
