"""Run logs open in another MCAP implementation: the TypeScript reader ``@mcap/core``.

Foxglove is built on ``@mcap/core``; if it reads our files, Foxglove does. The packages are
installed on first use into ``<repo>/.cache/node`` (gitignored) with ``npm install --prefix``;
without node/npm, or if the install fails (no network), the tests are skipped with the reason.
The node script reads every record twice, linearly with CRC validation (``McapStreamReader``)
and through the summary and indexes (``McapIndexedReader``), checks that every channel is
``json`` with a ``jsonschema`` schema, parses every message as JSON and prints counts per topic,
the first message of each topic, the schemas and the metadata as one JSON object.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.logs.topics import TOPIC_SCHEMAS
from pneutune.control.logs.writer import RunLogWriter

REPO = Path(__file__).resolve().parents[1]
NODE_DIR = REPO / ".cache" / "node"
#: Pinned so that the test is reproducible; fzstd is a pure-JS zstd decoder.
NODE_PACKAGES = {"@mcap/core": "2.2.2", "fzstd": "0.1.1"}

# The paper's rig (Qian et al. 2014, Sec. 5.1; plant.yaml's defaults, contract 2).
RIG: dict[str, float | str] = {
    "A_a": 7.854e-3, "A_b": 7.54e-3, "x_min": -0.0015, "x_max": 0.0485, "V0a": 5.036e-5,
    "V0b": 2.916e-5, "p0": 101325.0, "p_s": 6.0e5, "T0": 283.15, "n": 1.2, "R": 287.0,
    "Ts": 0.004, "pwm_hz": 60.0, "pwm_update": "immediate",
}

SCRIPT = r"""// Written by tests/test_mcap_external.py: read a run log with @mcap/core.
import { readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { decompress } from "fzstd";

const decompressHandlers = {
  zstd: (data, size) => decompress(data, new Uint8Array(Number(size))),
};
const utf8 = new TextDecoder("utf-8", { fatal: true });
const bytes = new Uint8Array(await readFile(process.argv[2]));
const fail = (message) => { throw new Error(message); };

// 1. Linear pass over every record, chunk CRCs validated.
const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
stream.append(bytes);
const streamChannels = new Map();
const streamCounts = {};
const metadata = {};
let header;
for (let rec; (rec = stream.nextRecord()); ) {
  if (rec.type === "Header") header = rec;
  else if (rec.type === "Channel") streamChannels.set(rec.id, rec);
  else if (rec.type === "Metadata") metadata[rec.name] = Object.fromEntries(rec.metadata);
  else if (rec.type === "Message") {
    const topic = streamChannels.get(rec.channelId).topic;
    streamCounts[topic] = (streamCounts[topic] ?? 0) + 1;
  }
}
if (!stream.done()) fail("stream reader did not reach the footer");

// 2. Indexed pass through the summary section, in log-time order.
const readable = {
  size: async () => BigInt(bytes.byteLength),
  read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)),
};
const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
const counts = {};
const first = {};
const schemas = {};
let lastTime = -1n;
for await (const msg of reader.readMessages()) {
  const channel = reader.channelsById.get(msg.channelId);
  const schema = reader.schemasById.get(channel.schemaId);
  if (schema?.encoding !== "jsonschema") fail(`${channel.topic}: schema encoding not jsonschema`);
  if (channel.messageEncoding !== "json") fail(`${channel.topic}: message encoding not json`);
  if (msg.logTime < lastTime) fail("indexed reader returned messages out of log-time order");
  lastTime = msg.logTime;
  const value = JSON.parse(utf8.decode(msg.data));
  counts[channel.topic] = (counts[channel.topic] ?? 0) + 1;
  if (!(channel.topic in first)) first[channel.topic] = { logTime: String(msg.logTime), value };
  schemas[channel.topic] ??= JSON.parse(utf8.decode(schema.data));
}
const statistics = {};
for (const [id, n] of reader.statistics?.channelMessageCounts ?? []) {
  statistics[reader.channelsById.get(id).topic] = Number(n);
}
process.stdout.write(JSON.stringify({
  profile: header.profile, counts, streamCounts, statistics, first, schemas, metadata,
  compression: [...new Set(reader.chunkIndexes.map((c) => c.compression))],
  chunks: reader.chunkIndexes.length,
}));
"""


def _installed() -> bool:
    for name, version in NODE_PACKAGES.items():
        manifest = NODE_DIR / "node_modules" / name / "package.json"
        try:
            if json.loads(manifest.read_text())["version"] != version:
                return False
        except (OSError, ValueError, KeyError):
            return False
    return True


@pytest.fixture(scope="module")
def mcap_node() -> list[str]:
    """Command prefix ``[node, script]``; installs the npm packages on first use."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node and npm are needed for the TypeScript MCAP reader; not on PATH")
    if not _installed():
        NODE_DIR.mkdir(parents=True, exist_ok=True)
        specs = [f"{name}@{version}" for name, version in NODE_PACKAGES.items()]
        # Fail fast without a registry: npm's default retries back off for minutes.
        command = [npm, "install", "--prefix", str(NODE_DIR), "--no-audit", "--no-fund",
                   "--save-exact", "--prefer-offline", "--fetch-retries=0",
                   "--fetch-timeout=20000", "--loglevel=error", *specs]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=45)
        except subprocess.TimeoutExpired:
            pytest.skip(f"`npm install {' '.join(specs)}` took over 45 s (registry unreachable?)")
        if done.returncode != 0 or not _installed():
            lines = [ln for ln in done.stderr.splitlines() if ln.strip() and "config" not in ln]
            tail = " | ".join(lines[:3])
            pytest.skip(f"`npm install {' '.join(specs)}` failed ({done.returncode}): {tail}")
    script = NODE_DIR / "read_mcap.mjs"
    script.write_text(SCRIPT, encoding="utf-8")
    return [node, str(script)]


def _run(command: list[str], path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*command, str(path)], capture_output=True, text=True, timeout=60)


def _write_log(path: Path, indexed: bool = True) -> tuple[dict[str, int], dict[str, dict]]:
    """A log with every topic over several chunks; returns counts and first messages."""
    n = 2000
    rng = np.random.default_rng(17)
    t = np.arange(n) * 0.004
    sensors = {"x": rng.uniform(0.0, 0.047, n), "p_a": rng.uniform(1e5, 6e5, n),
               "p_b": rng.uniform(1e5, 6e5, n), "p_s": np.full(n, 6.0e5)}
    sensors["x"][0] = np.nan  # written as null
    valves = {k: rng.uniform(0.0, 1.0, n) for k in ("u_a_in", "u_a_out", "u_b_in", "u_b_out")}
    state = {k: rng.normal(size=n) for k in
             ("e1", "e2", "e3", "x_hat", "v_hat", "a_hat", "F_pd", "dF_pd", "Q_Ld")}
    state["theta_hat"] = np.tile([0.9389, 0.0, 3500.0, 100.0, 0.0, 0.0], (n, 1))
    reference = {k: rng.normal(size=n) for k in ("x_r", "v_r", "a_r")}
    truth = {k: rng.normal(size=n) for k in ("v", "a", "F_friction", "F_ext", "mdot_a", "mdot_b")}
    segment = {"label": "chirp-1", "kind": "chirp", "params": {"f0_hz": 0.1, "f1_hz": 5.0}}
    event = {"level": "warning", "code": "x_limit", "message": "near the stroke end"}
    with RunLogWriter(path, RIG, {"seed": "17"}, chunk_size=64 * 1024, indexed=indexed) as log:
        log.write("/experiment/segment", 0.0, segment)
        log.write_many("/rig/sensors", t, sensors)
        log.write_many("/rig/valves", t, valves)
        log.write_many("/control/reference", t, reference)
        log.write_many("/control/state", t, state)
        log.write_many("/sim/truth", t, truth)
        log.write("/rig/events", 1.5, event)
        counts = log.message_counts
    first = {
        "/rig/sensors": {"x": None, **{k: v[0] for k, v in sensors.items() if k != "x"}},
        "/rig/valves": {k: v[0] for k, v in valves.items()},
        "/control/state": {k: (list(v[0]) if k == "theta_hat" else v[0])
                           for k, v in state.items()},
        "/experiment/segment": segment,
        "/rig/events": event,
    }
    return counts, first


def test_typescript_reader_reads_every_message(tmp_path: Path, mcap_node: list[str]) -> None:
    path = tmp_path / "run.mcap"
    counts, first = _write_log(path)
    done = _run(mcap_node, path)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["counts"] == counts  # every message, via the indexes
    assert out["streamCounts"] == counts  # every message, linearly with CRCs
    assert out["statistics"] == counts
    assert out["chunks"] > 1 and out["compression"] == ["zstd"]
    assert out["profile"] == ""
    assert out["schemas"] == {topic: TOPIC_SCHEMAS[topic] for topic in counts}
    assert out["metadata"]["rig"] == {k: (v if isinstance(v, str) else repr(v))
                                      for k, v in RIG.items()}
    assert out["metadata"]["run"]["seed"] == "17"
    assert out["metadata"]["run"]["schema"] == "pneutune.log/1"
    # JavaScript numbers are float64 and JSON.stringify prints the shortest round-trip form,
    # so the values come back exactly.
    for topic, expected in first.items():
        assert out["first"][topic]["value"] == expected, topic
    assert out["first"]["/rig/sensors"]["logTime"] == "0"
    assert out["first"]["/rig/events"]["logTime"] == "1500000000"


def test_typescript_reader_reads_an_unindexed_log(tmp_path: Path, mcap_node: list[str]) -> None:
    """``indexed=False`` (what ``simulate --experiment`` writes): the stream reader reads every
    message with CRCs; the summary lists no chunk index, so the indexed reader yields nothing
    and raises nothing, which is how Foxglove knows to read the file linearly."""
    path = tmp_path / "run.mcap"
    counts, _ = _write_log(path, indexed=False)
    done = _run(mcap_node, path)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["streamCounts"] == counts
    assert out["statistics"] == counts
    assert out["chunks"] == 0 and out["counts"] == {}
    assert out["metadata"]["run"]["seed"] == "17"


def test_typescript_reader_rejects_a_cut_file(tmp_path: Path, mcap_node: list[str]) -> None:
    """Control: the node script fails on a damaged file, so a pass above means something."""
    path = tmp_path / "run.mcap"
    _write_log(path)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-100])
    done = _run(mcap_node, cut)
    assert done.returncode != 0
