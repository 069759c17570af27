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

