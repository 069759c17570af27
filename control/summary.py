"""``python -m pneutune.control.summary``: reports/summary.md from deploy's ``--json`` outputs.

The command keeps its name; the code lives in :mod:`pneutune.control.cli.summary`.
"""

from pneutune.control.cli.common import run_cli
from pneutune.control.cli.summary import main

if __name__ == "__main__":  # pragma: no cover
    run_cli(main)
