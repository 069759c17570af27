"""The safety supervisor of the deploy runtime: faults that stop the loop, warnings that ask for
a new identification.

The supervisor looks at every sample *before* the control law does (a NaN fed to
:func:`pneutune.control.law.darc.step_into` closes the valves but corrupts the Kalman and θ̂ states
for good), and at θ̂ after the step. Its decisions are taken once, in C
(``control/law/c/pt_supervisor.c``, compiled into the law's library): the deploy runtime calls
that code through ctypes, and a target running the C law runs the same file around it. This
module holds the rules (below), the thresholds (:class:`SupervisorSettings`) and the
:class:`Event` messages; the C reads the thresholds packed by
:mod:`pneutune.control.rig.supervisor_pack`. No allocation per sample beyond the returned
events (about 3 µs per sample for both checks, see ``benchmarks/runtime_latency.py``); pure
apart from its own memory (:meth:`Supervisor.reset`), and knows nothing of rigs or logs: the
runtime (:mod:`pneutune.control.rig.runtime`) calls it and acts on what it returns.

Faults (level ``error``; each makes the runtime write :data:`FAIL_SAFE_DUTIES` in the same sample,
log the event on ``/rig/events`` and stop; ``deploy`` exits 3)
    checked in this order, the first one found is reported:

    ``sensor_nan``
        a reading of x, p_a, p_b or p_s is NaN or infinite.
    ``sensor_range``
        a reading outside what the sensor can deliver while it works: position outside
        [limits.x_min - x_span_margin, limits.x_max + x_span_margin] (a broken wire or a
        4-20 mA loop at its rail), a pressure below ``p_sensor_min`` (half an atmosphere
        absolute: a chamber of this rig cannot get there, a dead transmitter reads ~0 or
        negative) or above ``p_sensor_max`` (the transmitter's full scale).
    ``sensor_stale``
        no new value for more than ``limits.sensor_timeout_s``. "New" is decided by the rig
        when it can: a rig whose ``sample_times()`` is not None (the time each channel was last
        refreshed, :class:`pneutune.control.rig.protocol.Rig`) is stale on a channel when
        ``t - sample_times()[i] > sensor_timeout_s``. A rig without it is judged on the values:
        a *pressure* channel whose reading repeats bit for bit for more than the timeout is
        stale (a working analog pressure channel has noise far above its quantum: with the
        sim's 300 Pa noise and a 16-bit, 10 bar converter, the chance that one reading
        repeats exactly is ~1 %, that five in a row do is ~1e-10). The *position* is never
        judged on its values: it is quantised (1.2 µm) and a piston at rest can legitimately
        read the same count for seconds; a frozen position is caught only through
        ``sample_times()``, which is why every rig shipped here provides it.
    ``position_limit``
        the measured position outside [limits.x_min - x_tolerance, limits.x_max + x_tolerance]
        (x_tolerance 0.1 mm = 20 standard deviations of the position noise, so that a piston
        resting on an end stop that coincides with a limit does not trip it on noise; set the
        limits inside the stroke for a margin).
    ``overpressure``
        p_a or p_b above limits.p_max.
    ``supply_loss``
        p_s below p0 + supply_loss_fraction (p_s,model - p0): by default half of the model's
        gauge supply pressure (3.5 bar abs for the paper's 6 bar): the valves can no longer
        deliver the flows the controller was tuned for.

Warnings (level ``warning``, once per run and cause; the run goes on; "run identify again")
    ``reidentify_supply``
        the measured supply pressure has differed from the model's (controller ``rig.p_s``)
        by more than ``supply_warn_delta`` (1 bar) for more than ``supply_warn_hold_s``
        (0.5 s; a sustained change, not a dip during a large flow).
    ``reidentify_theta``
        θ̂ of the mass (θ1) or friction (θ3 = b_v, θ4 = A_f) within ``theta_band`` (2 %) of the
        width of its range [θ_min, θ_max] from a bound, continuously for more than
        ``theta_hold_s`` (1 s): the projection is holding it against the bound, the model's
        range no longer contains what the adaptation wants.

Fail-safe valve state: **all four valves closed** (:data:`FAIL_SAFE_DUTIES`, the paper's mode 3).
Closed valves trap the air in both chambers, so the piston is held by two air springs and
friction where it is; nothing is vented, nothing can draw more supply air, so a supply-side
fault cannot push the piston. It is also the state the rig reaches by itself when the
controller dies (on/off solenoid valves are normally closed: no coil current, no flow), so the
fail-safe needs no working software and a hardware watchdog that cuts the coil power gives the
same state. Exhausting both chambers (:data:`EXHAUST_DUTIES`, selectable) removes the stored
energy but lets the piston move freely under gravity or the load, and the unequal areas give it
a kick while the chambers vent; it is the right choice only when a person must reach the
axis, and is then done deliberately. An overpressure is not relieved by closing the valves:
the supply can no longer feed the chamber; the relief valve of the installation remains the
protection against the pressure itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pneutune.control.constants import THETA_NAMES, THETA_UNITS
from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.errors import PneutuneError

#: [Pa]: a pressure reading this much below the sensor range is likely gauge (the hint of a
#: ``sensor_range`` fault).
STANDARD_ATMOSPHERE = 101325.0

#: All valves closed: the fail-safe state (see the module docstring), [a_in, a_out, b_in, b_out].
FAIL_SAFE_DUTIES: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
#: Both chambers to exhaust (a_out and b_out open): the alternative, selectable fail-safe.
EXHAUST_DUTIES: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)
#: Fail-safe modes by name.
FAIL_SAFE_MODES: dict[str, tuple[float, float, float, float]] = {
    "hold": FAIL_SAFE_DUTIES, "exhaust": EXHAUST_DUTIES,
}

#: Sensor channel names, in the order of ``Rig.read()``.
CHANNELS: tuple[str, str, str, str] = ("x", "p_a", "p_b", "p_s")
#: θ̂ indices watched for drift onto a bound: M, b_v, A_f (θ1, θ3, θ4 of the paper).
WATCHED_THETA: tuple[int, ...] = (0, 2, 3)
#: Times are k Ts in floating point: "more than the timeout" means by more than 1 ns.
_TIME_EPS = 1.0e-9

#: Fault codes, in the order they are checked.
FAULT_CODES: tuple[str, ...] = ("sensor_nan", "sensor_range", "sensor_stale", "position_limit",
                                "overpressure", "supply_loss", "rig_io")
#: Warning codes.
WARNING_CODES: tuple[str, ...] = ("reidentify_supply", "reidentify_theta", "deadline_overrun")


class SupervisorError(PneutuneError, ValueError):
    """Supervisor settings that cannot work (e.g. a sensor range that excludes the limits)."""


@dataclass(frozen=True, slots=True)
class Event:
    """One ``/rig/events`` record.

    Attributes
    ----------
    t : float
        Time of the sample that raised it [s].
    level : str
        ``info``, ``warning`` or ``error``.
    code : str
        Machine-readable cause (:data:`FAULT_CODES`, :data:`WARNING_CODES`).
    message : str
        What happened, with the values.
    """

    t: float
    level: str
    code: str
    message: str

    def as_dict(self) -> dict[str, float | str]:
        """Plain dict (for JSON output)."""
        return {"t": self.t, "level": self.level, "code": self.code, "message": self.message}


@dataclass(frozen=True, slots=True)
class SupervisorSettings:
    """Thresholds of the supervisor, SI units.

    Parameters
    ----------
    x_min, x_max : float
        Allowed positions (``limits`` of controller.yaml) [m].
    p_max : float
        Highest allowed chamber pressure [Pa abs].
    sensor_timeout_s : float
        Longest time without a new sensor value [s].
    p0 : float
        Ambient pressure [Pa abs].
    p_s_model : float
        Supply pressure the controller was tuned for (controller ``rig.p_s``) [Pa abs].
    theta_min, theta_max : sequence of 6 float
        Bounds of θ̂ (controller ``adaptation``).
    x_tolerance : float
        Band outside [x_min, x_max] tolerated as position noise [m].
    x_span_margin : float
        The position sensor's span beyond [x_min, x_max] [m]; further out is ``sensor_range``.
    p_sensor_min, p_sensor_max : float or None
        Pressure sensor range [Pa abs]; default p0/2 and max(16 bar, 2 p_max).
    supply_loss_fraction : float
        Supply loss below p0 + fraction (p_s_model - p0) [-].
    supply_warn_delta : float
        Supply change that asks for a new identification [Pa].
    supply_warn_hold_s : float
        How long the change must last [s].
    theta_band : float
        Width of the band next to a θ bound, as a fraction of θ_max - θ_min [-].
    theta_hold_s : float
        How long θ̂ must stay in the band [s].
    freeze_detection : bool
        Judge pressure channels stale on bit-exact repetition when the rig has no
        ``sample_times()`` (disable for a noise-free simulated plant).
    """

    x_min: float
    x_max: float
    p_max: float
    sensor_timeout_s: float
    p0: float
    p_s_model: float
    theta_min: tuple[float, ...]
    theta_max: tuple[float, ...]
    x_tolerance: float = 1.0e-4
    x_span_margin: float = 0.01
    p_sensor_min: float | None = None
    p_sensor_max: float | None = None
    supply_loss_fraction: float = 0.5
    supply_warn_delta: float = 1.0e5
    supply_warn_hold_s: float = 0.5
    theta_band: float = 0.02
    theta_hold_s: float = 1.0
    freeze_detection: bool = True
    _p_lo: float = field(init=False, repr=False)
    _p_hi: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        lo = 0.5 * self.p0 if self.p_sensor_min is None else self.p_sensor_min
        hi = max(1.6e6, 2.0 * self.p_max) if self.p_sensor_max is None else self.p_sensor_max
        object.__setattr__(self, "_p_lo", float(lo))
        object.__setattr__(self, "_p_hi", float(hi))
        if not self.x_max > self.x_min:
            raise SupervisorError(f"x_max > x_min must hold, got x_min={self.x_min}, "
                                  f"x_max={self.x_max}")
        if not lo < self.p0 < hi:
            raise SupervisorError(f"p_sensor_min < p0 < p_sensor_max must hold, got "
                                  f"p_sensor_min={lo}, p0={self.p0}, p_sensor_max={hi}")
        if not 0.0 < self.supply_loss_fraction < 1.0:
            raise SupervisorError(f"0 < supply_loss_fraction < 1 must hold, got "
                                  f"{self.supply_loss_fraction}")
        if not 0.0 <= self.theta_band < 0.5:
            raise SupervisorError(f"0 <= theta_band < 0.5 must hold, got {self.theta_band}")
        if len(self.theta_min) != 6 or len(self.theta_max) != 6:
            raise SupervisorError("theta_min and theta_max must have 6 values each")

    @property
    def supply_min(self) -> float:
        """Supply pressure below which the supply is lost [Pa abs]."""
        return self.p0 + self.supply_loss_fraction * (self.p_s_model - self.p0)

    @property
    def p_sensor_range(self) -> tuple[float, float]:
        """(lowest, highest) pressure reading of a working sensor [Pa abs]."""
        return self._p_lo, self._p_hi

    @classmethod
    def from_controller(cls, cfg: ControllerConfig, **overrides: float | bool | None
                        ) -> SupervisorSettings:
        """Settings from a controller.yaml (its ``limits``, ``rig`` and θ bounds).

        Parameters
        ----------
        cfg : ControllerConfig
            The deployed config.
        **overrides
            Any other field of :class:`SupervisorSettings`.
        """
        lim = cfg.limits
        return cls(x_min=lim.x_min, x_max=lim.x_max, p_max=lim.p_max,
                   sensor_timeout_s=lim.sensor_timeout_s, p0=cfg.rig.p0,
                   p_s_model=cfg.rig.p_s, theta_min=tuple(cfg.adaptation.theta_min),
                   theta_max=tuple(cfg.adaptation.theta_max), **overrides)


def _fmt_p(p: float) -> str:
    return f"{p / 1e5:.4g} bar ({p:.6g} Pa)"


class Supervisor:
    """Per-sample fault and warning checks (see the module docstring for the rules).

    The decisions are the C supervisor's (``control/law/c/pt_supervisor.c``, the same code a
    target runs around the C law; :data:`pneutune.control.law.clib.LIB`), on the settings packed
    by :func:`pneutune.control.rig.supervisor_pack.pack_supervisor`: the thresholds computed in
    float64 from ``settings`` once. This class turns its status words into :class:`Event` objects,
    with the values and times the C holds in its state.

    Parameters
    ----------
    settings : SupervisorSettings
        The thresholds.

    Notes
    -----
    Call :meth:`check_sensors` with each sample before the control step, and
    :meth:`check_estimates` with θ̂ after it. Samples must come in time order.
    """

    def __init__(self, settings: SupervisorSettings) -> None:
        # imported here: supervisor_pack builds on this module's tables
        from pneutune.control.law.clib import LIB
        from pneutune.control.rig import supervisor_pack as sp

        self._lib = LIB
        self._sp = sp
        self._settings = settings
        self._vec = sp.pack_supervisor(settings)
        self._state = np.zeros(sp.SUP_STATE_SIZE)
        self._sensors = np.zeros(4)
        self._stamps = np.zeros(4)
        self._theta = np.zeros(6)
        self._p_vec = self._vec.ctypes.data
        self._p_state = self._state.ctypes.data
        self._p_sensors = self._sensors.ctypes.data
        self._p_stamps = self._stamps.ctypes.data
        self._p_theta = self._theta.ctypes.data
        self.reset()

    @property
    def settings(self) -> SupervisorSettings:
        """The thresholds. Setting new ones (a protocol relaxes a limit near an end stop)
        repacks them for the C and keeps what the supervisor has seen."""
        return self._settings

    @settings.setter
    def settings(self, value: SupervisorSettings) -> None:
        self._vec[:] = self._sp.pack_supervisor(value)
        self._settings = value

    def reset(self) -> None:
        """Forget everything seen (start of a run)."""
        self._lib.pt_sup_reset(self._p_state)

    def _status(self, status: int) -> int:
        if status & self._sp.CONFIG_MASK:  # cannot happen: the vector is packed here
            raise RuntimeError(f"the C supervisor rejected its settings: "
                               f"{', '.join(self._sp.status_codes(status))}")
        return status

    # -- faults ---------------------------------------------------------------------------------

    def check_sensors(self, t: float, sensors: np.ndarray | Sequence[float],
                      sample_times: np.ndarray | Sequence[float] | None = None) -> Event | None:
        """Check one sample before the control step.

        Parameters
        ----------
        t : float
            Time of the sample [s] (the rig's clock).
        sensors : (4,) array
            ``[x, p_a, p_b, p_s]`` [m, Pa abs].
        sample_times : (4,) array, optional
            Time each channel was last refreshed [s] (the rig's ``sample_times()``); None:
            judge staleness on the values (pressures only).

        Returns
        -------
        Event or None
            The fault (level ``error``), or None if the sample is fit for the controller.
        """
        self._sensors[:] = sensors
        stamps = None
        if sample_times is not None:
            self._stamps[:] = sample_times
            stamps = self._p_stamps
        t = float(t)
        status = self._status(self._lib.pt_sup_check_sensors(
            self._p_state, self._p_vec, t, self._p_sensors, stamps))
        code = self._sp.first_fault(status)
        if code is None:
            return None
        return Event(t, "error", code, self._fault_message(code, t, sample_times is not None))

    def _fault_message(self, code: str, t: float, stamped: bool) -> str:
        """What a fault found by the C says, with the readings and times it judged."""
        s = self.settings
        sp = self._sp
        vals = tuple(float(v) for v in self._sensors)
        x, p_s = vals[0], vals[3]
        i = int(self._state[sp.SUP_S_FAULT_CHANNEL])
        if code == "sensor_nan":
            return f"sensor {CHANNELS[i]} reads {vals[i]} at t={t:.4f} s"
        if code == "sensor_range":
            if i == 0:
                x_lo, x_hi = s.x_min - s.x_span_margin, s.x_max + s.x_span_margin
                hint = (" (in mm? the protocol's positions are in m)"
                        if x_lo <= x * 1e-3 <= x_hi and not x_lo <= x <= x_hi else "")
                return (f"sensor x reads {x:.6g} m at t={t:.4f} s, outside the sensor span "
                        f"[{x_lo:.6g}, {x_hi:.6g}] m{hint}")
            p_lo, p_hi = s.p_sensor_range
            p = vals[i]
            hint = ""
            if p < p_lo and (p + STANDARD_ATMOSPHERE >= p_lo or p_lo <= p * 1e5 <= p_hi):
                hint = " (gauge, or bar? the protocol's pressures are absolute, in Pa)"
            return (f"sensor {CHANNELS[i]} reads {_fmt_p(p)} at t={t:.4f} s, outside "
                    f"the sensor range [{p_lo:.6g}, {p_hi:.6g}] Pa{hint}")
        if code == "sensor_stale":
            timeout = s.sensor_timeout_s
            if stamped:
                age = t - float(self._stamps[i])
                if math.isnan(age):
                    return (f"sensor {CHANNELS[i]} reads {vals[i]!r} at t={t:.4f} s, but the "
                            "rig gives its sample time as NaN (never delivered): a value "
                            "without a sample time cannot be judged fresh")
                return (f"sensor {CHANNELS[i]}: no new sample for {age:.4f} s at t={t:.4f} s "
                        f"(limits.sensor_timeout_s = {timeout:g} s)")
            age = t - float(self._state[sp.SUP_S_CHANGED_AT + i])
            return (f"sensor {CHANNELS[i]} has read exactly {vals[i]!r} Pa for {age:.4f} s at "
                    f"t={t:.4f} s (limits.sensor_timeout_s = {timeout:g} s)")
        if code == "position_limit":
            side = "below limits.x_min" if x < s.x_min else "above limits.x_max"
            bound = s.x_min if x < s.x_min else s.x_max
            return (f"position x = {x * 1e3:.4f} mm at t={t:.4f} s is {side} = "
                    f"{bound * 1e3:.4f} mm (tolerance {s.x_tolerance * 1e3:.3g} mm)")
        if code == "overpressure":
            return (f"{CHANNELS[i]} = {_fmt_p(vals[i])} at t={t:.4f} s is above "
                    f"limits.p_max = {_fmt_p(s.p_max)}")
        return (f"supply pressure p_s = {_fmt_p(p_s)} at t={t:.4f} s is below "
                f"{_fmt_p(s.supply_min)} (p0 + {s.supply_loss_fraction:g} of the "
                f"model's gauge supply, rig.p_s = {_fmt_p(s.p_s_model)})")

    # -- warnings -------------------------------------------------------------------------------

    def check_estimates(self, t: float, p_s: float, theta: np.ndarray | Sequence[float]
                        ) -> list[Event]:
        """Re-identification warnings after the control step (each at most once per run).

        Parameters
        ----------
        t : float
            Time of the sample [s].
        p_s : float
            Measured supply pressure [Pa abs].
        theta : (6,) array
            θ̂ after the step.

        Returns
        -------
        list of Event
            New warnings (usually empty).
        """
        self._theta[:] = theta
        t = float(t)
        p_s = float(p_s)
        status = self._status(self._lib.pt_sup_check_estimates(
            self._p_state, self._p_vec, t, p_s, self._p_theta))
        if not status & self._sp.WARN_MASK:
            return []
        s = self.settings
        sp = self._sp
        out: list[Event] = []
        if status >> sp.STATUS_BITS["WARN_REIDENTIFY_SUPPLY"] & 1:
            held = t - float(self._state[sp.SUP_S_SUPPLY_SINCE])
            out.append(Event(t, "warning", "reidentify_supply",
                             f"supply pressure p_s = {_fmt_p(p_s)} has differed from the "
                             f"model's rig.p_s = {_fmt_p(s.p_s_model)} by more than "
                             f"{s.supply_warn_delta / 1e5:g} bar for {held:.2f} s: "
                             f"run identify again (and tune) at this supply pressure"))
        for j, i in enumerate(WATCHED_THETA):
            for side in (0, 1):
                if not status >> (sp.THETA_BIT0 + 2 * j + side) & 1:
                    continue
                held = t - float(self._state[sp.SUP_S_THETA_SINCE + 2 * j + side])
                bound = s.theta_min[i] if side == 0 else s.theta_max[i]
                out.append(Event(t, "warning", "reidentify_theta",
                                 f"θ̂ {THETA_NAMES[i]} = {float(self._theta[i]):.6g} "
                                 f"{THETA_UNITS[i]} has stayed within "
                                 f"{s.theta_band * 100:g} % of its "
                                 f"{'lower' if side == 0 else 'upper'} bound {bound:g} "
                                 f"{THETA_UNITS[i]} for {held:.2f} s: the model's range no "
                                 f"longer holds the plant; run identify again"))
        return out


__all__ = [
    "CHANNELS", "EXHAUST_DUTIES", "FAIL_SAFE_DUTIES", "FAIL_SAFE_MODES", "FAULT_CODES",
    "WARNING_CODES", "WATCHED_THETA", "Event", "Supervisor", "SupervisorError",
    "SupervisorSettings",
]
