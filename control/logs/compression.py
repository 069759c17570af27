"""The zstd level of the chunks the ``mcap`` package's Writer compresses.

The ``mcap`` package compresses each chunk with ``zstandard.compress`` (zstd's level 3) and
has no setting for the level: its Writer looks the name ``zstandard`` up in the namespace of
``mcap.writer`` whenever it closes a chunk. :func:`zstd_level` picks another level for the
writer calls made inside its block. While at least one such block is open (in any thread),
that name refers to :class:`_LevelledZstd`, which compresses at the level the calling thread
asked for and exactly as ``zstandard.compress`` otherwise, so other threads and other writers
write the same bytes as without it; when the last block closes, the name refers to the
``zstandard`` module again. Importing this module changes nothing in ``mcap``, nor does a
block with level None. The bytes stay standard zstd frames that every reader decompresses.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

import mcap.writer

__all__ = ["ZSTD_LEVELS", "zstd_level"]

#: zstd levels accepted by ``compression_level`` (zstd's own range without the negative ones).
ZSTD_LEVELS = range(1, 23)

#: The level each thread asked for (attribute ``level``; absent or None: the package's).
_local = threading.local()
#: Guards ``_open`` and the swap of ``mcap.writer.zstandard``.
_lock = threading.Lock()
#: Blocks of :func:`zstd_level` open in all threads, and the module they replaced.
_open = 0
_replaced: Any = None


class _LevelledZstd:
    """Stands in for the ``zstandard`` module inside ``mcap.writer``: ``compress`` at the
    level the calling thread set, else ``zstandard.compress``; every other name is the
    module's."""

    def __init__(self, module: Any) -> None:
        self._module = module

    def __getattr__(self, name: str) -> Any:
        return getattr(self._module, name)

    def compress(self, data: bytes) -> bytes:
        """Compress one chunk."""
        level = getattr(_local, "level", None)
        if level is None:
            return self._module.compress(data)
        return self._module.ZstdCompressor(level=level).compress(data)


def _install() -> None:
    global _open, _replaced
    with _lock:
        if _open == 0:
            _replaced = mcap.writer.zstandard
            mcap.writer.zstandard = _LevelledZstd(_replaced)  # type: ignore[assignment]
        _open += 1


def _uninstall() -> None:
    global _open, _replaced
    with _lock:
        _open -= 1
        if _open == 0:
            if isinstance(mcap.writer.zstandard, _LevelledZstd):
                mcap.writer.zstandard = _replaced
            _replaced = None


@contextlib.contextmanager
def zstd_level(level: int | None) -> Iterator[None]:
    """Compress the chunks that the calling thread's ``mcap`` Writer closes inside the block
    at ``level``.

    Parameters
    ----------
    level : int or None
        zstd level, one of :data:`ZSTD_LEVELS`; None keeps the package's (3) and changes
        nothing.

    Yields
    ------
    None
        Inside the block, ``mcap.writer.zstandard`` is :class:`_LevelledZstd`; it is the
        ``zstandard`` module again once no thread has a block open.
    """
    if level is None:
        yield
        return
    _install()
    previous = getattr(_local, "level", None)
    _local.level = level
    try:
        yield
    finally:
        _local.level = previous
        _uninstall()
