"""identify.prediction: the one-sample predictors reproduce the simulator they are built on.

On a noise-free open-loop run of the compiled plant, restarting the same plant from each
measured sample must land on the next sample exactly (the predictor and the simulator share
control.plant). A wrong mass or wrong valve delays must show, or the test could not fail.
"""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import P_DOFF, P_DON, P_M, pack_plant
from pneutune.identify.prediction import position_innovations, pressure_residuals

TS = 0.004


@pytest.fixture(scope="module")
def run():
    """2.4 s of alternating PWM drives (both directions, several duties), no sensor noise."""
    cfg = PlantConfig().with_updates({"sensors": {"x_noise": 0.0, "x_step": 0.0,
                                                  "p_noise": 0.0}})
    pp = pack_plant(cfg)
    blocks = [([0.6, 0, 0, 1.0], 80), ([0, 0.45, 0.7, 0], 100), ([1.0, 0, 0, 0.3], 60),
              ([0, 1.0, 0.5, 0], 100), ([0.2, 0.2, 0.2, 0.2], 60)]
    duties = np.vstack([np.tile(np.array(d, float), (n, 1)) for d, n in blocks])
    n = duties.shape[0]
    x0 = 0.5 * (cfg.rig.x_min + cfg.rig.x_max)
    pa0, pb0 = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, x0, pa0, pb0)
    sensors, truth = np.zeros((n, 4)), np.zeros((n, 6))
    plant.run_open_loop(pp.vec, s, duties, np.full(n, cfg.rig.p_s), pp.force_steps,
                        np.zeros((n, 4)), TS, sensors, truth)
    t = np.arange(n) * TS
    return pp, t, sensors, duties, truth


def _pressure_rms(p: np.ndarray, run) -> float:
    pp, t, y, u, _ = run
    ra, rb = np.zeros((1, len(t))), np.zeros((1, len(t)))
    pressure_residuals(p[None, :], pp.force_steps, t, y[:, 0], y[:, 1], y[:, 2], y[:, 3], u,
                       ra, rb)
    return float(np.sqrt(np.mean(ra**2 + rb**2)))


def _innovation_rms(p: np.ndarray, run) -> float:
    pp, t, y, u, _ = run
    out = np.zeros((1, len(t)))
    position_innovations(p[None, :], pp.force_steps, t, y[:, 0], y[:, 1], y[:, 2], y[:, 3], u,
                         np.array([0], np.int64), np.array([len(t)], np.int64), 0.3, out)
    return float(np.sqrt(np.mean(out**2)))


def test_the_run_moves(run):
    """The drive pattern really slides the piston (else the test below proves nothing)."""
    *_, truth = run
    assert np.max(np.abs(truth[:, 0])) > 0.05  # m/s


def test_true_plant_predicts_every_sample_exactly(run):
    """The true plant restarted at each sample: pressure errors below 1e-3 Pa (the sensor
    noise of a real rig is ~300 Pa), position innovations below 1e-9 m (both measured 0.0)."""
    pp = run[0]
    assert _pressure_rms(pp.vec, run) < 1.0e-3
    assert _innovation_rms(pp.vec, run) < 1.0e-9


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_wrong_delays_and_mass_show(run):
    """Delays 0.2 ms late leave pressure errors of hundreds of Pa (≈ 0.2 ms × dp/dt; measured
    469 Pa rms); twice the mass, a lag 0.3 ms longer, leaves position innovations of microns
    (measured 7.4 µm rms)."""
    pp = run[0]
    late = pp.vec.copy()
    late[P_DON:P_DON + 4] += 2.0e-4
    late[P_DOFF:P_DOFF + 4] += 2.0e-4
    assert _pressure_rms(late, run) > 50.0
    heavy = pp.vec.copy()
    heavy[P_M] *= 2.0
    assert _innovation_rms(heavy, run) > 1.0e-6


def test_stretches_outside_the_log_are_refused(run):
    """position_innovations checks its stretches (numba would read memory silently)."""
    pp, t, y, u, _ = run
    out = np.zeros((1, len(t)))
    for starts, ends in (([0], [len(t) + 1]), ([5], [5]), ([-1], [10])):
        with pytest.raises(ValueError):
            position_innovations(pp.vec[None, :], pp.force_steps, t, y[:, 0], y[:, 1], y[:, 2],
                                 y[:, 3], u, np.array(starts, np.int64),
                                 np.array(ends, np.int64), 0.3, out)
