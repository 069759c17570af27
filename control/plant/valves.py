"""On/off valves driven by PWM: the carrier, switching delays and the minimum pulse (numba).

Each valve really switches inside every PWM period; nothing is averaged.

Command signal
    A sawtooth carrier of period ``T_pwm = 1/pwm_hz`` starts at t = 0. The command signal of a
    valve is on while the carrier phase (0..1) is below its duty ``u``: an edge-aligned PWM, on
    from each period start for ``u T_pwm``. ``u >= 1`` is always on, ``u <= 0`` always off.
How a new duty acts (``rig.pwm_update``; the paper is silent, DESIGN.md)
    ``immediate``: the comparator uses the new duty at once, so a duty written mid-period can
    end the current pulse early or start one. ``latched``: the new duty is used from the next
    period start (a double-buffered compare register).
Valve response
    A rising command edge at ``t`` opens the valve at ``t + delay_on``; a falling edge closes it
    at ``t + delay_off``. The last edge wins: scheduling a transition cancels every pending one
    that would fire later (so a short off-gap with ``delay_off > delay_on`` leaves the valve
    open: saturation near duty 1). A command pulse shorter than ``min_pulse`` never opens the
    valve (dead zone near duty 0); ``min_pulse <= delay_on`` is required, so the decision is
    causal.

For a constant duty the resulting effective open fraction is :func:`effective_open_fraction`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pneutune.control.plant.params import (
    P_DOFF,
    P_DON,
    P_LATCHED,
    P_MINP,
    P_TPWM,
    PEND_MAX,
    S_CMD,
    S_DUTY,
    S_NPEND,
    S_OPEN,
    S_PEND_T,
    S_PEND_V,
    S_RISE,
    S_SIG,
)

#: Time tolerance for coincident events [s].
EPS_T: float = 1.0e-10


@njit(cache=True)
def _period_index(t: float, period: float) -> float:
    return math.floor(t / period + 1.0e-9)


@njit(cache=True)
def comparator(t: float, duty: float, period: float) -> float:
    """Command signal (0/1) of an edge-aligned PWM with carrier period ``period`` at time t."""
    if duty >= 1.0:
        return 1.0
    if duty <= 0.0:
        return 0.0
    phase = t / period - _period_index(t, period)
    return 1.0 if phase < duty - 1.0e-9 else 0.0


@njit(cache=True)
def _schedule(s: np.ndarray, i: int, t_tr: float, value: float) -> None:
    """Queue valve ``i`` to go to ``value`` at ``t_tr``; later pending transitions are cancelled."""
    base_t = S_PEND_T + i * PEND_MAX
    base_v = S_PEND_V + i * PEND_MAX
    n = int(s[S_NPEND + i])
    while n > 0 and s[base_t + n - 1] > t_tr:
        n -= 1
    if n == PEND_MAX:  # cannot happen with delays <= 4 periods (validated); keep the newest
        for j in range(n - 1):
            s[base_t + j] = s[base_t + j + 1]
            s[base_v + j] = s[base_v + j + 1]
        n -= 1
    s[base_t + n] = t_tr
    s[base_v + n] = value
    s[S_NPEND + i] = n + 1


@njit(cache=True)
def _cancel_pending_opens(s: np.ndarray, i: int) -> None:
    """Drop the pending openings of valve ``i`` (a command pulse shorter than min_pulse)."""
    base_t = S_PEND_T + i * PEND_MAX
    base_v = S_PEND_V + i * PEND_MAX
    n = int(s[S_NPEND + i])
    k = 0
    for j in range(n):
        if s[base_v + j] < 0.5:
            s[base_t + k] = s[base_t + j]
            s[base_v + k] = s[base_v + j]
            k += 1
    s[S_NPEND + i] = k


@njit(cache=True)
def _fire_due(s: np.ndarray, t: float) -> None:
    """Apply every pending transition due at or before ``t``."""
    for i in range(4):
        base_t = S_PEND_T + i * PEND_MAX
        base_v = S_PEND_V + i * PEND_MAX
        n = int(s[S_NPEND + i])
        k = 0
        while k < n and s[base_t + k] <= t + EPS_T:
            s[S_OPEN + i] = s[base_v + k]
            k += 1
        if k > 0:
            for j in range(n - k):
                s[base_t + j] = s[base_t + j + k]
                s[base_v + j] = s[base_v + j + k]
            s[S_NPEND + i] = n - k


@njit(cache=True)
def _update_signals(p: np.ndarray, s: np.ndarray, t: float) -> None:
    """Re-evaluate each comparator at ``t`` and turn its edges into valve transitions."""
    period = p[P_TPWM]
    for i in range(4):
        sig = comparator(t, s[S_DUTY + i], period)
        old = s[S_SIG + i]
        if sig > old:
            s[S_RISE + i] = t
            _schedule(s, i, t + p[P_DON + i], 1.0)
        elif sig < old:
            if t - s[S_RISE + i] < p[P_MINP + i] - EPS_T:
                _cancel_pending_opens(s, i)
            _schedule(s, i, t + p[P_DOFF + i], 0.0)
        s[S_SIG + i] = sig


@njit(cache=True)
def process_events(p: np.ndarray, s: np.ndarray, t: float) -> None:
    """Handle everything that happens at time ``t``: latching, valve transitions, PWM edges."""
    period = p[P_TPWM]
    if p[P_LATCHED] > 0.5:
        k = _period_index(t, period)
        if abs(t - k * period) <= EPS_T:
            for i in range(4):
                s[S_DUTY + i] = s[S_CMD + i]
    _fire_due(s, t)
    _update_signals(p, s, t)
    _fire_due(s, t)  # zero delays act at once


@njit(cache=True)
def set_duties(p: np.ndarray, s: np.ndarray, t: float, duties: np.ndarray) -> None:
    """Write the four commanded duties at time ``t`` (clipped to 0..1; NaN counts as 0)."""
    for i in range(4):
        u = duties[i]
        if not (u > 0.0):
            u = 0.0
        elif u > 1.0:
            u = 1.0
        s[S_CMD + i] = u
        if p[P_LATCHED] < 0.5:
            s[S_DUTY + i] = u
    process_events(p, s, t)


@njit(cache=True)
def next_event(p: np.ndarray, s: np.ndarray, t: float, t_end: float) -> float:
    """Time of the next switching event after ``t``, or ``t_end`` if none comes before it."""
    period = p[P_TPWM]
    k = _period_index(t, period)
    t_next = t_end
    t_ps = (k + 1.0) * period
    if t_ps < t_next:
        t_next = t_ps
    for i in range(4):
        u = s[S_DUTY + i]
        if 0.0 < u < 1.0:
            t_cross = (k + u) * period
            if t + EPS_T < t_cross < t_next:
                t_next = t_cross
        n = int(s[S_NPEND + i])
        if n > 0:
            t_p = s[S_PEND_T + i * PEND_MAX]
            if t_p < t_next:
                t_next = t_p
    return t_next


@njit(cache=True)
def open_fractions(p: np.ndarray, s: np.ndarray, duties: np.ndarray, t0: float, Ts: float,
                   out: np.ndarray) -> None:
    """Fraction of each sample interval that each valve is open, for duties written per sample.

    The valves alone, switched exactly as in the plant (:func:`set_duties`, :func:`next_event`,
    :func:`process_events`): the duties ``duties[k]`` are written at ``t0 + k Ts`` and hold until
    the next sample. This is the valve part of :func:`pneutune.control.plant.dynamics.advance`
    without
    the chamber and motion dynamics, for identification from a log whose duties are known.

    Parameters
    ----------
    p : ndarray
        Packed plant parameters (only the PWM and valve timing slots are read).
    s : ndarray
        A plant state (its valve slots are used and updated; start from
        :func:`pneutune.control.plant.dynamics.initial_state`).
    duties : ndarray, (N, 4)
        Commanded duties per sample.
    t0 : float
        Time of the first sample on the PWM carrier's clock (the carrier starts at 0) [s].
    Ts : float
        Sampling period [s].
    out : ndarray, (N, 4)
        Open fraction of ``[t0 + k Ts, t0 + (k + 1) Ts)`` per valve, 0..1.
    """
    n = duties.shape[0]
    for k in range(n):
        t = t0 + k * Ts
        t_end = t0 + (k + 1) * Ts
        for i in range(4):
            out[k, i] = 0.0
        set_duties(p, s, t, duties[k])
        while t < t_end - EPS_T:
            t_next = next_event(p, s, t, t_end)
            for i in range(4):
                out[k, i] += s[S_OPEN + i] * (t_next - t)
            t = t_next
            process_events(p, s, t)
        for i in range(4):
            out[k, i] /= Ts


@njit(cache=True)
def valve_open_fractions(p: np.ndarray, duties: np.ndarray, timings: np.ndarray,
                         phases: np.ndarray, Ts: float, out: np.ndarray) -> None:
    """Open fraction per sample of one valve alone, for several candidate timings in one call.

    Candidate ``m`` is the valve with ``timings[m] = (delay_on, delay_off, min_pulse)`` driven by
    ``duties`` written at ``phases[m] + k Ts``, switched exactly as :func:`open_fractions`
    switches a valve (the same comparator, edges, pending transitions, minimum-pulse rule and
    event tolerances), starting closed. It gives what :func:`open_fractions` gives for this
    valve when the other three are never commanded open, bit for bit. With the others switching,
    :func:`open_fractions` sums each sample's open time over the finer grid of all four valves'
    events, which rounds differently (a few 1e-12 of the fraction on a 144 s log); the switching
    itself is the same, since the valves do not interact. For searches that vary one valve at a
    time.

    Parameters
    ----------
    p : ndarray
        Packed plant parameters (only the PWM period and update mode are read).
    duties : ndarray, (N,)
        Commanded duty of the valve per sample.
    timings : ndarray, (M, 3)
        Per candidate: opening delay, closing delay and minimum pulse [s] (``min_pulse <=
        delay_on``, as the plant requires).
    phases : ndarray, (M,)
        Per candidate: time of the first sample on the PWM carrier's clock [s].
    Ts : float
        Sampling period [s].
    out : ndarray, (M, N)
        Open fraction of ``[phases[m] + k Ts, phases[m] + (k + 1) Ts)``, 0..1.
    """
    period = p[P_TPWM]
    latched = p[P_LATCHED] > 0.5
    n = duties.shape[0]
    pend_t = np.empty(PEND_MAX)
    pend_v = np.empty(PEND_MAX)
    for m in range(timings.shape[0]):
        don = timings[m, 0]
        doff = timings[m, 1]
        minp = timings[m, 2]
        t0 = phases[m]
        # the valve's slots of a fresh plant state: closed, command low, nothing pending
        sig = 0.0
        is_open = 0.0
        rise = 0.0
        duty = 0.0
        cmd = 0.0
        npend = 0
        for k in range(n):
            t = t0 + k * Ts
            t_end = t0 + (k + 1) * Ts
            acc = 0.0
            # set_duties
            u = duties[k]
            if not (u > 0.0):
                u = 0.0
            elif u > 1.0:
                u = 1.0
            cmd = u
            if not latched:
                duty = u
            first = True
            while True:
                if not first:
                    if not (t < t_end - EPS_T):
                        break
                    # next_event
                    kp = _period_index(t, period)
                    t_next = t_end
                    t_ps = (kp + 1.0) * period
                    if t_ps < t_next:
                        t_next = t_ps
                    if 0.0 < duty < 1.0:
                        t_cross = (kp + duty) * period
                        if t + EPS_T < t_cross < t_next:
                            t_next = t_cross
                    if npend > 0:
                        t_p = pend_t[0]
                        if t_p < t_next:
                            t_next = t_p
                    acc += is_open * (t_next - t)
                    t = t_next
                first = False
                # process_events: latching, due transitions, comparator edges, due again
                if latched:
                    kp = _period_index(t, period)
                    if abs(t - kp * period) <= EPS_T:
                        duty = cmd
                for stage in range(2):
                    j = 0
                    while j < npend and pend_t[j] <= t + EPS_T:
                        is_open = pend_v[j]
                        j += 1
                    if j > 0:
                        for q in range(npend - j):
                            pend_t[q] = pend_t[q + j]
                            pend_v[q] = pend_v[q + j]
                        npend -= j
                    if stage == 1:
                        break
                    new_sig = comparator(t, duty, period)
                    t_tr = -1.0
                    value = 0.0
                    if new_sig > sig:
                        rise = t
                        t_tr = t + don
                        value = 1.0
                    elif new_sig < sig:
                        if t - rise < minp - EPS_T:  # too short a pulse: drop pending openings
                            q = 0
                            for r in range(npend):
                                if pend_v[r] < 0.5:
                                    pend_t[q] = pend_t[r]
                                    pend_v[q] = pend_v[r]
                                    q += 1
                            npend = q
                        t_tr = t + doff
                        value = 0.0
                    if new_sig != sig:  # schedule; later pending transitions are cancelled
                        while npend > 0 and pend_t[npend - 1] > t_tr:
                            npend -= 1
                        if npend == PEND_MAX:
                            for q in range(npend - 1):
                                pend_t[q] = pend_t[q + 1]
                                pend_v[q] = pend_v[q + 1]
                            npend -= 1
                        pend_t[npend] = t_tr
                        pend_v[npend] = value
                        npend += 1
                    sig = new_sig
            out[m, k] = acc / Ts
