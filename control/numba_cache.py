"""Where numba caches pneutune's compiled functions, chosen per function by pneutune's ``njit``.

numba keys a cached function on its own source file only: after an edit of a module it calls
(or of index constants it imports), a cached caller would keep running the old code.
pneutune's compiled functions are therefore cached in a folder named by a hash of every source
file of ``pneutune.control``, ``pneutune.identify`` and ``pneutune.tune`` and the version
(``$XDG_CACHE_HOME/pneutune/numba/<hash>``, default ``~/.cache``): any change of the sources,
or a new version, compiles afresh.

The choice is made function by function: every module of pneutune decorates with
:func:`njit` from here instead of numba's, and ``njit(cache=True)`` gives the dispatcher a
cache whose locator is :class:`SourceTreeLocator` (numba's own locators after it). Nothing of
numba's is changed: its configuration, its locator list and every other package's caching stay
as they were. With ``NUMBA_CACHE_DIR`` set, or a cache folder that cannot be written, the
locator declines and numba's own locators decide.

pneutune's ``njit`` also makes numpy's error model the default (``error_model="numpy"``): a
float division by zero gives inf or nan, as IEEE 754 says, instead of raising
ZeroDivisionError. numba's default (the Python model) tests every divisor before dividing; no
pneutune function relies on the exception (the plant's contract keeps its divisors positive, and
the closed loop turns a non-finite state into an "unstable" run), and every result is the same
to the last bit without the tests (the plant's golden outputs, the law's reference replay and
the sensor and duty arrays of full tune evaluations). A function may still ask for
``error_model="python"``.

The one function compiled otherwise is the ufunc form of the ISO 6358 flow
(:func:`pneutune.control.physics.flow.signed_flow_array`, ``vectorize(cache=True)``, made on
first use): numba's own locator caches it beside its module, keyed on that module, which holds
everything it calls.
"""

from __future__ import annotations

import functools
import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import numba
from numba.core import caching

from pneutune.control.constants import VERSION

# public names since numba 0.61; underscored before
_UserProvidedCacheLocator: Any = (getattr(caching, "UserProvidedCacheLocator", None)
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


class SourceTreeLocator(_UserProvidedCacheLocator):
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
        return super(_UserProvidedCacheLocator, cls).from_function(py_func, py_file)


class _CacheImpl(caching.CompileResultCacheImpl):
    _locator_classes: ClassVar[list[Any]] = [SourceTreeLocator,
                                             *caching.CompileResultCacheImpl._locator_classes]


class FunctionCache(caching.FunctionCache):
    """numba's function cache, with :class:`SourceTreeLocator` first among its locators."""

    _impl_class = _CacheImpl


def njit(*args: Any, cache: bool = False, **kwargs: Any) -> Any:
    """numba's ``njit``; with ``cache=True`` the cache is :class:`FunctionCache`.

    Parameters
    ----------
    *args, **kwargs
        As :func:`numba.njit` (a function, or the options; signatures are not used here);
        ``error_model`` defaults to ``"numpy"`` (module docstring).
    cache : bool
        Cache the compiled code on disk (module docstring).

    Returns
    -------
    Dispatcher or decorator
    """
    kwargs.setdefault("error_model", "numpy")

    def decorate(fn: Callable[..., Any]) -> Any:
        dispatcher = numba.njit(**kwargs)(fn)
        if cache:
            dispatcher._cache = FunctionCache(dispatcher.py_func)  # numba's enable_caching
        return dispatcher

    if args and callable(args[0]):
        return decorate(args[0])
    return decorate


__all__ = ["ROOTS", "FunctionCache", "SourceTreeLocator", "cache_folder", "njit", "source_hash"]
