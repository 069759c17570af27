"""The lag estimate of the moving mass (identify/mass.py) and the fast identification log.

The analytic checks come from the first-order lag 1/(1 + s tau); the end-to-end ones from
simulated identification runs, whose truth is the plant.yaml they were simulated from.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError
from pneutune.control.rig.identification_run import (
    IDENT_SAMPLE_PERIOD,
    Segment,
    run_protocol,
    samples_per_control,
    simulate_identification,
)
from pneutune.control.rig.simrig import SimRig
from pneutune.identify.dataset import load_dataset
from pneutune.identify.mass import lag_filter, lag_filter3, sliding_windows
from pneutune.identify.pipeline import identify


@pytest.mark.parametrize("tau", [1e-4, 3e-4, 2e-3])
def test_lag_filter_is_exact_on_a_ramp(tau):
    """For u = t the lag's output is t - tau (1 - exp(-t/tau)) (steady state at t = 0): exact
    for an input linear between samples, whatever the sample period (0.5 ms here)."""
    h = 5e-4
    t = np.arange(400) * h
    y = lag_filter(t, tau, h)
    assert y == pytest.approx(t - tau * (1.0 - np.exp(-t / tau)), abs=1e-12)


@pytest.mark.parametrize("tau", [5e-6, 3e-4, 0.05])
def test_lag_filters_are_scipys_lfilter_bit_for_bit(tau):
    """The compiled filters give the floats of the scipy.signal.lfilter form they replace, on
    rough signals; lag_filter3 the same at the samples kept."""
    from scipy.signal import lfilter

    h = 5e-4
    rng = np.random.default_rng(7)
    signals = np.stack([np.cumsum(rng.normal(size=5000)) * 1e3,
                        np.cumsum(np.sign(rng.normal(size=5000))) * h,
                        np.arange(5000) * h])
    phi = np.exp(-h / tau)
    c = tau * (1.0 - phi) / h
    rows = np.flatnonzero(rng.uniform(size=5000) < 0.4)
    lagged = lag_filter3(signals, tau, h, rows)
    for u, kept in zip(signals, lagged, strict=True):
        ref = lfilter([1.0 - c, c - phi], [1.0, -phi], u - u[0]) + u[0]
        assert np.array_equal(lag_filter(u, tau, h), ref)
        assert np.array_equal(kept, ref[rows])


def test_sliding_windows():
    """Stretches lose `trim` samples at each end and are cut into windows of `length`; a
    remainder of half a window or more is a window of its own, a shorter one is dropped."""
    ok = np.zeros(40, dtype=bool)
    ok[2:30] = True                      # 28 samples -> 24 after trimming 2 at each end
    g = sliding_windows(ok, length=10, trim=2)
    assert np.count_nonzero(g == 0) == 10 and np.count_nonzero(g == 1) == 10
    assert g.max() == 1                  # the remainder of 4 < 5 is dropped
    assert (g[:4] == -1).all() and (g[28:] == -1).all()
    ok[30:36] = True                     # now 34 -> 30 samples: three whole windows
    assert sliding_windows(ok, length=10, trim=2).max() == 2


def test_samples_per_control():
    """The logging period must divide the control period."""
    assert samples_per_control(0.004, 0.0005) == 8
    assert samples_per_control(0.004, 0.004) == 1
    for bad in (0.0003, 0.005, 0.0):
        with pytest.raises(ExperimentError):
            samples_per_control(0.004, bad)


@pytest.fixture(scope="module")
def short_fast_log(tmp_path_factory):
    """Two seconds of a position loop and fixed duties, control every 4 ms, logged every
    0.5 ms."""
    plant = PlantConfig()
    fast = plant.with_updates({"rig": {"Ts": IDENT_SAMPLE_PERIOD}})
    segs = [Segment("rest", "rest", 0.3, {}, np.zeros(4)),
            Segment("hold", "hold", 1.7, {}, None, lambda t: (0.03 + 0.005 * t, 0.005, 0.0))]
    rec = run_protocol(SimRig(fast, seed=3), segs, band=0.0025, per_control=8)
    path = tmp_path_factory.mktemp("fast") / "run.mcap"
    rec.save(path, rig=plant.rig_metadata(), run={"seed": "3"})
    return path, rec


def test_fast_log_states_its_period(short_fast_log):
    """The log keeps rig.Ts = 4 ms (the control period) and says sample_period = 0.0005."""
    path, rec = short_fast_log
    d = load_dataset(path)
    assert d.rig.Ts == 0.004 and d.Ts == pytest.approx(5e-4)
    assert d.n == rec.n == 4000


def test_at_control_rate_is_exact(short_fast_log):
    """The duties change only every 8th sample, so the control-rate view is every 8th sample,
    4 ms apart, with the duties in force over each of its periods."""
    path, _ = short_fast_log
    d = load_dataset(path)
    c = d.at_control_rate()
    assert c.n == 500 and c.Ts == 0.004
    assert np.diff(c.t) == pytest.approx(np.full(499, 0.004))
    assert np.array_equal(c.u, d.u[::8]) and np.array_equal(c.x, d.x[::8])
    blocks = d.u.reshape(500, 8, 4)
    assert (blocks == blocks[:, :1, :]).all()
    assert np.ptp(c.u[:, 0]) > 0.0  # the loop did move the duties


@pytest.mark.parametrize("value", ["abc", "0.01", "-0.0005", "nan"])
def test_bad_sample_period_is_one_line(tmp_path, short_fast_log, value):
    """A sample_period that is not a decimal in (0, rig.Ts]: exit 2, one line naming it."""
    _, rec = short_fast_log
    path = tmp_path / "bad.mcap"
    rec.save(path, rig=PlantConfig().rig_metadata(), run={"sample_period": value})
    out = subprocess.run([sys.executable, "-m", "pneutune.identify.cli", str(path),
                          "--out", str(tmp_path / "o")], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "sample_period" in lines[0], out.stderr
    assert not (tmp_path / "o").exists()


def test_controller_rate_log_keeps_the_mass_honest(tmp_path):
    """At the control period (4 ms, 4 samples per PWM period) the lag is not resolved: the
    lag estimator declines, the mass is flagged not identifiable and its range contains the
    truth (docs/identifiability.md)."""
    plant = PlantConfig()
    rec = simulate_identification(plant, seed=2, sample_period=plant.rig.Ts)
    rec.save(tmp_path / "run.mcap", rig=plant.rig_metadata(), run={"seed": "2"})
    r = identify(tmp_path / "run.mcap")
    lo, hi = r.model.mass_range
    assert lo <= plant.total_mass <= hi
    assert any(n.startswith("mass: not identifiable") for n in r.model.notes)
    assert "lag" not in r.mass_basis
