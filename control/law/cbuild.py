"""Build the control law's C as a target would, and run it from Python (software in the loop).

The install compiles ``control/law/c/ptlaw.c`` once into the library the simulator calls
(:mod:`.clib`). A target compiles the same sources its own way: strict C99, maybe in ``float``.
:func:`build` does that here, with the flags the sources promise to compile cleanly under
(:data:`CFLAGS`), into a folder of the caller's choosing; :class:`CLaw` loads the result with
ctypes and offers :meth:`CLaw.step_into` with the signature of
:func:`pneutune.control.law.darc.step_into`, so the deploy runtime can run a closed loop through
the target's build (``simulate --law c`` / ``c-float``).

A ``float`` build (``-DPT_REAL_FLOAT``) keeps its state in single precision; :class:`CLaw`
converts the caller's float64 vectors to float32 for each call and back. float32 to float64
and back is exact, so the state the caller holds between steps is exactly the target's.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

from pneutune.control.errors import ExperimentError

#: The C sources of the law (ptlaw.c and its headers).
SOURCE_DIR = Path(__file__).resolve().parent / "c"
#: The flags the sources compile cleanly under (any warning is an error).
CFLAGS: tuple[str, ...] = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2",
                           "-ffp-contract=off")
#: Precisions a build can have.
REALS: tuple[str, ...] = ("double", "float")


def compiler() -> str:
    """The C compiler: ``$CC``, else ``cc``, ``gcc`` or ``clang``, the first on the PATH.

    Raises
    ------
    ExperimentError
        None found.
    """
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    raise ExperimentError("no C compiler found (set CC, or install gcc or clang)")


def build(out_dir: str | os.PathLike[str], real: str = "double",
          sources: tuple[str, ...] = ("ptlaw.c",)) -> Path:
    """Compile the law's C into a shared library in ``out_dir``, as a target would.

    Parameters
    ----------
    out_dir : path-like
        Folder of the library (made if missing). A library built before from the same
        sources, flags and compiler is reused.
    real : str
        ``double`` or ``float`` (``-DPT_REAL_FLOAT``).
    sources : tuple of str
        The .c files of :data:`SOURCE_DIR` to compile.

    Returns
    -------
    Path
        The library.

    Raises
    ------
    ExperimentError
        An unknown ``real``, no compiler, or a compile that fails (its diagnostics quoted).
    """
    if real not in REALS:
        raise ExperimentError(f"real must be one of {', '.join(REALS)}, got {real!r}")
    cc = compiler()
    flags = [*CFLAGS, "-fPIC", "-shared", *(["-DPT_REAL_FLOAT"] if real == "float" else [])]
    paths = [SOURCE_DIR / s for s in sources]
    h = hashlib.sha256(" ".join([cc, *flags]).encode())
    for p in sorted([*paths, *SOURCE_DIR.glob("*.h")]):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lib = out / f"libptlaw-{real}-{h.hexdigest()[:12]}.so"
    if lib.is_file():
        return lib
    tmp = lib.with_suffix(f".{os.getpid()}.tmp")
    cmd = [cc, *flags, f"-I{SOURCE_DIR}", *map(str, paths), "-o", str(tmp), "-lm"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tmp.unlink(missing_ok=True)
        raise ExperimentError(f"compiling the control law failed ({' '.join(cmd)}):\n"
                              f"{done.stderr.strip()}")
    os.replace(tmp, lib)
    return lib


class CLaw:
    """A build of the law loaded with ctypes (:func:`build`).

    Parameters
    ----------
    path : path-like
        The library.
    real : str
        Its precision, as built: ``double`` or ``float``.
    """

    def __init__(self, path: str | os.PathLike[str], real: str = "double") -> None:
        if real not in REALS:
            raise ExperimentError(f"real must be one of {', '.join(REALS)}, got {real!r}")
        self.path = Path(path)
        self.real = real
        self.dtype = np.float64 if real == "double" else np.float32
        self._lib = ctypes.CDLL(str(self.path))
        ptr = ctypes.POINTER(ctypes.c_double if real == "double" else ctypes.c_float)
        self._ptr = ptr
        self._lib.pt_step_into.argtypes = [ptr, ptr, ptr, ptr]
        self._lib.pt_step_into.restype = ctypes.c_int

    def step_into(self, state: np.ndarray, meas: np.ndarray, cfg: np.ndarray,
                  duties_out: np.ndarray) -> int:
        """One step, as :func:`pneutune.control.law.darc.step_into` (float64 in and out).

        Parameters
        ----------
        state, meas, cfg, duties_out : ndarray of float64
            As ``step_into``; ``state`` and ``duties_out`` are updated in place.

        Returns
        -------
        int
            The Eq. (33) case, or 0 for a config of another layout.
        """
        if self.real == "double":
            return int(self._lib.pt_step_into(
                state.ctypes.data_as(self._ptr), np.ascontiguousarray(meas).ctypes.data_as(
                    self._ptr), np.ascontiguousarray(cfg).ctypes.data_as(self._ptr),
                duties_out.ctypes.data_as(self._ptr)))
        s = state.astype(np.float32)
        m = np.asarray(meas, dtype=np.float32)
        c = np.asarray(cfg, dtype=np.float32)
        d = np.zeros(4, dtype=np.float32)
        case = int(self._lib.pt_step_into(s.ctypes.data_as(self._ptr), m.ctypes.data_as(self._ptr),
                                          c.ctypes.data_as(self._ptr), d.ctypes.data_as(self._ptr)))
        state[:] = s
        duties_out[:] = d
        return case


__all__ = ["CFLAGS", "REALS", "SOURCE_DIR", "CLaw", "build", "compiler"]
