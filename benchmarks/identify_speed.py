"""Wall time of ``identify LOG.mcap`` (target: at most 8 s for data/run.mcap on the 2-core
machine), and where it goes.

Prints, for the logs given (default: data/run.mcap):

* **command**: the wall time of the ``identify`` command in a fresh process (imports, loading
  the cached numba code, reading, fitting, validation, cross-check, report with figures,
  model.yaml), ``--repeats`` times: every run, the median and the range;
* **imports**: the time a fresh process takes to import the command's modules (part of the
  above);
* **stages** (unless ``--no-stages``): the same command run in this process, once as a fresh
  process would after its imports (the first run loads numba's cached code and the modules
  imported inside functions), then ``--repeats`` times warm, with the pipeline's steps timed by
  wrapping them where :mod:`pneutune.identify.pipeline` looks them up (load, valves and their
  timing search, friction, mass, bounds, validation, cross-check, report). Each stage's time
  excludes the stages it calls (``valves`` is without its timing search); what no stage covers
  is ``other``. A stage the pipeline has none of the steps of is reported as not timed, not
  guessed.

Several logs (``--logs A.mcap B.mcap C.mcap``) are passed to one ``identify`` command together,
for "three logs together". A command that does not accept several logs fails, and this script
says so and exits 2. Nothing here asserts a time: the figures are printed, to be compared with
a baseline measured in the same session (the machine is shared, so repeat and read ranges).

    .venv/bin/python benchmarks/identify_speed.py [--logs A.mcap [B.mcap ...]] [--repeats 3]
        [--no-stages]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

RUN = Path(__file__).resolve().parents[1] / "data" / "run.mcap"

#: What a fresh ``identify`` process imports before it reads the log.
IMPORTS = ("pneutune.identify.cli", "pneutune.identify.pipeline", "pneutune.identify.report")

#: Stage name -> (module, attribute paths) of the callables timed in-process. Methods are
#: wrapped on their class; functions where the pipeline (or the report module) looks them up.
#: Every path found is wrapped (the names of the single-log and the several-log pipeline are
#: both listed); a stage none of whose paths exists is reported as not timed.
STAGES: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("load", "pneutune.identify.pipeline", ("load_dataset", "load_datasets", "pool", "coverage")),
    ("valves", "pneutune.identify.pipeline", ("ValveIdentifier.fit",)),
    ("valves: timing search", "pneutune.identify.pipeline", ("ValveIdentifier._fit_timing",)),
    ("friction", "pneutune.identify.pipeline", ("FrictionIdentifier.fit",)),
    ("mass", "pneutune.identify.pipeline", ("choose_mass",)),
    ("bounds", "pneutune.identify.pipeline", ("FrictionIdentifier.smooth_bootstrap",
                                              "theta_bounds", "build_model")),
    ("validation", "pneutune.identify.pipeline", ("validate",)),
    ("cross-check", "pneutune.identify.pipeline", ("cross_check", "narrowed_model")),
    ("report", "pneutune.identify.report", ("write_report",)),
    ("report", "pneutune.identify.cli", ("save_model",)),
)


def _summary(values: Sequence[float]) -> str:
    """``median s (range min-max, n=...)`` of a sample."""
    return (f"{statistics.median(values):.2f} s (range {min(values):.2f}-{max(values):.2f}, "
            f"n={len(values)})")


def command_wall(logs: Sequence[Path], repeats: int) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds of ``identify LOGS --out TMP`` in a fresh process, ``repeats``
    times.

    Parameters
    ----------
    logs : sequence of Path
        The run logs, passed together to one command.
    repeats : int
        Number of runs.

    Returns
    -------
    (list of float, list of float)
        Wall time of each run, and its CPU time (user and system, every thread) [s]. On the
        shared machine the CPU time moves less with the load than the wall time (BLAS threads
        waiting for a busy core still inflate it).

    Raises
    ------
    SystemExit
        With status 2 when the command fails (e.g. it does not accept several logs yet).
    """
    walls, cpus = [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as out:
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "pneutune.identify.cli",
                                   *map(str, logs), "--out", out],
                                  capture_output=True, text=True)
            walls.append(time.perf_counter() - t0)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
        if proc.returncode != 0:
            err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
            what = err[-1] if err else f"exit status {proc.returncode}"
            several = " (does it accept several logs yet?)" if len(logs) > 1 else ""
            print(f"error: identify {' '.join(map(str, logs))} failed{several}: {what}",
                  file=sys.stderr)
            raise SystemExit(2)
    return walls, cpus


def import_times(repeats: int) -> list[float]:
    """Seconds a fresh process takes to import :data:`IMPORTS`, ``repeats`` times."""
    code = ("import time; t = time.perf_counter()\n"
            + "".join(f"import {m}\n" for m in IMPORTS)
            + "print(time.perf_counter() - t)")
    return [float(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                 text=True).stdout) for _ in range(repeats)]


class StageTimer:
    """Exclusive wall time per stage: a stage called inside another counts only for itself."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self._stack: list[list[Any]] = []

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` timed as stage ``name``."""

        def timed(*args: Any, **kwargs: Any) -> Any:
            frame = [name, 0.0]  # [stage, time spent in nested stages]
            self._stack.append(frame)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                self._stack.pop()
                self.totals[name] = self.totals.get(name, 0.0) + dt - frame[1]
                if self._stack:
                    self._stack[-1][1] += dt

        timed.__wrapped__ = fn  # type: ignore[attr-defined]
        return timed


@contextlib.contextmanager
def _stages_wrapped(timer: StageTimer, missing: list[str]) -> Iterator[None]:
    """Wrap every callable of :data:`STAGES` found; restore them on exit."""
    import importlib

    absent = object()  # a method the class inherits: restored by deleting the wrapper
    restore = []
    found: dict[str, bool] = {}
    try:
        for stage, module, attrs in STAGES:
            found.setdefault(stage, False)
            for attr in attrs:
                owner: Any = importlib.import_module(module)
                *path, leaf = attr.split(".")
                try:
                    for part in path:
                        owner = getattr(owner, part)
                    fn = getattr(owner, leaf)
                except AttributeError:
                    continue
                found[stage] = True
                original = vars(owner).get(leaf, absent)
                wrapped = timer.wrap(stage, fn)
                restore.append((owner, leaf, original))
                setattr(owner, leaf, staticmethod(wrapped) if isinstance(original, staticmethod)
                        else wrapped)
        for stage, ok in found.items():
            if not ok:
                names = [a for st, _, attrs in STAGES if st == stage for a in attrs]
                missing.append(f"{stage} (looked for {', '.join(names)})")
        yield
    finally:
        for owner, leaf, original in reversed(restore):
            if original is absent:
                delattr(owner, leaf)
            else:
                setattr(owner, leaf, original)


def stage_times(logs: Sequence[Path], repeats: int
                ) -> tuple[float, dict[str, float], list[dict[str, float]], list[str]]:
    """Per-stage seconds of the command run in this process: its first run, then ``repeats``.

    The first run is what a fresh ``identify`` process does after its imports (numba's cached
    code loaded, modules imported inside functions); the later ones are warm.

    Returns
    -------
    (float, dict, list of dict, list of str)
        The seconds to import :data:`IMPORTS` here; the first run's stage -> exclusive seconds
        (``other`` and ``total`` included); the same per later run; the stages of
        :data:`STAGES` the pipeline has none of the steps of.
    """
    import importlib

    t0 = time.perf_counter()
    for module in IMPORTS:
        importlib.import_module(module)
    t_import = time.perf_counter() - t0
    from pneutune.identify import cli

    def run() -> dict[str, float]:
        timer = StageTimer()
        quiet = io.StringIO()
        with _stages_wrapped(timer, missing if not rows else []), \
                tempfile.TemporaryDirectory() as out, \
                contextlib.redirect_stderr(quiet), contextlib.redirect_stdout(quiet):
            t0 = time.perf_counter()
            status = cli.main([*map(str, logs), "--out", out])
            total = time.perf_counter() - t0
        if status != 0:
            raise SystemExit(f"error: identify failed in-process (exit status {status})")
        row = dict(timer.totals)
        row["other"] = total - sum(row.values())
        row["total"] = total
        return row

    missing: list[str] = []
    rows: list[dict[str, float]] = []
    first = run()
    for _ in range(repeats):
        rows.append(run())
    return t_import, first, rows, missing


def main(argv: Sequence[str] | None = None) -> None:
    """Print the figures (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", nargs="+", type=Path, default=[RUN], metavar="LOG.mcap",
                    help="run logs, passed together to one identify command (default: "
                         "data/run.mcap)")
    ap.add_argument("--repeats", type=int, default=3, help="runs per figure (default 3)")
    ap.add_argument("--no-stages", action="store_true",
                    help="skip the in-process stage breakdown")
    args = ap.parse_args(argv)
    for log in args.logs:
        if not log.is_file():
            ap.error(f"{log}: no such file")
    names = " ".join(log.name for log in args.logs)
    repeats = max(1, args.repeats)

    load = os.getloadavg()[0]
    walls, cpus = command_wall(args.logs, repeats)
    print(f"identify {names}: command (fresh process, report and figures included; target "
          f"<= 8 s for run.mcap): wall {_summary(walls)}; runs: "
          + ", ".join(f"{w:.2f}" for w in walls))
    print(f"  CPU time of the command (user + system): {_summary(cpus)}; load average before: "
          f"{load:.1f} (2 = both cores busy on the 2-core machine)")
    imports = import_times(repeats)
    print(f"  imports of a fresh process ({', '.join(IMPORTS)}): {_summary(imports)}")
    if args.no_stages:
        return
    t_import, first, runs, missing = stage_times(args.logs, repeats)
    print(f"  stages, in-process (exclusive seconds; imports {t_import:.2f} s before the first "
          f"run; later runs: median and range of {repeats}):")
    print(f"    {'stage':<22} {'first run':>9}   later runs")
    order = list(dict.fromkeys([stage for stage, _, _ in STAGES] + ["other", "total"]))
    for stage in order:
        if stage not in first and not any(stage in r for r in runs):
            continue
        vals = [r.get(stage, 0.0) for r in runs]
        print(f"    {stage:<22} {first.get(stage, 0.0):7.2f} s  {statistics.median(vals):6.2f} s "
              f"({min(vals):.2f}-{max(vals):.2f})")
    for name in missing:
        print(f"    (not timed, the pipeline has none of its steps: {name})")


if __name__ == "__main__":
    main()
