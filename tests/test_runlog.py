"""Run log, contract 1 (``pneutune.log/1``): round trip, and every way a file can be bad.

Bad files are built with the ``mcap`` package's own writer (not with :class:`RunLogWriter`), so
the reader is tested against files it did not write. Expected values are the values written;
the rig values are the paper's rig (Qian et al. 2014, Sec. 5.1, = plant.yaml's defaults,
contract 2).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from pneutune.control.constants import LOG_SCHEMA, RIG_KEYS
from pneutune.control.errors import (
    EmptyLogError,
    LogError,
    LogSchemaError,
    MissingMetadataError,
    MissingTopicError,
    NonFiniteValueError,
    NotMcapError,
    TimeOrderError,
    TruncatedLogError,
)
from pneutune.control.logs.decode import _bulk_numeric
from pneutune.control.logs.mcap_json import JsonDecoderFactory, decode_json, encode_json
from pneutune.control.logs.reader import MCAP_MAGIC, RunLog, read_run_log
from pneutune.control.logs.topics import TOPIC_SCHEMAS, TOPIC_SPECS, TOPICS
from pneutune.control.logs.writer import RunLogWriter

# The paper's rig (Sec. 5.1; plant.yaml's defaults, contract 2).
RIG: dict[str, float | str] = {
    "A_a": 7.854e-3, "A_b": 7.54e-3, "x_min": -0.0015, "x_max": 0.0485, "V0a": 5.036e-5,
    "V0b": 2.916e-5, "p0": 101325.0, "p_s": 6.0e5, "T0": 283.15, "n": 1.2, "R": 287.0,
    "Ts": 0.004, "pwm_hz": 60.0, "pwm_update": "immediate",
}
RIG_MD = {k: (v if isinstance(v, str) else repr(v)) for k, v in RIG.items()}
RUN_MD = {"schema": LOG_SCHEMA, "created_by": "test", "version": "0"}

FIELDS = {
    "/rig/sensors": ("x", "p_a", "p_b", "p_s"),
    "/rig/sensor_age": ("x", "p_a", "p_b", "p_s"),
    "/rig/valves": ("u_a_in", "u_a_out", "u_b_in", "u_b_out"),
    "/control/reference": ("x_r", "v_r", "a_r"),
    "/control/state": (
        "e1", "e2", "e3", "x_hat", "v_hat", "a_hat", "F_pd", "dF_pd", "Q_Ld", "theta_hat",
    ),
    "/sim/truth": ("v", "a", "F_friction", "F_ext", "mdot_a", "mdot_b"),
}
SENSORS = {"x": 0.0235, "p_a": 3.5e5, "p_b": 3.6e5, "p_s": 6.0e5}
VALVES = {"u_a_in": 0.25, "u_a_out": 0.0, "u_b_in": 0.0, "u_b_out": 0.25}


# -- helpers ---------------------------------------------------------------------------------


def js(**fields: Any) -> bytes:
    """Compact JSON of a message, as another writer might produce it."""
    return json.dumps(fields, separators=(",", ":")).encode()


def write_raw(
    path: Path,
    messages: Iterable[tuple[str, int, bytes]],
    *,
    rig: dict[str, str] | None = RIG_MD,
    run: dict[str, str] | None = RUN_MD,
    schema_encoding: str = "jsonschema",
    message_encoding: str = "json",
    chunked: bool = True,
    compression: CompressionType = CompressionType.ZSTD,
    crcs: bool = True,
) -> Path:
    """Write an MCAP file with the mcap package's writer: (topic, log time ns, payload)."""
    with open(path, "wb") as fh:
        writer = Writer(
            fh, compression=compression, use_chunking=chunked, enable_crcs=crcs,
            enable_data_crcs=crcs,
        )
        writer.start()
        if rig is not None:
            writer.add_metadata("rig", rig)
        if run is not None:
            writer.add_metadata("run", run)
        channels: dict[str, int] = {}
        for topic, ns, payload in messages:
            if topic not in channels:
                schema = json.dumps(TOPIC_SCHEMAS.get(topic, {})).encode()
                sid = writer.register_schema(topic, schema_encoding, schema)
                channels[topic] = writer.register_channel(topic, message_encoding, sid)
            writer.add_message(channels[topic], ns, payload, ns)
        writer.finish()
    return path


def minimal(extra: Iterable[tuple[str, int, bytes]] = ()) -> list[tuple[str, int, bytes]]:
    """Two samples of the required topics, plus ``extra``."""
    msgs = []
    for ns in (0, 4_000_000):
        msgs.append(("/rig/sensors", ns, js(**SENSORS)))
        msgs.append(("/rig/valves", ns, js(**VALVES)))
    return msgs + list(extra)


def expect(cls: type[LogError], path: Path, *fragments: str, **kwargs: Any) -> LogError:
    """Read ``path``, expect exactly ``cls``, and check the message names file and fragments."""
    with pytest.raises(LogError) as info:
        read_run_log(path, **kwargs)
    assert type(info.value) is cls, f"{type(info.value).__name__}: {info.value}"
    text = str(info.value)
    assert str(path) in text
    for fragment in fragments:
        assert fragment in text, text
    return info.value


def small_log(path: Path, n: int = 3) -> tuple[Path, dict[str, int]]:
    """A short log with every topic, written by RunLogWriter; returns path and counts."""
    t = np.arange(n) * 0.004
    with RunLogWriter(path, RIG, {"seed": "7"}) as log:
        log.write("/experiment/segment", 0.0, {"label": "hold", "kind": "hold", "params": {}})
        for topic, names in FIELDS.items():
            cols = {}
            for k, name in enumerate(names):
                if name == "theta_hat":
                    cols[name] = np.tile([0.9389, 0.0, 3500.0, 100.0, 0.0, 0.0], (n, 1))
                else:
                    cols[name] = np.linspace(0.1 * k, 0.1 * k + 1.0, n)
            log.write_many(topic, t, cols)
        log.write("/rig/events", 0.008, {"level": "info", "code": "end", "message": "done"})
        counts = log.message_counts
    return path, counts


# -- round trip ------------------------------------------------------------------------------


def test_round_trip_every_topic(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    n = 50
    rng = np.random.default_rng(20140101)
    t = np.arange(n) * 0.004  # Ts of the paper's rig
    written: dict[str, dict[str, np.ndarray]] = {}
    with RunLogWriter(path, RIG, {"seed": "7", "created_by": "test_runlog"}) as log:
        log.write("/experiment/segment", 0.0,
                  {"label": "chirp-1", "kind": "chirp", "params": {"f0_hz": 0.1, "n": [1, 2]}})
        for topic, names in FIELDS.items():
            cols = {name: rng.normal(size=(n, 6) if name == "theta_hat" else n) for name in names}
            written[topic] = cols
            log.write_many(topic, t, cols)
        log.write("/rig/events", 0.1, {"level": "warning", "code": "x_limit", "message": "ä"})
    assert sorted(os.listdir(tmp_path)) == ["run.mcap"]  # no temporary file left

    run_log = read_run_log(path)
    assert isinstance(run_log, RunLog) and run_log.path == str(path)
    assert set(run_log.topics) == set(TOPICS)
    assert all(run_log.has(topic) for topic in TOPICS)
    for topic, cols in written.items():
        frame = run_log[topic]
        assert frame.index.name == "t"
        assert frame.index.dtype == np.float64
        np.testing.assert_array_equal(frame.index.to_numpy(), np.round(t * 1e9) / 1e9)
        for name, values in cols.items():
            if name == "theta_hat":
                got = frame[[f"theta_hat_{k}" for k in range(6)]].to_numpy()
            else:
                got = frame[name].to_numpy()
            np.testing.assert_array_equal(got, values)  # bit for bit
    seg = run_log["/experiment/segment"]
    assert list(seg.columns) == ["label", "kind", "params"]
    assert seg["params"].iloc[0] == {"f0_hz": 0.1, "n": [1, 2]}
    assert seg.index[0] == 0.0
    events = run_log["/rig/events"]
    assert events.iloc[0].to_dict() == {"level": "warning", "code": "x_limit", "message": "ä"}
    assert events.index[0] == 0.1
    assert run_log.rig == RIG
    assert run_log.run == {"seed": "7", "created_by": "test_runlog", "schema": LOG_SCHEMA,
                           "version": run_log.run["version"]}
    assert len(run_log.sha256) == 64


def test_rig_numbers_round_trip_exactly(tmp_path: Path) -> None:
    rig = dict(RIG, V0a=0.1 + 0.2, R=float(np.nextafter(287.0, 300.0)), pwm_update="latched")
    path = tmp_path / "run.mcap"
    with RunLogWriter(path, rig, {}) as log:
        log.write("/rig/sensors", 0.0, SENSORS)
        log.write("/rig/valves", 0.0, VALVES)
    got = read_run_log(path).rig
    assert got == rig
    assert got["V0a"] == 0.30000000000000004  # repr(0.1 + 0.2), not 0.3


def test_time_is_rounded_to_nearest_nanosecond(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with RunLogWriter(path, RIG, {}) as log:
        for t in (0.0, 1.6e-9, 0.0040000004, 1.0):
            log.write("/rig/sensors", t, SENSORS)
        log.write_many("/rig/valves", np.array([1.6e-9, 2.0000000006]),
                       {k: np.full(2, v) for k, v in VALVES.items()})
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        ns = {topic: [] for topic in ("/rig/sensors", "/rig/valves")}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            assert message.publish_time == message.log_time
            ns[channel.topic].append(message.log_time)
    # 1.6 ns rounds up to 2 (truncation would give 1); 4000000.4 ns rounds down.
    assert ns["/rig/sensors"] == [0, 2, 4_000_000, 1_000_000_000]
    assert ns["/rig/valves"] == [2, 2_000_000_001]
    frame = read_run_log(path)["/rig/sensors"]
    np.testing.assert_array_equal(frame.index.to_numpy(), [0.0, 2e-9, 0.004, 1.0])


def test_single_writes_equal_bulk_writes(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    cols = {name: rng.normal(size=(5, 6) if name == "theta_hat" else 5)
            for name in FIELDS["/control/state"]}
    cols["e1"][2] = np.inf
    t = np.arange(5) * 0.004
    paths = []
    for mode in ("single", "bulk"):
        path = tmp_path / f"{mode}.mcap"
        with RunLogWriter(path, RIG, {}) as log:
            log.write("/rig/sensors", 0.0, SENSORS)
            log.write("/rig/valves", 0.0, VALVES)
            if mode == "bulk":
                log.write_many("/control/state", t, cols)
            else:
                for i in range(5):
                    log.write("/control/state", float(t[i]),
                              {k: (list(v[i]) if v.ndim == 2 else v[i]) for k, v in cols.items()})
        paths.append(path)
    payloads = []
    for path in paths:
        with open(path, "rb") as fh:
            payloads.append([m.data for _, c, m in make_reader(fh).iter_messages()
                             if c.topic == "/control/state"])
    assert payloads[0] == payloads[1]
    assert b'"e1":null' in payloads[0][2]  # +inf is written as null


def test_file_layout_for_other_readers(tmp_path: Path) -> None:
    """Channels, schemas, metadata and compression as contract 1 says, seen by mcap's reader."""
    path, counts = small_log(tmp_path / "run.mcap")
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[JsonDecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        assert summary is not None
        assert header.profile == ""
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert sorted(c.topic for c in summary.channels.values()) == sorted(counts)
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json"
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data) == TOPIC_SCHEMAS[channel.topic]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert metadata["rig"] == RIG_MD
        assert metadata["run"]["schema"] == LOG_SCHEMA and metadata["run"]["seed"] == "7"
        seen: dict[str, int] = {}
        for _, channel, _, decoded in reader.iter_decoded_messages():
            assert set(decoded) == set(TOPIC_SCHEMAS[channel.topic]["required"])
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
    assert seen == counts


def test_topic_schemas_describe_contract_1() -> None:
    assert set(TOPIC_SCHEMAS) == set(TOPICS) == set(FIELDS) | {"/experiment/segment",
                                                                "/rig/events"}
    for topic, schema in TOPIC_SCHEMAS.items():
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert schema["type"] == "object"
        assert schema["required"] == list(schema["properties"])
        assert schema["additionalProperties"] is False
        for name, prop in schema["properties"].items():
            assert prop["description"], (topic, name)
            if prop["type"] in ("number", "array"):
                assert "[" in prop["description"], f"{topic}.{name}: no unit"
                assert "null" in prop["description"]
    for topic, names in FIELDS.items():
        assert tuple(TOPIC_SCHEMAS[topic]["required"]) == names
    theta = TOPIC_SCHEMAS["/control/state"]["properties"]["theta_hat"]
    assert (theta["type"], theta["minItems"], theta["maxItems"]) == ("array", 6, 6)
    assert TOPIC_SCHEMAS["/rig/events"]["properties"]["level"]["enum"] == [
        "info", "warning", "error"]
    assert TOPIC_SCHEMAS["/experiment/segment"]["properties"]["params"]["type"] == "object"


def test_mcap_json_codec() -> None:
    assert encode_json({"a": 1.5, "b": "é"}) == '{"a":1.5,"b":"é"}'.encode()
    with pytest.raises(ValueError):
        encode_json({"a": math.nan})
    assert decode_json(b'{"a":[1,2.5,null]}') == {"a": [1, 2.5, None]}
    with pytest.raises(ValueError):
        decode_json(b"\xff")
    factory = JsonDecoderFactory()
    assert factory.decoder_for("json", None) is decode_json
    assert factory.decoder_for("cdr", None) is None


# -- non-finite values -----------------------------------------------------------------------


def test_nonfinite_is_written_as_null_and_rejected(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with RunLogWriter(path, RIG, {}) as log:
        log.write_many("/rig/sensors", np.array([0.0, 0.004, 0.008]),
                       {"x": np.array([0.01, np.nan, 0.02]), "p_a": np.array([1.0, 2.0, np.inf]),
                        "p_b": np.full(3, 3.0), "p_s": np.full(3, -np.inf)})
        log.write("/rig/valves", 0.0, VALVES)
    with open(path, "rb") as fh:
        data = [m.data for _, c, m in make_reader(fh).iter_messages() if c.topic == "/rig/sensors"]
    assert data[1] == b'{"x":null,"p_a":2.0,"p_b":3.0,"p_s":null}'
    expect(NonFiniteValueError, path, "/rig/sensors", "x", "t=0.004000000 s")
    frame = read_run_log(path, allow_nonfinite=True)["/rig/sensors"]
    np.testing.assert_array_equal(frame["x"].to_numpy(), [0.01, np.nan, 0.02])
    assert np.isnan(frame["p_a"].iloc[2])  # +inf reads back as NaN
    assert frame["p_s"].isna().all()


@pytest.mark.parametrize(
    ("payload", "field", "what"),
    [
        (b'{"x":null,"p_a":1.0,"p_b":1.0,"p_s":1.0}', "x", "(null or NaN)"),
        (b'{"x":0.0,"p_a":NaN,"p_b":1.0,"p_s":1.0}', "p_a", "(null or NaN)"),  # non-standard
        (b'{"x":0.0,"p_a":1.0,"p_b":-Infinity,"p_s":1.0}', "p_b", "(-Infinity"),
        (b'{"x":0.0,"p_a":1.0,"p_b":1.0,"p_s":1e999}', "p_s", "(+Infinity"),  # overflows
        (b'{"p_s":1.0,"x":0.0,"p_a":1.0,"p_b":null}', "p_b", "(null or NaN)"),  # key order
    ],
)
def test_nonfinite_from_other_writers(tmp_path: Path, payload: bytes, field: str,
                                      what: str) -> None:
    """The message names the field, the time and what the file holds (the command line has
    no allow_nonfinite, so the message does not tell the user to pass it)."""
    path = write_raw(tmp_path / "nf.mcap", minimal([("/rig/sensors", 8_000_000, payload)]))
    err = expect(NonFiniteValueError, path, f"/rig/sensors: {field} ", "t=0.008000000 s", what)
    assert "pass allow_nonfinite" not in str(err)


def test_nonfinite_theta_hat_names_the_element(tmp_path: Path) -> None:
    state = dict.fromkeys(FIELDS["/control/state"][:-1], 0.0)
    state["theta_hat"] = [1.0, 0.0, 3500.0, None, 0.0, 0.0]
    path = write_raw(tmp_path / "nf.mcap", minimal([("/control/state", 0, js(**state))]))
    expect(NonFiniteValueError, path, "/control/state", "theta_hat[3]", "t=0.000000000 s")
    frame = read_run_log(path, allow_nonfinite=True)["/control/state"]
    assert np.isnan(frame["theta_hat_3"].iloc[0]) and frame["theta_hat_2"].iloc[0] == 3500.0


# -- atomic writing and writer validation ----------------------------------------------------


def test_exception_inside_with_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with pytest.raises(RuntimeError, match="simulated crash"):
        with RunLogWriter(path, RIG, {}) as log:
            log.write("/rig/sensors", 0.0, SENSORS)
            raise RuntimeError("simulated crash")
    assert os.listdir(tmp_path) == []


def test_exception_keeps_an_older_file(tmp_path: Path) -> None:
    path, _ = small_log(tmp_path / "run.mcap")
    before = path.read_bytes()
    with pytest.raises(KeyError):
        with RunLogWriter(path, RIG, {}) as log:
            log.write("/rig/sensors", 0.0, SENSORS)
            raise KeyError("boom")
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["run.mcap"]


def test_file_appears_only_on_close(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "run.mcap"
    log = RunLogWriter(path, RIG, {})
    log.write("/rig/sensors", 0.0, SENSORS)
    log.write("/rig/valves", 0.0, VALVES)
    assert not path.exists()
    log.close()
    log.close()  # idempotent
    assert read_run_log(path).has("/rig/valves")
    with pytest.raises(ValueError, match="closed"):
        log.write("/rig/sensors", 0.1, SENSORS)
    other = RunLogWriter(tmp_path / "sub" / "aborted.mcap", RIG, {})
    other.abort()
    assert os.listdir(tmp_path / "sub") == ["run.mcap"]


@pytest.mark.parametrize(
    ("rig", "match"),
    [
        ({k: v for k, v in RIG.items() if k != "T0"}, "missing: T0"),
        (dict(RIG, L=0.05), "unknown: L"),
        (dict(RIG, p_s=math.inf), "rig.p_s must be a finite number"),
        (dict(RIG, A_a="7.854e-3"), "rig.A_a must be a finite number"),
        (dict(RIG, pwm_update="sometimes"), "rig.pwm_update"),
    ],
)
def test_writer_rejects_bad_rig(tmp_path: Path, rig: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        RunLogWriter(tmp_path / "run.mcap", rig, {})
    assert os.listdir(tmp_path) == []


def test_writer_rejects_bad_run(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="string map"):
        RunLogWriter(tmp_path / "a.mcap", RIG, {"seed": 1})  # type: ignore[dict-item]
    with pytest.raises(ValueError, match=r"run\.schema"):
        RunLogWriter(tmp_path / "b.mcap", RIG, {"schema": "pneutune.log/2"})
    assert os.listdir(tmp_path) == []


def test_writer_rejects_bad_messages(tmp_path: Path) -> None:
    with RunLogWriter(tmp_path / "run.mcap", RIG, {}) as log:
        with pytest.raises(ValueError, match="unknown topic"):
            log.write("/rig/sensor", 0.0, SENSORS)
        with pytest.raises(ValueError, match="missing: p_s"):
            log.write("/rig/sensors", 0.0, {"x": 0.0, "p_a": 1.0, "p_b": 1.0})
        with pytest.raises(ValueError, match="unknown: T"):
            log.write("/rig/sensors", 0.0, dict(SENSORS, T=293.0))
        with pytest.raises(TypeError, match="x must be a real number"):
            log.write("/rig/sensors", 0.0, dict(SENSORS, x="0.1"))
        with pytest.raises(TypeError, match="x must be a real number"):
            log.write("/rig/sensors", 0.0, dict(SENSORS, x=True))
        with pytest.raises(ValueError, match="time must be finite"):
            log.write("/rig/sensors", -0.004, SENSORS)
        with pytest.raises(ValueError, match="time must be finite"):
            log.write("/rig/sensors", math.nan, SENSORS)
        with pytest.raises(ValueError, match="level"):
            log.write("/rig/events", 0.0, {"level": "fatal", "code": "c", "message": "m"})
        with pytest.raises(ValueError, match="params must be finite"):
            log.write("/experiment/segment", 0.0,
                      {"label": "a", "kind": "b", "params": {"f": math.nan}})
        with pytest.raises(ValueError, match=r"with write\(\)"):
            log.write_many("/rig/events", np.zeros(1), {})
        log.write("/rig/sensors", 0.008, SENSORS)
        with pytest.raises(ValueError, match="goes backwards"):
            log.write("/rig/sensors", 0.004, SENSORS)
        cols = {k: np.zeros(3) for k in VALVES}
        with pytest.raises(ValueError, match="goes backwards"):
            log.write_many("/rig/valves", np.array([0.0, 0.008, 0.004]), cols)
        with pytest.raises(ValueError, match="shape"):
            log.write_many("/rig/valves", np.zeros(2), cols)
        with pytest.raises(TypeError, match="numeric"):
            log.write_many("/rig/valves", np.zeros(3), dict(cols, u_a_in=np.array(["a"] * 3)))
        state = {k: np.zeros(3) for k in FIELDS["/control/state"]}
        with pytest.raises(ValueError, match=r"theta_hat must have shape \(3, 6\)"):
            log.write_many("/control/state", np.zeros(3), state)
        log.write("/rig/valves", 0.0, VALVES)


# -- bad files -------------------------------------------------------------------------------


def test_minimal_foreign_file_reads(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "ok.mcap", minimal())
    run_log = read_run_log(path)
    assert run_log["/rig/sensors"].to_dict("records") == [SENSORS, SENSORS]
    assert run_log.rig == RIG and run_log.run == RUN_MD


@pytest.mark.parametrize(
    "content",
    [b"x,p_a\n0.1,2e5\n", b"\x89PNG\r\n\x1a\n" + bytes(100), b"\x89MCAP1\r\n" + bytes(40)],
    ids=["csv", "png", "future-mcap"],
)
def test_not_mcap(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    expect(NotMcapError, path, "not an MCAP file")


def test_unreadable_path(tmp_path: Path) -> None:
    expect(LogError, tmp_path / "absent.mcap", "cannot read")
    expect(LogError, tmp_path, "cannot read")  # a folder


def test_cut_short_at_chosen_offsets(tmp_path: Path) -> None:
    src, _ = small_log(tmp_path / "full.mcap")
    data = src.read_bytes()
    for offset in (0, 1, 7, 8, 9, 40, len(data) // 2, len(data) - 37, len(data) - 9,
                   len(data) - 1):
        path = tmp_path / f"cut{offset}.mcap"
        path.write_bytes(data[:offset])
        expect(TruncatedLogError, path, "cut short")


def offsets(size: int, exhaustive: bool, seed: int) -> list[int]:
    """Every offset, or the first and last 64 and 200 seeded random ones in between."""
    if exhaustive or size <= 400:
        return list(range(size))
    rng = np.random.default_rng(seed)
    middle = rng.choice(np.arange(64, size - 64), size=200, replace=False)
    return sorted({*range(64), *range(size - 64, size), *middle.tolist()})


@pytest.mark.parametrize("exhaustive", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_cut_short_at_many_offsets(tmp_path: Path, exhaustive: bool) -> None:
    src, _ = small_log(tmp_path / "full.mcap")
    data = src.read_bytes()
    path = tmp_path / "cut.mcap"
    for offset in offsets(len(data), exhaustive, seed=1):
        path.write_bytes(data[:offset])
        with pytest.raises(TruncatedLogError):
            read_run_log(path)


@pytest.mark.parametrize("exhaustive", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_byte_flips_are_detected(tmp_path: Path, exhaustive: bool) -> None:
    """The writer enables chunk, data-section and summary CRCs: any damaged byte is caught."""
    src, _ = small_log(tmp_path / "full.mcap")
    data = src.read_bytes()
    path = tmp_path / "flip.mcap"
    kinds: set[str] = set()
    for pos in offsets(len(data), exhaustive, seed=2):
        damaged = bytearray(data)
        damaged[pos] ^= 0xFF if pos % 2 else 0x01
        path.write_bytes(bytes(damaged))
        with pytest.raises(LogError) as info:
            read_run_log(path)
        kinds.add(type(info.value).__name__)
        if pos >= len(MCAP_MAGIC):
            assert isinstance(info.value, TruncatedLogError), (pos, info.value)
    assert kinds == {"NotMcapError", "TruncatedLogError"}


@pytest.mark.parametrize("exhaustive", [False, pytest.param(True, marks=pytest.mark.slow)])
@pytest.mark.parametrize(
    ("compression", "chunked"),
    [(CompressionType.ZSTD, True), (CompressionType.NONE, True), (CompressionType.NONE, False)],
)
def test_damaged_files_without_crcs_raise_only_log_errors(
    tmp_path: Path, compression: Any, chunked: bool, exhaustive: bool
) -> None:
    """Without CRCs a damaged byte may go unnoticed, but nothing but a LogError escapes."""
    event = js(level="info", code="c", message="m")
    src = write_raw(tmp_path / "src.mcap", minimal([("/rig/events", 0, event)]), crcs=False,
                    compression=compression, chunked=chunked)
    data = src.read_bytes()
    rng = np.random.default_rng(6358)
    path = tmp_path / "bad.mcap"
    for pos in offsets(len(data), exhaustive, seed=3):
        damaged = bytearray(data)
        damaged[pos] = int(rng.integers(256))
        path.write_bytes(bytes(damaged))
        try:
            read_run_log(path)
        except LogError:
            pass


def test_random_garbage_blocks_raise_only_log_errors(tmp_path: Path) -> None:
    src, _ = small_log(tmp_path / "full.mcap", n=200)
    data = src.read_bytes()
    rng = np.random.default_rng(2014)
    path = tmp_path / "bad.mcap"
    for _ in range(300):
        start = int(rng.integers(8, len(data)))
        block = rng.integers(0, 256, size=int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        path.write_bytes(data[:start] + block + data[start + len(block):])
        with pytest.raises(TruncatedLogError):
            read_run_log(path)


def test_trailing_bytes_are_corruption(tmp_path: Path) -> None:
    src, _ = small_log(tmp_path / "full.mcap")
    path = tmp_path / "tail.mcap"
    path.write_bytes(src.read_bytes() + b"\n")
    expect(TruncatedLogError, path, "after the closing magic")


def test_empty_log(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "empty.mcap", [])
    expect(EmptyLogError, path, "no messages")
    path = tmp_path / "empty2.mcap"
    RunLogWriter(path, RIG, {}).close()
    expect(EmptyLogError, path, "no messages")


def test_missing_required_topic(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "m.mcap", [("/rig/sensors", 0, js(**SENSORS))])
    expect(MissingTopicError, path, "/rig/valves", "present: /rig/sensors")
    assert read_run_log(path, required_topics=("/rig/sensors",)).has("/rig/sensors")
    expect(MissingTopicError, path, "/sim/truth", required_topics=("/sim/truth",))
    with pytest.raises(ValueError, match="unknown topic"):
        read_run_log(path, required_topics=("/rig/valve",))


def test_time_going_backwards(tmp_path: Path) -> None:
    msgs = minimal([("/rig/valves", 2_000_000, js(**VALVES))])  # after 4 ms
    path = write_raw(tmp_path / "back.mcap", msgs)
    expect(TimeOrderError, path, "/rig/valves", "t=0.004000000 s", "t=0.002000000 s")


def test_equal_times_are_allowed(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "eq.mcap", minimal([("/rig/sensors", 4_000_000, js(**SENSORS))]))
    assert list(read_run_log(path)["/rig/sensors"].index) == [0.0, 0.004, 0.004]


def test_missing_rig_record(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "norig.mcap", minimal(), rig=None)
    expect(MissingMetadataError, path, "'rig' metadata record")


@pytest.mark.parametrize("key", RIG_KEYS)
def test_rig_record_missing_a_key(tmp_path: Path, key: str) -> None:
    rig = {k: v for k, v in RIG_MD.items() if k != key}
    path = write_raw(tmp_path / "rig.mcap", minimal(), rig=rig)
    expect(MissingMetadataError, path, f"lacks key {key}")


@pytest.mark.parametrize("text", ["", "abc", "1,5", "nan", "inf", "1e999", "0x10", "1_0"])
def test_rig_record_unparsable_number(tmp_path: Path, text: str) -> None:
    path = write_raw(tmp_path / "rig.mcap", minimal(), rig=dict(RIG_MD, p_s=text))
    expect(MissingMetadataError, path, "p_s", repr(text))


def test_rig_record_bad_mode_or_unknown_key(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "a.mcap", minimal(), rig=dict(RIG_MD, pwm_update="fast"))
    expect(MissingMetadataError, path, "pwm_update", "'fast'")
    path = write_raw(tmp_path / "b.mcap", minimal(), rig=dict(RIG_MD, L="0.05"))
    expect(LogSchemaError, path, "unknown key(s) L")


def test_run_record(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "a.mcap", minimal(), run=None)
    expect(MissingMetadataError, path, "'run' metadata record")
    path = write_raw(tmp_path / "b.mcap", minimal(), run={"created_by": "x"})
    expect(MissingMetadataError, path, "lacks key schema")
    path = write_raw(tmp_path / "c.mcap", minimal(), run=dict(RUN_MD, schema="pneutune.log/2"))
    expect(LogSchemaError, path, "pneutune.log/2")


@pytest.mark.parametrize(
    ("payload", "fragment"),
    [
        (b'{"x":0.0,"p_a":1.0,"p_b":1.0}', "missing field(s) p_s"),
        (b'{"x":0.0,"p_a":1.0,"p_b":1.0,"p_s":1.0,"T":1.0}', "unknown field(s) T"),
        (b'{"x":"0.0","p_a":1.0,"p_b":1.0,"p_s":1.0}', "x = '0.0' is not a number"),
        (b'{"x":true,"p_a":1.0,"p_b":1.0,"p_s":1.0}', "x = True is not a number"),
        (b"[0.0,1.0,1.0,1.0]", "expected a JSON object"),
        (b'{"x":0.0,"p_a":1.0', "not valid UTF-8 JSON"),
        (b'{"x":0.0,"p_a":1.0,"p_b":1.0,"p_s":"\xff"}', "not valid UTF-8 JSON"),
    ],
)
def test_message_not_matching_schema(tmp_path: Path, payload: bytes, fragment: str) -> None:
    path = write_raw(tmp_path / "s.mcap", minimal([("/rig/sensors", 8_000_000, payload)]))
    expect(LogSchemaError, path, "/rig/sensors", "t=0.008000000 s", fragment)


def test_string_topics_are_checked(tmp_path: Path) -> None:
    bad_level = js(level="fatal", code="c", message="m")
    path = write_raw(tmp_path / "a.mcap", minimal([("/rig/events", 0, bad_level)]))
    expect(LogSchemaError, path, "/rig/events", "level = 'fatal'")
    bad_params = js(label="a", kind="b", params=[1])
    path = write_raw(tmp_path / "b.mcap", minimal([("/experiment/segment", 0, bad_params)]))
    expect(LogSchemaError, path, "/experiment/segment", "params = [1]")
    short_theta = dict.fromkeys(FIELDS["/control/state"][:-1], 0.0)
    short_theta["theta_hat"] = [1.0] * 5
    path = write_raw(tmp_path / "c.mcap", minimal([("/control/state", 0, js(**short_theta))]))
    expect(LogSchemaError, path, "theta_hat", "not a list of 6 numbers")


def test_channel_encoding_is_checked(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "a.mcap", minimal(), message_encoding="cdr")
    expect(LogSchemaError, path, "'cdr'")
    path = write_raw(tmp_path / "b.mcap", minimal(), schema_encoding="protobuf")
    expect(LogSchemaError, path, "'protobuf'")


def test_unknown_topics_are_ignored(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "a.mcap", minimal([("/diagnostics", 0, b'{"cpu":0.5}')]))
    run_log = read_run_log(path)
    assert run_log.ignored_topics == ("/diagnostics",)
    assert set(run_log.topics) == {"/rig/sensors", "/rig/valves"}


@pytest.mark.parametrize(
    ("chunked", "compression"),
    [(False, CompressionType.NONE), (True, CompressionType.NONE), (True, CompressionType.LZ4)],
)
def test_other_file_layouts_read(tmp_path: Path, chunked: bool, compression: Any) -> None:
    if compression == CompressionType.LZ4:
        pytest.importorskip("lz4")
    path = write_raw(tmp_path / "a.mcap", minimal(), chunked=chunked, compression=compression)
    assert read_run_log(path)["/rig/valves"].to_dict("records") == [VALVES, VALVES]


# -- properties ------------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False)
nullable = st.one_of(finite, st.none(), st.sampled_from([math.inf, -math.inf, math.nan]))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.tuples(*([finite] * 15)), min_size=1, max_size=20))
def test_round_trip_property(tmp_path_factory: pytest.TempPathFactory,
                             rows: list[tuple[float, ...]]) -> None:
    """Any finite float64 (subnormals, -0.0, extremes) reads back bit for bit."""
    values = np.array(rows, dtype=np.float64)
    n = len(rows)
    path = tmp_path_factory.mktemp("prop") / "run.mcap"
    t = np.arange(n) * 0.004
    names = FIELDS["/control/state"]
    cols = {name: values[:, k] for k, name in enumerate(names[:-1])}
    cols["theta_hat"] = values[:, 9:15]
    with RunLogWriter(path, RIG, {}) as log:
        log.write_many("/control/state", t, cols)
        log.write_many("/rig/sensors", t, dict(zip(FIELDS["/rig/sensors"], values.T[:4],
                                                   strict=True)))
        for i in range(n):
            log.write("/rig/valves", float(t[i]), dict(zip(FIELDS["/rig/valves"],
                                                           rows[i][4:8], strict=True)))
    run_log = read_run_log(path)
    state = run_log["/control/state"].to_numpy()
    assert state.view(np.int64).tolist() == values.view(np.int64).tolist()  # sign of zero too
    sensors = run_log["/rig/sensors"].to_numpy()
    assert sensors.view(np.int64).tolist() == values[:, :4].view(np.int64).tolist()
    valves = run_log["/rig/valves"].to_numpy()
    assert valves.view(np.int64).tolist() == values[:, 4:8].view(np.int64).tolist()


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.tuples(*([nullable] * 4)), min_size=1, max_size=20))
def test_bulk_decoding_equals_json_decoding(tmp_path_factory: pytest.TempPathFactory,
                                            rows: list[tuple[float | None, ...]]) -> None:
    """Our compact layout (bulk path) and another writer's layout (JSON path) agree."""
    folder = tmp_path_factory.mktemp("prop")
    names = FIELDS["/rig/sensors"]
    ours = folder / "ours.mcap"
    values = np.array([[math.nan if v is None else v for v in row] for row in rows])
    with RunLogWriter(ours, RIG, {}) as log:
        log.write_many("/rig/sensors", np.arange(len(rows)) * 0.004,
                       dict(zip(names, values.T, strict=True)))
        log.write("/rig/valves", 0.0, VALVES)
    foreign = []
    for i, row in enumerate(rows):  # reversed key order, spaces: JSON path
        message = {k: (None if v is None or not math.isfinite(v) else v)
                   for k, v in reversed(list(zip(names, row, strict=True)))}
        foreign.append(("/rig/sensors", i * 4_000_000, json.dumps(message).encode()))
    theirs = write_raw(folder / "theirs.mcap", [*foreign, ("/rig/valves", 0, js(**VALVES))])
    a = read_run_log(ours, allow_nonfinite=True)["/rig/sensors"]
    b = read_run_log(theirs, allow_nonfinite=True)["/rig/sensors"]
    assert a.index.equals(b.index)
    assert np.array_equal(a.to_numpy(), b.to_numpy(), equal_nan=True)
    assert a.to_numpy().view(np.int64)[~np.isnan(a.to_numpy())].tolist() == \
        b.to_numpy().view(np.int64)[~np.isnan(b.to_numpy())].tolist()


def test_unique_temp_name_does_not_collide_with_readers(tmp_path: Path) -> None:
    """While a log is open, its folder holds only a hidden temporary file."""
    path = tmp_path / "run.mcap"
    log = RunLogWriter(path, RIG, {})
    names = os.listdir(tmp_path)
    assert len(names) == 1 and names[0].startswith(".run.mcap.")
    log.abort()
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("topic", list(FIELDS))
def test_writer_output_takes_the_bulk_path(tmp_path: Path, topic: str) -> None:
    """White-box guard of reading speed: the writer's layout of every numeric topic is decoded
    in bulk (a fallback to per-message JSON would still be correct, only ~3x slower, so no
    black-box test would notice)."""
    rng = np.random.default_rng(11)
    n = 100
    cols = {name: rng.normal(size=(n, 6) if name == "theta_hat" else n) for name in FIELDS[topic]}
    cols[FIELDS[topic][0]][5] = np.nan
    path = tmp_path / "run.mcap"
    with RunLogWriter(path, RIG, {}) as log:
        log.write_many(topic, np.arange(n) * 0.004, cols)
    with open(path, "rb") as fh:
        payloads = [m.data for _, _, m in make_reader(fh).iter_messages()]
    values = _bulk_numeric(TOPIC_SPECS[topic], payloads)
    assert values is not None
    expected = np.column_stack([cols[name] for name in FIELDS[topic]])
    np.testing.assert_array_equal(values, expected)
    # ... and anything else falls back (here: one message with a space).
    payloads[3] = payloads[3].replace(b":", b": ", 1)
    assert _bulk_numeric(TOPIC_SPECS[topic], payloads) is None


def test_path_and_sha256(tmp_path: Path) -> None:
    """Reading works from a str or a Path, reports the path as given, hashes the bytes."""
    path, _ = small_log(tmp_path / "run.mcap")
    assert read_run_log(str(path)).path == str(path)
    assert read_run_log(path).sha256 == hashlib.sha256(path.read_bytes()).hexdigest()


def test_compression_level_changes_only_the_chunk_bytes(tmp_path: Path) -> None:
    """RunLogWriter(compression_level=19): the same messages as the default writer (read back
    by the mcap package's reader and by read_run_log, equal), fewer bytes on a compressible
    series, and the default writer is not affected afterwards (the level is per writer).
    An out-of-range level is refused."""
    n = 20000
    t = np.arange(n) * 5.0e-4
    sensors = {"x": 0.0235 + 1e-3 * np.sin(t), "p_a": 3e5 + 1e3 * np.cos(t),
               "p_b": np.full(n, 3.1e5), "p_s": np.full(n, 6.1e5)}
    valves = {k: np.full(n, 0.5) for k in ("u_a_in", "u_a_out", "u_b_in", "u_b_out")}
    sizes, messages = {}, {}
    for name, level in (("default", None), ("level19", 19), ("default-again", None)):
        path = tmp_path / f"{name}.mcap"
        with RunLogWriter(path, RIG, {}, compression_level=level) as log:
            log.write_many("/rig/sensors", t, sensors)
            log.write_many("/rig/valves", t, valves)
        sizes[name] = path.stat().st_size
        with open(path, "rb") as fh:
            messages[name] = [(c.topic, m.log_time, m.data)
                              for _, c, m in make_reader(fh).iter_messages()]
        run = read_run_log(path)
        np.testing.assert_array_equal(run["/rig/sensors"]["x"].to_numpy(), sensors["x"])
    assert messages["level19"] == messages["default"]
    assert sizes["level19"] < sizes["default"]
    assert sizes["default-again"] == sizes["default"]
    with pytest.raises(ValueError, match=r"compression_level must be in 1\.\.22"):
        RunLogWriter(tmp_path / "bad.mcap", RIG, {}, compression_level=23)
