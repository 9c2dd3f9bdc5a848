"""run.mcap read by an independent reader: Foxglove's own TypeScript library (@mcap/core).

The Node packages come from the npm registry at test time (pinned versions), into a cache
under the repo's .venv (or a temporary folder): CI starts from a clean clone with node and
npm. Node reads every channel, decodes every JSON message and sends back what it saw; the
test compares that with what the Python writer put in, sample for sample.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from commission.cli import main
from commission.mcaplog import PLOT_TOPIC, append_result, read_recording, read_results, write_recording
from commission.recording import SIGNAL_UNITS

ROOT = Path(__file__).resolve().parents[1]
NPM_PACKAGES = ["@mcap/core@2.2.2", "@mcap/support@1.1.0", "@mcap/nodejs@1.0.2"]

NODE_READER = r"""
const { McapIndexedReader } = require("@mcap/core");
const { FileHandleReadable } = require("@mcap/nodejs");
const { loadDecompressHandlers } = require("@mcap/support");
const fs = require("fs/promises");

(async () => {
  const decompressHandlers = await loadDecompressHandlers();
  const handle = await fs.open(process.argv[2], "r");
  const reader = await McapIndexedReader.Initialize({
    readable: new FileHandleReadable(handle), decompressHandlers });
  const out = { library: reader.header.library, profile: reader.header.profile,
                channels: {}, metadata: {},
                statistics: reader.statistics ? Number(reader.statistics.messageCount) : null };
  for (const [id, ch] of reader.channelsById) {
    const schema = reader.schemasById.get(ch.schemaId);
    out.channels[ch.topic] = {
      messageEncoding: ch.messageEncoding, metadata: Object.fromEntries(ch.metadata),
      schemaName: schema ? schema.name : null, schemaEncoding: schema ? schema.encoding : null,
      schema: schema ? JSON.parse(new TextDecoder().decode(schema.data)) : null,
      count: 0, lastSequence: null, firstLogTime: null, lastLogTime: null,
      values: [], t: [], firstSamples: [], samples: [], payloads: [] };
  }
  const dec = new TextDecoder();
  for await (const msg of reader.readMessages()) {
    const topic = reader.channelsById.get(msg.channelId).topic;
    const c = out.channels[topic];
    const payload = JSON.parse(dec.decode(msg.data));
    c.count += 1;
    const lt = msg.logTime.toString();
    if (c.firstLogTime === null) c.firstLogTime = lt;
    c.lastLogTime = lt;
    if (Array.isArray(payload.values)) {
      c.firstSamples.push(payload.first_sample);
      c.values.push(...payload.values);
      c.t.push(...payload.t_s);
    } else if (typeof payload.sample === "number") {
      c.samples.push(payload);
    } else {
      c.payloads.push(payload);
    }
  }
  for await (const m of reader.readMetadata()) out.metadata[m.name] = Object.fromEntries(m.metadata);
  await handle.close();
  process.stdout.write(JSON.stringify(out));
})().catch((err) => { console.error(err && err.stack ? err.stack : String(err)); process.exit(1); });
"""


def _npm_dir() -> Path:
    venv = ROOT / ".venv"
    base = venv if venv.is_dir() and os.access(venv, os.W_OK) else Path(tempfile.gettempdir())
    return base / "node-mcap-reader"


@pytest.fixture(scope="module")
def node_reader() -> tuple[str, Path]:
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.fail("node and npm are needed for the independent MCAP reader test (Debian: apt-get install nodejs npm)")
    where = _npm_dir()
    where.mkdir(parents=True, exist_ok=True)
    if not all((where / "node_modules" / p.rsplit("@", 1)[0]).is_dir() for p in NPM_PACKAGES):
        done = subprocess.run(
            [npm, "install", "--no-audit", "--no-fund", "--loglevel=error", "--prefix", str(where), *NPM_PACKAGES],
            capture_output=True, text=True, timeout=300, cwd=where,
        )
        if done.returncode != 0:
            pytest.fail(f"npm install {' '.join(NPM_PACKAGES)} failed:\n{done.stderr[-2000:]}")
    script = where / "read_mcap.cjs"
    script.write_text(NODE_READER, encoding="utf-8")
    return node, script


def _read_with_node(node_reader: tuple[str, Path], path: Path) -> dict:
    node, script = node_reader
    done = subprocess.run([node, str(script), str(path)], capture_output=True, text=True, timeout=120,
                          cwd=script.parent)
    assert done.returncode == 0, f"@mcap/core could not read {path}:\n{done.stderr[-3000:]}"
    return json.loads(done.stdout)


def _check_against_python(seen: dict, path: Path) -> None:
    rec = read_recording(path)
    results = read_results(path)
    # every signal channel: the exact samples and times, in order, with schema and unit
    for name, values in rec.signals():
        ch = seen["channels"][f"/{name}"]
        assert ch["messageEncoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
        assert ch["schemaName"] == f"commission.{name}" and ch["metadata"]["unit"] == SIGNAL_UNITS[name]
        assert ch["schema"]["properties"]["unit"]["const"] == SIGNAL_UNITS[name]
        assert ch["firstSamples"] == sorted(ch["firstSamples"]) and ch["firstSamples"][0] == 0
        assert np.array_equal(np.asarray(ch["values"]), values), name
        assert np.array_equal(np.asarray(ch["t"]), rec.t), name
    # the per-sample plot topic, when the file has one: exact samples at every n-th index
    if PLOT_TOPIC in seen["channels"]:
        ch = seen["channels"][PLOT_TOPIC]
        every = int(seen["metadata"]["recording"]["plot_every"])
        idx = np.array([s["sample"] for s in ch["samples"]])
        assert np.array_equal(idx, np.arange(0, len(rec), every))
        assert set(ch["schema"]["required"]) == {"sample", "t_s", *(n for n, _ in rec.signals())}
        for name, values in rec.signals():
            assert np.array_equal([s[name] for s in ch["samples"]], values[idx]), name
        assert np.array_equal([s["t_s"] for s in ch["samples"]], rec.t[idx])
    # result topics: the same JSON objects
    for topic, payloads in results.items():
        assert seen["channels"][topic]["payloads"] == payloads, topic
    # nothing in the file that this test did not look at
    known = {f"/{n}" for n, _ in rec.signals()} | set(results) | {PLOT_TOPIC}
    assert set(seen["channels"]) <= known
    assert sum(c["count"] for c in seen["channels"].values()) == seen["statistics"]
    assert seen["library"].startswith("drive-commission/")
    assert seen["metadata"]["recording_end"]["status"] == "complete"
    assert {"recording", "recording_metadata", "config", "recording_end"} <= set(seen["metadata"])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run")
    assert main(["--sim", "--out", str(out), "--json", "--no-identify"]) == 0
    return out


def test_node_reads_every_channel_of_a_run(node_reader: tuple[str, Path], run_dir: Path) -> None:
    """The run's own run.mcap, as the sequencer wrote it."""
    path = run_dir / "run.mcap"
    seen = _read_with_node(node_reader, path)
    assert {f"/{n}" for n in ("torque_ref", "motor_velocity")} <= set(seen["channels"])
    _check_against_python(seen, path)


def test_node_reads_the_foxglove_topics_and_the_identification(
    node_reader: tuple[str, Path], run_dir: Path, tmp_path: Path
) -> None:
    """A log with every kind of channel: the sample blocks, /samples for Foxglove's Plot
    panel, and /identification appended after the file was finished."""
    rec = read_recording(run_dir / "run.mcap")
    path = tmp_path / "full.mcap"
    write_recording(path, rec, config={"sim": {"epsilon_deg": 0.4}}, plot_every=8)
    ident = {"backlash": {"epsilon_deg": 0.4, "epsilon_interval_deg": [0.39, 0.41]},
             "two_mass": {"J_m": 4.78e-4, "J_l": 1.92e-4, "B_m": 8.4e-3, "B_l": 5.3e-3, "K": 23.1, "D": 1.54e-2},
             "notes": ["ε = 0.4°, μ-ℓ ünïcödé"]}
    append_result(path, "/identification", ident)
    seen = _read_with_node(node_reader, path)
    assert set(seen["channels"]) == {*(f"/{n}" for n, _ in rec.signals()), PLOT_TOPIC, "/identification"}
    assert seen["channels"]["/identification"]["payloads"] == [ident]
    assert seen["channels"][PLOT_TOPIC]["count"] == -(-len(rec) // 8)
    # the result sits at the end of the recording on the timeline, not at "now"
    others = [int(c["lastLogTime"]) for t, c in seen["channels"].items() if t != "/identification"]
    assert int(seen["channels"]["/identification"]["firstLogTime"]) == max(others)
    _check_against_python(seen, path)
