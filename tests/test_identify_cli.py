"""identify from the command line: bad logs give exit 2 and one clear line; closed-loop logs
(no segment labels, no /sim/truth) and deploy logs identify; nothing is written on failure."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.contracts.model import load_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.logs.reader import read_run_log
from pneutune.control.logs.writer import RunLogWriter

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "data" / "run.mcap"
PAPER = ROOT / "data" / "controller-paper.yaml"


def _identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pneutune.identify.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def source():
    return read_run_log(RUN)


def _write(path: Path, source, topics=("/rig/sensors", "/rig/valves"), rig=None,
           edit=None) -> Path:
    """A log made from data/run.mcap's topics, optionally edited (column arrays)."""
    run = {"seed": "1"}
    if "sample_period" in source.run:  # the identification run logs faster than rig.Ts
        run["sample_period"] = source.run["sample_period"]
    with RunLogWriter(path, rig=rig or source.rig, run=run) as w:
        for topic in topics:
            df = source[topic]
            cols = {c: df[c].to_numpy().copy() for c in df.columns}
            t = df.index.to_numpy().copy()
            if edit is not None:
                t, cols = edit(topic, t, cols)
            w.write_many(topic, t, cols)
    return path


def _still_window(source) -> tuple[float, tuple[float, float], float]:
    """(start of prepare:a, the approach onto x_min [start, end), start of the friction part) of
    an identification run: the stretches where its piston sits on an end stop."""
    seg = source["/experiment/segment"]
    at = {lab: float(t) for t, lab in zip(seg.index, seg["label"], strict=True)}
    return at["prepare:a"], (at["approach:b:x_min"], at["prepare:b"]), at["hold:start_friction"]


def _one_error_line(res: subprocess.CompletedProcess) -> str:
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.stderr
    return lines[0]


def _refusal(tmp_path, source, topic: str, change) -> str:
    """identify's one error line on data/run.mcap with ``change(columns)`` applied to the
    columns of ``topic``; nothing is written."""
    def edit(tp, t, cols):
        if tp == topic:
            change(cols)
        return t, cols

    bad = _write(tmp_path / "edited.mcap", source, edit=edit)
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert str(bad) in line and not (tmp_path / "o" / "model.yaml").exists()
    return line


def test_not_mcap(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("not a log")
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert str(bad) in line and "MCAP" in line
    assert not (tmp_path / "o").exists()


def test_cut_short(tmp_path):
    data = RUN.read_bytes()
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(data[: len(data) // 2])
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert str(bad) in line
    assert not (tmp_path / "o" / "model.yaml").exists()


def test_missing_topic(tmp_path, source):
    bad = _write(tmp_path / "novalves.mcap", source, topics=("/rig/sensors",))
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert "/rig/valves" in line


def test_nan_value(tmp_path, source):
    line = _refusal(tmp_path, source, "/rig/sensors", lambda c: c["p_a"].__setitem__(1234, np.nan))
    assert "p_a" in line and "/rig/sensors" in line


def test_time_backwards(tmp_path, source):
    """The writer refuses to write time going backwards, so the log is made by a raw MCAP
    writer here (another tool's log)."""
    from mcap.writer import Writer

    from pneutune.control.logs.topics import TOPIC_SCHEMAS

    bad = tmp_path / "back.mcap"
    with open(bad, "wb") as fh:
        w = Writer(fh)
        w.start()
        w.add_metadata("rig", {k: repr(v) if isinstance(v, float) else str(v)
                               for k, v in source.rig.items()})
        for topic, fields in (("/rig/sensors", ("x", "p_a", "p_b", "p_s")),
                              ("/rig/valves", ("u_a_in", "u_a_out", "u_b_in", "u_b_out"))):
            import json

            sid = w.register_schema(topic, "jsonschema",
                                    json.dumps(TOPIC_SCHEMAS[topic]).encode())
            cid = w.register_channel(topic, "json", sid)
            for k, ts in enumerate((0, 4_000_000, 2_000_000)):
                msg = {f: (0.01 if f == "x" else 2e5 if f.startswith("p") else 0.0)
                       for f in fields}
                w.add_message(cid, log_time=ts, publish_time=ts, sequence=k,
                              data=json.dumps(msg).encode())
        w.finish()
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert "backwards" in line or "time" in line


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_missing_rig_metadata_key(tmp_path, source):
    """The writer insists on every rig key, so this log is the shipped one with the metadata
    record rewritten through a raw MCAP writer."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    bad = tmp_path / "norig.mcap"
    with open(RUN, "rb") as src, open(bad, "wb") as dst:
        reader = make_reader(src)
        w = Writer(dst)
        w.start()
        for meta in reader.iter_metadata():
            data = dict(meta.metadata)
            if meta.name == "rig":
                data.pop("V0b")
            w.add_metadata(meta.name, data)
        ids = {}
        for schema, channel, message in reader.iter_messages():
            if channel.id not in ids:
                sid = w.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = w.register_channel(channel.topic, channel.message_encoding,
                                                     sid)
            w.add_message(ids[channel.id], log_time=message.log_time,
                          publish_time=message.publish_time, sequence=message.sequence,
                          data=message.data)
        w.finish()
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert "V0b" in line


def test_pressures_in_bar_are_implausible(tmp_path, source):
    def to_bar(cols):
        for c in ("p_a", "p_b", "p_s"):
            cols[c] /= 1e5

    line = _refusal(tmp_path, source, "/rig/sensors", to_bar)
    assert "Pa" in line and "p_a" in line


def test_valve_never_opens_is_not_identifiable(tmp_path, source):
    line = _refusal(tmp_path, source, "/rig/valves", lambda c: c["u_b_out"].fill(0.0))
    assert "b_out" in line and "never" in line


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_piston_never_moves_is_not_identifiable(tmp_path, source):
    """A log of only the valve tests, the piston on an end stop throughout: both chambers'
    tests from their preparations on, without the approach onto the second stop, which the
    log skips (its time cut out, so the piston jumps between two samples): the valves
    identify, friction does not."""
    t0, (a, b), t_end = _still_window(source)

    def edit(topic, t, cols):
        keep = (t >= t0) & (t < t_end) & ~((t >= a) & (t < b))
        t = t[keep]
        return np.where(t >= b, t - (b - a), t) - t0, {c: v[keep] for c, v in cols.items()}

    bad = _write(tmp_path / "still.mcap", source, edit=edit)
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o", "--holdout", "0.05"))
    assert "hardly moves" in line


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_closed_loop_log_without_labels_or_truth(tmp_path):
    """A real user's log: a closed-loop run (here deploy's, paper config) with only
    /rig/sensors, /rig/valves and the rig metadata. identify must run, write a model that
    validates, and say in its notes what the log cannot separate: here the mass (the pole
    b_v/M above the 4 ms Nyquist frequency) and the chambers' constant terms (their valves never
    all shut for a window). The valves do run at full duty: Eq. (33)'s full opening commands
    duty 1 (control/law/duty.py), which pins C."""
    full = tmp_path / "deploy.mcap"
    res = subprocess.run([sys.executable, "-m", "pneutune.control.cli.deploy", str(PAPER),
                          "--scenario", "sine-0.75hz", "--log", str(full), "--seed", "3"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    bare = _write(tmp_path / "bare.mcap", read_run_log(full))
    out = tmp_path / "id"
    res = _identify(bare, "--out", out)
    assert res.returncode == 0, res.stderr
    model = load_model(out / "model.yaml")
    assert (out / "report.md").exists()
    assert any(n.startswith("mass: not identifiable") for n in model.notes)
    assert any(n.startswith("D_an:") for n in model.notes)
    assert not any("never runs at full duty" in n for n in model.notes)
    # consistent with the plant it came from (log -> identify -> model)
    truth = PlantConfig()
    assert model.friction.b_v == pytest.approx(truth.friction.b_v, rel=0.15)
    for v, t in zip(model.valves.ordered(), truth.valves.ordered(), strict=True):
        assert v.C_min <= t.C <= v.C_max
    assert model.theta.min[2] <= truth.friction.b_v <= model.theta.max[2]


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_json_and_outputs(tmp_path):
    """--json prints exactly one JSON object; model.yaml and report.md with its figures land in
    --out."""
    import json

    out = tmp_path / "id"
    res = _identify(RUN, "--out", out, "--json")
    assert res.returncode == 0, res.stderr
    obj = json.loads(res.stdout)
    assert obj["schema"] == "pneutune.model/1"
    assert obj["source"]["sha256"] == read_run_log(RUN).sha256
    for name in ("model.yaml", "report.md", "valves.png", "pwm.png", "friction.png",
                 "validation.png"):
        assert (out / name).exists(), name
    # one PWM curve per valve (valves.<v>.pwm): each within 0.005 of the curve of the rig's own
    # valve timing (measured: 0.001 at most, 2026-11-24), the top-level pwm their mean
    from pneutune.control.physics.pwm import effective_open_fraction

    model = load_model(out / "model.yaml")
    truth = PlantConfig()
    curves = []
    for v, t in zip(model.valves.ordered(), truth.valves.ordered(), strict=True):
        assert v.pwm is not None
        duty, ratio = np.array(v.pwm.duty), np.array(v.pwm.ratio)
        true = effective_open_fraction(duty, truth.rig.pwm_period, t.delay_on, t.delay_off,
                                       t.min_pulse)
        np.testing.assert_allclose(ratio, true, atol=0.005)
        curves.append(ratio)
    np.testing.assert_allclose(model.pwm.ratio, np.maximum.accumulate(np.mean(curves, axis=0)),
                               atol=1e-6)


def test_mass_below_any_cylinder_is_refused(tmp_path):
    """--mass takes the rig.mass hint's range (1 g to 1000 kg): a nanogram mass would make
    every simulation of the model take steps of femtoseconds (the run never ends)."""
    line = _one_error_line(_identify(RUN, "--mass", "1e-9", "--out", tmp_path / "o"))
    assert "--mass" in line and "[0.001, 1000] kg" in line


def test_stuck_chamber_sensor(tmp_path, source):
    """A chamber pressure that never moves while its valves open is a sensor fault, refused
    before any fit (the fits would otherwise turn it into nonsense friction)."""
    line = _refusal(tmp_path, source, "/rig/sensors", lambda c: c["p_a"].fill(3.5e5))
    assert "/rig/sensors.p_a" in line and "stuck" in line


def test_supply_reading_below_the_chambers(tmp_path, source):
    """A supply reading at ambient while the chambers reach several bar: the supply sensor
    is wrong, and the valve fits (which use it) would be too."""
    line = _refusal(tmp_path, source, "/rig/sensors", lambda c: c["p_s"].fill(1.01325e5))
    assert "supply reading" in line and "1.013 bar" in line


@pytest.mark.parametrize("how", ["cut short", "every fourth control period"])
def test_valve_commands_missing(tmp_path, source, how):
    """Duties must be known at every sample: a valve topic that stops early, or skips control
    periods, is refused with where the commands are missing."""
    def edit(topic, t, cols):
        if topic != "/rig/valves":
            return t, cols
        if how == "cut short":
            keep = t < 0.5 * t[-1]
        else:  # the log samples every 0.5 ms: one message in 32 is one every 16 ms
            keep = np.arange(t.size) % 32 == 0
        return t[keep], {c: v[keep] for c, v in cols.items()}

    bad = _write(tmp_path / "valves.mcap", source, edit=edit)
    line = _one_error_line(_identify(bad, "--out", tmp_path / "o"))
    assert "/rig/valves has no message from" in line and "once per control period" in line
