"""``python -m pneutune.control.driver serve``: the example driver of the pipe protocol.

The command keeps its name; the code lives in :mod:`pneutune.control.rig.pipe`.
"""

from pneutune.control.rig.pipe import main

if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
