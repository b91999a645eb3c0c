"""Train the RL baseline; see ``python scripts/train_rl.py --help``.

The same command is installed as ``lfm-train``.
"""

from experiments.cli import train_main

if __name__ == "__main__":
    raise SystemExit(train_main())
