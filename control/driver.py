"""``python -m pneutune.control.driver serve|check``: the example rig driver and the conformance
check of any driver program.

``serve`` answers the pipe protocol ``pneutune.rig/1`` for the simulated rig on stdin/stdout
(:mod:`pneutune.control.rig.pipe_server`); ``check "CMD ARGS"`` tells a driver's author whether
their program speaks it (:mod:`pneutune.control.rig.conformance`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from pneutune.control.errors import PneutuneError
from pneutune.control.rig.conformance import add_check_parser
from pneutune.control.rig.pipe_server import add_serve_parser
from pneutune.control.rig.wire import PROTOCOL


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``serve`` or ``check``; a bad argument is one ``error:`` line and exit status 2."""
    parser = argparse.ArgumentParser(
        prog="python -m pneutune.control.driver",
        description=f"Rig drivers speaking {PROTOCOL} on stdin/stdout (docs/deploy.md): the "
                    "example driver (serve) and the conformance check of any driver (check).")
    sub = parser.add_subparsers(dest="cmd", required=True)
    add_serve_parser(sub)
    add_check_parser(sub)
    args = parser.parse_args(argv)
    try:
        return int(args.run(args))
    except PneutuneError as exc:
        sys.stderr.write(f"error: {exc}\n")
        return 2


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
