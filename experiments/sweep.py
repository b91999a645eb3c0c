"""The risk trade-off: one agent setting swept over values, each against a baseline agent.

A sweep answers "what does this knob buy, and what does it cost?": for each value of one
setting of the ``agents`` section (the back-off ``agents.backoff``, ``agents.n_scenarios``,
``agents.estimator``, ``agents.n_particles``, ``agents.robust.backoff``, ...), it runs the
evaluation of one agent over env seeds (:func:`experiments.evaluation.run.evaluate`) and
compares it with a baseline agent on the same seeds (same hidden latent force and noise):
violation steps beyond each tolerance of the system, zero-violation episodes and time to
goal, each with the paired bootstrap interval of the difference to the baseline.

Sweep folder (``out``)::

    out/sweep.json              what was swept: agent, key, values, baseline, seeds
    out/baseline/               the baseline agent on the base config (an evaluation folder)
    out/<key>=<value>/          the agent with the key set to the value (one per value)
    out/sweep.md, out/sweep.png the table and the Pareto picture

Every evaluation folder resumes as the evaluation does (finished episodes are kept, so an
interrupted sweep loses at most the episodes in flight); rerunning the same sweep resumes
it. The sweep folder may be a results folder of ``lfm-evaluate`` too: ``lfm-report``
then includes the sweep's table and figure (or give ``--sweep DIR``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import types
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml

from controllers.agents.registry import AGENT_REGISTRY
from controllers.config import ConfigError, ExperimentConfig, load_config
from experiments.evaluation import run as evaluation
from experiments.evaluation.agent_lookup import OwnAgentSpec, resolve_agents
from experiments.evaluation.episode import check_seeds
from experiments.evaluation.storage import check_folder
from experiments.report.sweep_summary import (
    BASELINE_FOLDER,
    MANIFEST,
    SweepSummary,
    SweepValue,
    load_sweep,
    read_manifest,
    sweep_errors,
    sweep_figure,
    sweep_metrics,
    sweep_table,
    value_folder,
    write_sweep,
)

SECTION = "agents"  # the sweep varies agent settings only: the episodes stay the same


# --------------------------------------------------------------------------- the setting


def split_values(text: str) -> list[str]:
    """Comma-separated values, commas inside brackets kept: ``"0,[1,2]"`` -> ``["0", "[1,2]"]``."""
    values, depth, current = [], 0, []
    for ch in text:
        depth += {"[": 1, "]": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            values.append("".join(current).strip())
            current = []
        else:
            current.append(ch)
    values.append("".join(current).strip())
    return values


def _field_types(obj: Any) -> dict[str, Any]:
    """The annotated types of a config dataclass's init fields."""
    hints = typing.get_type_hints(type(obj))
    return {f.name: hints[f.name] for f in dataclasses.fields(obj) if f.init}


def _optional(tp: Any) -> tuple[Any, bool]:
    """``(inner type, whether None is allowed)`` of ``X | None``; other types unchanged."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return inner[0], len(inner) < len(typing.get_args(tp))
    return tp, False


def _parse_text(text: str, tp: Any) -> Any:
    """A value given on the command line, read as the config field's type ``tp`` reads it.

    Strings stay as written; numbers are read as numbers (``1e-3`` too); a list field
    takes ``[a, b]`` or one value, which becomes a list of one. What does not parse is
    passed on as text, so the config's own check names the key.
    """
    tp, nullable = _optional(tp)
    if nullable and text.strip().lower() in ("null", "none", "~"):
        return None
    text = text.strip()
    if tp is str:
        return text
    if tp is int:
        return int(text) if re.fullmatch(r"[+-]?\d+", text) else text
    if tp is float:
        try:
            return float(text)
        except ValueError:
            return text
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if text.startswith("[") and text.endswith("]"):
            inner = text[1:-1].strip()
            items = split_values(inner) if inner else []
        else:
            items = [text]
        if len(args) == 2 and args[1] is Ellipsis:
            return [_parse_text(i, args[0]) for i in items]
        return [_parse_text(i, a) for i, a in zip(items, args, strict=False)] + items[len(args) :]
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def config_with(config: Any, key: str, text: str) -> ExperimentConfig:
    """The config with one dotted key of the ``agents`` section set to a value.

    Args:
        config: the base config (a path, a dict, an ``ExperimentConfig`` or ``None``).
        key: a dotted key under ``agents``, e.g. ``"agents.backoff"`` or
            ``"agents.robust.backoff"``.
        text: the value as written, read by the field's type (``"2"`` for a list field
            is ``[2.0]``; ``"[1, 2, 0]"`` a list; ``"null"`` None where allowed).

    Raises:
        ConfigError: naming the key, for a key outside ``agents``, an unknown key, a
            section given as the key, or a value the config refuses.
    """
    base = load_config(config)
    parts = key.split(".")
    if len(parts) < 2 or parts[0] != SECTION or not all(parts):
        raise ConfigError(
            f"--set {key}: give a dotted key of the agents section, e.g. agents.backoff or "
            "agents.robust.backoff (a sweep compares agents on the same episodes, so env "
            "settings are not swept)"
        )
    data = base.to_dict()
    node, obj = data[SECTION], base.agents
    for depth, name in enumerate(parts[1:], start=1):
        where = ".".join(parts[:depth])
        fields = _field_types(obj)
        if name not in fields:
            raise ConfigError(
                f"--set {key}: {where} has no key {name!r}; its keys are {sorted(fields)}"
            )
        tp, _ = _optional(fields[name])
        last = depth == len(parts) - 1
        if not last:
            if not dataclasses.is_dataclass(tp):
                raise ConfigError(f"--set {key}: {where}.{name} is a value, not a section")
            current = getattr(obj, name)
            obj = current if current is not None else tp()
            if not isinstance(node.get(name), dict):
                node[name] = {}
            node = node[name]
        elif dataclasses.is_dataclass(tp):
            raise ConfigError(
                f"--set {key}: {key} is a section; set one of its keys {sorted(_field_types(tp()))}"
            )
        else:
            node[name] = _parse_text(text, fields[name])
    try:
        return load_config(data)
    except ConfigError as exc:
        raise ConfigError(f"--set {key}={text}: {' '.join(str(exc).split())}") from None


def parse_setting(text: str, config: Any = None) -> tuple[str, list[str], list[ExperimentConfig]]:
    """``"agents.backoff=0,1,2"`` -> the key, the value texts and the config of each value.

    Raises:
        ConfigError: naming the key, for a malformed text, repeated values, or a key or
            value the config refuses (:func:`config_with`).
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
    base = load_config(config)
    return key, texts, [config_with(base, key, t) for t in texts]


# --------------------------------------------------------------------------- running


def _registered_agents(agents: Any) -> list[str]:
    """Registered agent names only: the sweep's manifest stores the agents by name."""
    specs = resolve_agents(agents)
    own = [s.text for s in specs if isinstance(s, OwnAgentSpec)]
    if own:
        raise ValueError(
            f"agents {own}: only registered agents here; choose from {sorted(AGENT_REGISTRY)}"
        )
    return specs


def run_sweep(
    agent: str,
    setting: str,
    seeds: Iterable[int] | str,
    config: Any = None,
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
        setting: ``"KEY=V1,V2,..."`` with a dotted key of the agents section
            (:func:`parse_setting`).
        seeds: env seeds (integers >= 0) or a text such as ``"0:100"``.
        config: the base config (a path, a dict, an ``ExperimentConfig`` or ``None``).
        out: the sweep folder (see the module docstring).
        baseline: the agent every value is compared with, run once on the base config.
        jobs, scheduler, dask_workers: how each evaluation runs
            (:func:`experiments.evaluation.run.evaluate`).
        progress: progress bars (one per evaluation, labelled with its value).
        retry_failed: re-run saved episodes that raised an error.
        episode_timeout: wall-clock limit of one episode [s]; ``None`` for the base
            config's ``evaluation.episode_timeout``, 0 for none (as
            :func:`experiments.evaluation.run.evaluate`).

    Returns:
        The summary read back from the folder (:func:`load_sweep`).

    Raises:
        ValueError: unknown agents, bad seeds, a bad setting (naming the key) or a folder
            that holds another sweep or another config, before any episode runs.
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


__all__ = [
    "SweepSummary",
    "SweepValue",
    "config_with",
    "load_sweep",
    "parse_setting",
    "run_sweep",
    "split_values",
    "sweep_errors",
    "sweep_figure",
    "sweep_metrics",
    "sweep_table",
    "value_folder",
    "write_sweep",
]
