"""Run one episode and render it to a GIF or PNG; see ``python scripts/render.py --help``.

The same command is installed as ``lfm-render``.
"""

from experiments.cli import render_main

if __name__ == "__main__":
    raise SystemExit(render_main())
