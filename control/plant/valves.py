"""On/off valves driven by PWM: the carrier, switching delays and the minimum pulse (numba).

Each valve really switches inside every PWM period; nothing is averaged.

Command signal
    A sawtooth carrier of period ``T_pwm = 1/pwm_hz`` starts at t = 0. The command signal of a
    valve is on while the carrier phase (0..1) is below its duty ``u``: an edge-aligned PWM, on
    from each period start for ``u T_pwm``. ``u >= 1`` is always on, ``u <= 0`` always off.
How a new duty acts (``rig.pwm_update``; the paper is silent)
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

from pneutune.control.numba_cache import njit
from pneutune.control.plant.params import (
    N_STATE,
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


@njit(cache=True, inline="always")
def _period_index(t: float, period: float) -> float:
    return math.floor(t / period + 1.0e-9)


@njit(cache=True, inline="always")
def comparator(t: float, duty: float, period: float) -> float:
    """Command signal (0/1) of an edge-aligned PWM with carrier period ``period`` at time t."""
    if duty >= 1.0:
        return 1.0
    if duty <= 0.0:
        return 0.0
    phase = t / period - _period_index(t, period)
    return 1.0 if phase < duty - 1.0e-9 else 0.0


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def _fire_due(s: np.ndarray, i: int, t: float) -> None:
    """Apply every pending transition of valve ``i`` due at or before ``t``."""
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


@njit(cache=True, inline="always")
def _update_signal(p: np.ndarray, s: np.ndarray, i: int, t: float) -> None:
    """Re-evaluate valve ``i``'s comparator at ``t`` and turn its edge into a transition."""
    sig = comparator(t, s[S_DUTY + i], p[P_TPWM])
    old = s[S_SIG + i]
    if sig > old:
        s[S_RISE + i] = t
        _schedule(s, i, t + p[P_DON + i], 1.0)
    elif sig < old:
        if t - s[S_RISE + i] < p[P_MINP + i] - EPS_T:
            _cancel_pending_opens(s, i)
        _schedule(s, i, t + p[P_DOFF + i], 0.0)
    s[S_SIG + i] = sig


@njit(cache=True, inline="always")
def _at_period_start(p: np.ndarray, t: float) -> bool:
    """Whether ``t`` is a PWM period start, where a latched duty takes effect."""
    period = p[P_TPWM]
    k = _period_index(t, period)
    return abs(t - k * period) <= EPS_T


@njit(cache=True, inline="always")
def valve_events(p: np.ndarray, s: np.ndarray, i: int, t: float, period_start: bool) -> None:
    """Everything that happens to valve ``i`` at time ``t``: the switching of one valve.

    In latched mode the commanded duty takes effect at a period start; the transitions due
    fire; the comparator's edge at ``t`` (if any) schedules the next transition (cancelling
    the pending openings of a command pulse shorter than the minimum pulse, and every pending
    transition later than the new one); zero delays fire at once. The plant
    (:func:`process_events`), :func:`open_fractions` and :func:`valve_open_fractions` switch
    every valve with this function; the valves do not interact.

    Parameters
    ----------
    p : ndarray
        Packed plant parameters (the PWM period, update mode and valve ``i``'s timing).
    s : ndarray
        Plant state; valve ``i``'s slots are updated.
    i : int
        Valve index, 0..3.
    t : float
        Time [s].
    period_start : bool
        Whether ``t`` is a PWM period start (:func:`_at_period_start`; computed once for the
        four valves, and only in latched mode, the only one that reads it).
    """
    if period_start and p[P_LATCHED] > 0.5:
        s[S_DUTY + i] = s[S_CMD + i]
    _fire_due(s, i, t)
    _update_signal(p, s, i, t)
    _fire_due(s, i, t)  # zero delays act at once


@njit(cache=True)
def process_events(p: np.ndarray, s: np.ndarray, t: float) -> None:
    """Handle everything that happens at time ``t``: latching, valve transitions, PWM edges."""
    period_start = p[P_LATCHED] > 0.5 and _at_period_start(p, t)
    for i in range(4):
        valve_events(p, s, i, t, period_start)


@njit(cache=True, inline="always")
def write_duty(p: np.ndarray, s: np.ndarray, i: int, u: float) -> None:
    """Command duty ``u`` to valve ``i`` (clipped to 0..1; NaN counts as 0); in immediate mode
    the comparator uses it at once, in latched mode from the next period start."""
    if not (u > 0.0):
        u = 0.0
    elif u > 1.0:
        u = 1.0
    s[S_CMD + i] = u
    if p[P_LATCHED] < 0.5:
        s[S_DUTY + i] = u


@njit(cache=True)
def set_duties(p: np.ndarray, s: np.ndarray, t: float, duties: np.ndarray) -> None:
    """Write the four commanded duties at time ``t`` (clipped to 0..1; NaN counts as 0)."""
    for i in range(4):
        write_duty(p, s, i, duties[i])
    process_events(p, s, t)


@njit(cache=True, inline="always")
def valve_next_event(p: np.ndarray, s: np.ndarray, i: int, t: float, k: float,
                     t_next: float) -> float:
    """The earlier of ``t_next`` and valve ``i``'s next comparator edge or pending transition
    after ``t`` (``k``: the index of the PWM period holding ``t``)."""
    u = s[S_DUTY + i]
    if 0.0 < u < 1.0:
        t_cross = (k + u) * p[P_TPWM]
        if t + EPS_T < t_cross < t_next:
            t_next = t_cross
    n = int(s[S_NPEND + i])
    if n > 0:
        t_p = s[S_PEND_T + i * PEND_MAX]
        if t_p < t_next:
            t_next = t_p
    return t_next


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
        t_next = valve_next_event(p, s, i, t, k, t_next)
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


@njit(cache=True, inline="always")
def _rest_level(s: np.ndarray, u: float) -> float:
    """0.0 or 1.0 when duty ``u`` leaves valve 0 of state ``s`` at rest for a whole sample, else
    -1.0.

    At rest: the valve shut (open) with its command, latched duty and comparator signal at 0
    (1), nothing pending, and ``u`` clipped to the same 0 (1). Then :func:`write_duty` and
    every :func:`valve_events` of the sample leave the state as it is (the comparator gives 0
    (1) at every time, so no edge, no transition, no latching of another duty).
    """
    if s[S_NPEND] != 0.0:
        return -1.0
    level = s[S_OPEN]
    if not (u > 0.0):
        u = 0.0
    elif u > 1.0:
        u = 1.0
    if u == level and s[S_SIG] == level and s[S_DUTY] == level and s[S_CMD] == level:
        return level
    return -1.0


@njit(cache=True)
def valve_open_fractions(p: np.ndarray, duties: np.ndarray, timings: np.ndarray,
                         phases: np.ndarray, Ts: float, out: np.ndarray,
                         write_delay: float = 0.0) -> None:
    """Open fraction per sample of one valve alone, for several candidate timings in one call.

    Candidate ``m`` is the valve with ``timings[m] = (delay_on, delay_off, min_pulse)`` driven by
    ``duties`` written at ``phases[m] + k Ts``, starting closed, switched by the plant's own
    functions (:func:`write_duty`, :func:`valve_events`, :func:`valve_next_event`) in slot 0
    of a scratch parameter vector and state. It gives what :func:`open_fractions` gives for
    this valve when the other three are never commanded open, bit for bit (both sum the open
    time over the same events: the period starts and this valve's). With the others switching,
    :func:`open_fractions` sums each sample's open time over the finer grid of all four valves'
    events, which rounds differently (a few 1e-12 of the fraction on a 144 s log); the switching
    itself is the same, since the valves do not interact. For searches that vary one valve at a
    time. A sample that leaves the valve at rest (shut with duty 0, or open with duty 1, nothing
    pending: :func:`_rest_level`) has no event that changes anything; its open time is summed
    without them, over the same intervals (the same floats).

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
    write_delay : float
        Every duty acts this long after its sample [s], as the plant's ``io.delay`` makes it
        (:func:`pneutune.control.plant.dynamics.set_duties`): until then the valve runs on the
        duty before. The open fraction is still summed over the sample (for the search of a
        loop delay; 0 by default).
    """
    period = p[P_TPWM]
    n = duties.shape[0]
    shift = math.floor(write_delay / Ts + 1.0e-9)
    within = write_delay - shift * Ts
    # the valve in slot 0 of a scratch plant: its parameters with the candidate's timing, and
    # the valve slots of a fresh plant state (closed, command low, nothing pending)
    latched = p[P_LATCHED] > 0.5
    q = p.copy()
    s = np.empty(N_STATE)
    for m in range(timings.shape[0]):
        q[P_DON] = timings[m, 0]
        q[P_DOFF] = timings[m, 1]
        q[P_MINP] = timings[m, 2]
        s[:] = 0.0
        t0 = phases[m]
        for k in range(n):
            t = t0 + k * Ts
            t_end = t0 + (k + 1) * Ts
            if write_delay > 0.0:  # the earlier duty until the write, then this sample's
                t_w = t + within
                acc = _open_time(q, s, t, t_w, period, latched)
                if k - shift >= 0:
                    write_duty(q, s, 0, duties[k - shift])
                    valve_events(q, s, 0, t_w, latched and _at_period_start(q, t_w))
                out[m, k] = (acc + _open_time(q, s, t_w, t_end, period, latched)) / Ts
                continue
            acc = 0.0
            level = _rest_level(s, duties[k])
            if level == 0.0:  # shut and kept shut: no event changes anything
                out[m, k] = 0.0
                continue
            if level == 1.0:  # open and kept open: the same open time, without the events
                while t < t_end - EPS_T:
                    kp = _period_index(t, period)
                    t_next = t_end
                    t_ps = (kp + 1.0) * period
                    if t_ps < t_next:
                        t_next = t_ps
                    acc += t_next - t
                    t = t_next
                out[m, k] = acc / Ts
                continue
            write_duty(q, s, 0, duties[k])
            valve_events(q, s, 0, t, latched and _at_period_start(q, t))
            out[m, k] = _open_time(q, s, t, t_end, period, latched) / Ts


@njit(cache=True, inline="always")
def _open_time(q: np.ndarray, s: np.ndarray, t: float, t_end: float, period: float,
               latched: bool) -> float:
    """Open time of valve 0 of ``s`` from ``t`` to ``t_end``, switching it on the way."""
    acc = 0.0
    while t < t_end - EPS_T:
        kp = _period_index(t, period)
        t_next = t_end
        t_ps = (kp + 1.0) * period
        if t_ps < t_next:
            t_next = t_ps
        t_next = valve_next_event(q, s, 0, t, kp, t_next)
        acc += s[S_OPEN] * (t_next - t)
        t = t_next
        valve_events(q, s, 0, t, latched and _at_period_start(q, t))
    return acc
