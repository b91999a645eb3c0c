"""Tests of the packaging: the presets found by name from any folder, the package list,
the licence and the citation metadata."""

from __future__ import annotations

import subprocess
import sys
from fnmatch import fnmatch
from pathlib import Path

import pytest
import yaml

from experiments.cli import config_file, preset_names
from experiments.evaluation import resolve_config

REPO = Path(__file__).resolve().parents[2]
PRESETS = ("matlab_reference", "paper", "quadrotor", "quick")


def pyproject() -> dict:
    """``pyproject.toml``, parsed (``tomllib``: Python >= 3.11)."""
    tomllib = pytest.importorskip("tomllib")
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def run(code: str, cwd: Path) -> subprocess.CompletedProcess:
    """Python ``code`` in a fresh interpreter started in ``cwd`` (not the repository)."""
    return subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=600
    )


def test_presets_are_the_configs_folder_and_load():
    assert preset_names() == sorted(p.stem for p in (REPO / "configs").glob("*.yaml"))
    assert set(PRESETS) <= set(preset_names())
    for name in PRESETS:
        path = config_file(name)
        assert path.read_text() == (REPO / "configs" / f"{name}.yaml").read_text()
        assert config_file(f"{name}.yaml") == path
        resolve_config(path)  # every preset is a valid config
    assert config_file(None) == config_file("paper")


def test_a_path_wins_and_an_unknown_name_lists_the_presets(tmp_path, monkeypatch):
    own = tmp_path / "quick"  # a file named like a preset: the path is meant
    own.write_text((REPO / "configs" / "quick.yaml").read_text())
    monkeypatch.chdir(tmp_path)
    assert config_file("quick") == Path("quick")
    assert config_file(str(own)) == own
    with pytest.raises(ValueError, match="--config nope: .*presets: matlab_reference, paper"):
        config_file("nope")
    with pytest.raises(ValueError, match="no such file"):
        config_file("configs/quick.yaml")  # a relative path from another folder is a path


def test_commands_find_presets_by_name_from_another_folder(tmp_path):
    code = (
        "import sys; from experiments.cli import evaluate_main; "
        "sys.exit(evaluate_main(['--config', 'quick', '--agents', 'nominal', '--seeds', '0', "
        "'--out', 'out', '--no-report', '--quiet']))"
    )
    done = run(code, tmp_path)
    assert done.returncode == 0, done.stderr
    saved = yaml.safe_load((tmp_path / "out" / "config.yaml").read_text())
    assert saved["env"]["max_steps"] == 150  # quick.yaml's
    assert (tmp_path / "out" / "episodes" / "nominal__seed0.json").is_file()

    code = (
        "import sys; from experiments.cli import calibrate_main; "
        "sys.exit(calibrate_main(['--config', 'quick', '--seeds', '1000', "
        "'--out', 'learned.yaml']))"
    )
    done = run(code, tmp_path)
    assert done.returncode == 0, done.stderr
    learned = yaml.safe_load((tmp_path / "learned.yaml").read_text())
    assert learned["agents"]["latent_force"]["variance"] > 0.0


def test_every_function_that_takes_a_config_takes_a_preset_by_name(tmp_path):
    """Issue 35, item 3: load_config, make_agent, evaluate and gym.make took a path only."""
    code = (
        "import gymnasium as gym, lfm_env\n"
        "from controllers.agents import make_agent\n"
        "from controllers.config import load_config\n"
        "from experiments.evaluation import evaluate\n"
        "assert load_config('paper').agents.n_particles == 7000\n"
        "assert make_agent('scenario', 'paper').problem.n_scenarios == 150\n"
        "rows = evaluate(['nominal'], [0], config='quick', progress=False)\n"
        "assert rows[0]['error'] == '' and rows[0]['steps'] > 0\n"
        "env = gym.make('lfm_env/SineTrack-v0', config='paper')\n"
        "assert env.unwrapped.config == load_config('paper').env\n"
        "print('ok')\n"
    )
    done = run(code, tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok"


@pytest.mark.parametrize(
    "command", ["evaluate_main", "render_main", "sweep_main", "calibrate_main", "train_main"]
)
def test_every_config_option_refuses_an_unknown_name_naming_the_presets(command, tmp_path):
    module, func = "experiments.cli", command
    extra = {"render_main": ", '--out', 'x.png'", "sweep_main": ", '--set', 'agents.horizon=5'"}
    code = (
        f"import sys; from {module} import {func}; "
        f"sys.exit({func}(['--config', 'nope'{extra.get(func, '')}]))"
    )
    done = run(code, tmp_path)
    assert done.returncode == 2
    assert "--config nope" in done.stderr
    assert "presets: matlab_reference, paper, quadrotor, quick" in done.stderr


def test_the_package_list_holds_every_package_of_the_source_tree():
    setuptools = pyproject()["tool"]["setuptools"]
    listed = set(setuptools["packages"])
    found = {
        ".".join(p.parent.relative_to(REPO).parts)
        for top in ("lfm_env", "controllers", "experiments")
        for p in (REPO / top).rglob("__init__.py")
    }
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"
    assert listed - found == {"lfm_env.presets", "controllers.solvers.fast.codegen.c"}
    assert setuptools["package-dir"] == {"lfm_env.presets": "configs"}
    assert setuptools["package-data"]["lfm_env.presets"] == ["*.yaml"]


def test_the_c_files_are_package_data():
    """The fast solver's C files, read with importlib.resources, ship with their package."""
    setuptools = pyproject()["tool"]["setuptools"]
    data = setuptools["package-data"]
    sources = [
        p for top in ("lfm_env", "controllers", "experiments") for p in (REPO / top).rglob("*.[ch]")
    ]
    assert {p.name for p in sources} >= {"driver.c", "elastic_ipm.c"}
    for path in sources:
        package = ".".join(path.parent.relative_to(REPO).parts)
        assert package in setuptools["packages"], f"add {package} to [tool.setuptools] packages"
        patterns = data.get(package, [])
        assert any(fnmatch(path.name, p) for p in patterns), (
            f"{package}: {path.name} not in {patterns}"
        )


def test_licence_and_citation():
    meta = pyproject()["project"]
    assert meta["license"] == "MIT" and meta["license-files"] == ["LICENSE"]
    licence = (REPO / "LICENSE").read_text()
    assert licence.startswith("MIT License") and "the lfm-scenario-mpc authors" in licence
    cff = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["license"] == "MIT"
    paper = cff["preferred-citation"]
    assert paper["type"] == "conference-paper" and paper["year"] == 2021
    assert paper["title"].startswith("Model Predictive Control of Nonlinear Latent Force Models")
    assert [a["family-names"] for a in paper["authors"]] == ["Woodruff", "Askari", "Wang", "Fang"]
    readme = (REPO / "README.md").read_text()
    citing = readme.split("\n## Citing\n", 1)[1]
    assert "@inproceedings{" in citing and paper["title"] in citing
