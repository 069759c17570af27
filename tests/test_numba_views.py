"""control/numba_views.py: the plant's views without reference counting see and change the
array they were made from, and leave an array that is not C-contiguous as it is."""

from __future__ import annotations

import numba
import numpy as np

from pneutune.control.numba_views import unowned


@numba.njit
def _bump_and_sum(a: np.ndarray) -> float:
    b = unowned(a)
    b[0] += 1.0
    return float(b.sum())


def test_unowned_is_a_view_of_the_same_memory() -> None:
    """A write through the view lands in the array; its sum is the array's (0+..+5 = 15, +1)."""
    a = np.arange(6.0)
    assert _bump_and_sum(a) == 16.0
    assert a[0] == 1.0
    rows = np.arange(12.0).reshape(3, 4)
    assert _bump_and_sum(rows[1]) == 4.0 + 5.0 + 6.0 + 7.0 + 1.0  # a row of a C array
    assert rows[1, 0] == 5.0


def test_unowned_leaves_a_strided_array_as_it_is() -> None:
    """Every other element of 0..11 (0+2+..+10 = 30, +1): the strided view is used as it is,
    never read as if it were contiguous."""
    a = np.arange(12.0)
    assert _bump_and_sum(a[::2]) == 31.0
    assert a[0] == 1.0 and a[1] == 1.0
