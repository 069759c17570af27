"""``identify``: from run logs (MCAP) to model.yaml, a report and a summary."""

from __future__ import annotations

import contextlib
import functools
import gc
from collections.abc import Iterator, Sequence

from pneutune.control.cli.common import info, make_parser, print_json, run_cli

DESCRIPTION = """\
Identify the servo-pneumatic axis behind a run log (MCAP, contract pneutune.log/1): valve
conductances C and critical ratios b (ISO 6358), the PWM duty curve (a monotone QP), Stribeck
friction, the smooth friction model, the moving mass, the constant disturbance terms, and the
bounds θ_min..θ_max of the DARC's θ = [M, F_n, b_v, A_f, D_an, D_bn]. The model is then
simulated on the held-out part of the log (the end of every 10 s) and its NRMSE reported.

Works on any honest log: the identification run (simulate --experiment identification, or the
same protocol on a rig), another protocol (simulate --experiment commissioning shows one), and
ordinary closed-loop logs at the control rate (what deploy --log writes). It uses only
/rig/sensors, /rig/valves and the rig metadata, never /sim/truth or segment labels. The valves'
opening is computed sample by sample from their fitted delays and the PWM carrier, so duties
that change every sample are no obstacle; friction comes from Eq. (1) integrated over sliding
windows; stick and break-away events bound the stiction force from both sides.

Every range in model.yaml has its basis (statistics, data bound or prior), and every range end
that tune would sample and that is not a statistical fit is replayed on the held-out log: an end
the log rules out (its NRMSE over 5 times the best fit's) is moved in, and the report says so.

Several logs of one rig (equal rig metadata; their sampling periods may differ: an
identification run at 0.5 ms, a partial rerun, a closed-loop log at 4 ms) give one model: each
fit uses every log where its data are valid (valve tests from the log that has them, friction
from every log's motion, the mass from the logs sampled fast enough), no fit window straddles
two logs, every log has the end of each of its 10 s held out, and each basis names the logs it
came from. A protocol run cut short is used for what it holds; the notes say what it lacks.

Writes DIR/model.yaml (contract pneutune.model/1, atomically), DIR/report.md with a plot of
each fit, and prints a summary.
"""

EPILOG = """\
examples:
  identify data/run.mcap
  identify reports/deploy/sine-0.5hz.mcap --out reports/identify-closed-loop
  identify data/run.mcap --mass 1.05 --json
  identify data/run.mcap reports/deploy/sine-0.5hz.mcap --out reports/identify-both

The moving mass is often not identifiable from 4 ms samples (the piston's mechanical time
constant M/b_v is far shorter); the model then says so and uses a prior range from the cylinder
geometry (0.5-4 times piston and rod), or from a rig.mass hint in the log's rig metadata (÷/×
1.4). Give --mass with the datasheet mass plus the weighed payload to narrow θ1.
exit status: 0 done, 2 bad log, logs of different rigs or too little excitation (one error:
line), 1 internal error.
"""


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``identify``."""
    return _main(argv, fresh_process=False)


def _main(argv: Sequence[str] | None, fresh_process: bool) -> int:
    """:func:`main`; in a process that runs only this command (``fresh_process``), the
    fitting modules are imported with the garbage collector paused (:func:`_collector_paused`).
    """
    parser = make_parser("identify", DESCRIPTION, EPILOG)
    parser.add_argument("logs", metavar="LOG.mcap", nargs="+",
                        help="the run log to identify from; several logs of one rig give one "
                             "model fitted to all of them")
    parser.add_argument("--out", metavar="DIR", default="reports/identify",
                        help="output folder (default: reports/identify)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object (the model and notes) on stdout")
    parser.add_argument("--mass", type=float, metavar="KG",
                        help="known total moving mass [kg] (piston, rod and payload)")
    parser.add_argument("--mass-tol", type=float, default=0.05, metavar="REL",
                        help="relative tolerance of --mass (default 0.05)")
    parser.add_argument("--holdout", type=float, default=0.2, metavar="FRAC",
                        help="fraction of every 10 s of each log kept for validation "
                             "(default 0.2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the bootstraps")
    args = parser.parse_args(argv)

    with _collector_paused() if fresh_process else contextlib.nullcontext():
        from .pipeline import check_arguments, identify
        from .report import format_summary

    check_arguments(args.holdout, args.mass, args.mass_tol)
    info(f"identify: reading {' '.join(args.logs)}")
    result = identify(args.logs[0] if len(args.logs) == 1 else args.logs, holdout=args.holdout,
                      mass=args.mass, mass_tol=args.mass_tol, seed=args.seed)
    paths = result.save(args.out)
    if args.json:
        print_json({**paths, **result.model.to_dict()})
    else:
        info(format_summary(result))
        info(f"wrote {paths['model']} and {paths['report']}")
    return 0


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """Run the block with the cyclic garbage collector paused, and freeze what it made.

    The command's imports (numba, scipy, cvxpy, matplotlib, pandas) make hundreds of thousands
    of objects that live as long as the process. The collector would run several full passes
    over them while they are made (about 0.3 s of ``identify`` on data/run.mcap) and traverse
    them again in every later full pass; frozen (:func:`gc.freeze`), they are left out of all
    later collections. Only for a process that runs one command: objects frozen are never
    collected, even once unreachable.

    Yields
    ------
    None
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(functools.partial(_main, fresh_process=True))


if __name__ == "__main__":  # pragma: no cover
    entry()
