"""What a serial run's child process costs: the same serial evaluation in the run's own process
(``isolate=False``) and in one child process (the default), side by side, alternating.

    python scripts/isolation_cost.py                      # quick preset, 3 agents x 3 seeds
    python scripts/isolation_cost.py --seeds 0:5 --repeats 5

Prints each run's wall time, the medians, and whether the rows agree (every column but the
timings). Run with ``OPENBLAS_NUM_THREADS=1``, as evaluations are.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time

from experiments.evaluation import TIMING_COLUMNS, evaluate


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
    args = parser.parse_args()
    times: dict[bool, list[float]] = {False: [], True: []}
    rows: dict[bool, list[dict]] = {}
    evaluate(args.agents, "0", args.config, progress=False, isolate=False)  # warm caches
    for _ in range(args.repeats):
        for isolate in (False, True):
            with tempfile.TemporaryDirectory() as out:
                t0 = time.perf_counter()
                got = evaluate(
                    args.agents, args.seeds, args.config, out=out, progress=False, isolate=isolate
                )
                times[isolate].append(time.perf_counter() - t0)
            rows[isolate] = _comparable(got)
            where = "child process" if isolate else "own process  "
            print(f"{where}: {times[isolate][-1]:.2f} s ({len(got)} episodes)", flush=True)
    own, child = statistics.median(times[False]), statistics.median(times[True])
    n = len(rows[True])
    print(
        f"median over {args.repeats} runs of {n} episodes: own process {own:.2f} s, child "
        f"process {child:.2f} s: +{child - own:.2f} s per run ({100 * (child / own - 1):+.1f}%), "
        f"+{(child - own) / n:.3f} s per episode; rows equal: {rows[True] == rows[False]}"
    )


if __name__ == "__main__":
    main()
