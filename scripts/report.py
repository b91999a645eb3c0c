"""Write the report of a results folder; see ``python scripts/report.py --help``.

The same command is installed as ``lfm-report``.
"""

from experiments.cli import report_main

if __name__ == "__main__":
    raise SystemExit(report_main())
