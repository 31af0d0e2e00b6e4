"""The run log opens in the ecosystem's tools: every channel is written with an encoding and schema that Foxglove,
Lichtblick and ``ros2 bag`` decode (JSON with a JSON Schema, CDR with its ros2msg, Foxglove's protobuf schemas),
on the simulated clock aligned with the recording, and the twin's own readers read it back (and older msgpack logs).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore

from conductor.runlog import RunLog, read_metadata, read_run_log
from conductor.runlog.encoding import joint_state_cdr, joint_state_of_cdr, to_json
from conductor.sources.recording import load_recording
from protocol import codec

ROOT = Path(__file__).resolve().parent.parent
STORE = get_typestore(Stores.ROS2_HUMBLE)  # an independent CDR decoder: the ROS 2 type store of rosbags
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def twin(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                          timeout=600, env=ENV, cwd=ROOT)


def decode_every_message(path: Path) -> dict[str, Counter]:
    """Decode every message of ``path`` with its channel's declared encoding and schema: JSON validated against
    its JSON Schema, CDR through the ROS 2 type store, protobuf through its FileDescriptorSet. Returns
    topic -> Counter(schema name); raises on the first message that does not decode."""
    protobuf = DecoderFactory()
    ts = STORE
    seen: dict[str, Counter] = {}
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            where = f"{channel.topic} #{message.sequence}"
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema", where
                v = validators.get(schema.id)
                if v is None:
                    v = validators[schema.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
                v.validate(json.loads(message.data))
            elif channel.message_encoding == "cdr":
                assert schema.encoding == "ros2msg", where
                first = {"sensor_msgs/msg/JointState": "std_msgs/Header header", "std_msgs/msg/String": "string data"}
                assert schema.data.decode().startswith(first[schema.name]), where
                ts.deserialize_cdr(message.data, schema.name)
            elif channel.message_encoding == "protobuf":
                assert schema.name.startswith("foxglove."), where
                decoder = protobuf.decoder_for(channel.message_encoding, schema)
                assert decoder is not None, where
                decoder(message.data)
            else:
                raise AssertionError(f"{where}: encoding {channel.message_encoding!r} no viewer reads")
            seen.setdefault(channel.topic, Counter())[schema.name] += 1
    return seen


def viewer_fields(schema: dict, path: str = "") -> list[str]:
    """The field paths a viewer builds from a JSON Schema, under the rules of Foxglove's and Lichtblick's
    ``parseJsonSchema``: an object with ``properties`` at the root and for each nested object; each property one
    ``type`` of boolean, string, number, integer, object or array; arrays with ``items`` of one of those but
    array. Raises AssertionError naming the first property the viewer would refuse (it would drop the whole topic)."""
    assert schema.get("type") == "object", f"{path or 'root'}: not an object"
    assert isinstance(schema.get("properties"), dict), f"{path or 'root'}: an object without properties"
    out = []
    for name, prop in (schema.get("properties") or {}).items():
        where = f"{path}.{name}" if path else name
        kind = prop.get("type")
        assert kind in ("boolean", "string", "number", "integer", "object", "array"), f"{where}: type {kind!r}"
        assert prop.get("contentEncoding") in (None, "base64"), where
        if kind == "object":
            out += viewer_fields(prop, where)
        elif kind == "array":
            item = (prop.get("items") or {}).get("type")
            assert item in ("boolean", "string", "number", "integer", "object"), f"{where}[]: item type {item!r}"
            if item == "object":
                out += viewer_fields(prop["items"], where + "[]")
        out.append(where)
    return out


@pytest.fixture(scope="module")
def ball_drop_log(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fmt")
    r = twin("run", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_00.mcap", "--run-dir", str(d),
             "--summary", str(d / "summary.json"))
    assert r.returncode == 0, r.stdout + r.stderr
    return d / "run.mcap"


def outcome(summary_file: Path) -> tuple:
    s = json.loads(summary_file.read_text())
    return (s["status"], s["semantic_state"],
            [(h["tick"], h["entity"], h["attribute"], h["from"], h["to"], h["trigger"]) for h in s["handovers"]])


def test_every_channel_decodes_with_its_schema(ball_drop_log):
    seen = decode_every_message(ball_drop_log)
    # the twin's own channels, the robot's joint states, queries and replies, and the Foxglove views
    for topic, schema in [
            ("/step", "twin.tick"), ("/done/physics", "twin.step_reply"), ("/ownership", "twin.ownership"),
            ("/joint_states", "sensor_msgs/msg/JointState"), ("/action", "std_msgs/msg/String"),
            ("/conductor/register/physics", "twin.register"), ("/model/physics/init", "twin.init"),
            ("/model/physics/release", "twin.release"), ("/reply/physics/release", "twin.release_reply"),
            ("/model/in_hand/acquire", "twin.acquire"), ("/reply/physics/eval/closest", "twin.value_reply"),
            ("/event/_conductor/handover", "twin.event"), ("/twin/tf", "foxglove.FrameTransforms"),
            ("/twin/scene", "foxglove.SceneUpdate"), ("/twin/log", "foxglove.Log"),
            ("/twin/ownership", "twin.ownership")]:
        assert seen.get(topic, {}).get(schema), f"no {schema} on {topic}: {sorted(seen)}"
    with open(ball_drop_log, "rb") as f:
        summary = make_reader(f).get_summary()
    fields = {}
    for sc in summary.schemas.values():  # every JSON schema in the subset the viewers read
        if sc.encoding == "jsonschema":
            fields[sc.name] = viewer_fields(json.loads(sc.data))
    assert "owners.ball.pose" in fields["twin.ownership"] and "state.ball.pose" in fields["twin.step_reply"]
    rec = load_recording(ROOT / "recordings" / "ball_drop_00.mcap")
    assert sum(seen["/joint_states"].values()) == sum(1 for _, k, _ in rec.items if k == "joint_state")


def test_the_log_runs_on_the_simulated_clock_of_the_recording(ball_drop_log):
    rec = load_recording(ROOT / "recordings" / "ball_drop_00.mcap")
    ts = STORE
    with open(ball_drop_log, "rb") as f:
        reader = make_reader(f)
        stats = reader.get_summary().statistics
        joints = [(m.log_time, m.publish_time, ts.deserialize_cdr(m.data, "sensor_msgs/msg/JointState"))
                  for _, _, m in reader.iter_messages(topics=["/joint_states"])]
        steps = [(m.log_time, json.loads(m.data)) for _, _, m in reader.iter_messages(topics=["/step"])]
    # the robot's first joint state is where the recording's first message was; the log spans the recording
    assert joints[0][0] == rec.origin_ns + round(rec.items[0][0] * 1e9)
    assert (stats.message_end_time - stats.message_start_time) * 1e-9 == pytest.approx(rec.duration, abs=0.05)
    for log_time, _, js in joints[:50]:
        assert js.header.stamp.sec * 10**9 + js.header.stamp.nanosec == log_time
    for log_time, step in steps:  # tick t at origin + t
        assert log_time == rec.origin_ns + round(step["t"] * 1e9)
    wall = [p for _, p, _ in joints]  # the wall clock is kept as the publish time
    assert abs(wall[0] * 1e-9 - __import__("time").time()) < 3600 and wall == sorted(wall)
    with open(ball_drop_log, "rb") as f:  # each tick's poses at its own time, though ticks come in batches
        tf = sorted({m.log_time for _, _, m in make_reader(f).iter_messages(topics=["/twin/tf"])})
    assert len(tf) >= 0.9 * 60 * rec.duration and tf[0] >= rec.origin_ns  # 60 poses per simulated second
    info = read_metadata(ball_drop_log)["twin.log"]
    assert info["format"] == "2" and int(info["origin_ns"]) == rec.origin_ns


def test_the_twins_readers_read_it_back(ball_drop_log):
    rec = load_recording(ROOT / "recordings" / "ball_drop_00.mcap")
    joints = [m for k, _, m in read_run_log(ball_drop_log) if k.endswith("/telemetry/joint_states")]
    first = next(m for _, kind, m in rec.items if kind == "joint_state")
    assert joints[0]["stamp"] == first["stamp"] and joints[0]["name"] == first["name"]
    assert joints[0]["position"] == pytest.approx(first["position"])
    keys = {k for k, _, _ in read_run_log(ball_drop_log)}
    assert "twin/default/ownership" in keys and "twin/default/state/physics" in keys  # from the step answers
    assert not any(k.startswith("/twin/") for k in keys)  # the viewers' channels are not the ensemble's messages
    r = twin("view", str(ball_drop_log), "--foxglove-layout", str(ball_drop_log.with_suffix(".json")))
    assert r.returncode == 0, r.stderr
    lay = json.loads(ball_drop_log.with_suffix(".json").read_text())
    lanes = [p["value"] for p in lay["configById"]["StateTransitions!ownership"]["paths"]]
    assert "/twin/ownership.owners.ball.pose" in lanes
    assert lay["configById"]["Plot!joints"]["paths"][0]["label"] == joints[0]["name"][0]
    for where in (ball_drop_log.parent, Path("/proc/no/layout.json")):  # a folder, a place it cannot be: one line
        r = twin("view", str(ball_drop_log), "--foxglove-layout", str(where))
        assert r.returncode == 1 and "cannot write the layout" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = twin("view", str(ball_drop_log), "--out", str(ball_drop_log.with_suffix(".rrd")))
    assert r.returncode == 0 and "as the run log carries it" in r.stdout, r.stdout + r.stderr


def test_the_log_is_a_recording_the_twin_replays(ball_drop_log, tmp_path):
    """Its /joint_states and /action are what a robot's bag holds, its metadata the perceived scene: replayed as a
    recording it gives the same handovers and answer."""
    r = twin("run", "scenes/ball_drop.yaml", "--recording", str(ball_drop_log), "--run-dir", str(tmp_path),
             "--summary", str(tmp_path / "again.json"))
    assert r.returncode == 0, r.stdout + r.stderr
    first, again = outcome(ball_drop_log.parent / "summary.json"), outcome(tmp_path / "again.json")
    assert first == again and first[0] == "complete" and first[2]


def test_values_json_cannot_hold_are_written_so_that_they_validate(tmp_path):
    log = RunLog(tmp_path / "r.mcap", prefix="twin/e", dt=0.01)
    log.record("twin/e/state/m", codec.encode_unchecked("state", {
        "model": "m", "tick": 1, "t": 0.01, "values": {"b": {"pose": np.arange(7.0), "nan": float("nan")}}}))
    log.record("twin/e/out/m/x", b"\xc1 not msgpack")  # kept, as bytes, with the reason
    log.record("twin/e/out/m/y", codec.pack([1, 2]))  # msgpack, but not a message
    log.close()
    seen = decode_every_message(tmp_path / "r.mcap")
    assert seen["/out/m/x"]["twin.raw"] == 1 and seen["/out/m/y"]["twin.raw"] == 1
    got = list(read_run_log(tmp_path / "r.mcap"))
    assert got[0][2]["values"]["b"] == {"pose": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0], "nan": None}
    assert got[1][2] is None and [raw for k, _, raw in read_run_log(tmp_path / "r.mcap", decode=False)][1] == \
        b"\xc1 not msgpack"
    assert json.loads(to_json({"a": float("inf"), "b": b"\x00"})) == {"a": None, "b": "AA=="}


def test_a_time_the_log_cannot_hold_is_kept_raw_and_the_rest_written(tmp_path):
    """A robot stamping its joint states in nanoseconds for seconds (1.7e18 'seconds'), or an event at t=1e11 s: the
    writer's thread died on the first (a struct error out of the CDR header or the MCAP log time), every later
    message was lost, the file had no end and the run failed. Such a message is now kept as raw JSON with why, and
    the log goes on."""
    errors: list[str] = []
    log = RunLog(tmp_path / "r.mcap", prefix="twin/e", dt=0.01, on_error=errors.append)
    for k in range(3):
        log.record("twin/e/clock", codec.encode("clock", tick=k, t=k / 100, dt=0.01))
    log.record("twin/e/telemetry/joint_states", codec.encode(
        "joint_state", stamp=1.7e18, name=["j1"], position=[0.1], velocity=[], effort=[]))
    log.record("twin/e/event/_conductor/x", codec.encode("event", model="_conductor", name="x", tick=3, t=1e11,
                                                         data={}))
    for k in range(3, 6):
        log.record("twin/e/clock", codec.encode("clock", tick=k, t=k / 100, dt=0.01))
    log.close()
    assert errors == [] and log.error is None
    seen = decode_every_message(tmp_path / "r.mcap")
    assert seen["/clock"] == {"twin.clock": 6}, seen
    assert seen["/telemetry/joint_states"]["twin.raw"] == 1 and seen["/event/_conductor/x"]["twin.raw"] == 1, seen


def test_joint_states_round_trip_through_cdr():
    js = {"v": 1, "type": "joint_state", "stamp": 1.25, "name": ["a", "b"], "position": [0.1, -2.0],
          "velocity": [], "effort": [3.0, 4.0]}
    back = joint_state_of_cdr(joint_state_cdr(js, 10**18 + 1_250_000_000), 10**18)
    assert back == {**js, "stamp": pytest.approx(1.25)}
    assert math.isclose(joint_state_of_cdr(joint_state_cdr(js, 1_250_000_000), None)["stamp"], 1.25)


def test_a_format_1_log_still_reads(tmp_path):
    path = tmp_path / "old.mcap"  # what the twin wrote before: msgpack with an empty schema
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="twin", library="twin-runlog")
        sid = w.register_schema(name="twin.msgpack", encoding="", data=b"")
        ch = w.register_channel(topic="twin/e/ownership", message_encoding="msgpack", schema_id=sid)
        w.add_message(ch, log_time=5, publish_time=5, data=codec.encode_unchecked(
            "ownership", {"version": 1, "tick": 0, "t": 0.0, "owners": {"b": {"pose": "m"}}, "change": None}))
        w.finish()
    [(key, t, msg)] = list(read_run_log(path))
    assert key == "twin/e/ownership" and t == 5 and msg["owners"] == {"b": {"pose": "m"}}


VIEWERS = ROOT / "tests" / "viewers"


@pytest.mark.slow
def test_the_viewers_decoders_read_every_message(ball_drop_log):
    """The npm packages Lichtblick and Foxglove decode with (tests/viewers/decode.mjs) read every message of the
    log, and hold its JSON schemas to the rules under which they build field lists."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("Node.js is not installed here: the viewers' decoders cannot run")
    if not (VIEWERS / "node_modules").is_dir():
        r = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=VIEWERS, capture_output=True, text=True,
                           timeout=300)
        if r.returncode != 0:  # no registry to install from: the check cannot run here (it is not the log's fault)
            pytest.skip(f"npm ci could not install the viewers' decoders: {r.stderr.strip()[-500:]}")
    r = subprocess.run(["node", "decode.mjs", str(ball_drop_log)], cwd=VIEWERS, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    got = json.loads(r.stdout)
    assert got["n_errors"] == 0 and got["messages"] == sum(t["count"] for t in got["topics"].values())
    with open(ball_drop_log, "rb") as f:
        assert got["messages"] == make_reader(f).get_summary().statistics.message_count


def test_a_log_cut_short_still_says_what_ran(ball_drop_log, tmp_path):
    """The scene, perception and provenance are written first: a log cut by a crash still carries them; a re-run
    from it replays the telemetry before the cut and says so (degraded), and twin view still draws it."""
    data = ball_drop_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 3 // 5])
    meta = read_metadata(cut)
    assert {"twin.scene_text", "twin.perception", "twin.recording", "twin.log"} <= set(meta)
    assert "twin.summary" not in meta
    r = twin("run", "--from-log", str(cut), "--run-dir", str(tmp_path / "again"), "--summary",
             str(tmp_path / "again.json"))
    s = json.loads((tmp_path / "again.json").read_text())
    assert r.returncode == 3 and s["status"] == "degraded", r.stdout + r.stderr
    assert any("cut short" in why for why in s["status_reasons"]), s["status_reasons"]
    r = twin("view", str(cut), "--out", str(tmp_path / "cut.rrd"))  # drawn up to the cut, and said (exit 4)
    assert r.returncode == 4 and "as the run log carries it" in r.stdout and "is cut short" in r.stderr, \
        r.stdout + r.stderr


def test_a_log_with_attributes_beyond_pose_validates_and_logs_every_event(tmp_path):
    """An insertion run has a collision attribute (True, or {enabled, ignore, by}) besides the poses: its schemas
    said every attribute was an array of numbers, and 30 step answers failed them. And ``/twin/log``, Foxglove's
    log of every event, had only the conductor's: a model's events come in its step answers, and were left out
    (the connector's ``connected``, the scene's answer, among them)."""
    r = twin("run", "scenes/insertion.yaml", "--recording", "recordings/insertion_00.mcap", "--run-dir", str(tmp_path))
    assert r.returncode == 0, r.stdout + r.stderr
    log = tmp_path / "run.mcap"
    decode_every_message(log)  # (raises on the first message its schema refuses)
    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
    for sc in summary.schemas.values():
        if sc.encoding == "jsonschema":
            viewer_fields(json.loads(sc.data))
    events = Counter(f"{m['model']}.{m['name']}" for k, _, m in read_run_log(log)
                     if isinstance(m, dict) and m.get("type") == "event")
    with open(log, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        logged = Counter(m.message.split(" ", 1)[0] for *_, m in reader.iter_decoded_messages(topics=["/twin/log"]))
    assert events["connector.connected"] == 1 and logged == events, (logged, events)
