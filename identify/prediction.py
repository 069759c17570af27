"""One-step predictions of a run log by the compiled plant, for prediction-error fits (numba).

The identified model is checked against the log *between* samples: from the measured state at
sample k, the plant of :mod:`pneutune.control.plant.dynamics` (the one implementation, with every
valve
switching inside the sample) runs under the logged duties to sample k+1, and the prediction is
compared with the measurement there. Two predictors:

* :func:`pressure_residuals`: position and both pressures are reset to the measured values at
  every sample (the velocity runs free), so the residual of p_a and p_b at k+1 is the error of
  one sample of Eqs. (5)-(7) with the PWM timing. It is what the valve delays show in.
* :func:`position_innovations`: a fixed-gain observer. At each sample the predicted position and
  pressures move a fraction ``gain`` toward the measurements; the position innovation is what the
  motion equation (1), with its mass, failed to predict. Over sliding stretches it carries the
  0.3 ms lag M/b_v that a 4 ms sample cannot show as an acceleration (docs/identifiability.md).

Both take a stack of packed parameter vectors and run them in parallel (``prange``): the
candidates of a grid search or the columns of a finite-difference Jacobian.
benchmarks/mass_identifiability.py uses them to measure how far the mass and the valve delays
can be fitted from 4 ms samples (docs/identifiability.md).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from pneutune.control.numba_cache import njit
from pneutune.control.plant.dynamics import advance, initial_state, set_duties
from pneutune.control.plant.params import S_PA, S_PB, S_X


@njit(cache=True, parallel=True)
def pressure_residuals(P: np.ndarray, force_steps: np.ndarray, t: np.ndarray, x: np.ndarray,
                       pa: np.ndarray, pb: np.ndarray, ps: np.ndarray, u: np.ndarray,
                       res_a: np.ndarray, res_b: np.ndarray) -> None:
    """One-sample pressure prediction errors for each parameter vector.

    Parameters
    ----------
    P : ndarray, shape (G, N_PARAMS)
        Packed plant parameters, one candidate per row.
    force_steps : ndarray, shape (K, 2)
        External force steps (none for a log: pass an empty (0, 2) array).
    t, x, pa, pb, ps : ndarray, shape (N,)
        Sample times [s], position [m] and pressures [Pa abs] of the log.
    u : ndarray, shape (N, 4)
        Logged duties.
    res_a, res_b : ndarray, shape (G, N)
        Outputs: measured minus predicted p_a and p_b [Pa]; 0 at sample 0.
    """
    n = t.shape[0]
    for g in prange(P.shape[0]):
        p = P[g]
        s = initial_state(p, x[0], pa[0], pb[0], t[0])
        res_a[g, 0] = 0.0
        res_b[g, 0] = 0.0
        for k in range(n - 1):
            s[S_X] = x[k]
            s[S_PA] = pa[k]
            s[S_PB] = pb[k]
            set_duties(p, s, t[k], u[k])
            advance(p, s, t[k + 1], ps[k], force_steps)
            res_a[g, k + 1] = pa[k + 1] - s[S_PA]
            res_b[g, k + 1] = pb[k + 1] - s[S_PB]


@njit(cache=True, parallel=True)
def position_innovations(P: np.ndarray, force_steps: np.ndarray, t: np.ndarray, x: np.ndarray,
                         pa: np.ndarray, pb: np.ndarray, ps: np.ndarray, u: np.ndarray,
                         starts: np.ndarray, ends: np.ndarray, gain: float,
                         out: np.ndarray) -> None:
    """Position innovations of a fixed-gain observer over stretches of the log.

    Each stretch ``[starts[j], ends[j])`` starts from rest at the measured state with the valves
    closed; give it a lead-in of a few PWM periods before the samples that are scored, so that
    the valve states and the observer have settled.

    Parameters
    ----------
    P : ndarray, shape (G, N_PARAMS)
        Packed plant parameters, one candidate per row.
    force_steps, t, x, pa, pb, ps, u
        As in :func:`pressure_residuals`.
    starts, ends : ndarray of int64
        Stretch bounds (sample indices, ``ends`` exclusive).
    gain : float
        Observer gain on position and pressures, 0 < gain <= 1.
    out : ndarray, shape (G, N)
        Output: measured minus predicted position [m] inside the stretches (left as it is
        elsewhere).

    Raises
    ------
    ValueError
        A stretch outside the log, empty, or ``starts`` and ``ends`` of different lengths.
    """
    n = t.shape[0]
    if starts.shape[0] != ends.shape[0]:
        raise ValueError("starts and ends differ in length")
    for j in range(starts.shape[0]):
        if starts[j] < 0 or ends[j] > n or starts[j] >= ends[j]:
            raise ValueError("a stretch lies outside the log or is empty")
    for g in prange(P.shape[0]):
        p = P[g]
        for j in range(starts.shape[0]):
            k0, k1 = starts[j], ends[j]
            s = initial_state(p, x[k0], pa[k0], pb[k0], t[k0])
            for k in range(k0, k1):
                e = x[k] - s[S_X]
                out[g, k] = e
                s[S_X] += gain * e
                s[S_PA] += gain * (pa[k] - s[S_PA])
                s[S_PB] += gain * (pb[k] - s[S_PB])
                if k == k1 - 1:
                    break
                set_duties(p, s, t[k], u[k])
                advance(p, s, t[k + 1], ps[k], force_steps)


__all__ = ["position_innovations", "pressure_residuals"]
