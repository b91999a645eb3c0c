"""Sweep one risk knob of an agent over env seeds; see ``python scripts/sweep.py --help``.

The same command is installed as ``lfm-sweep``.
"""

from experiments.cli import sweep_main

if __name__ == "__main__":
    raise SystemExit(sweep_main())
