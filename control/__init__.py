"""The rig and its controller: plant model and simulator, valves and PWM, friction, Kalman
filters, DARC variants, scenarios, closed loop, MCAP run logs, config schemas and the runtime.

The package is layered; each layer imports only those before it (checked by import-linter in
``make lint``, docs/architecture.md): ``constants``/``errors`` -> ``physics`` -> ``contracts`` ->
``logs`` -> ``plant`` -> ``law`` -> ``sim`` -> ``rig`` -> ``cli``. It never imports
``pneutune.identify`` or ``pneutune.tune``.

numba cache: numba keys a cached compiled function on its own source file only, so after an
edit of a module it calls (or of index constants it imports) a cached caller would keep running
the old code. pneutune therefore points numba's cache at a folder named by a hash of every source
file of this package and its subpackages (unless ``NUMBA_CACHE_DIR`` is set): any change of the
sources, or a new version, compiles afresh.
"""

import hashlib
import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

try:
    __version__ = version("pneutune")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"


def _source_hash() -> str:
    h = hashlib.sha256(__version__.encode())
    root = Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _configure_numba_cache() -> None:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    import numba

    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    folder = base / "pneutune" / "numba" / _source_hash()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # read-only home: fall back to numba's default (beside the sources)
        return
    numba.config.CACHE_DIR = str(folder)


_configure_numba_cache()
