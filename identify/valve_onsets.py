"""The delay from a valve's full-opening command to the chamber pressure's response.

A log sampled several times per PWM period (an identification run logs every 0.5 ms) shows, at
each step of a valve's duty from 0 to 1 with the piston at rest and the chamber's other valve
commanded shut from the edge on, when the chamber pressure starts to follow the valve. That
time holds everything between the written duty and the pressure sensor: the IO delay, the
valve's opening delay, its armature lag, the line between valve and chamber and the
transmitter's lag. The control-rate fit sees it only through window sums, where the opening
delay trades against the carrier phase, the pulse lengthening and an IO delay; on a fleet rig
with lags (benchmarks/fleet.py, plant 0) it put two valves' opening delays at 2 ms where their
step onsets are 5 ms.

Per edge, the measured pressure change from the edge on is compared with a closed volume's
(Eq. 5 with V fixed, Eq. 7 with the C and b of the control-rate fit) through the valve opening
``d`` after the edge, for ``d`` on a grid. The protocol shuts the chamber's other valve at the
sample it opens this one, and that valve's closing lags its command: the model keeps it open
until a second searched time, so a chamber still venting at the edge, or venting through both
valves for a while, is not read as a late opening (without this an inlet's onset came out
0.4 ms late on data/run.mcap). A free gain on the change absorbs an error of C: the shape
near the onset decides, not the level. The valve's onset is the median over its edges, its
range their spread.

Only the immediate PWM update mode times a full-opening command from the write; a latched rig
starts it at the next carrier period, whose phase the control-rate search finds later, so no
onsets are measured there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pneutune.control.numba_cache import njit
from pneutune.control.physics.flow import signed_flow

from .dataset import Dataset
from .mass import MIN_SAMPLES_PER_PWM, samples_per_pwm

#: Time after an edge the response is compared over [s].
HORIZON = 0.040
#: Largest piston travel over an edge's window for the volume to count as fixed [m].
STILL = 1.0e-4
#: Largest pressure change over the samples before an edge for the chamber to count as
#: settled (the other valve, shut at the edge, then passes next to nothing) [Pa].
SETTLED = 1.0e4
#: Least pressure change over the horizon for an edge to count [Pa].
MIN_SWING = 2.0e4
#: Grid step of the delay [s].
GRID_STEP = 1.0e-4
#: Grid step of the time both valves of the chamber pass air after the opening (the other
#: valve's command falls at the same edge, its closing lags) [s].
OVERLAP_STEP = 5.0e-4
#: Integration substeps per sample of the closed-volume response.
SUBSTEPS = 4
#: Edges further than this from the median of a valve's edges are left out [s].
OUTLIER = 1.0e-3
#: Least edges per valve for an onset.
MIN_EDGES = 3
#: Range of the free gain on the pressure change within which an edge's fit is kept [-].
GAIN_RANGE = (0.5, 2.0)
#: Samples before an edge averaged as the pressure before it.
PRE_SAMPLES = 6


@dataclass(frozen=True)
class Onset:
    """A valve's response delay to a full-opening command [s].

    Attributes
    ----------
    delay : float
        Median over the edges.
    low, high : float
        Smallest and largest edge estimate.
    edges : int
        Number of edges used.
    """

    delay: float
    low: float
    high: float
    edges: int


@njit(cache=True)
def _net_flow(p: float, C: float, b: float, inlet: bool, one: bool, C2: float, b2: float,
              both: bool, p_s: float, p0: float, T: float) -> float:
    """Flow into the chamber [kg/s]: the opening valve once ``one``, the other one while
    ``both``."""
    f = 0.0
    if one:
        f = signed_flow(C, b, p_s, p, T) if inlet else -signed_flow(C, b, p, p0, T)
    if both:
        f += -signed_flow(C2, b2, p, p0, T) if inlet else signed_flow(C2, b2, p_s, p, T)
    return f


@njit(cache=True)
def _closed_volume_response(p_start: float, V: float, C: float, b: float, inlet: bool,
                            C2: float, b2: float, opening: float, closing: float, p_s: float,
                            p0: float, T: float, nRT: float, h: float, n: int, sub: int,
                            out: np.ndarray) -> None:
    """Pressure of a fixed volume at ``n`` samples ``h`` apart from an edge (explicit midpoint
    steps of ``h / sub``) into ``out``: a valve opening ``opening`` after the edge, and the
    chamber's other valve (conductance ``C2``, ``b2``) open until ``closing``."""
    p = p_start
    out[0] = p
    dt = h / sub
    k = nRT / V
    t = 0.0
    for j in range(1, n):
        for _ in range(sub):
            tm = t + 0.5 * dt
            one = tm >= opening
            both = tm < closing
            f1 = _net_flow(p, C, b, inlet, one, C2, b2, both, p_s, p0, T)
            pm = p + 0.5 * dt * k * f1
            p = p + dt * k * _net_flow(pm, C, b, inlet, one, C2, b2, both, p_s, p0, T)
            t += dt
        out[j] = p


@njit(cache=True)
def _edge_costs(y: np.ndarray, p_start: float, V: float, C: float, b: float, inlet: bool,
                C2: float, b2: float, openings: np.ndarray, closings: np.ndarray, p_s: float,
                p0: float, T: float, nRT: float, h: float, sub: int,
                cost: np.ndarray, gain: np.ndarray) -> None:
    """Per (opening, closing) pair: the least-squares gain on the model's pressure change and
    the residual against the measured change ``y`` from the edge on."""
    n = y.shape[0]
    traj = np.empty(n)
    for a in range(openings.shape[0]):
        for c in range(closings.shape[0]):
            _closed_volume_response(p_start, V, C, b, inlet, C2, b2, openings[a], closings[c],
                                    p_s, p0, T, nRT, h, n, sub, traj)
            mm = 0.0
            my = 0.0
            for j in range(n):
                m = traj[j] - p_start
                mm += m * m
                my += m * y[j]
            g = my / mm if mm > 0.0 else 0.0
            r = 0.0
            for j in range(n):
                e = y[j] - g * (traj[j] - p_start)
                r += e * e
            cost[a, c] = r if mm > 0.0 else np.inf
            gain[a, c] = g


def step_onsets(logs: Sequence[Dataset], C: np.ndarray, b: np.ndarray, max_delay: float
                ) -> list[Onset | None]:
    """Each valve's delay from a full-opening command to the chamber pressure's response.

    Parameters
    ----------
    logs : sequence of Dataset
        Logs at their own sampling period; those with fewer than
        :data:`~.mass.MIN_SAMPLES_PER_PWM` samples per PWM period (as the mass's lag estimate
        needs), or a latched PWM update, are skipped.
    C, b : ndarray, (4,)
        Sonic conductance [m^3/(s Pa)] and critical pressure ratio of each valve (a_in, a_out,
        b_in, b_out), as fitted at the control rate.
    max_delay : float
        Longest delay searched [s].

    Returns
    -------
    list of Onset or None
        Per valve; None with fewer than :data:`MIN_EDGES` usable edges within
        :data:`OUTLIER` of their median (the others are left out).
    """
    found: list[list[float]] = [[] for _ in range(4)]
    for d in logs:
        rig = d.rig
        h = d.Ts
        if rig.pwm_update != "immediate" or samples_per_pwm(d) < MIN_SAMPLES_PER_PWM:
            continue
        H = round(HORIZON / h)
        grid = np.arange(0.0, max_delay + 0.5 * GRID_STEP, GRID_STEP)
        closings = np.arange(0.0, max_delay + 0.5 * OVERLAP_STEP, OVERLAP_STEP)
        cost = np.empty((grid.size, closings.size))
        gain = np.empty_like(cost)
        Va, Vb = d.volumes()
        nRT = rig.n * rig.R * rig.T0
        for i in range(4):
            ch, port = divmod(i, 2)
            inlet = port == 0
            other = 2 * ch + 1 - port
            u, uo = d.u[:, i], d.u[:, other]
            p = d.p_a if ch == 0 else d.p_b
            V = Va if ch == 0 else Vb
            for k in np.flatnonzero((u[1:] >= 0.999) & (u[:-1] <= 0.0)) + 1:
                lo, hi = k - PRE_SAMPLES, k + H
                if lo < 0 or hi > d.n or np.any(u[k:hi] < 0.999) or np.any(uo[k:hi] > 0.0):
                    continue
                if np.ptp(d.x[lo:hi]) > STILL or np.ptp(p[lo:k]) > SETTLED:
                    continue
                # the pressure at the edge: the line through the samples before it
                tk = np.arange(lo - k, 0, dtype=float)
                _, level = np.polyfit(tk, p[lo:k], 1)
                p_start = float(level)
                y = np.ascontiguousarray(p[k:hi] - p_start)
                if np.max(np.abs(y)) < MIN_SWING:
                    continue
                _edge_costs(y, p_start, float(V[k]), float(C[i]), float(b[i]), inlet,
                            float(C[other]), float(b[other]), grid, closings,
                            float(d.p_s[k]), rig.p0, rig.T0, nRT, h, SUBSTEPS, cost, gain)
                a, c = np.unravel_index(int(np.argmin(cost)), cost.shape)
                if np.isfinite(cost[a, c]) and GAIN_RANGE[0] <= gain[a, c] <= GAIN_RANGE[1]:
                    found[i].append(float(grid[a]))
    out: list[Onset | None] = []
    for f in found:
        a = np.asarray(f)
        if a.size:
            a = a[np.abs(a - np.median(a)) <= OUTLIER]
        if a.size < MIN_EDGES:
            out.append(None)
            continue
        out.append(Onset(float(np.median(a)), float(a.min()), float(a.max()), a.size))
    return out


__all__ = ["MIN_EDGES", "Onset", "step_onsets"]
