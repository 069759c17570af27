"""Per-channel sample times: ``/rig/sensor_age`` is written when a rig's channels are sampled
at other instants than their message's time, and identify brings each channel back to the
message times before it fits anything.

The signals are smooth sines, so the expected values are known in closed form: a skew of
``a`` seconds misplaces a signal of slope ``s`` by ``a s``, while linear interpolation between
samples ``h`` apart errs by at most ``h**2 / 8`` times the curvature.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from drivers import other_sim_driver as osd

from pneutune.control.cli.record import main as record_main
from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.model import load_model
from pneutune.control.logs.reader import read_run_log
from pneutune.control.logs.recording import Recording
from pneutune.control.logs.topics import AGE_RESOLUTION
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.scenario_run import run_scenario, sim_rig_for
from pneutune.control.sim.scenarios import SCENARIOS, Scenario
from pneutune.identify import dataset as dataset_module
from pneutune.identify.cli import main as identify_main
from pneutune.identify.dataset import IdentificationError, load_dataset
from pneutune.identify.sample_times import align_channels

RIG: dict[str, float | str] = {
    "A_a": 7.854e-3, "A_b": 7.54e-3, "x_min": -0.0015, "x_max": 0.0485, "V0a": 5.036e-5,
    "V0b": 2.916e-5, "p0": 101325.0, "p_s": 6.0e5, "T0": 283.15, "n": 1.2, "R": 287.0,
    "Ts": 0.004, "pwm_hz": 60.0, "pwm_update": "immediate",
}
H = 0.0005  # logging period of an identification run [s]
#: A multiplexed ADC: x, p_a and p_b sampled 0.75, 0.5 and 0.25 periods before the message
SKEW = np.array([0.75, 0.5, 0.25, 0.0]) * H


def _truth(t: np.ndarray) -> np.ndarray:
    """Smooth channel values at times ``t`` (columns x, p_a, p_b, p_s)."""
    t = np.asarray(t, dtype=float)
    return np.column_stack([0.0235 + 0.01 * np.sin(2 * np.pi * 2.0 * t),
                            3.0e5 + 1.0e5 * np.sin(2 * np.pi * 3.0 * t),
                            3.5e5 - 1.0e5 * np.sin(2 * np.pi * 3.0 * t + 0.4),
                            np.full_like(t, 6.0e5)])


def _frames(n: int, skew: np.ndarray) -> tuple[pd.DataFrame, pd.DataFrame]:
    t = np.arange(n) * H
    values = np.column_stack([_truth(t - skew[j])[:, j] for j in range(4)])
    index = pd.Index(t, name="t")
    cols = ["x", "p_a", "p_b", "p_s"]
    return (pd.DataFrame(values, index=index, columns=cols),
            pd.DataFrame(np.tile(skew, (n, 1)), index=index, columns=cols))


def test_skewed_channels_come_back_to_the_message_times() -> None:
    sensors, ages = _frames(2000, SKEW)
    out, note = align_channels(sensors, ages)
    truth = _truth(sensors.index.to_numpy())
    inner = slice(2, -2)  # np.interp holds the last sample past the end
    err_before = np.abs(sensors.to_numpy() - truth)[inner].max(axis=0)
    err_after = np.abs(out.to_numpy() - truth)[inner].max(axis=0)
    # skew x slope: x 0.375 ms * 0.126 m/s = 47 um; p_a 0.25 ms * 1.9e6 Pa/s = 471 Pa
    assert err_before[0] == pytest.approx(4.71e-5, rel=0.01)
    assert err_before[1] == pytest.approx(471.0, rel=0.01)
    # interpolation: (0.5 ms)^2 / 8 * curvature: x 0.05 um, p_a 11 Pa
    assert err_after[0] < 1.0e-7
    assert err_after[1] < 12.0 and err_after[2] < 12.0
    assert np.array_equal(out["p_s"].to_numpy(), sensors["p_s"].to_numpy())  # age 0: untouched
    assert "x 0.375 ms" in note and "p_a 0.25 ms" in note and "p_s" not in note


def test_a_held_reading_is_interpolated_between_the_samples_it_took() -> None:
    # p_a refreshed on every other message: its age alternates 0 and one period
    n = 400
    t = np.arange(n) * H
    age = np.where(np.arange(n) % 2 == 0, 0.0, H)
    sensors = pd.DataFrame(_truth(t), index=pd.Index(t, name="t"),
                           columns=["x", "p_a", "p_b", "p_s"])
    sensors["p_a"] = _truth(t - age)[:, 1]
    ages = pd.DataFrame({"x": 0.0, "p_a": age, "p_b": 0.0, "p_s": 0.0}, index=sensors.index)
    out, note = align_channels(sensors, ages)
    err = np.abs(out["p_a"].to_numpy() - _truth(t)[:, 1])[:-1]
    # held: up to one period's change, 0.5 ms * 1.9e6 Pa/s = 940 Pa; interpolated over 1 ms:
    # (1 ms)^2 / 8 * 3.6e7 Pa/s^2 = 44 Pa
    assert np.abs(sensors["p_a"].to_numpy() - _truth(t)[:, 1]).max() > 800.0
    assert err.max() < 50.0
    assert "p_a 0.25 ms" in note  # the median of 0 and 0.5 ms


def test_no_ages_or_ages_within_a_clocks_rounding_change_nothing() -> None:
    sensors, ages = _frames(100, np.full(4, 0.5 * AGE_RESOLUTION))
    assert align_channels(sensors, None) == (sensors, "")
    out, note = align_channels(sensors, ages)
    assert out is sensors and note == ""


def test_a_sensor_message_without_its_age_counts_as_of_its_own_time() -> None:
    sensors, ages = _frames(300, SKEW)
    out, _ = align_channels(sensors, ages.iloc[::2])
    # the odd messages have no age: each is a sample at its own time, so interpolation at
    # that time returns its reading exactly
    odd = slice(1, None, 2)
    assert np.array_equal(out["x"].to_numpy()[odd], sensors["x"].to_numpy()[odd])
    assert not np.array_equal(out["x"].to_numpy()[::2], sensors["x"].to_numpy()[::2])


def _recording(n: int, skew: np.ndarray | None) -> Recording:
    rec = Recording(n, H)
    t = rec.t
    sk = np.zeros(4) if skew is None else skew
    rec.sensors_[:] = np.column_stack([_truth(t - sk[j])[:, j] for j in range(4)])
    # duties that open and close every valve in turn, so the pressures' response checks pass
    phase = (np.arange(n) // 80) % 4
    rec.duties_[:] = 0.0
    rec.duties_[np.arange(n), phase] = 0.6
    for k in range(n):
        rec.sample_ages(k, float(t[k]), t[k] - sk if skew is not None else None)
    return rec


@pytest.fixture
def logs(tmp_path) -> tuple[Path, Path]:
    """The same signals logged by a skewed rig and by one that samples every channel at once."""
    run = {"sample_period": repr(H)}
    _recording(800, SKEW).save(tmp_path / "skew.mcap", RIG, run)
    _recording(800, None).save(tmp_path / "plain.mcap", RIG, run)
    return tmp_path / "skew.mcap", tmp_path / "plain.mcap"


def test_record_writes_the_ages_only_for_a_skewed_rig(logs) -> None:
    skewed, plain = (read_run_log(path) for path in logs)
    assert not plain.has("/rig/sensor_age")
    ages = skewed["/rig/sensor_age"]
    assert np.array_equal(ages.index.to_numpy(), skewed["/rig/sensors"].index.to_numpy())
    assert np.allclose(ages.to_numpy(), SKEW, atol=1e-12)


def test_identify_reads_a_skewed_log_as_the_unskewed_one(logs) -> None:
    skewed, plain = (load_dataset(path) for path in logs)
    inner = slice(2, -2)
    # the stored log rounds x to 1 nm and pressures to 1 mPa; interpolation adds < 0.1 um, 12 Pa
    assert np.abs(skewed.x - plain.x)[inner].max() < 1.0e-7
    assert np.abs(skewed.p_a - plain.p_a)[inner].max() < 12.0
    assert np.abs(skewed.p_b - plain.p_b)[inner].max() < 12.0
    assert "sample times" in skewed.repairs and plain.repairs == ""


@pytest.mark.slow  # 17 s of the protocol at 0.5 ms through the other simulator, two identifies
def test_a_multiplexed_adc_no_longer_biases_the_mass(tmp_path, monkeypatch, capsys) -> None:
    """The other simulator (tests/drivers/other_sim_driver.py) samples x, p_a and p_b 0.3, 0.2
    and 0.1 ms before each 0.5 ms sample and says so in its sample times. Its moving mass is
    1.05 kg (``--print-plant``). Measured on this log: identify gives 1.04 kg [0.85, 1.22]; with
    the channels left where they were sampled, 1.55 kg [1.36, 1.73], whose range misses the
    truth (the position 0.2 ms behind the pressures, times b_v 3500 N s/m, is 0.7 kg)."""
    driver = Path(osd.__file__).resolve()
    rig = (f"exec:{shlex.quote(sys.executable)} {shlex.quote(str(driver))} --scenario "
           "{scenario} --seed {seed} --sample-period {sample_period} --channel-skew 0.6 0.4 0.2 0")
    log = tmp_path / "skew.mcap"
    assert record_main(["--experiment", "identification", "--segments", "rest,acceleration",
                        "--sample-period", "0.0005", "--rig", rig, "--out", str(log)]) == 0
    ages = read_run_log(log)["/rig/sensor_age"]
    assert np.allclose(ages.iloc[1:].to_numpy(), [3e-4, 2e-4, 1e-4, 0.0], atol=1e-9)
    capsys.readouterr()

    def mass(out: str) -> tuple[float, float, float]:
        assert identify_main([str(log), "--out", str(tmp_path / out)]) == 0
        theta = load_model(tmp_path / out / "model.yaml").theta
        return theta.nominal[0], theta.min[0], theta.max[0]

    m, lo, hi = mass("aligned")
    assert lo <= 1.05 <= hi and m == pytest.approx(1.05, rel=0.1)
    monkeypatch.setattr(dataset_module, "align_channels", lambda s, a: (s, ""))
    m, lo, hi = mass("skewed")
    assert lo > 1.05 and m > 1.4


def test_deploy_logs_the_ages_its_rig_reports() -> None:
    """The runtime records each reading's age from the rig's sample times (here a rig whose
    position is sampled 1 ms before each 4 ms sample); the controller still gets the readings
    as they are, so the closed loop is the one without the ages."""
    paper = load_controller(Path(__file__).resolve().parents[1] / "data"
                            / "controller-paper.yaml")
    base = SCENARIOS["sine-0.5hz"]
    sc = Scenario("sine-0.5hz-1s", base.description, 1.0, base.period, base.reference)

    class SkewedRig(DeploySimRig):
        def sample_times(self) -> np.ndarray | None:
            st = super().sample_times()
            return None if st is None else st - np.array([1e-3, 0.0, 0.0, 0.0])

    rig, _, _ = sim_rig_for(sc, seed=3)
    plain = run_scenario(paper, sc, rig).loop.recording
    rig, _, _ = sim_rig_for(sc, seed=3)
    rig.__class__ = SkewedRig
    skewed = run_scenario(paper, sc, rig).loop.recording
    assert np.array_equal(skewed.sensors_, plain.sensors_)
    assert np.allclose(skewed.ages_, [1e-3, 0.0, 0.0, 0.0], atol=1e-12)
    assert not plain.ages_.any()


def test_a_negative_age_is_refused_naming_the_field_and_time(tmp_path) -> None:
    rec = _recording(800, SKEW)
    rec.ages_[300, 2] = -1e-3
    rec.save(tmp_path / "bad.mcap", RIG, {"sample_period": repr(H)})
    with pytest.raises(IdentificationError) as info:
        load_dataset(tmp_path / "bad.mcap")
    text = str(info.value)
    assert "bad.mcap" in text and "/rig/sensor_age.p_b is -0.001 s at log time 0.150000 s" in text
