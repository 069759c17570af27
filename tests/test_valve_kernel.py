"""One valve switched alone (:func:`~pneutune.control.plant.valves.valve_open_fractions`) is the
plant's valve (:func:`~pneutune.control.plant.valves.open_fractions`), bit for bit.

Both switch a valve with the plant's own functions (``write_duty``, ``valve_events``,
``valve_next_event``); with the other three valves never commanded open, both sum the open time
over the same events, so every open fraction must be the same float. The duty sequence holds
every kind of edge: duties that start or end a pulse mid-period, pulses shorter than the
minimum pulse, short off-gaps that a longer closing delay bridges, full and zero duty, steps
every sample and steady stretches, NaN and out-of-range commands; in both PWM update modes,
for several timings and carrier phases.
"""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant.dynamics import initial_state
from pneutune.control.plant.params import P_DOFF, P_DON, P_MINP, pack_plant
from pneutune.control.plant.valves import open_fractions, valve_open_fractions

TS = 0.0005
#: (delay_on, delay_off, min_pulse) [s]: the paper's valves, a slow one, zero delays, a closing
#: delay far longer than the opening one (off-gaps bridged), a minimum pulse equal to delay_on.
TIMINGS = np.array([[2.0e-3, 3.0e-3, 1.5e-3],
                    [3.0e-3, 2.0e-3, 2.5e-3],
                    [0.0, 0.0, 0.0],
                    [1.0e-3, 6.0e-3, 0.5e-3],
                    [4.0e-3, 4.5e-3, 4.0e-3]])
PHASES = np.array([0.0, 0.0013, 0.0161, 1.0 / 120.0, 0.00025])


def _duties(n: int = 6000, seed: int = 3) -> np.ndarray:
    """Duties with every kind of edge (module docstring)."""
    rng = np.random.default_rng(seed)
    parts = [
        np.zeros(80), np.ones(200), np.zeros(150),                # full on and off
        np.repeat(rng.uniform(0.0, 1.0, 40), 33),                  # steady partial duties
        rng.uniform(0.0, 1.0, 600),                                # a new duty every sample
        rng.uniform(0.0, 0.15, 400),                               # pulses below min_pulse
        rng.uniform(0.85, 1.0, 400),                               # short off-gaps
        np.repeat([0.0, 1.0, 0.5, 0.0, 0.999, 0.001, 1.0], 17),    # steps between the extremes
        np.array([np.nan, -0.3, 1.7, 0.5, np.nan, 2.0, -1.0]),     # NaN and out-of-range
        np.tile([0.0, 1.0], 100),                                  # toggling every sample
        np.repeat(rng.choice([0.0, 0.2, 0.6, 1.0], 60), 8),        # 4 ms steps
    ]
    u = np.concatenate(parts)
    return np.resize(u, n)


@pytest.mark.parametrize("mode", ["immediate", "latched"])
@pytest.mark.parametrize("valve", [0, 3])
def test_one_valve_alone_is_the_plants_valve_bit_for_bit(mode: str, valve: int) -> None:
    """Each candidate timing and phase, one valve commanded and the other three shut: the open
    fractions of both kernels are the same floats, and the valve does open and close (a whole
    sample open sums its sub-intervals to 1 within rounding)."""
    p = pack_plant(PlantConfig().with_updates({"rig": {"pwm_update": mode}})).vec.copy()
    u = _duties()
    alone = np.empty((len(TIMINGS), len(u)))
    valve_open_fractions(p, u, TIMINGS, PHASES, TS, alone)
    duties = np.zeros((len(u), 4))
    duties[:, valve] = u
    for m, (timing, phase) in enumerate(zip(TIMINGS, PHASES, strict=True)):
        q = p.copy()
        q[P_DON + valve], q[P_DOFF + valve], q[P_MINP + valve] = timing
        out = np.empty((len(u), 4))
        open_fractions(q, initial_state(q, 0.02, 2e5, 2e5), duties, float(phase), TS, out)
        assert np.array_equal(alone[m], out[:, valve]), (mode, valve, m)
        others = np.delete(out, valve, axis=1)
        assert not others.any()
        assert 0.0 < alone[m].mean() < 1.0 and alone[m].max() == pytest.approx(1.0, abs=1e-9)



@pytest.mark.parametrize("mode", ["immediate", "latched"])
@pytest.mark.parametrize("write_delay", [1.0e-3, 5.0e-3])
def test_a_write_delay_switches_the_valve_as_the_plants_io_delay(mode: str,
                                                                 write_delay: float) -> None:
    """valve_open_fractions(..., write_delay) against the plant with ``io.delay`` (the duties
    it writes wait in its state), its valve's state summed on a 10 us grid: the two agree to
    one grid step of the 4 ms sample (0.0025), and 0 delay gives the undelayed kernel exactly."""
    from pneutune.control.plant import dynamics
    from pneutune.control.plant.params import S_OPEN

    Ts, n, dt = 0.004, 120, 1.0e-5
    pp = pack_plant(PlantConfig().with_updates({"rig": {"pwm_update": mode}}))
    duties = _duties()[1750:1750 + n].copy()  # a new duty every sample
    tm = np.array([[2.0e-3, 3.0e-3, 1.5e-3]])
    got = np.empty((1, n))
    valve_open_fractions(pp.vec, duties, tm, np.zeros(1), Ts, got, write_delay)
    rig = pack_plant(PlantConfig().with_updates({"rig": {"pwm_update": mode},
                                                 "io": {"delay": write_delay}}))
    s = dynamics.initial_state(rig.vec, 0.02, 2.0e5, 2.0e5)
    steps = round(Ts / dt)
    want = np.empty(n)
    for k in range(n):
        dynamics.set_duties(rig.vec, s, k * Ts, np.array([duties[k], 0.0, 0.0, 0.0]))
        acc = 0.0
        for j in range(steps):
            dynamics.advance(rig.vec, s, k * Ts + (j + 1) * dt, 6.0e5, rig.force_steps)
            acc += s[S_OPEN]
        want[k] = acc / steps
    assert np.max(np.abs(got[0] - want)) <= dt / Ts + 1e-9
    plain, zero = np.empty((1, n)), np.empty((1, n))
    valve_open_fractions(pp.vec, duties, tm, np.zeros(1), Ts, plain)
    valve_open_fractions(pp.vec, duties, tm, np.zeros(1), Ts, zero, 0.0)
    assert np.array_equal(plain, zero)


@pytest.mark.parametrize("mode", ["immediate", "latched"])
@pytest.mark.parametrize("Ts", [0.0005, 0.004])
def test_io_delay_and_valve_delays_trade_against_the_carrier_phase(mode: str, Ts: float) -> None:
    """Writes later by x, the carrier later by x (its time at the first sample less by x) and
    both valve delays shorter by x: every edge keeps its time on the log's clock
    (docs/identification.md, "Limit: IO delay against the valves' own"). With latched PWM the
    open fractions are the same to rounding; with immediate PWM they differ only where a new
    coil pulse starts while the valve is still switching from the last one, which depends on
    the valve's delay itself: at most 0.5 % of the samples of these duties (24 of 6000 at
    0.5 ms), all in the stretches with a new duty every sample."""
    p = pack_plant(PlantConfig().with_updates({"rig": {"pwm_update": mode}})).vec.copy()
    u = _duties()
    for don, doff, mp, phase, delay, x in [(2e-3, 3e-3, 1e-3, 3e-3, 1.2e-3, 0.7e-3),
                                           (4e-3, 2.5e-3, 1.5e-3, 0.011, 0.5e-3, 2.0e-3),
                                           (2e-3, 3e-3, 1e-3, 3e-3, 0.0, 0.9e-3)]:
        a, b = np.empty((1, len(u))), np.empty((1, len(u)))
        valve_open_fractions(p, u, np.array([[don, doff, mp]]), np.array([phase]), Ts, a, delay)
        valve_open_fractions(p, u, np.array([[don - x, doff - x, mp]]), np.array([phase - x]),
                             Ts, b, delay + x)
        differ = np.abs(a - b)[0] > 1e-9
        if mode == "latched":
            assert not differ.any()
        else:
            assert differ.mean() <= 0.005
            assert not differ[:430 + 40 * 33].any()  # full steps, then steady partial duties
