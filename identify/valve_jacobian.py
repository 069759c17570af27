"""The Jacobian of the valve fit's least squares: scipy's 2-point numbers in fewer evaluations.

``least_squares``'s default ``jac='2-point'`` evaluates the residuals once per parameter. In
the valve fit (:class:`~pneutune.identify.valves.ValveIdentifier`) a parameter of chamber A
moves only chamber A's window residuals (and a critical ratio b its prior), and one of chamber B
only B's, so one evaluation with a parameter of each perturbed gives both columns
(:func:`valve_fit_groups`): six evaluations per Jacobian instead of eleven.
:func:`grouped_jacobian` computes the numbers scipy's would: the same steps (scipy's, adjusted
to the bounds alike), each column the difference of two residual evaluations over its step,
the rows a parameter does not move ``0 / step`` (a negative zero for a step turned back at a
bound, as there).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

try:  # scipy's own step rules of jac='2-point' (private: without them, least_squares' default)
    from scipy.optimize._numdiff import _adjust_scheme_to_bounds, _compute_absolute_step
except ImportError:  # pragma: no cover - a scipy that moved them
    _adjust_scheme_to_bounds = _compute_absolute_step = None


def valve_fit_groups(na: int, nb: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The valve fit's parameters perturbed together in one residual evaluation, and their rows.

    Rows: chamber A's windows, chamber B's, the four b priors; parameters: C, b of a_in,
    a_out, b_in, b_out, the leak, D_a, D_b. A chamber's valves and D move only its windows
    (and b its prior), so a parameter of A and one of B are perturbed together.

    Parameters
    ----------
    na, nb : int
        Number of windows of chamber A and of chamber B.

    Returns
    -------
    list of (ndarray, ndarray)
        Per group: the parameter indices, and per parameter the rows it moves (an object
        array of index arrays).
    """
    rows_a, rows_b = np.arange(na), na + np.arange(nb)
    prior = na + nb + np.arange(4)
    rows = []
    for j in range(8):
        r = rows_a if j < 4 else rows_b
        rows.append(np.append(r, prior[j // 2]) if j % 2 else r)  # b: its prior too
    rows += [np.concatenate([rows_a, rows_b]), rows_a, rows_b]
    out = []
    for cols in ([0, 4], [1, 5], [2, 6], [3, 7], [8], [9, 10]):
        held = np.empty(len(cols), dtype=object)
        held[:] = [rows[j] for j in cols]
        out.append((np.array(cols), held))
    return out


def grouped_jacobian(residuals: Callable[..., np.ndarray],
                     at_point: Callable[..., np.ndarray],
                     groups: Sequence[tuple[np.ndarray, np.ndarray]], lo: np.ndarray,
                     hi: np.ndarray) -> Callable[..., np.ndarray] | str:
    """The Jacobian of ``residuals`` for ``least_squares`` with these bounds (module docstring).

    Parameters
    ----------
    residuals : callable
        ``residuals(theta, *args)``, the function ``least_squares`` minimises.
    at_point : callable
        ``at_point(theta, *args)``: the residuals at the point the Jacobian is taken at (the
        evaluation ``least_squares`` just made there, where it is at hand).
    groups : sequence of (ndarray, ndarray)
        The parameters perturbed together and the rows each moves
        (:func:`valve_fit_groups`): each parameter in exactly one group, the parameters of a
        group moving disjoint rows.
    lo, hi : ndarray
        The bounds given to ``least_squares``.

    Returns
    -------
    callable or str
        ``jac(theta, *args)`` giving the Jacobian (rows: residuals, columns: parameters), or
        ``"2-point"`` with a scipy that does not have the step rules.
    """
    if _compute_absolute_step is None:  # pragma: no cover
        return "2-point"

    def jac(theta: np.ndarray, *args: object) -> np.ndarray:
        f0 = at_point(theta, *args)
        h = _compute_absolute_step(None, theta, f0, "2-point")
        h, _ = _adjust_scheme_to_bounds(theta, h, 1, "1-sided", lo, hi)
        dx = (theta + h) - theta
        J = np.zeros((len(theta), len(f0)))  # transposed, as scipy fills it
        J /= dx[:, None]
        for cols, rows in groups:
            x = theta.copy()
            x[cols] = theta[cols] + h[cols]
            df = residuals(x, *args) - f0
            for j, r in zip(cols, rows, strict=True):
                J[j, r] = df[r] / dx[j]
        return J.T

    return jac
