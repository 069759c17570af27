"""Wall time of ``identify data/run.mcap`` (target: at most 15 s on the 2-core machine).

Prints the wall time of the whole command in a fresh process (reading, fitting, validation,
report with figures, model.yaml) and of the fitting alone (in-process, after warm-up).

    .venv/bin/python benchmarks/identify_speed.py
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUN = Path(__file__).resolve().parents[1] / "data" / "run.mcap"


def main() -> None:
    """Print the figures."""
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pneutune.identify.cli", str(RUN), "--out", out],
                       check=True, capture_output=True)
        wall = time.perf_counter() - t0
    from pneutune.identify.pipeline import identify

    identify(RUN)  # warm-up: numba caches, imports
    t0 = time.perf_counter()
    identify(RUN)
    fit = time.perf_counter() - t0
    print(f"identify {RUN.name}: {wall:.1f} s wall for the command (fresh process, report and "
          f"figures included; target <= 15 s); {fit:.1f} s for the fits and validation alone")


if __name__ == "__main__":
    main()
