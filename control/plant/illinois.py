"""The Illinois variant of regula falsi, as the plant's root finders use it (numba).

Two searches of the plant bracket a root and shrink the bracket with it: the instant inside an
RK4 step at which the piston reaches a stop or its velocity zero
(:func:`pneutune.control.plant.dynamics.advance`), and the pressure of a line's junction at
which the valves' flows balance the line's (:func:`pneutune.control.plant.flows.line_flow`).
Each computes its own trial point and stopping test; the bracket update is this one.
"""

from __future__ import annotations

from pneutune.control.numba_cache import njit


@njit(cache=True, inline="always")
def illinois_update(a: float, fa: float, b: float, fb: float, c: float, fc: float,
                    side: int) -> tuple[float, float, float, float, int]:
    """Replace the end of the bracket ``[a, b]`` on the side of ``c`` by ``c``.

    Parameters
    ----------
    a, fa, b, fb : float
        The bracket's ends and the function's values there (of opposite signs).
    c, fc : float
        The new point and its value.
    side : int
        Which end the previous update replaced: -1 ``b``, 1 ``a``, 0 none yet.

    Returns
    -------
    a, fa, b, fb : float
        The new bracket. When the same end is replaced twice running, the value kept at the
        other end is halved (the Illinois step), so that the bracket shrinks from both sides.
    side : int
        The end replaced now.
    """
    if fc * fb > 0.0:
        b, fb = c, fc
        if side == -1:
            fa *= 0.5
        side = -1
    else:
        a, fa = c, fc
        if side == 1:
            fb *= 0.5
        side = 1
    return a, fa, b, fb, side


__all__ = ["illinois_update"]
