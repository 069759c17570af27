"""The PWM curve: what fraction of each period an on/off valve is open at a constant duty.

A valve driven by an edge-aligned PWM (period ``1/pwm_hz``) opens ``delay_on`` after each rising
command edge and closes ``delay_off`` after each falling one, and a command pulse shorter than
``min_pulse`` never opens it (the switching itself is simulated event by event in
:mod:`pneutune.control.plant.valves`). For a constant duty that gives the closed form
:func:`effective_open_fraction`: a dead zone near 0, the duty shifted by the difference of the
delays, saturation near 1. :func:`sample_pwm_curve` turns it into the points of a contract-4
``pwm`` curve with its corners exact; the controller inverts those (Fig. 2 of the paper).
"""

from __future__ import annotations

import numpy as np


def effective_open_fraction(duty: float | np.ndarray, period: float, delay_on: float,
                            delay_off: float, min_pulse: float) -> float | np.ndarray:
    """Steady-state fraction of each PWM period that a valve is open, for a constant duty.

    Parameters
    ----------
    duty : float or array
        Commanded duty, 0..1.
    period : float
        PWM period [s].
    delay_on, delay_off, min_pulse : float
        Valve switching behaviour [s] (see the module docstring).

    Returns
    -------
    float or array
        0 when the pulse ``duty * period`` is shorter than ``min_pulse`` or ``duty <= 0``;
        otherwise ``clip(duty + (delay_off - delay_on) / period, 0, 1)``, which is 1 as soon as
        the off-gap ``(1 - duty) period`` is shorter than ``delay_off - delay_on``.
    """
    d = np.asarray(duty, dtype=np.float64)
    pulse = d * period
    frac = np.clip(d + (delay_off - delay_on) / period, 0.0, 1.0)
    out = np.where((d <= 0.0) | (pulse < min_pulse), 0.0, np.where(d >= 1.0, 1.0, frac))
    return float(out) if np.ndim(out) == 0 else out


def sample_pwm_curve(period: float, delay_on: float, delay_off: float, min_pulse: float,
                     n: int = 41) -> tuple[list[float], list[float]]:
    """The plant's PWM curve sampled for a controller config, with its corners kept exact.

    Samples :func:`pneutune.control.physics.pwm.effective_open_fraction` on ``n`` evenly spaced
    duties and adds the two corners of the formula: the dead-zone jump at
    ``d_j = min_pulse / period`` (as two points (d_j, 0) and (d_j, ratio(d_j)), a vertical step)
    and the saturation corner where the fraction first reaches 1.

    Parameters
    ----------
    period : float
        PWM period [s].
    delay_on, delay_off, min_pulse : float
        Valve switching behaviour [s].
    n : int
        Number of evenly spaced duties in [0, 1].

    Returns
    -------
    duty, ratio : list of float
        Non-decreasing curve from (0, 0) to (1, ratio(1)).
    """
    def frac(d: float) -> float:
        return round(float(effective_open_fraction(d, period, delay_on, delay_off, min_pulse)), 12)

    duties = {round(float(d), 12) for d in np.linspace(0.0, 1.0, n)}
    d_j = min_pulse / period
    d_sat = 1.0 - (delay_off - delay_on) / period
    pts: list[tuple[float, float]] = [(d, frac(d)) for d in sorted(duties)]
    if 0.0 < d_j < 1.0:
        pts.append((d_j, 0.0))
        # the formula's value just above the jump (the pulse reaches min_pulse)
        pts.append((d_j, round(min(max(d_j + (delay_off - delay_on) / period, 0.0), 1.0), 12)))
    if 0.0 < d_sat < 1.0 and d_sat > d_j:
        pts.append((d_sat, 1.0))
    pts = sorted(set(pts))
    return [p[0] for p in pts], [p[1] for p in pts]


__all__ = ["effective_open_fraction", "sample_pwm_curve"]
