"""Where numba caches pneutune's compiled functions.

numba keys a cached function on its own source file only: after an edit of a module it calls
(or of index constants it imports), a cached caller would keep running the old code. pneutune's
functions are therefore cached in a folder named by a hash of every source file of
``pneutune.control``, ``pneutune.identify`` and ``pneutune.tune`` and the version
(``$XDG_CACHE_HOME/pneutune/numba/<hash>``, default ``~/.cache``): any change of the sources,
or a new version, compiles afresh.

This is done by a cache locator that answers for pneutune's own files only and declines
everything else, so numba's configuration and the caching of every other package's functions
stay as they were. With ``NUMBA_CACHE_DIR`` set, or a cache folder that cannot be written,
it declines too and numba's own locators decide.
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path
from typing import Any

from numba.core import caching

from pneutune.control.constants import VERSION

# public names since numba 0.61; underscored before
CacheImpl: Any = getattr(caching, "CacheImpl", None) or caching._CacheImpl
UserProvidedCacheLocator: Any = (getattr(caching, "UserProvidedCacheLocator", None)
                                 or caching._UserProvidedCacheLocator)

_PACKAGE = Path(__file__).resolve().parent.parent
#: The source trees whose functions this locator caches (the folders of the three packages).
ROOTS: tuple[Path, ...] = tuple(_PACKAGE / name for name in ("control", "identify", "tune")
                                if (_PACKAGE / name).is_dir())


@functools.lru_cache(maxsize=1)
def source_hash() -> str:
    """SHA-256 (16 hex digits) of the version and every source file of the package trees."""
    h = hashlib.sha256(VERSION.encode())
    for root in ROOTS:
        for path in sorted(root.rglob("*.py")):
            h.update(path.relative_to(root.parent).as_posix().encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def cache_folder() -> Path:
    """The folder of this source tree's compiled functions."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "pneutune" / "numba" / source_hash()


def _ours(py_file: str) -> bool:
    path = Path(py_file).resolve()
    return any(path.is_relative_to(root) for root in ROOTS)


class SourceTreeLocator(UserProvidedCacheLocator):
    """numba cache locator of pneutune's functions (module docstring)."""

    def __init__(self, py_func: Any, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(cache_folder() / self.get_suitable_cache_subpath(py_file))

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> SourceTreeLocator | None:
        """This locator for a function of pneutune's sources, None for any other (or with
        ``NUMBA_CACHE_DIR`` set, or an unwritable folder)."""
        if os.environ.get("NUMBA_CACHE_DIR") or not _ours(py_file):
            return None
        # the mixin's: None for a missing file or a folder that cannot be written
        return super(UserProvidedCacheLocator, cls).from_function(py_func, py_file)


def register_locator() -> None:
    """Put :class:`SourceTreeLocator` first among numba's cache locators (once)."""
    classes = CacheImpl._locator_classes
    if SourceTreeLocator not in classes:
        classes.insert(0, SourceTreeLocator)
