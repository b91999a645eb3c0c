"""What the commands' --help says (issue 35, item 8): the same --config wording everywhere,
lfm-train's real defaults, and where the fast solver's compiled C library is cached."""

from __future__ import annotations

import pytest

from experiments.cli.benchmark import build_parser as benchmark_parser
from experiments.cli.calibrate import _calibrate_parser
from experiments.cli.evaluate import _evaluate_parser
from experiments.cli.render import _render_parser
from experiments.cli.sweep import _sweep_parser
from experiments.cli.train import _train_parser

PARSERS = {
    "lfm-evaluate": _evaluate_parser,
    "lfm-render": _render_parser,
    "lfm-sweep": _sweep_parser,
    "lfm-calibrate": _calibrate_parser,
    "lfm-train": _train_parser,
    "lfm-benchmark": benchmark_parser,
}


def help_text(name: str) -> str:
    return " ".join(PARSERS[name]().format_help().split())


@pytest.mark.parametrize("name", sorted(PARSERS))
def test_every_config_option_takes_a_preset_by_name(name):
    text = help_text(name)
    assert "--config NAME|YAML a preset's name (matlab_reference, paper, quadrotor, quick)" in text
    assert "config YAML" not in text


def test_lfm_trains_help_states_its_defaults():
    import inspect

    from experiments.rl_training import DEFAULT_N_ENVS, train

    text = help_text("lfm-train")
    assert DEFAULT_N_ENVS == 8 == inspect.signature(train).parameters["n_envs"].default
    assert f"(default {DEFAULT_N_ENVS})" in text and "(default 1e6)" in text
    assert "(default: none, the --timesteps cap alone)" in text and "OUT/eval.yaml" in text


@pytest.mark.parametrize("name", ["lfm-evaluate", "lfm-benchmark"])
def test_the_cache_of_the_compiled_c_library_is_named(name, monkeypatch):
    from controllers.solvers.fast.codegen.build import CACHE_ENV, cache_dir

    monkeypatch.delenv(CACHE_ENV, raising=False)
    text = help_text(name)
    assert f"${CACHE_ENV} (default ~/{cache_dir().relative_to(cache_dir().home())})" in text
