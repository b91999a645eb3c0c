"""Evaluate agents over env seeds; see ``python scripts/evaluate.py --help``.

The same command is installed as ``lfm-evaluate``.
"""

from experiments.cli import evaluate_main

if __name__ == "__main__":
    raise SystemExit(evaluate_main())
