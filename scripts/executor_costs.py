"""What each executor of ``evaluate`` costs: the same episodes in the run's own process
(``isolate=False``), in a serial run's child process (the default), on a pool of two
processes and on a private local Dask cluster of two workers, side by side, in turn.

    OPENBLAS_NUM_THREADS=1 python scripts/executor_costs.py                 # quick, 3 x 3
    OPENBLAS_NUM_THREADS=1 python scripts/executor_costs.py --seeds 0:5 --repeats 5

Prints each run's wall time, the medians, each executor's difference to the run's own
process (per run and per episode), and whether every executor's rows equal the own
process's (every column but the timings). The C library cache is warmed first.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time

from experiments.evaluation import TIMING_COLUMNS, evaluate

EXECUTORS = {
    "own process": {"isolate": False},
    "serial child": {},
    "--jobs 2": {"jobs": 2},
    "--dask-workers 2": {"dask_workers": 2},
}


def _comparable(rows: list[dict]) -> list[dict]:
    return [
        {
            k: ("nan" if isinstance(v, float) and math.isnan(v) else v)
            for k, v in r.items()
            if k not in TIMING_COLUMNS
        }
        for r in rows
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="quick")
    parser.add_argument("--agents", default="nominal,pf,scenario")
    parser.add_argument("--seeds", default="0:3")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--executors", default=",".join(EXECUTORS))
    args = parser.parse_args()
    chosen = [e.strip() for e in args.executors.split(",")]
    times: dict[str, list[float]] = {e: [] for e in chosen}
    rows: dict[str, list[dict]] = {}
    evaluate(args.agents, "0", args.config, progress=False, isolate=False)  # warm the cache
    for _ in range(args.repeats):
        for name in chosen:
            with tempfile.TemporaryDirectory() as out:
                t0 = time.perf_counter()
                got = evaluate(
                    args.agents, args.seeds, args.config, out=out, progress=False,
                    **EXECUTORS[name],
                )  # fmt: skip
                times[name].append(time.perf_counter() - t0)
            rows[name] = _comparable(got)
            print(f"{name:>16}: {times[name][-1]:6.2f} s ({len(got)} episodes)", flush=True)
    n = len(next(iter(rows.values())))
    base = statistics.median(times[chosen[0]])
    print(f"medians over {args.repeats} runs of {n} episodes ({args.config}, {args.agents}):")
    for name in chosen:
        median = statistics.median(times[name])
        extra = median - base
        print(
            f"{name:>16}: {median:6.2f} s, {extra:+6.2f} s per run ({extra / n:+.3f} s per "
            f"episode); rows equal to the {chosen[0]}'s: {rows[name] == rows[chosen[0]]}"
        )


if __name__ == "__main__":
    main()
