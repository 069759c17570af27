"""The rig and its controller: plant model and simulator, valves and PWM, friction, Kalman
filters, DARC variants, scenarios, closed loop, MCAP run logs, config schemas and the runtime.

``deploy(controller, rig, scenarios)`` does what the ``deploy`` command does
(:mod:`pneutune.control.rig.deploy`; imported on first use)::

    from pneutune.control import deploy
    result = deploy("data/controller-paper.yaml", scenarios="table1")

The package is layered; each layer imports only those before it (checked by import-linter in
``make lint``, docs/architecture.md): ``constants``/``errors`` -> ``physics`` -> ``contracts`` ->
``logs`` -> ``plant`` -> ``law`` -> ``sim`` -> ``rig`` -> ``cli``. It never imports
``pneutune.identify`` or ``pneutune.tune``.

Compiled functions are cached on disk in a folder named by a hash of pneutune's sources: each
module compiles with :func:`pneutune.control.numba_cache.njit`, which chooses that cache for
pneutune's own functions and changes nothing of numba's.
"""

from typing import Any

from pneutune.control.constants import VERSION

__version__ = VERSION


def __getattr__(name: str) -> Any:
    if name in ("deploy", "DeployResult"):
        from pneutune.control.rig import deploy as module

        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
