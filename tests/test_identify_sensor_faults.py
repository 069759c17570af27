"""What identify checks of a log's signals before it trusts them, and the slips of a logger
it repairs: the sensor samples are evenly spaced (a few missing or duplicated samples are
repaired), the valve commands cover every sample, the force balance has the right sign, the
rig metadata's supply agrees with the supply reading, and the rig.mass hint lies in its
range."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mcap.records import Metadata

from pneutune.control.errors import LogSchemaError
from pneutune.control.logs.metadata import parse_rig_hints
from pneutune.identify.dataset import (
    IdentificationError,
    check_valve_coverage,
    load_dataset,
    regular_samples,
    supply_note,
)
from pneutune.identify.friction_choice import check_force_balance
from pneutune.identify.motion import FrictionIdentifier

RUN = Path(__file__).resolve().parents[1] / "data" / "run.mcap"


@pytest.fixture(scope="module")
def dataset():
    """data/run.mcap (the paper's rig, an identification run) at the control instants."""
    return load_dataset(RUN).at_control_rate()


def test_valves_at_the_control_rate_cover_faster_sensors():
    """Sensors every 0.5 ms, duties once per 4 ms control period (zero-order hold): accepted;
    with jitter of a tenth of a period too."""
    ts = np.arange(0.0, 2.0, 5e-4)
    tv = np.arange(0.0, 2.0, 4e-3)
    check_valve_coverage("log", ts, tv, 4e-3)
    jitter = np.random.default_rng(1).uniform(-4e-4, 4e-4, tv.size)
    jitter[0] = 0.0
    check_valve_coverage("log", ts, tv + jitter, 4e-3)


@pytest.mark.parametrize(("tv", "where"), [
    (np.arange(0.02, 2.0, 4e-3), "from t = 0.000000 s to 0.020000 s"),  # starts late
    (np.arange(0.0, 1.0, 4e-3), "from t = 0.996000 s to 1.999500 s"),  # stops early
    (np.concatenate([np.arange(0.0, 0.5, 4e-3), np.arange(0.6, 2.0, 4e-3)]),
     "from t = 0.496000 s to 0.600000 s"),  # a gap of 26 periods
])
def test_valve_gaps_are_named(tv, where):
    ts = np.arange(0.0, 2.0, 5e-4)
    with pytest.raises(IdentificationError) as info:
        check_valve_coverage("log.mcap", ts, tv, 4e-3)
    assert where in str(info.value) and "log.mcap" in str(info.value)


def test_force_balance_runs_backwards_when_the_chambers_are_swapped(dataset):
    """On the paper's rig the smooth friction fit gives θ3 = b_v near 3500 N s/m (its true
    3500); with p_a and p_b exchanged it gives about -3570 N s/m, far beyond its bootstrap
    uncertainty (about 130 N s/m), and identify stops with what to check."""
    mask = np.ones(dataset.n, bool)
    right = FrictionIdentifier(mass=1.0).fit(dataset, mask)
    check_force_balance("run.mcap", right, right.smooth_bootstrap(n_boot=50, block=50, seed=1))
    assert right.smooth_[1] == pytest.approx(3500.0, rel=0.05)
    swapped = dataclasses.replace(dataset, p_a=dataset.p_b, p_b=dataset.p_a)
    wrong = FrictionIdentifier(mass=1.0).fit(swapped, mask)
    with pytest.raises(IdentificationError) as info:
        check_force_balance("run.mcap", wrong,
                            wrong.smooth_bootstrap(n_boot=50, block=50, seed=1))
    assert "runs backwards" in str(info.value) and "p_a is chamber A" in str(info.value)


def test_supply_note_names_metadata_and_reading(dataset):
    """The shipped log's metadata and reading agree (6 bar); metadata in gauge pressure
    (4.99 bar 'absolute' against a 6 bar reading) is noted with both figures."""
    assert supply_note(dataset) is None
    gauge = dataclasses.replace(
        dataset, rig=dataset.rig.model_copy(update={"p_s": dataset.rig.p_s - dataset.rig.p0}))
    note = supply_note(gauge)
    assert note is not None
    assert "p_s = 4.987 bar" in note and "median of 6 bar" in note


@pytest.mark.parametrize("text", ["1e-9", "0", "1e9", "-2", "heavy"])
def test_rig_mass_hint_outside_its_range(text):
    with pytest.raises(LogSchemaError) as info:
        parse_rig_hints("log.mcap", [Metadata(name="rig", metadata={"mass": text})])
    assert "within [0.001, 1000]" in str(info.value)
    assert parse_rig_hints("log.mcap", [Metadata(name="rig", metadata={"mass": "1.6"})]) == {
        "mass": 1.6}


def _sensors(t: np.ndarray) -> pd.DataFrame:
    """Sensor columns linear in time (so that linear interpolation restores them exactly)."""
    return pd.DataFrame({"x": 0.01 + 0.02 * t, "p_a": 2e5 + 1e4 * t, "p_b": 3e5 - 1e4 * t,
                         "p_s": np.full(t.size, 6e5)}, index=pd.Index(t, name="t"))


def test_a_loggers_slips_are_repaired_and_said():
    """1000 samples every 4 ms with three missing in a row, one more missing alone, and two
    logged twice (6 repairs, under the 1 % allowed): the samples come back evenly spaced,
    the filled ones on the line, and the note counts both kinds."""
    Ts = 4e-3
    full = np.arange(1000) * Ts
    t = np.delete(full, [100, 101, 102, 500])
    t = np.sort(np.r_[t, t[300], t[700]])
    out, note = regular_samples(_sensors(t), Ts)
    np.testing.assert_allclose(out.index.to_numpy(), full, atol=1e-12)
    pd.testing.assert_frame_equal(out, _sensors(out.index.to_numpy()), rtol=1e-12)
    assert "4 missing sample(s) in 2 gap(s) (the first after t = 0.396000 s)" in note
    assert "2 duplicated sample(s) dropped" in note


@pytest.mark.parametrize("cut", [
    [100, 101, 102, 103],  # four missing in a row: more than MAX_FILL
    list(range(100, 300, 2))[:11],  # 11 single gaps in 1000 samples: more than 1 %
])
def test_more_than_a_slip_is_left_for_the_check_to_refuse(cut):
    Ts = 4e-3
    s = _sensors(np.delete(np.arange(1000) * Ts, cut))
    out, note = regular_samples(s, Ts)
    assert out is s and note == ""


def test_unix_time_stamps_count_from_the_first_sample(tmp_path):
    """MCAP recorders stamp messages in Unix time (here 2025-11-24, 1.764e9 s). identify
    counts from the first sensor sample, so its simulations keep microsecond clocks: the
    closed-loop log of the paper's rig stamped so gave the held-out NRMSE 0.062/0.060/0.027
    (x/p_a/p_b) before, 0.006/0.015/0.017 after, as the log stamped from zero."""
    from pneutune.control.contracts.plant import PlantConfig
    from pneutune.control.logs.writer import RunLogWriter

    n, Ts, epoch = 600, 4e-3, 1.764e9
    k = np.arange(n)
    t = epoch + k * Ts
    wave = np.sin(2 * np.pi * 0.5 * k * Ts)
    path = tmp_path / "unix.mcap"
    with RunLogWriter(path, rig=PlantConfig().rig_metadata(), run={"seed": "1"}) as w:
        w.write_many("/rig/sensors", t, {"x": 0.0235 + 0.0175 * wave,
                                         "p_a": 3.5e5 + 1e5 * wave, "p_b": 3.5e5 - 1e5 * wave,
                                         "p_s": np.full(n, 6e5)})
        w.write_many("/rig/valves", t, {"u_a_in": np.clip(wave, 0, 1),
                                        "u_a_out": np.clip(-wave, 0, 1),
                                        "u_b_in": np.clip(-wave, 0, 1),
                                        "u_b_out": np.clip(wave, 0, 1)})
        for j, label in ((0, "first"), (300, "second")):
            w.write("/experiment/segment", t[j], {"label": label, "kind": "hold", "params": {}})
    d = load_dataset(path)
    assert d.t[0] == 0.0
    np.testing.assert_allclose(d.t, k * Ts, atol=1e-6)  # float seconds of 1.7e9: 0.24 us
    assert [(round(s, 6), lab) for s, lab, _ in d.segments] == [(0.0, "first"), (1.2, "second")]
