"""Bounds on the break-away force F_S from the stick and break-away events of a run log.

F_S is weakly identified by the sliding-friction fit (:mod:`~pneutune.identify.motion`): the
Stribeck peak lasts less than a control sample. Stiction itself bounds it from both sides
(Eq. 2, the F_e branch; the simulator's rule in :mod:`pneutune.control.plant.dynamics`): a piston at
rest away from the end stops carries a net applied force ``|F| <= F_S``, and it breaks away,
in the direction of the force, when ``|F|`` reaches F_S. Here ``F = A_a p_a - A_b p_b - p0 A_r
+ F_n`` from the measured pressures and the constant force F_n (known to ``+-F_n_half``). Only
``/rig/sensors`` and ``/rig/valves`` are used (contract 1), at the rate the log was
sampled (0.5 ms identification run, 4 ms closed loop); no labels, no simulator truth.

Rest intervals
    Maximal runs of samples whose positions stay within ``+-B`` of their running mean,
    ``B = Z_X sigma_x`` (4.5 position-noise standard deviations, estimated from the log by
    :func:`position_noise_std`). A run ends at the first sample outside the band: a 4.5 sigma
    outlier is rarer than a micro-slip. Runs centred within :data:`STOP_MARGIN` of an end stop
    are not used at all, since there the stop, not friction, may hold the piston; the stop is
    the stroke end of the rig metadata, or the outermost rest position within
    :data:`STOP_SNAP` of it (a stop a little off its nominal position).

Lower bound (rest intervals): ``F_S >= |F| - creep - margin``
    "At rest" is only "within the noise", so each sample allows for creep: by Eqs. (1)-(2) a
    sliding piston has ``|F| <= F_S + b_v |v| + M |a|``. At each sample k of a run whose window
    ``[k - g, k + g]`` fits inside it (:data:`T_WIN_MIN` <= g h <= :data:`T_GUARD`), a local
    least-squares quadratic gives v and a with their standard errors, and a line over the
    shortest window gives v again (a wide fit smooths over the corner of a slide-through
    reversal or a micro-slip of a hunting closed loop, which 4 ms samples and 10 um noise
    hide); the creep margin is ``b_v_max (|v| + 3 s.e.) + m_max (|a| + 3 s.e.)`` with the
    larger v term. The window guards come with the fit: where the piston arrives or leaves,
    speed and acceleration show. The force a sample counts with is the one it *held*: the
    smallest ``|F|`` of one sign over :data:`HOLD` samples either side (F averaged over
    :data:`T_AVG` at fast sampling: the mean of forces each at most F_S is at most F_S), less
    the largest creep margin among them, so that one 4 ms sample caught mid-slip (a hunting
    closed loop's micro-slips hide in 10 um noise) does not set the bound. The
    noise margin: a held value exceeds F_S + z sigma_F/sqrt(w) only if each of its ``n_ind``
    independent force values does, so z is set for a chance ALPHA = 1e-3 over all samples
    tried (Bonferroni) with ``Phi(-z)^n_ind`` per sample and sign (white pressure noise), plus
    ``F_n_half``.

Upper bound (break-aways): ``F_S <= s F + gas-spring drop + margin``
    A run that ends with the piston beyond the band on one side ``s`` for two samples in a row
    (the first, ``m``, is certainly after the break-away) counts if

    * the piston had stopped: the run lasts at least :data:`T_STOP` and its drift speed (LS
      slope + 3 s.e.) is at most :data:`V_STOP`. A reversal through v = 0 without a visible
      stop is not used (the simulator's creep, below);
    * no valve that lowers ``s F`` can act near the break-away: the bracket starts after the
      last such command plus a PWM period and :data:`T_VALVE` (a closing delay; a latched duty
      acts for a whole period). Between two samples ``s F`` then only rises through the valves
      and falls through the motion, by at most the gas-spring stiffness
      ``k_gas = n (p_a A_a^2 / V_a + p_b A_b^2 / V_b)`` times the displacement, so with the
      break-away somewhere in the bracket ``F_S <= max_k (s F_k + k_gas max(0, s dx_k))``;
    * the stick was strong: ``s F`` (averaged over T_AVG) reached, in the bracket, what the best
      rest interval held less its noise margin, and at least ``lo + margin_lo``; and the
      event's bound is not below ``lo``. Under Eq. (2) a break-away from a slowly rising force
      qualifies; a "rest" that was no stick (the simulator's creep below, a vibration, a
      sensor glitch) rarely does, nor does a force that jumps through F_S inside one sample
      (a loose bound anyway), and a piston moving against the force never does.

    The upper bound is the smallest event bound, each plus ``z sigma_e`` (z for a chance
    ALPHA over the events; ``sigma_e`` the force noise and the gas-spring term's position
    noise) and ``F_n_half``. With no qualifying break-away (or no lower bound) it is absent and
    the caller uses a prior.

Noise
    sigma_F: given (``p_noise``), or the robust (MAD) scatter of third differences of the
    chamber pressures where all valves have been shut for a PWM period, or, when the log has
    no such samples (a closed loop keeps some valve pulsing), of the supply pressure (assumed
    a sensor like the chambers'). sigma_x likewise from the position, refined on the samples
    that look still (a closed loop's PWM ripple makes differences alone read 15 um for 5 um).

Validation (simulated logs, truth from plant.yaml): identification run at 0.5 and 4 ms,
commissioning run at 4 and 0.5 ms, closed-loop sine-0.5hz, sine-0.75hz and square-0.5hz; eight
named plants spanning F_C 30-120 N, F_S/F_C 1.1-1.8, v_s 2-8 mm/s, alpha 1-3, b_v 1500-5000 N
s/m, valve C +-30 %, delays 1-4 ms, min pulse 1-3 ms, payload 0-1.5 kg, x noise 2-10 um,
p noise 100-600 Pa, both pwm_update modes, three noise seeds, and 72 random plants from the
same ranges (F_n from the friction fit on 60 logs): every interval contained F_S, 808 runs on
about 640 logs (simulated before the plant's stop fix, see below). With the fixed plant, seed 1
of the paper's rig (F_S = 75 N): identification run [62, 131] N at 0.5 ms, [55, 144] N at 4 ms;
commissioning run [54, 126] N (tests/test_stiction.py). Closed-loop logs give lower bounds and
upper bounds that are loose or absent: few of their break-aways start from a slowly rising force
with the valves pushing one way.

The stop and held-force conditions were first needed for a simulator fault, since fixed
(control/plant/dynamics.py, 2026-11-24): an RK4 stage that strayed past v = 0 flipped the
friction, the stop was missed and the piston crept, and could leave a "rest" at a force below
F_S. They stay: a real rig's sensor can show a creep as a rest too. With the stops found
exactly the piston breaks away from true rests while the force keeps rising through the two
samples that detect the motion, so the upper bounds are looser than before (1.4-2 F_S against
1.3-1.6 F_S); estimating the break-away instant from the motion that follows would tighten
them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d, uniform_filter1d
from scipy.stats import norm

from pneutune.control.numba_cache import njit

from .dataset import Dataset

#: Half-width of the rest band in position-noise standard deviations.
Z_X = 4.5
#: Smallest position noise assumed [m] (a noise-free log is quantised or exact).
X_NOISE_FLOOR = 0.5e-6
#: Samples in a row beyond the band, on one side, that confirm a departure from rest.
K_CONFIRM = 2
#: Largest and smallest half-window of the local fit of the lower bound [s].
T_GUARD, T_WIN_MIN = 0.05, 8.0e-3
#: Averaging time of the force [s] (noise / sqrt(T_AVG / h) at fast sampling).
T_AVG = 4.0e-3
#: Samples either side over which a rest sample must hold its force: at 4 ms one sample may
#: catch a micro-slip that the positions cannot show.
HOLD = 1
#: Default upper limits of the viscous coefficient [N s/m] and of the moving mass [kg] for the
#: creep margin (the pipeline's priors: twice the plant spread of b_v, MASS_PRIOR's top).
B_V_MAX, M_MAX = 1.0e4, 10.0
#: A break-away needs a rest of at least T_STOP [s] drifting at most V_STOP [m/s].
T_STOP, V_STOP = 0.02, 5.0e-4
#: Standard errors on the fitted speed, acceleration and drift.
Z_DRIFT = 3.0
#: Longest valve closing delay allowed for [s] (the plants of the brief: 1-4 ms).
T_VALVE = 5.0e-3
#: Rest intervals centred within STOP_MARGIN of an end stop are not used [m]; a rest position
#: within STOP_SNAP of a stroke end is taken as that stop [m].
STOP_MARGIN, STOP_SNAP = 5.0e-4, 2.0e-3
#: Chance that a bound fails through sensor noise (Bonferroni over the candidates).
ALPHA = 1.0e-3
#: Fewest samples for a noise estimate from shut valves or from still positions.
MIN_QUIET, MIN_STILL = 200, 100


@dataclass(frozen=True)
class StictionEvent:
    """A rest interval or a break-away, and the bound on F_S it gives.

    Attributes
    ----------
    kind : str
        ``"rest"`` or ``"breakaway"``.
    t : float
        Time of the sample that sets the value [s].
    F : float
        Measured net applied force there, F_n included [N], signed: for a rest the force it
        held (the smallest of one sign over :data:`HOLD` samples either side, averaged over
        :data:`T_AVG`), for a break-away the force at the sample that sets the bound.
    value : float
        Bound on F_S before the noise and F_n margins [N]: ``|F|`` less the creep margin for
        a rest; ``s F`` plus the gas-spring allowance for a break-away in direction ``s``.
    t_start, t_end : float
        First and last sample of the rest interval [s].
    direction : int
        Sign of the force (rest) or of the motion (break-away).
    margin : float
        What the bound adds (break-away) or subtracts (rest) for noise and F_n [N].
    """

    kind: str
    t: float
    F: float
    value: float
    t_start: float
    t_end: float
    direction: int
    margin: float = 0.0

    @property
    def bound(self) -> float:
        """The bound this event alone gives [N]."""
        return self.value + self.margin if self.kind == "breakaway" else self.value - self.margin


@dataclass(frozen=True)
class StictionBounds:
    """Bounds on F_S and what they rest on.

    Attributes
    ----------
    lo, hi : float or None
        F_S >= lo and F_S <= hi [N]; None when the log has no usable rest interval (lo) or
        break-away (hi).
    n_rest, n_breakaway : int
        Rest intervals and break-aways that gave a bound.
    lo_event, hi_event : StictionEvent or None
        The events that set lo and hi.
    margin_lo, margin_hi : float
        Noise and F_n margins of lo and hi [N].
    sigma_F, sigma_x : float
        Force [N] and position [m] noise used.
    basis : str
        One line: where the bounds come from.
    rest_events, breakaway_events : tuple of StictionEvent
        Every event that gave a bound (for plots).
    rejected : dict
        Break-aways left out, by reason.
    """

    lo: float | None
    hi: float | None
    n_rest: int
    n_breakaway: int
    lo_event: StictionEvent | None
    hi_event: StictionEvent | None
    margin_lo: float
    margin_hi: float
    sigma_F: float
    sigma_x: float
    basis: str
    rest_events: tuple[StictionEvent, ...] = ()
    breakaway_events: tuple[StictionEvent, ...] = ()
    rejected: dict[str, int] | None = None


def _mad_std(d: np.ndarray) -> float:
    """Robust standard deviation: 1.4826 x median absolute deviation."""
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def position_noise_std(x: np.ndarray) -> float:
    """Position sensor noise, standard deviation [m].

    The robust scatter of third differences (white noise: variance 20 sigma^2), then, up to
    three times, of second differences (6 sigma^2) on the samples whose five-sample range
    lies within the rest band of the current estimate: a closed loop's position has PWM
    ripple that differences alone take for noise (15 um estimated for 5 um).

    Parameters
    ----------
    x : ndarray
        Positions [m].

    Returns
    -------
    float
        At least :data:`X_NOISE_FLOOR`.
    """
    if x.size < 8:
        return X_NOISE_FLOOR
    s = max(_mad_std(np.diff(x, 3)) / np.sqrt(20.0), X_NOISE_FLOOR)
    for _ in range(3):
        spread = maximum_filter1d(x, 5) - minimum_filter1d(x, 5)
        still = spread[1:-1] <= 2.0 * Z_X * s
        d2 = np.diff(x, 2)[still]
        if d2.size < MIN_STILL:
            break
        s_new = max(_mad_std(d2) / np.sqrt(6.0), X_NOISE_FLOOR)
        if s_new >= s:
            break
        s = s_new
    return s


def force_noise_std(data: Dataset) -> tuple[float, str]:
    """Noise of the pressure force A_a p_a - A_b p_b, standard deviation [N], and its source.

    From the third differences of the chamber pressures at samples whose valves have all been
    shut for a PWM period plus :data:`T_VALVE` (at least :data:`MIN_QUIET` of them), else of
    the supply pressure (both chambers' sensors assumed alike).

    Parameters
    ----------
    data : Dataset
        The log.

    Returns
    -------
    (float, str)
        sigma_F [N] and where it comes from.
    """
    rig = data.rig
    back = max(1, int(np.ceil((1.0 / rig.pwm_hz + T_VALVE) / data.Ts)))
    active = np.concatenate([[0], np.cumsum(np.any(data.u != 0.0, axis=1))])
    k = np.arange(max(data.n - 3, 0))
    quiet = (active[k + 3] - active[np.clip(k - back, 0, None)]) == 0
    if np.count_nonzero(quiet) >= MIN_QUIET:
        sa = _mad_std(np.diff(data.p_a, 3)[quiet]) / np.sqrt(20.0)
        sb = _mad_std(np.diff(data.p_b, 3)[quiet]) / np.sqrt(20.0)
        return float(np.hypot(rig.A_a * sa, rig.A_b * sb)), "chamber sensors, valves shut"
    ss = _mad_std(np.diff(data.p_s, 3)) / np.sqrt(20.0)
    return float(ss * np.hypot(rig.A_a, rig.A_b)), "supply sensor, taken as alike"


@dataclass(frozen=True)
class _Run:
    """Samples i..j within the band around their mean c; k is the first sample after."""

    i: int
    j: int
    c: float
    k: int


def _rest_runs(x: np.ndarray, B: float, ok: np.ndarray) -> list[_Run]:
    """Maximal runs of samples within +-B of their running mean (see the module docstring)."""
    first, last, centre, after = _rest_run_arrays(np.ascontiguousarray(x, dtype=np.float64),
                                                  float(B), np.ascontiguousarray(ok, dtype=bool))
    return [_Run(i, j, c, k) for i, j, c, k in zip(first.tolist(), last.tolist(),
                                                   centre.tolist(), after.tolist(), strict=True)]


@njit(cache=True)
def _rest_run_arrays(x: np.ndarray, B: float, ok: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_rest_runs` as arrays: each run's i, j, c and k (:class:`_Run`)."""
    n = x.shape[0]
    first = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    centre = np.empty(n)
    after = np.empty(n, dtype=np.int64)
    m = 0
    i = 0
    while i < n:
        if not ok[i]:
            i += 1
            continue
        total = x[i]
        count = 1
        k = i + 1
        while k < n and ok[k] and abs(x[k] - total / count) <= B:
            total += x[k]
            count += 1
            k += 1
        j = k - 1
        c = total / count
        while i < j and abs(x[i] - c) > B:  # the tail of the arrival
            i += 1
        first[m], last[m], centre[m], after[m] = i, j, c, k
        m += 1
        i = k
    return first[:m], last[:m], centre[:m], after[:m]


def _drift_speed(t: np.ndarray, x: np.ndarray, sigma: float) -> float:
    """Upper bound on the mean speed over a run: |LS slope| + Z_DRIFT s.e. [m/s]."""
    if len(t) < 3:
        return np.inf
    tc = t - t.mean()
    sxx = float(np.dot(tc, tc))
    return abs(float(np.dot(tc, x - x.mean())) / sxx) + Z_DRIFT * sigma / np.sqrt(sxx)


def _running_sums(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cumulative sums of x, i x and i^2 x (i = 0, 1, ...), each with a leading 0.

    Taken over one rest interval with x about its mean, so that the differences the local
    fits take stay well inside double precision.
    """
    i = np.arange(x.size, dtype=float)
    return tuple(np.concatenate([[0.0], np.cumsum(i**p * x)]) for p in range(3))


def _local_fit(ks: np.ndarray, g: np.ndarray, h: float, sigma: float,
               cum: tuple[np.ndarray, np.ndarray, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Speed and acceleration of a least-squares quadratic over [k - g, k + g], with s.e.

    Parameters
    ----------
    ks, g : ndarray
        Window centres and half-widths [samples], indices into the sums.
    h : float
        Sampling period [s].
    sigma : float
        Position noise [m].
    cum : tuple of ndarray
        :func:`_running_sums` of the positions.

    Returns
    -------
    (v, a, se_v, se_a) : ndarrays [m/s, m/s^2]
    """
    c0, c1, c2 = cum
    lo, hi = (ks - g).astype(int), (ks + g).astype(int) + 1
    s0 = c0[hi] - c0[lo]
    s1 = c1[hi] - c1[lo]
    s2 = c2[hi] - c2[lo]
    u1 = s1 - ks * s0  # sum (i - k) x_i
    u2 = s2 - 2.0 * ks * s1 + ks * ks * s0  # sum (i - k)^2 x_i
    n = 2.0 * g + 1.0
    d2 = g * (g + 1.0) * (2.0 * g + 1.0) / 3.0  # sum (i - k)^2
    d4 = d2 * (3.0 * g * g + 3.0 * g - 1.0) / 5.0  # sum (i - k)^4
    q = d4 - d2 * d2 / n
    v = u1 / (h * d2)
    a = 2.0 * (u2 - d2 / n * s0) / (q * h * h)
    return v, a, sigma / (h * np.sqrt(d2)), 2.0 * sigma / (h * h * np.sqrt(q))


def stiction_bounds(data: Dataset, F_n: float, F_n_half: float,
                    mask: np.ndarray | None = None, p_noise: float | None = None,
                    x_noise: float | None = None, b_v_max: float = B_V_MAX,
                    m_max: float = M_MAX) -> StictionBounds:
    """Bounds on the break-away force F_S from the rest intervals and break-aways of a log.

    Parameters
    ----------
    data : Dataset
        The log at its own sampling period (``Dataset.Ts``: 0.5 ms for an identification run,
        the control period for a closed-loop log; both work).
    F_n : float
        Constant force on the piston [N] (θ2, e.g. from the friction fit).
    F_n_half : float
        Half-width of its uncertainty [N].
    mask : ndarray of bool, optional
        Samples that may be used (e.g. the fit part of :meth:`Dataset.split`).
    p_noise : float, optional
        Pressure sensor noise, standard deviation [Pa]; estimated from the log if not given.
    x_noise : float, optional
        Position sensor noise, standard deviation [m]; estimated if not given.
    b_v_max : float
        Largest viscous coefficient to allow for in the creep margin [N s/m].
    m_max : float
        Largest moving mass to allow for in the creep margin [kg].

    Returns
    -------
    StictionBounds
    """
    n = data.n
    ok = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if ok.shape != (n,):
        raise ValueError(f"mask must have one entry per sample, got shape {ok.shape} for "
                         f"{n} samples")
    rig, h, x, t = data.rig, data.Ts, data.x, data.t
    F = data.F_p + F_n
    sx = position_noise_std(x) if x_noise is None else max(float(x_noise), X_NOISE_FLOOR)
    if p_noise is None:
        sF, noise_src = force_noise_std(data)
    else:
        sF, noise_src = float(p_noise) * float(np.hypot(rig.A_a, rig.A_b)), "given"
    B = Z_X * sx
    runs = _rest_runs(x, B, ok)

    # end stops: the metadata's, or the outermost rest position near it
    lo_stop, hi_stop = rig.x_min, rig.x_max
    centres = np.array([r.c for r in runs if r.j - r.i >= 2])
    near = centres[np.abs(centres - rig.x_min) <= STOP_SNAP]
    if near.size:
        lo_stop = max(lo_stop, float(near.min()))
    near = centres[np.abs(centres - rig.x_max) <= STOP_SNAP]
    if near.size:
        hi_stop = min(hi_stop, float(near.max()))
    lo_zone, hi_zone = lo_stop + STOP_MARGIN, hi_stop - STOP_MARGIN
    free = (x > lo_zone) & (x < hi_zone)

    g_max = max(1, int(np.ceil(T_GUARD / h)))
    g_min = max(2, int(np.ceil(T_WIN_MIN / h)))
    w = max(1, round(T_AVG / h))
    Fbar = uniform_filter1d(F, w, mode="nearest") if w > 1 else F
    # the force a sample held: the smallest |F| of one sign over +-HOLD samples (<= 0: none)
    span = 2 * HOLD + 1
    held_pos = minimum_filter1d(Fbar, span, mode="nearest")
    held_neg = -maximum_filter1d(Fbar, span, mode="nearest")
    hold = np.maximum(held_pos, held_neg)
    hold_sign = np.where(held_pos >= held_neg, 1, -1)
    lag = int(np.ceil((1.0 / rig.pwm_hz + T_VALVE) / h))
    push = (data.u[:, 0] > 0.0) | (data.u[:, 3] > 0.0)  # mode 1 raises F
    pull = (data.u[:, 1] > 0.0) | (data.u[:, 2] > 0.0)  # mode 2 lowers it
    Va, Vb = data.volumes()
    k_gas = rig.n * (data.p_a * rig.A_a**2 / Va + data.p_b * rig.A_b**2 / Vb)

    rest: list[StictionEvent] = []
    cands: list[tuple[StictionEvent, float, float]] = []  # (event, held force, k_gas term)
    n_tried = 0
    rejected = {"drifting": 0, "valves reversing": 0, "near a stop": 0}
    for r in runs:
        if r.c <= lo_zone or r.c >= hi_zone:
            continue
        t0, t1 = float(t[r.i]), float(t[r.j])
        # lower bound: every sample with a fitting window inside the interval
        # (a run shorter than 2 g_min + 1 samples has no such sample)
        if r.j - r.i >= 2 * g_min:
            ks = np.arange(r.i, r.j + 1)
            g = np.minimum(np.minimum(ks - r.i, r.j - ks), g_max)
            ks, g = ks[g >= g_min], g[g >= g_min].astype(float)
            if ks.size:
                cum = _running_sums(x[r.i:r.j + 1] - r.c)
                kl = (ks - r.i).astype(float)
                v, a, se_v, se_a = _local_fit(kl, g, h, sx, cum)
                creep = (b_v_max * (np.abs(v) + Z_DRIFT * se_v)
                         + m_max * (np.abs(a) + Z_DRIFT * se_a))
                # the speed at the shortest scale too: a wide fit smooths over the corner of a
                # slide-through reversal or a micro-slip
                vs, _, se_vs, _ = _local_fit(kl, np.full(ks.size, float(g_min)), h, sx, cum)
                creep = np.maximum(creep, b_v_max * (np.abs(vs) + Z_DRIFT * se_vs))
                # every sample of the hold window must be covered: the largest margin in it
                local = np.full(r.j - r.i + 1, np.inf)
                local[ks - r.i] = creep
                creep = maximum_filter1d(local, span, mode="constant", cval=np.inf)[ks - r.i]
                vals = hold[ks] - creep
                n_tried += ks.size
                if np.isfinite(vals).any():
                    best = int(np.argmax(vals))
                    k = int(ks[best])
                    rest.append(StictionEvent("rest", float(t[k]),
                                              float(hold_sign[k] * hold[k]),
                                              float(vals[best]), t0, t1, int(hold_sign[k])))
        # upper bound: a confirmed departure from a real stop
        m = r.k
        if t1 - t0 + h < T_STOP:  # a pause, not a rest that proves a stop
            continue
        if m + K_CONFIRM > n or not ok[m:m + K_CONFIRM].all():
            continue
        side = 1 if x[m] > r.c else -1
        if not np.all(side * (x[m:m + K_CONFIRM] - r.c) > B):
            continue
        if _drift_speed(t[r.i:r.j + 1], x[r.i:r.j + 1], sx) > V_STOP:
            rejected["drifting"] += 1
            continue
        start = r.i
        opposing = np.flatnonzero((pull if side > 0 else push)[max(start - lag, 0):m + 1])
        if opposing.size:
            start = max(start, max(start - lag, 0) + int(opposing[-1]) + 1 + lag)
            if start > r.j:
                rejected["valves reversing"] += 1
                continue
        br = np.arange(start, m + 1)
        if not free[br].all():
            rejected["near a stop"] += 1
            continue
        drop = np.zeros(br.size)
        drop[1:] = (np.maximum(side * np.diff(x[br]), 0.0)
                    * np.maximum(k_gas[br[:-1]], k_gas[br[1:]]))
        vals = side * F[br] + drop
        best = int(np.argmax(vals))
        k = int(br[best])
        held = float(np.max(side * Fbar[start:r.j + 1]))
        spring = float(k_gas[k]) if best > 0 else 0.0
        cands.append((StictionEvent("breakaway", float(t[k]), float(F[k]), float(vals[best]),
                                    t0, t1, side), held, spring))

    # a held value exceeds F_S + margin only if every independent force value in its window
    # does: chance Phi(-z)^n_ind per sample and sign
    n_ind = max(1, span // w)
    z_lo = float(norm.isf((ALPHA / (2.0 * max(1, n_tried))) ** (1.0 / n_ind)))
    m_lo = z_lo * sF / np.sqrt(w) + F_n_half
    rest = [StictionEvent(e.kind, e.t, e.F, e.value, e.t_start, e.t_end, e.direction, m_lo)
            for e in rest]
    lo_event = max(rest, key=lambda e: e.value) if rest else None
    lo = max(lo_event.bound, 0.0) if lo_event else None

    # a break-away counts only from a stick that held, within the noise, as much as the best
    # rest interval did, and at least what the lower bound certifies
    strong = max(lo + m_lo, abs(lo_event.F) - m_lo) if lo_event is not None else np.inf
    z_hi = float(norm.isf(ALPHA / max(1, len(cands))))
    brk: list[StictionEvent] = []
    rejected["weak stick"] = rejected["below the lower bound"] = 0
    for e, held, spring in cands:
        if lo is None or held < strong:
            rejected["weak stick"] += 1
            continue
        sigma_e = float(np.hypot(sF, np.sqrt(2.0) * spring * sx))
        e = StictionEvent(e.kind, e.t, e.F, e.value, e.t_start, e.t_end, e.direction,
                          z_hi * sigma_e + F_n_half)
        if e.bound < lo:
            rejected["below the lower bound"] += 1
            continue
        brk.append(e)
    hi_event = min(brk, key=lambda e: e.bound) if brk else None
    hi = hi_event.bound if hi_event else None
    m_hi = hi_event.margin if hi_event else z_hi * sF + F_n_half
    basis = _basis(lo_event, hi_event, len(rest), len(brk), sF, sx, noise_src)
    return StictionBounds(lo, hi, len(rest), len(brk), lo_event, hi_event, m_lo, m_hi, sF, sx,
                          basis, tuple(rest), tuple(brk), rejected)


def _basis(lo: StictionEvent | None, hi: StictionEvent | None, n_rest: int, n_brk: int,
           sF: float, sx: float, noise_src: str) -> str:
    """One line for report.md."""
    parts = []
    if lo is not None:
        parts.append(f"at rest at {abs(lo.F):.0f} N at t = {lo.t:.2f} s (lower bound "
                     f"{max(lo.bound, 0.0):.0f} N after creep and {lo.margin:.0f} N noise/F_n "
                     f"margins; {n_rest} rest intervals)")
    else:
        parts.append("no rest interval away from the end stops")
    if hi is not None:
        parts.append(f"broke away at {abs(hi.F):.0f} N at t = {hi.t:.2f} s (upper bound "
                     f"{hi.bound:.0f} N with +{hi.margin:.0f} N; {n_brk} break-aways)")
    else:
        parts.append("no usable break-away, no upper bound")
    return "; ".join(parts) + (f"; noise {sF:.1f} N ({noise_src}), {sx * 1e6:.1f} um")
