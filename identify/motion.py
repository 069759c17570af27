"""Friction (Eq. 2), the smooth model (Eqs. 3-4), the moving mass and F_n, from Eq. (1).

Eq. (1) rearranged with the measured pressure force F_p = A_a p_a - A_b p_b - p0 A_r:

    F_p = M a + F_f(v) - F_n        (while sliding)

* :class:`FrictionIdentifier`: nonlinear least squares (``scipy.optimize.least_squares``) for
  the Stribeck parameters F_S, F_C, v_s, alpha, b_v and F_n on the sliding samples, and linear
  least squares for the smooth model θ2..θ4 of the paper (F_p = θ1 a - θ2 + θ3 v + θ4 S_f(v)).
  Velocity comes from a Savitzky-Golay derivative of x (no phase lag).
* :class:`MassIdentifier`: the integrated form ``M Δv = ∫(F_p - F_f + F_n) dt`` over windows,
  which needs no acceleration; with a block bootstrap for its interval. On a rig like the
  paper's the mechanical pole b_v/M (~530 Hz) lies far above the 125 Hz Nyquist frequency of
  4 ms sampling and the interval is wide: see docs/identifiability.md. A known mass (datasheet
  plus weighed payload) can be given instead.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from pneutune.control.physics.friction import smooth_sign_array as smooth_sign
from pneutune.control.physics.friction import stribeck

from .base import Identifier
from .dataset import Dataset, IdentificationError

#: Samples slower than this are not "sliding" for the friction fit [m/s].
V_SLIDE = 2.0e-3
#: Speed above which friction is taken as Coulomb plus viscous alone [m/s]. The Stribeck fit
#: that follows keeps v_s <= V_COULOMB/3 and alpha >= 1, so the term left at this speed is at
#: most e^-3 (5 %) of F_S - F_C, and 1e-4 for the paper's v_s = 5 mm/s, alpha = 2.
V_COULOMB = 2.0e-2
#: A sample slides steadily when its raw speed (central difference of two samples) is at least
#: this fraction of the smoothed speed: a piston in stick-slip (a stiction well above the
#: Coulomb level, one jerk per PWM period) stops between samples while the smoothed speed stays
#: well above V_COULOMB. On fleet plant 0 (F_S/F_C 1.78) 29 % of the windows held such stops
#: (/sim/truth), and F_C came out 6-13 % high and b_v 3-11 % low on every log kind; with this
#: rule 0.5 % and 0.3 % (benchmarks/fleet.py, docs/identification.md).
STEADY_FRACTION = 0.5
#: Fewest sliding samples the friction fit accepts.
MIN_SLIDING = 200
#: Samples per window of the integrated Coulomb + viscous fit (40 ms at 4 ms).
COULOMB_WINDOW = 10


def sliding_windows(v: np.ndarray, ok: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Start and end samples of windows of ``w`` samples, half overlapping, inside ``ok`` and
    sliding one way throughout (same sign of v at both ends)."""
    n = v.shape[0]
    bad = np.concatenate([[0], np.cumsum(~ok)])
    k0 = np.arange(0, n - w - 1, max(1, w // 2))
    k0 = k0[((bad[k0 + w + 1] - bad[k0]) == 0) & (np.sign(v[k0]) == np.sign(v[k0 + w]))]
    return k0, k0 + w


def _full(p: np.ndarray, fixed: np.ndarray | None) -> tuple[float, ...]:
    """(F_S, F_C, v_s, alpha, b_v, F_n) from the free parameters and the fixed (F_C, b_v, F_n)."""
    if fixed is None:
        return tuple(float(q) for q in p)
    F_S, v_s, alpha = p
    return float(F_S), float(fixed[0]), float(v_s), float(alpha), float(fixed[1]), float(fixed[2])


class FrictionIdentifier(Identifier):
    """Stribeck friction, F_n and the smooth model's θ2..θ4.

    Parameters
    ----------
    mass : float
        Moving mass used for the (small) inertial term M a [kg].
    v_slide : float
        Threshold on |v| for sliding samples [m/s].
    sg_window : int
        Savitzky-Golay window of the velocity and acceleration estimates [samples].

    Attributes
    ----------
    F_S_, F_C_, v_s_, alpha_, b_v_, F_n_ : float
        Stribeck parameters [N, N, m/s, -, N s/m] and the constant force F_n [N].
    stiction_resolved_ : bool
        The stiction excess F_S - F_C shows (at least 2 % of F_C) and the Stribeck shape is an
        interior optimum (alpha and v_s off their bounds); otherwise F_S is not measured.
    std_ : dict
        Standard errors of the Stribeck fit.
    smooth_ : ndarray (3,)
        θ2 = F_n [N], θ3 = b_v [N s/m], θ4 = A_f [N] of the smooth model (θ1 = ``mass``),
        fitted like the Coulomb + viscous stage on Eq. (1) integrated over sliding windows.
    y_ : ndarray
        F_p - M a on the sliding samples (for plots).
    residual_std_, residual_max_ : float
        Residual force of the Stribeck fit on sliding samples, rms and 99.9th percentile [N].
    sliding_ : ndarray of bool
        Samples used.
    coulomb_from_fast_ : bool
        True when F_C, b_v and F_n came from the samples faster than V_COULOMB (the two-stage
        fit); False when they were fitted jointly with the Stribeck terms. In the two-stage
        fit the standard errors of F_S, v_s and alpha are conditional on the held F_C, b_v, F_n.
    """

    def __init__(self, mass: float, v_slide: float = V_SLIDE, sg_window: int = 7) -> None:
        self.mass = mass
        self.v_slide = v_slide
        self.sg_window = sg_window

    def fit(self, data: Dataset, mask: np.ndarray | None = None) -> FrictionIdentifier:
        """Fit on the sliding samples where ``mask`` is True.

        Raises
        ------
        IdentificationError
            The piston hardly moves: friction is not identifiable.
        """
        mask = np.ones(data.n, dtype=bool) if mask is None else mask
        v = savgol_filter(data.x, self.sg_window, 3, deriv=1, delta=data.Ts)
        a = savgol_filter(data.x, self.sg_window, 3, deriv=2, delta=data.Ts)
        # sliding throughout the derivative's window: around a stick or a reversal the smoothed
        # velocity is wrong, and those samples would bias F_C and hide the Stribeck bump
        fast = np.abs(v) > self.v_slide
        same_sign = np.sign(v)
        h = self.sg_window // 2
        steady = np.ones(data.n, dtype=bool)
        for k in range(-h, h + 1):
            steady &= np.roll(fast, k) & (np.roll(same_sign, k) == same_sign)
        steady[:h] = steady[-h:] = False
        slide = mask & steady
        stroke = data.rig.x_max - data.rig.x_min
        if slide.sum() < MIN_SLIDING or np.ptp(data.x[mask]) < 0.05 * stroke:
            raise IdentificationError(
                data.path, f"the piston hardly moves in the fitted part of the log "
                f"({int(slide.sum())} samples faster than {self.v_slide * 1e3:g} mm/s, travel "
                f"{np.ptp(data.x[mask]) * 1e3:.2f} mm): friction and mass are not identifiable; "
                f"record motion at several speeds (the identification run does)")
        y = data.F_p[slide] - self.mass * a[slide]
        vs = v[slide]
        fixed = self._coulomb_viscous(data, mask)

        def resid(p: np.ndarray) -> np.ndarray:
            F_S, F_C, v_s, alpha, b_v, F_n = _full(p, fixed)
            return stribeck(vs, F_S, F_C, v_s, alpha, b_v) - F_n - y

        # start from the linear Coulomb + viscous fit over all sliding samples
        A = np.column_stack([np.sign(vs), vs, -np.ones_like(vs)])
        (Fc0, bv0, Fn0), *_ = np.linalg.lstsq(A, y, rcond=None)
        if fixed is not None:
            Fc0, bv0, Fn0 = fixed
        Fc0 = max(float(Fc0), 1.0)
        p0 = np.array([1.3 * Fc0, Fc0, 5e-3, 2.0, max(float(bv0), 1.0), float(Fn0)])
        lo = np.array([0.0, 0.0, 2e-4, 0.3, 0.0, -1e4])
        hi = np.array([1e4, 1e4, 0.2, 8.0, 1e5, 1e4])
        free = slice(0, 6) if fixed is None else [0, 2, 3]
        # The Stribeck term lives at low speed: v_s <= V_COULOMB/3 and alpha >= 1. Stage 1
        # assumed it decayed by V_COULOMB; without stage 1 (the joint fit) a bump free to reach
        # 200 mm/s trades the Coulomb level against the viscous slope instead (on data/run.mcap
        # with one direction's fast samples masked: F_C +19 %, a bump of v_s = 29 mm/s).
        hi[2], lo[3] = V_COULOMB / 3.0, 1.0
        sol = least_squares(resid, p0[free], bounds=(lo[free], hi[free]), x_scale="jac",
                            loss="soft_l1",
                            f_scale=max(1.0, 3.0 * float(np.std(y - A @ [Fc0, bv0, Fn0]))))
        F_S, F_C, v_s, alpha, b_v, F_n = _full(sol.x, fixed)
        if F_C > F_S:  # the Stribeck bump vanished: the data show no stiction excess
            F_S = F_C
        # a shape on its bounds (alpha or v_s) is no interior optimum: F_S is then not measured
        shape = np.array([v_s, alpha])
        on_bound = np.any(np.abs(shape - lo[2:4]) <= 0.01 * lo[2:4]) or np.any(
            np.abs(shape - hi[2:4]) <= 0.01 * hi[2:4])
        self.stiction_resolved_ = bool(F_S - F_C >= 0.02 * max(F_C, 1e-9) and not on_bound)
        self.F_S_, self.F_C_, self.v_s_, self.alpha_, self.b_v_, self.F_n_ = (
            float(F_S), float(F_C), float(v_s), float(alpha), float(b_v), float(F_n))
        self.coulomb_from_fast_ = fixed is not None
        r = resid(sol.x)
        self.residual_std_ = float(np.sqrt(np.mean(r**2)))
        self.residual_max_ = float(np.quantile(np.abs(r), 0.999))
        # neighbouring residuals share the derivative window: inflate by its length
        J = sol.jac
        sd_free = np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)), 0.0, None)
                          * self.residual_std_**2 * float(self.sg_window))
        if fixed is None:
            sd = sd_free
        else:
            sd = np.array([sd_free[0], self._fixed_sd[0], sd_free[1], sd_free[2],
                           self._fixed_sd[1], self._fixed_sd[2]])
        self.std_ = dict(zip(("F_S", "F_C", "v_s", "alpha", "b_v", "F_n"), sd, strict=True))
        # the paper's smooth model, θ1 = mass fixed, integrated over sliding windows as the
        # Coulomb + viscous stage (the same errors-in-variables reason):
        # ∫F_p dt - M Δv = -θ2 T + θ3 Δx + θ4 ∫S_f(v) dt
        k0, k1 = sliding_windows(v, slide, COULOMB_WINDOW)
        force = cumulative_trapezoid(data.F_p, dx=data.Ts, initial=0.0)
        sf = cumulative_trapezoid(smooth_sign(v), dx=data.Ts, initial=0.0)
        T = (k1 - k0) * data.Ts
        B = np.column_stack([-T, data.x[k1] - data.x[k0], sf[k1] - sf[k0]])
        yw = (force[k1] - force[k0]) - self.mass * (v[k1] - v[k0])
        self.smooth_, *_ = np.linalg.lstsq(B, yw, rcond=None)
        self._B, self._y = B, yw
        self.y_ = y
        self.sliding_ = slide
        self.fitted_ = True
        return self

    def _coulomb_viscous(self, data: Dataset, mask: np.ndarray) -> np.ndarray | None:
        """F_C, b_v, F_n by linear least squares on windows sliding faster than V_COULOMB, or
        None.

        Above a few Stribeck velocities the friction is F_C sgn v + b_v v alone, so these
        windows pin the Coulomb level without the Stribeck terms trading off against it. Eq. (1)
        integrated over a window of ``COULOMB_WINDOW`` samples sliding one way,

            ∫ F_p dt - M Δv = F_C T sgn v + b_v Δx - F_n T,

        needs no acceleration and takes the viscous term exactly from the position change, so
        the velocity ripple of the PWM (which a derivative pairs with the pressure ripple, an
        errors-in-variables bias) drops out: on closed-loop logs of simulated rigs F_C came out
        13 % low and b_v 14 % high per sample, within 2 % and 1 % this way (benchmarks/fleet.py
        plants; docs/identification.md). Only samples sliding steadily (:data:`STEADY_FRACTION`)
        enter a window: stick-slip between samples would add stiction to the Coulomb level.
        None (the joint fit is used) with fewer than
        MIN_SLIDING/2 fast samples in either direction, or an unphysical F_C < 0 or b_v <= 0.
        """
        self._fixed_sd = None
        v = data.v
        raw = np.empty_like(data.x)  # central differences: the speed between samples, unsmoothed
        raw[1:-1] = (data.x[2:] - data.x[:-2]) / (2.0 * data.Ts)
        raw[0], raw[-1] = raw[1], raw[-2]
        steady = raw * np.sign(v) >= STEADY_FRACTION * np.abs(v)
        fast = mask & (np.abs(v) >= V_COULOMB) & steady
        per_direction = min(np.count_nonzero(fast & (v > 0)), np.count_nonzero(fast & (v < 0)))
        if per_direction < MIN_SLIDING // 2:
            return None
        k0, k1 = sliding_windows(v, fast, COULOMB_WINDOW)
        if len(k0) < 10:
            return None
        force = cumulative_trapezoid(data.F_p, dx=data.Ts, initial=0.0)
        T = (k1 - k0) * data.Ts
        y = (force[k1] - force[k0]) - self.mass * (v[k1] - v[k0])
        A = np.column_stack([np.sign(v[k0]) * T, data.x[k1] - data.x[k0], -T])
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        if coef[0] < 0.0 or coef[1] <= 0.0:  # unphysical: leave it to the bounded joint fit
            return None
        r = y - A @ coef
        # windows overlap by half: two windows share each sample
        cov = np.linalg.pinv(A.T @ A) * float(np.mean(r**2)) * 2.0
        self._fixed_sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return coef

    def smooth_bootstrap(self, n_boot: int, block: int, seed: int) -> np.ndarray:
        """Moving-block bootstrap of the smooth model's θ2..θ4, shape (n_boot, 3)."""
        self._require_fitted()
        rng = np.random.default_rng(seed)
        n = len(self._y)
        if n < block:  # a short log: blocks of a quarter of it, so that resampling still varies
            block = max(1, n // 4)
        nb = max(1, n // block)
        out = np.empty((n_boot, 3))
        for i in range(n_boot):
            starts = rng.integers(0, max(1, n - block), nb)
            idx = (starts[:, None] + np.arange(block)[None, :]).ravel()
            out[i], *_ = np.linalg.lstsq(self._B[idx], self._y[idx], rcond=None)
        return out


class MassIdentifier(Identifier):
    """Moving mass from the integrated motion equation, with a bootstrap interval.

    Over a window [k0, k1] while sliding: ``M (v1 - v0) = Σ (F_p - F_f(v) + F_n) Ts``, with the
    friction of a fitted :class:`FrictionIdentifier`. One equation per window, least squares
    through the origin.

    Parameters
    ----------
    friction : FrictionIdentifier
        Fitted friction (F_f and F_n).
    window : int
        Window length [samples].
    n_boot : int
        Bootstrap replicates (over windows).
    seed : int
        Bootstrap seed.

    Attributes
    ----------
    M_ : float
        Estimate [kg] (clipped to >= 0.01 kg).
    ci_ : (float, float)
        Central 99 % bootstrap interval [kg].
    n_windows_ : int
        Windows used.
    """

    def __init__(self, friction: FrictionIdentifier, window: int = 25, n_boot: int = 400,
                 seed: int = 0) -> None:
        self.friction = friction
        self.window = window
        self.n_boot = n_boot
        self.seed = seed

    def fit(self, data: Dataset, mask: np.ndarray | None = None) -> MassIdentifier:
        """Fit on windows that lie inside ``mask`` and are sliding throughout."""
        f = self.friction
        mask = np.ones(data.n, dtype=bool) if mask is None else mask
        v = data.v
        force = data.F_p - stribeck(v, f.F_S_, f.F_C_, f.v_s_, f.alpha_, f.b_v_) + f.F_n_
        # trapezoid with the viscous part exact from positions: ∫ b_v v dt = b_v Δx
        force_nv = data.F_p - (stribeck(v, f.F_S_, f.F_C_, f.v_s_, f.alpha_, 0.0)) + f.F_n_
        c = cumulative_trapezoid(force_nv, dx=data.Ts, initial=0.0)
        del force
        ok = mask & (np.abs(v) > V_SLIDE)
        bad = np.concatenate([[0], np.cumsum(~ok)])
        w = self.window
        k0 = np.arange(0, data.n - w, max(1, w // 2))
        k0 = k0[(bad[k0 + w + 1] - bad[k0]) == 0]
        k1 = k0 + w
        if len(k0) < 10:
            raise IdentificationError(data.path, f"only {len(k0)} sliding windows of "
                                      f"{w * data.Ts:g} s: the mass is not identifiable")
        dv = v[k1] - v[k0]
        rhs = (c[k1] - c[k0]) - f.b_v_ * (data.x[k1] - data.x[k0])
        M = float(np.dot(dv, rhs) / np.dot(dv, dv))
        rng = np.random.default_rng(self.seed)
        boots = np.empty(self.n_boot)
        for i in range(self.n_boot):
            j = rng.integers(0, len(k0), len(k0))
            boots[i] = np.dot(dv[j], rhs[j]) / np.dot(dv[j], dv[j])
        self.M_ = max(M, 0.01)
        lo, hi = np.quantile(boots, [0.005, 0.995])
        self.ci_ = (float(max(lo, 0.0)), float(max(hi, lo + 1e-6)))
        self.n_windows_ = len(k0)
        self.fitted_ = True
        return self
