"""Files in the working folder cannot break a run: only the modules a command names are
imported from it, by name and last, in the run's own process and in every worker.

A working folder holds ``signal.py``, ``random.py`` and ``numpy.py`` (each, if imported,
leaves a marker file and raises, as a careless user's script of that name would break the
real module's users) and ``mymod.py``, a user's agent named on the command line as
``mymod:Healthy``. ``lfm-evaluate`` runs from that folder, as a console script, serially,
on a process pool (``--jobs 2``) and on a real local Dask cluster (``--dask-workers 2``):
every episode runs, the named module is found, and no shadowing file is ever imported.
Before, one ``signal.py`` made every pool row "a native crash, OOM kill or kill", the Dask
run an 84-line traceback without results, and ``random.py`` cost every row of a pool run
with a ``module:attr`` agent.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

LFM_EVALUATE = Path(sys.executable).with_name("lfm-evaluate")
SHADOWS = ("signal", "random", "numpy")

MYMOD = '''
import numpy as np


class Healthy:
    """Brakes gently and steers straight: a user's agent beside the config."""

    name = "healthy"

    def __init__(self, config):
        self.system = config.make_system()

    def reset(self, seed=None):
        pass

    def act(self, obs):
        return self.system.clip_input(np.array([-0.5, -0.3 * float(obs[3])]))
'''


def shadow(name: str, folder: Path) -> str:
    marker = folder / f"imported_{name}"
    return (
        f"open({str(marker)!r}, 'w').write('the working folder\\'s {name}.py was imported')\n"
        f"raise ImportError('the working folder\\'s {name}.py was imported')\n"
    )


@pytest.fixture
def folder(tmp_path) -> Path:
    work = tmp_path / "work"
    work.mkdir()
    for name in SHADOWS:
        (work / f"{name}.py").write_text(shadow(name, tmp_path))
    (work / "mymod.py").write_text(MYMOD)
    (work / "tiny.yaml").write_text(
        "env:\n  max_steps: 15\nagents:\n  horizon: 5\n  n_scenarios: 5\n  n_particles: 300\n"
    )
    return work


@pytest.mark.parametrize(
    "executor", [[], ["--jobs", "2"], ["--dask-workers", "2"]], ids=["serial", "pool", "dask"]
)
def test_files_in_the_working_folder_never_shadow_and_the_named_module_is_found(executor, folder):
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    env.pop("PYTHONPATH", None)
    cmd = [str(LFM_EVALUATE), "--config", "tiny.yaml", "--agents", "nominal,mymod:Healthy"]
    cmd += ["--seeds", "0:2", "--out", "out", "--no-report", "--quiet", *executor]
    done = subprocess.run(cmd, cwd=folder, env=env, capture_output=True, text=True, timeout=600)
    markers = sorted(p.name for p in folder.parent.glob("imported_*"))
    assert not markers, (markers, done.stderr[-3000:])
    assert done.returncode == 0, done.stderr[-3000:]
    with open(folder / "out" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted((r["agent"], r["seed"], r["error"]) for r in rows) == [
        (a, s, "") for a in ("healthy", "nominal") for s in ("0", "1")
    ]


def test_a_named_module_is_imported_last_and_by_name_only(folder, monkeypatch):
    """In Python: a name that Python finds elsewhere (the standard library, an installed
    package) is never taken from the folder; a name found nowhere else is, and only it."""
    from lfm_env import working_folder

    monkeypatch.chdir(folder)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(folder))])
    random = working_folder.import_named("random")
    assert random.__file__ != str(folder / "random.py")
    mymod = working_folder.import_named("mymod")
    assert mymod.__file__ == str(folder / "mymod.py")
    assert str(folder) not in sys.path and "" not in sys.path
    with pytest.raises(ModuleNotFoundError):
        working_folder.import_named("no_such_module_anywhere")
    sys.modules.pop("mymod", None)
