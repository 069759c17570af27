"""The example rig driver: the simulated rig served over the pipe protocol on stdin/stdout.

:func:`serve` answers the requests of ``pneutune.rig/1`` (:mod:`pneutune.control.rig.wire`)
for a :class:`~pneutune.control.rig.deploy_simrig.DeploySimRig`; :func:`serve_main` is
``python -m pneutune.control.driver serve`` (:func:`add_serve_parser` adds its options), the
program ``deploy --rig pipe-sim`` starts (:class:`~pneutune.control.rig.exec_rig.PipeRig`).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, BinaryIO

import numpy as np

from pneutune.control.errors import ExperimentError, PneutuneError
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.wire import (
    FRAME_DUTIES,
    FRAME_LENGTH,
    FRAME_READ,
    FRAME_TIME,
    FRAME_TRUTH,
    MAX_ERROR,
    PROTOCOL,
)


def _reply_error(out: BinaryIO, message: str) -> None:
    body = message.encode("utf-8")[:MAX_ERROR]
    out.write(b"E" + FRAME_LENGTH.pack(len(body)) + body)
    out.flush()


def _read_exact(inp: BinaryIO, n: int) -> bytes | None:
    data = b""
    while len(data) < n:
        chunk = inp.read(n - len(data))
        if not chunk:
            return None
        data += chunk
    return data


def serve(rig: DeploySimRig, inp: BinaryIO, out: BinaryIO) -> int:
    """Answer pipe-protocol requests for ``rig`` until ``C`` or end of input.

    Whatever ends the session (``C``, end of input, a bad request), the rig's fail-safe duties
    are written last.

    Parameters
    ----------
    rig : DeploySimRig
        The rig served.
    inp, out : binary file objects
        Requests in, replies out.

    Returns
    -------
    int
        0 after ``C`` or end of input, 1 after a protocol error.
    """
    hello = json.dumps({"protocol": PROTOCOL, "Ts": rig.Ts,
                        "rig": rig.rig_metadata()}).encode("utf-8")
    try:
        while True:
            op = inp.read(1)
            if not op:
                return 0
            if op == b"R":
                vals = rig.read()
                st = rig.sample_times()
                out.write(b"K" + FRAME_READ.pack(rig.t, *vals.tolist(), *st.tolist()))
            elif op == b"W":
                raw = _read_exact(inp, FRAME_DUTIES.size)
                if raw is None:
                    return 0
                d = np.array(FRAME_DUTIES.unpack(raw))
                if not np.all((d >= 0.0) & (d <= 1.0)):
                    _reply_error(out, f"duties must be in [0, 1], got {d.tolist()}")
                    return 1
                rig.write(d)
                out.write(b"K")
            elif op == b"A":
                rig.advance()
                out.write(b"K" + FRAME_TIME.pack(rig.t))
            elif op == b"T":
                out.write(b"K" + FRAME_TRUTH.pack(*rig.truth().tolist()))
            elif op == b"H":
                out.write(b"K" + FRAME_LENGTH.pack(len(hello)) + hello)
            elif op == b"C":
                rig.close()
                out.write(b"K")
                out.flush()
                return 0
            else:
                _reply_error(out, f"unknown request {op!r}")
                return 1
            out.flush()
    except BrokenPipeError:
        return 0
    finally:
        rig.close()


def add_serve_parser(sub: Any) -> None:
    """Add the ``serve`` subcommand to the subparsers of ``python -m pneutune.control.driver``.

    Parameters
    ----------
    sub : argparse subparsers action
        What ``ArgumentParser.add_subparsers`` returned; ``serve`` runs :func:`serve_main`.
    """
    p = sub.add_parser(
        "serve", help="serve the simulated rig on stdin/stdout (the example driver)",
        description=f"Serve the simulated rig on stdin/stdout ({PROTOCOL}; "
                    "pneutune/control/rig/pipe_server.py). Started by `deploy --rig pipe-sim`, "
                    "or by `deploy --rig exec:\"python -m pneutune.control.driver serve --scenario "
                    "{scenario} --seed {seed}\"`.")
    p.add_argument("--plant", help="plant.yaml (default: the paper's rig)")
    p.add_argument("--scenario", help="apply this scenario's plant changes, start at its x_r(0)")
    p.add_argument("--seed", type=int, help="sensor-noise seed (default: sim.seed)")
    p.add_argument("--sample-period", type=float, metavar="S",
                   help="sample (and tick) every S seconds, dividing the plant's rig.Ts "
                        "(default rig.Ts); the hello's Ts is S, its rig block keeps rig.Ts")
    p.set_defaults(run=serve_main)


def serve_main(args: argparse.Namespace) -> int:
    """``serve``: the simulated rig on this process's stdin/stdout until ``C`` or end of input.

    ``--scenario`` takes a scenario's name (the rig of
    :func:`~pneutune.control.rig.scenario_run.sim_rig_for`: its plant changes, the piston at
    rest at its x_r(0)) or an experiment's name
    (:data:`~pneutune.control.rig.excitation_plan.EXPERIMENTS`: the plant as it is, the piston
    at rest mid-stroke), so that one driver command line serves ``deploy`` and ``record``.

    A bad plant or scenario is answered with ``E`` (the client waits for the hello) and one
    ``error:`` line on stderr; exit status 2.

    Parameters
    ----------
    args : argparse.Namespace
        The options of :func:`add_serve_parser`: ``plant``, ``scenario``, ``seed``,
        ``sample_period``.

    Returns
    -------
    int
        Exit status: that of :func:`serve`, or 2 for a bad plant or scenario.
    """
    from pneutune.control.plant.params import load_sim_plant
    from pneutune.control.rig.excitation_plan import EXPERIMENTS
    from pneutune.control.rig.scenario_run import sim_rig_for
    from pneutune.control.sim.scenarios import resolve_scenarios

    try:
        plant_cfg = load_sim_plant(args.plant)
        rig: DeploySimRig
        if args.scenario is None or args.scenario in EXPERIMENTS:
            rig = DeploySimRig(plant_cfg, seed=args.seed, sample_period=args.sample_period)
        else:
            found = resolve_scenarios(args.scenario)
            if len(found) != 1:
                raise ExperimentError(f"--scenario takes one scenario name, got "
                                      f"{args.scenario!r} ({len(found)} scenarios)")
            rig, _, _ = sim_rig_for(found[0], plant_cfg, args.seed,
                                    sample_period=args.sample_period)
    except PneutuneError as exc:
        sys.stderr.write(f"error: {exc}\n")
        try:
            _reply_error(sys.stdout.buffer, str(exc))
        except OSError:
            pass
        return 2
    return serve(rig, sys.stdin.buffer, sys.stdout.buffer)

__all__ = ["add_serve_parser", "serve", "serve_main"]
