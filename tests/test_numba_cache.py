"""pneutune's ``njit`` (control/numba_cache.py): numpy's error model by default.

The closed loop relies on a float division by zero giving an IEEE 754 inf or nan (caught by its
finite-state check) rather than raising, and on every non-zero division giving the same bits
as under numba's Python error model, which only adds a test of the divisor.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from pneutune.control.numba_cache import njit


@njit
def _ratio(a: float, b: float) -> float:
    return a / b


@njit(error_model="python")
def _ratio_python(a: float, b: float) -> float:
    return a / b


def test_division_by_zero_gives_ieee_results_by_default() -> None:
    assert _ratio(1.0, 0.0) == math.inf
    assert _ratio(-1.0, 0.0) == -math.inf
    assert math.isnan(_ratio(0.0, 0.0))


def test_python_error_model_can_still_be_asked_for() -> None:
    with pytest.raises(ZeroDivisionError):
        _ratio_python(1.0, 0.0)


def test_both_error_models_divide_to_the_same_bits() -> None:
    # 10,000 random quotients, overflowing and subnormal ones included: bit for bit equal
    rng = np.random.default_rng(7)
    a = rng.standard_normal(10_000) * 10.0 ** rng.uniform(-20, 20, 10_000)
    b = rng.standard_normal(10_000) * 10.0 ** rng.uniform(-300, 20, 10_000)
    got = np.array([_ratio(x, y) for x, y in zip(a, b, strict=True)])
    ref = np.array([_ratio_python(x, y) for x, y in zip(a, b, strict=True)])
    assert np.array_equal(got.view(np.int64), ref.view(np.int64))
    with np.errstate(over="ignore", under="ignore"):
        direct = a / b
    assert np.array_equal(got.view(np.int64), direct.view(np.int64))


def test_wrapper_passes_other_options_through() -> None:
    assert isinstance(_ratio, numba.core.registry.CPUDispatcher)
    assert _ratio.targetoptions["error_model"] == "numpy"
    assert _ratio_python.targetoptions["error_model"] == "python"
