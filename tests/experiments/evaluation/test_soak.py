"""Long runs stay healthy, and the same seeds give bit-identical tables.

The soak (slow) runs 300 consecutive full-length episodes of the quick config in one
process, the four agents in turn on 75 seeds, with the IPOPT and the fast solver in
alternate rounds, and checks that after a warm-up of 30 episodes the resident memory
grows by less than 10 %, and that live agents, envs, filters, solvers, CasADi functions,
threads and open files do not pile up. Episodes are not shortened: they take about 0.3 s
on an idle two-core machine (a few times that under load), so the soak takes minutes.
Its measurements are attached to the test report (``record_property``; read them with
``--junitxml=FILE -o junit_family=xunit1``).

The determinism test (default run) evaluates the same seeds twice in this process and
once in a fresh interpreter, and compares the tables and trajectories bit for bit apart
from the timing columns.
"""

from __future__ import annotations

import csv
import gc
import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import yaml

from controllers.agents.mpc import MPCAgent
from controllers.config import load_config
from controllers.estimators.particle_filter import ParticleFilter
from controllers.solvers.casadi.ipopt import IpoptScenarioSolver
from controllers.solvers.fast.solver import FastScenarioSolver
from experiments.evaluation.run import TIMING_COLUMNS, evaluate, run_episode
from lfm_env.worlds import SineTrackEnv

REPO = Path(__file__).resolve().parents[3]
#: lfm-evaluate through this interpreter (as the installed command runs it).
EVALUATE_MAIN = "import sys; from experiments.cli import evaluate_main; sys.exit(evaluate_main())"
AGENT_CYCLE = ("nominal", "pf", "scenario", "oracle")
SOAK_EPISODES = 300
WARM_UP = 30  # episodes before the memory baseline: imports, caches and allocator pools
MAX_RSS_GROWTH = 0.10
LIVE_KINDS = {
    "agents": MPCAgent,
    "envs": SineTrackEnv,
    "particle_filters": ParticleFilter,
    "ipopt_solvers": IpoptScenarioSolver,
    "fast_solvers": FastScenarioSolver,
    "casadi_functions": ca.Function,
}


def rss_bytes() -> int:
    """Resident memory of this process now (not the peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def live_counts() -> dict[str, int]:
    """Objects that would pile up if an episode leaked its agent, env or solver."""
    gc.collect()
    counts = dict.fromkeys(LIVE_KINDS, 0)
    for obj in gc.get_objects():
        for name, kind in LIVE_KINDS.items():
            if isinstance(obj, kind):
                counts[name] += 1
    counts["threads"] = threading.active_count()
    counts["open_files"] = len(os.listdir("/proc/self/fd"))
    return counts


def without_timing(row: dict) -> dict:
    """A row without timing columns, NaN made comparable."""
    return {
        k: ("NaN" if isinstance(v, float) and math.isnan(v) else v)
        for k, v in row.items()
        if k not in TIMING_COLUMNS
    }


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_300_consecutive_episodes_stay_healthy(record_property):
    quick = REPO / "configs" / "quick.yaml"
    configs = [load_config(quick, [f"agents.solver={s}"]) for s in ("ipopt", "fast")]
    first_row = None
    rss_after = []
    successes = 0
    started = time.perf_counter()
    for i in range(SOAK_EPISODES):
        name, seed = AGENT_CYCLE[i % len(AGENT_CYCLE)], i // len(AGENT_CYCLE)
        config = configs[seed % 2]
        row, _ = run_episode(name, config, seed, record=False)  # an error would raise
        successes += row["success"]
        first_row = first_row or row
        if i + 1 == WARM_UP:
            baseline_counts = live_counts()
            baseline_rss = rss_bytes()
        rss_after.append(rss_bytes())
    wall = time.perf_counter() - started
    del row
    end_counts = live_counts()
    end_rss = rss_bytes()
    growth_max = max(rss_after[WARM_UP:]) / baseline_rss - 1.0
    growth_end = end_rss / baseline_rss - 1.0

    record_property("episodes", SOAK_EPISODES)
    record_property("episodes_reaching_the_goal", successes)
    record_property("wall_time_s", round(wall, 1))
    record_property("rss_baseline_MiB", round(baseline_rss / 2**20, 1))
    record_property("rss_max_after_warm_up_MiB", round(max(rss_after[WARM_UP:]) / 2**20, 1))
    record_property("rss_end_MiB", round(end_rss / 2**20, 1))
    record_property("rss_growth_max_percent", round(100 * growth_max, 2))
    record_property("rss_growth_end_percent", round(100 * growth_end, 2))
    record_property("live_objects_after_warm_up", json.dumps(baseline_counts))
    record_property("live_objects_at_end", json.dumps(end_counts))

    assert growth_max < MAX_RSS_GROWTH, (baseline_rss, max(rss_after[WARM_UP:]))
    for name, count in end_counts.items():
        assert count <= baseline_counts[name], (name, baseline_counts, end_counts)
    # Nothing of an episode outlives it (the soak holds no agent, env or solver).
    for name in ("agents", "envs", "particle_filters", "ipopt_solvers", "fast_solvers"):
        assert end_counts[name] == 0, end_counts
    # 300 episodes later, the first one is still the same bit for bit.
    again, _ = run_episode(AGENT_CYCLE[0], configs[0], 0, record=False)
    assert without_timing(again) == without_timing(first_row)


# ------------------------------------------------------------------------------ determinism

DETERMINISM_CONFIG = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 5, "n_particles": 300},
}
DETERMINISM_AGENTS = ",".join(AGENT_CYCLE)
DETERMINISM_SEEDS = "0,3,7"


def table_without_timing(out: Path) -> list[list[str]]:
    """The cells of episodes.csv as written (floats in shortest exact text), no timings."""
    with (out / "episodes.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    keep = [i for i, name in enumerate(rows[0]) if name not in TIMING_COLUMNS]
    return [[row[i] for i in keep] for row in rows]


def trajectories(out: Path) -> dict[str, dict[str, np.ndarray]]:
    found = {}
    for path in sorted((out / "episodes").glob("*.npz")):
        with np.load(path, allow_pickle=False) as data:
            found[path.stem] = {
                k: data[k] for k in data.files if k not in ("solve_time", "step_time")
            }
    return found


def test_same_seeds_give_bit_identical_tables(tmp_path):
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(DETERMINISM_CONFIG))
    outs = [tmp_path / "first", tmp_path / "second", tmp_path / "fresh_process"]
    for out in outs[:2]:
        evaluate(DETERMINISM_AGENTS, DETERMINISM_SEEDS, config, out=out, progress=False)
    cmd = [
        sys.executable,
        "-c",
        EVALUATE_MAIN,
        *("--config", str(config), "--agents", DETERMINISM_AGENTS),
        *("--seeds", DETERMINISM_SEEDS, "--out", str(outs[2]), "--no-report", "--quiet"),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr

    reference = table_without_timing(outs[0])
    assert len(reference) == 1 + 4 * 3
    assert all(row[-1] == "" for row in reference[1:])  # no episode raised
    ref_traj = trajectories(outs[0])
    assert len(ref_traj) == 12
    for out in outs[1:]:
        assert table_without_timing(out) == reference, out.name
        traj = trajectories(out)
        assert traj.keys() == ref_traj.keys()
        for stem, arrays in traj.items():
            assert arrays.keys() == ref_traj[stem].keys()
            for key, value in arrays.items():
                np.testing.assert_array_equal(value, ref_traj[stem][key], err_msg=f"{stem}.{key}")
