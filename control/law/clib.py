"""The compiled control law: its shared library and the C functions numba calls.

The control law exists once, as C99 in ``control/law/c/`` (``ptlaw.c``, the same sources
``deploy --emit c`` gives a target), and so does the deploy runtime's safety supervisor
(``pt_supervisor.c``, called through :data:`LIB`). The install compiles both into a plain
shared library, ``pneutune/control/law/_ptlaw*.so`` (``[[tool.setuptools.ext-modules]]`` in
pyproject.toml: not a Python extension module, never imported as one; ``pip install -e .`` or
``make`` rebuilds it after an edit of the C). This module loads it into the process's symbol table
(:func:`llvmlite.binding.load_library_permanently`) and declares each C function as a numba
:class:`~numba.core.types.ExternalFunction`: compiled code calls the function by its symbol, so
numba's on-disk cache stays valid across processes (a ctypes function pointer would be an
address baked into the cache). Arrays pass as their data pointers (``a.ctypes``): the wrappers
in :mod:`.kalman`, :mod:`.projection`, :mod:`.duty` and :mod:`.darc` take C-contiguous float64
arrays, as the step's flat vectors are.

Python-level calls that are not compiled (:func:`pneutune.control.law.darc.init_state`) go
through :data:`LIB`, the same library opened with ctypes.
"""

from __future__ import annotations

import ctypes
import importlib.util
from pathlib import Path

from llvmlite import binding
from numba import types

#: The extension-module name the install builds the library under.
MODULE = "pneutune.control.law._ptlaw"
#: The C sources of the law.
SOURCE_DIR = Path(__file__).resolve().parent / "c"


class LawLibraryError(ImportError):
    """The compiled control law is not there: the package was not installed with its build."""


def library_path() -> Path:
    """The shared library of the control law, as the install built it.

    Returns
    -------
    Path

    Raises
    ------
    LawLibraryError
        No library: the sources were not installed with ``pip install -e .`` (``make``).
    """
    spec = importlib.util.find_spec(MODULE)
    if spec is None or spec.origin is None or not Path(spec.origin).is_file():
        raise LawLibraryError(
            f"the compiled control law ({MODULE.replace('.', '/')}*.so) is missing: install "
            "pneutune with `pip install -e .` (or run `make test`), which compiles "
            f"{SOURCE_DIR / 'ptlaw.c'} with the C compiler")
    return Path(spec.origin)


PATH = library_path()
binding.load_library_permanently(str(PATH))
#: The library opened with ctypes, for calls from Python.
LIB = ctypes.CDLL(str(PATH))

_p = types.voidptr
_f = types.float64
_i = types.intc
_long = types.long_

#: ``int pt_step_into(state, meas, cfg, duties_out)``
pt_step_into = types.ExternalFunction("pt_step_into", _i(_p, _p, _p, _p))
#: ``void pt_kf_predict_into(x, Pf, A, WQWt, work, n)``
pt_kf_predict_into = types.ExternalFunction("pt_kf_predict_into",
                                            types.void(_p, _p, _p, _p, _p, _i))
#: ``void pt_kf_update_into(x, Pf, z, H, R, work, n)``
pt_kf_update_into = types.ExternalFunction("pt_kf_update_into",
                                           types.void(_p, _p, _f, _p, _f, _p, _i))
#: ``void pt_proj_into(theta_hat, v, theta_min, theta_max, out, n)``
pt_proj_into = types.ExternalFunction("pt_proj_into", types.void(_p, _p, _p, _p, _p, _i))
#: ``void pt_sat_into(v, rate_max, out, n)``
pt_sat_into = types.ExternalFunction("pt_sat_into", types.void(_p, _p, _p, _i))
#: ``void pt_adaptation_rate_into(theta_hat, tau, gamma, rate_max, theta_min, theta_max, out, n)``
pt_adaptation_rate_into = types.ExternalFunction(
    "pt_adaptation_rate_into", types.void(_p, _p, _p, _p, _p, _p, _p, _i))
#: ``void pt_adapt_step_into(theta_hat, tau, gamma, rate_max, theta_min, theta_max, Ts,
#: rate_out, n)``
pt_adapt_step_into = types.ExternalFunction(
    "pt_adapt_step_into", types.void(_p, _p, _p, _p, _p, _p, _f, _p, _i))
#: ``double pt_fully_open_q_l(q_ld, p_a, p_b, p_s, p0, T0, nR, A_a, A_b, V_a, V_b, C, b)``
pt_fully_open_q_l = types.ExternalFunction(
    "pt_fully_open_q_l", _f(_f, _f, _f, _f, _f, _f, _f, _f, _f, _f, _f, _p, _p))
#: ``int pt_eq33_into(q_ld, q_lf, u_out)``
pt_eq33_into = types.ExternalFunction("pt_eq33_into", _i(_f, _f, _p))
#: ``double pt_pwm_inverse(ratio, duty_pts, ratio_pts, m)``
pt_pwm_inverse = types.ExternalFunction("pt_pwm_inverse", _f(_f, _p, _p, _long))
#: ``int pt_duties_into(q_ld, q_lf, n_pts, duty_pts, ratio_pts, stride, u_work, duties_out)``
pt_duties_into = types.ExternalFunction(
    "pt_duties_into", _i(_f, _f, _p, _p, _p, _long, _p, _p))
#: ``void pt_dither_into(u, duties, t, Ts, period, d_k, r_k, acc, pulse, last)``
pt_dither_into = types.ExternalFunction(
    "pt_dither_into", types.void(_p, _p, _f, _f, _f, _p, _p, _p, _p, _p))

_dp = ctypes.POINTER(ctypes.c_double)
LIB.pt_init_state.argtypes = [_dp, _dp, ctypes.c_double, ctypes.c_double, ctypes.c_double]
LIB.pt_init_state.restype = ctypes.c_int
# the safety supervisor (pt_supervisor.h), called per sample by the deploy runtime
# (pneutune.control.rig.supervisor.Supervisor); vectors pass as their data addresses
_vp, _d, _u32 = ctypes.c_void_p, ctypes.c_double, ctypes.c_uint32
if not hasattr(LIB, "pt_sup_check_sensors"):
    raise LawLibraryError(f"{PATH} was built without the safety supervisor (pt_supervisor.c): "
                          "rebuild it with `pip install -e .` (or `make test`)")
LIB.pt_sup_reset.argtypes = [_vp]
LIB.pt_sup_reset.restype = None
LIB.pt_sup_layout_ok.argtypes = [_vp]
LIB.pt_sup_layout_ok.restype = ctypes.c_int
LIB.pt_sup_check_sensors.argtypes = [_vp, _vp, _d, _vp, _vp]
LIB.pt_sup_check_sensors.restype = _u32
LIB.pt_sup_check_estimates.argtypes = [_vp, _vp, _d, _d, _vp]
LIB.pt_sup_check_estimates.restype = _u32

__all__ = ["LIB", "MODULE", "PATH", "SOURCE_DIR", "LawLibraryError", "library_path"]
