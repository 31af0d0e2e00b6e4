"""ROS 2 robots on rmw_zenoh: the twin attaches to a publisher that emits exactly rmw_zenoh's format.

The publisher in this file is written from rmw_zenoh's design document (docs/design.md), independently
of protocol/ros2.py: data key ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, CDR payload
with its encapsulation header, a 33-byte attachment (int64 LE sequence number, int64 LE source timestamp in
ns, one byte GID length = 16, 16 bytes GID), and the graph's liveliness tokens with mangled names.
"""
from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.netns import python_cmd, wait_exit
from conductor.core import Conductor, RunOptions
from conductor.launch import open_router
from conductor.runlog import read_run_log
from conductor.scene import load_scene
from conductor.sources import ros2 as ros2_source
from conductor.sources.recording import load_recording
from protocol import ros2
from protocol.errors import RunAborted
from protocol.keys import Keys
from recordings.simple import core_recording

from .conftest import spawn_agents, wait_until
from .test_compose import explain, handover_story, single_host_reference

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
SCENE = "tests/core_scene.yaml"

JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


# ------------------------------------------------------------ a ROS 2 node, by the book
def cdr_joint_state(sec: int, nanosec: int, names, position, velocity, effort) -> bytes:
    body = bytearray()

    def align(n):
        body.extend(b"\x00" * (-len(body) % n))

    def u32(v, fmt="<I"):
        align(4)
        body.extend(struct.pack(fmt, v))

    def string(s):
        raw = s.encode() + b"\x00"
        u32(len(raw))
        body.extend(raw)

    def doubles(xs):
        u32(len(xs))
        if xs:
            align(8)
            body.extend(struct.pack(f"<{len(xs)}d", *xs))

    u32(sec, "<i")          # header.stamp.sec (int32)
    u32(nanosec)            # header.stamp.nanosec (uint32)
    string("")              # header.frame_id
    u32(len(names))         # name: sequence<string>
    for n in names:
        string(n)
    doubles(position)
    doubles(velocity)
    doubles(effort)
    return b"\x00\x01\x00\x00" + bytes(body)  # CDR little endian encapsulation


def cdr_string(s: str) -> bytes:
    raw = s.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


class RosNode:
    """A ROS 2 node on rmw_zenoh publishing /joint_states and /action in domain ``domain``."""

    def __init__(self, session, domain: int, node: str = "franka_state", keyed: bool = False):
        self.session, self.keyed = session, keyed  # keyed: the attachment of rmw_zenoh's first releases
        zid = str(session.info.zid())
        self.js_key = f"{domain}/joint_states/sensor_msgs::msg::dds_::JointState_/{JOINT_STATE_HASH}"
        self.act_key = f"{domain}/action/std_msgs::msg::dds_::String_/{STRING_HASH}"
        lv = f"@ros2_lv/{domain}/{zid}/0"
        self.tokens = [
            session.liveliness().declare_token(f"{lv}/0/NN/%/%/{node}"),
            session.liveliness().declare_token(
                f"{lv}/10/MP/%/%/{node}/%joint_states/sensor_msgs::msg::dds_::JointState_/{JOINT_STATE_HASH}/::,10:,:,:,,"),
            session.liveliness().declare_token(
                f"{lv}/11/MP/%/%/{node}/%action/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"),
        ]
        self.pubs = {"js": session.declare_publisher(self.js_key), "act": session.declare_publisher(self.act_key)}
        self.gids = {"js": os.urandom(16), "act": os.urandom(16)}
        self.seq = {"js": 0, "act": 0}

    def _put(self, which: str, payload: bytes) -> None:
        self.seq[which] += 1
        if self.keyed:  # (Jazzy 0.2.0-0.2.3: each value after its name, strings and the GID after a varint length)
            att = (b"\x0fsequence_number" + struct.pack("<q", self.seq[which]) + b"\x10source_timestamp"
                   + struct.pack("<q", time.time_ns()) + b"\x0asource_gid" + bytes([16]) + self.gids[which])
            assert len(att) == 77
        else:
            att = struct.pack("<qqB", self.seq[which], time.time_ns(), 16) + self.gids[which]
            assert len(att) == 33
        self.pubs[which].put(payload, attachment=att)

    def joint_state(self, names, position, velocity, effort, stamp_ns: int | None = None) -> None:
        """Stamped by this host's wall clock, or ``stamp_ns`` (a robot on sim time; 0: a header left unstamped)."""
        now = time.time_ns() if stamp_ns is None else stamp_ns
        self._put("js", cdr_joint_state(now // 10**9, now % 10**9, names, position, velocity, effort))

    def action(self, operation: str, phase: str, **params) -> None:
        self._put("act", cdr_string(json.dumps({"operation": operation, "phase": phase, "params": params})))

    def raw(self, which: str, payload: bytes) -> None:
        self._put(which, payload)

    def close(self) -> None:
        for p in self.pubs.values():
            p.undeclare()
        for t in self.tokens:
            t.undeclare()


# ------------------------------------------------------------------------- tests
def test_key_expressions_follow_the_design_document():
    """The twin builds the exact keys of rmw_zenoh's design document examples."""
    assert ros2.topic_key(0, "/chatter", ros2.STRING, STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.topic_key(0, "chatter", ros2.STRING, STRING_HASH, namespace="/robot1") == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.topic_key(2, "/joint_states", ros2.JOINT_STATE) == \
        "2/joint_states/sensor_msgs::msg::dds_::JointState_/*"
    assert ros2.liveliness_key(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "MP", "talker", topic="/chatter",
                               ros_type=ros2.STRING, type_hash=STRING_HASH, qos="::,7:,:,:,,") == \
        f"@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    assert ros2.liveliness_key(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 0, "NN", "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert ros2.mangle("/robot1/joint_states") == "%robot1%joint_states"


def test_cdr_matches_rosbags_and_decodes_back():
    """The twin's CDR encoder writes what rosbags writes; its decoder reads what this file's node writes."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    JS, H, T = (ts.types[n] for n in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header",
                                      "builtin_interfaces/msg/Time"))
    names, pos, vel = ["panda_joint1", "panda_finger_joint1"], [0.25, 0.04], [0.5, -1.0]
    ref = ts.serialize_cdr(JS(header=H(stamp=T(sec=1_700_000_001, nanosec=500_000_000), frame_id=""), name=names,
                              position=np.array(pos), velocity=np.array(vel), effort=np.array([], dtype=float)),
                           "sensor_msgs/msg/JointState")
    assert ros2.encode_joint_state(1_700_000_001.5, names, pos, vel, []) == bytes(ref)
    assert cdr_joint_state(1_700_000_001, 500_000_000, names, pos, vel, []) == bytes(ref)
    msg = ros2.decode_joint_state(bytes(ref))
    assert msg == {"stamp": 1_700_000_001.5, "name": names, "position": pos, "velocity": vel, "effort": []}
    act = ros2.decode_action(cdr_string('{"operation": "move_hand", "phase": "end", "params": {"command": "close"}}'),
                             1_700_000_002_000_000_000)
    assert act == {"stamp": 1_700_000_002.0, "operation": "move_hand", "phase": "end", "params": {"command": "close"}}
    seq, stamp, gid = ros2.decode_attachment(struct.pack("<qqB", 7, 123, 16) + b"g" * 16)
    assert (seq, stamp, gid) == (7, 123, b"g" * 16)
    with pytest.raises(ValueError):
        ros2.decode_attachment(b"\x00" * 32)


_floats = st.lists(st.floats(allow_nan=False, width=64), max_size=11)


@settings(max_examples=150, deadline=None)
@given(names=st.lists(st.text(max_size=13), max_size=11), frame=st.text(max_size=9), pos=_floats, vel=_floats,
       eff=_floats, ns=st.integers(0, 2**31 * 10**9 - 1), as_array=st.booleans())
def test_joint_state_cdr_matches_rosbags_for_any_layout(names, frame, pos, vel, eff, ns, as_array):
    """Every padding the sequences can need (names and frame ids of any length, sequences of any length, empty
    ones, sequences given as numpy arrays): the encoder writes byte for byte what rosbags writes."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    JS, H, T = (ts.types[n] for n in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header",
                                      "builtin_interfaces/msg/Time"))
    sec, nanosec = divmod(ns, 1_000_000_000)
    ref = ts.serialize_cdr(JS(header=H(stamp=T(sec=sec, nanosec=nanosec), frame_id=frame), name=names,
                              position=np.array(pos, dtype=float), velocity=np.array(vel, dtype=float),
                              effort=np.array(eff, dtype=float)), "sensor_msgs/msg/JointState")
    seqs = [np.array(v, dtype=float) if as_array else v for v in (pos, vel, eff)]
    assert ros2.encode_joint_state(0.0, names, *seqs, frame_id=frame, stamp_ns=ns) == bytes(ref)


@pytest.mark.slow
def test_twin_attaches_to_a_ros2_robot(tmp_path, procs):
    """A ROS 2 node in domain 0 drives the core scene through the twin's Ros2Source: same interpretation as
    the replay, lag measured, a node of another domain ignored, a malformed CDR message counted, joint states with
    a NaN effort (a gripper driver's) taken with the efforts before, not left out."""
    rec_path = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    rec = load_recording(rec_path)
    session, endpoint = open_router()
    keys = Keys("ros")
    scene = load_scene(ROOT / SCENE)
    robot_session = other_session = None
    c = None
    try:
        spawn_agents(procs, scene, endpoint, "ros")
        source = ros2_source.Ros2Source(session, keys, domain=0, idle_timeout=1.5)
        c = Conductor(scene, session, keys, source, RunOptions(run_log=str(tmp_path / "run.mcap"), register_timeout=60))
        result = {}
        runner = threading.Thread(target=lambda: result.setdefault("summary", c.run()), daemon=True)
        runner.start()
        agents = c.registry.agents
        assert wait_until(lambda: len(agents) == len(scene.models) and all(a.ready for a in agents.values()),
                          timeout=60)
        from protocol.config import ZenohOptions

        robot_session = ZenohOptions(mode="client", connect=[endpoint]).open()
        other_session = ZenohOptions(mode="client", connect=[endpoint]).open()
        robot, other = RosNode(robot_session, 0), RosNode(other_session, 1, node="another_robot")
        time.sleep(0.3)
        robot.raw("js", b"\x00\x01\x00\x00\x05")  # a truncated CDR message: counted, never fatal
        start, nans = time.monotonic(), 0
        for stamp, kind, msg in rec.items:  # the robot works at its own pace (wall clock)
            delay = start + stamp - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if kind == "joint_state":
                nans += (nan := bool(msg["effort"]) and nans < 10 and stamp > 1.0)  # a gripper driver's NaN effort
                robot.joint_state(msg["name"], msg["position"], msg["velocity"],
                                  [math.nan] * len(msg["effort"]) if nan else msg["effort"])
                other.joint_state(msg["name"], [9.0] * len(msg["name"]), msg["velocity"], msg["effort"])
            else:
                robot.action(msg["operation"], msg["phase"], **msg["params"])
        runner.join(timeout=60)
        assert not runner.is_alive()
        s = result["summary"]
        robot.close()
        other.close()
    finally:
        if c is not None:
            c.close()
        for sess in (robot_session, other_session):
            if sess is not None:
                sess.close()
        session.close()
    assert s["errors"] == [], s["errors"]
    lag = s["lag"]
    assert lag["ros2_domain"] == 0 and lag["received"] == {"joint_state": 300, "action": 1}
    assert lag["malformed"] == 1 and lag["sequence_gaps"] == 0
    # ten joint states with a NaN effort were taken (their efforts from the one before), not left out
    assert nans == 10 and "10 joint states with NaN or infinite efforts: each taken from the joint state before, " \
        "or left out (the positions are whole)" in s.get("input_notes", []), s.get("input_notes")
    assert lag["samples"] == 300 and 0 <= lag["p50_ms"] <= lag["p99_ms"]
    # clock-driven models and the run log saw the robot through the twin's own telemetry keys
    finger = [m["position"] for k, _, m in read_run_log(s["run_log"]) if k.endswith("/telemetry/joint_states")]
    assert len(finger) == 300 and all(9.0 not in p for p in finger)  # nothing from domain 1
    ref = single_host_reference(tmp_path, SCENE, rec_path)
    assert s["semantic_state"] == ref["semantic_state"], explain(s, ref)
    assert handover_story(s) == handover_story(ref), explain(s, ref)


def test_robot_play_publishes_rmw_zenoh_format(tmp_path):
    """`twin robot play --ros2-domain 3` emits rmw_zenoh keys, CDR that rosbags reads, 33-byte attachments
    and a publisher liveliness token, as a ROS 2 node would."""
    from rosbags.typesys import Stores, get_typestore

    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    session, endpoint = open_router()
    got, tokens = [], []
    sub = session.declare_subscriber("3/**", lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment is not None else None)))
    lv = session.liveliness().declare_subscriber("@ros2_lv/3/**", lambda s: tokens.append(str(s.key_expr)))
    try:
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "robot", "play", str(rec), "--connect", endpoint,
                            "--ros2-domain", "3", "--lead-in", "0.5"],
                           capture_output=True, text=True, timeout=60, env=ENV, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        time.sleep(0.2)
    finally:
        sub.undeclare()
        lv.undeclare()
        session.close()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    js = [(k, p, a) for k, p, a in got if "/joint_states/" in k]
    assert len(js) == 100
    assert {k for k, _, _ in js} == {f"3/joint_states/sensor_msgs::msg::dds_::JointState_/{JOINT_STATE_HASH}"}
    seqs = []
    for _, payload, att in js:
        m = ts.deserialize_cdr(payload, "sensor_msgs/msg/JointState")
        assert list(m.name) == ["j1", "finger"] and m.header.stamp.sec > 1_700_000_000
        assert len(att) == 33 and att[16] == 16
        seqs.append(struct.unpack("<q", att[:8])[0])
    assert seqs == list(range(1, 101))
    acts = [p for k, p, _ in got if k.startswith("3/action/std_msgs::msg::dds_::String_/")]
    assert len(acts) == 1 and json.loads(ts.deserialize_cdr(acts[0],
                                                            "std_msgs/msg/String").data)["operation"] == "move_hand"
    assert any("/MP/%/%/twin_robot_play/%joint_states/sensor_msgs::msg::dds_::JointState_/" in t for t in tokens)


def _cli_has_ros2_flag() -> bool:
    from conductor.cli.main import build_parser

    _, extra = build_parser().parse_known_args(["run", "scene.yaml", "--ros2-domain", "0"])
    return not extra


@pytest.mark.slow
@pytest.mark.skipif(not _cli_has_ros2_flag(), reason="`twin run --ros2-domain` not wired into conductor/cli.py yet "
                                                     "(change reported with issue 5)")
def test_cli_twin_follows_ros2_robot_on_another_host(lan, tmp_path):
    """`twin run SCENE --ros2-domain 0` on one host follows `twin robot play --ros2-domain 0` on another:
    lag reported, same interpretation as the replay."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    twin_host, robot_host = lan.add_host("twin"), lan.add_host("robot")
    summary = tmp_path / "ros2.json"
    twin = twin_host.spawn("twin", python_cmd(
        "run", SCENE, "--ros2-domain", "0", "--listen", "tcp/0.0.0.0:7447", "--ensemble", "ros2cli",
        "--open-bus",  # a ROS 2 robot on rmw_zenoh brings no twin credentials
        "--idle-timeout", "2", "--summary", str(summary), "--run-dir", str(tmp_path / "run")), cwd=str(ROOT))
    lan.wait_reachable(robot_host, twin_host)
    robot = robot_host.spawn("robot", python_cmd(
        "robot", "play", str(rec), "--connect", "tcp/twin:7447", "--ensemble", "ros2cli", "--wait-twin", "90",
        "--ros2-domain", "0"))
    assert wait_exit(robot, 120, lan.logdir / "agent-robot.log") == 0
    assert wait_exit(twin, 60, lan.logdir / "agent-twin.log") == 0
    s = json.loads(summary.read_text())
    assert s["errors"] == [], s["errors"]
    assert s["lag"]["ros2_domain"] == 0 and s["lag"]["received"] == {"joint_state": 300, "action": 1}
    ref = single_host_reference(tmp_path, SCENE, rec)
    assert s["semantic_state"] == ref["semantic_state"], explain(s, ref)
    assert handover_story(s) == handover_story(ref), explain(s, ref)


def test_a_ros2_robot_on_sim_time_keeps_its_actions():
    """A robot on sim time stamps its joint states by the simulation; an action annotation (a String, no header)
    and a JointState whose header says 0 have no stamp of their own. They were stamped by the sender's wall clock
    (ROS 2's source timestamp): the actions, 1.7e9 s ahead of the joint states, were all left out. Now a message
    without a stamp is stamped by the robot's clock as it comes (the last joint state's stamp and the time since);
    a robot on the wall clock keeps the sender's time, as before. Real Zenoh, rmw_zenoh's wire format."""
    from protocol.config import ZenohOptions

    session, endpoint = open_router()
    source = ros2_source.Ros2Source(session, Keys("simtime"), domain=0, republish=False)
    robot_session = None
    try:
        robot_session = ZenohOptions(mode="client", connect=[endpoint]).open()
        robot = RosNode(robot_session, 0)
        time.sleep(0.3)
        sim0 = 12_000_000_000  # the simulation's clock: 12 s
        for i in range(60):
            stamp = 0 if i == 30 else sim0 + i * 10_000_000
            robot.joint_state(["j1"], [0.01 * i], [], [], stamp_ns=stamp)
            if i in (20, 40):
                robot.action("grip", "start" if i == 20 else "end")
            time.sleep(0.01)
        assert wait_until(lambda: sum(source.queued.values()) + sum(source.left_out.values()) >= 62, timeout=10)
        robot.close()
        taken = source.due(1e9)
        assert source.left_out == {}, source.left_out
        assert [k for k, _ in taken].count("action") == 2 and [k for k, _ in taken].count("joint_state") == 60
        actions = {m["phase"]: m["stamp"] for k, m in taken if k == "action"}
        for i, phase in ((20, "start"), (40, "end")):  # on the simulation's clock, after the joint state before it
            assert 12.0 + i * 0.01 <= actions[phase] <= 12.0 + i * 0.01 + 0.5, (phase, actions)
        unstamped = next(m["stamp"] for k, m in taken if k == "joint_state" and m["position"] == [0.3])
        assert 12.29 <= unstamped <= 12.29 + 0.5, unstamped
        assert source.warnings() == [], source.warnings()
    finally:
        source.close()
        if robot_session is not None:
            robot_session.close()
        session.close()


def test_a_ros2_robot_whose_first_joint_states_say_stamp_0_keeps_its_sim_time_after():
    """A ROS 2 node on sim time stamps 0 until its first /clock: its first joint states were stamped as they came
    (the wall clock, 1.7e9 s), and every one after them, on the simulation's 12 s, was left out as stamped before
    the one before it. Now the robot's clock, when it comes, is taken to go on from the unstamped ones, and the
    run says so. Real Zenoh, rmw_zenoh's wire format."""
    from protocol.config import ZenohOptions

    session, endpoint = open_router()
    source = ros2_source.Ros2Source(session, Keys("simstart"), domain=0, republish=False)
    robot_session = None
    try:
        robot_session = ZenohOptions(mode="client", connect=[endpoint]).open()
        robot = RosNode(robot_session, 0)
        time.sleep(0.3)
        sim0 = 12_000_000_000
        for i in range(60):
            robot.joint_state(["j1"], [0.01 * i], [], [], stamp_ns=0 if i < 10 else sim0 + i * 10_000_000)
            if i in (5, 40):
                robot.action("grip", "start" if i == 5 else "end")
            time.sleep(0.01)
        assert wait_until(lambda: sum(source.queued.values()) + sum(source.left_out.values()) >= 62, timeout=10)
        robot.close()
        taken = source.due(1e12)
        assert source.left_out == {}, source.left_out
        joints = [m["stamp"] for k, m in taken if k == "joint_state"]
        assert len(joints) == 60 and [k for k, _ in taken].count("action") == 2
        steps = [b - a for a, b in zip(joints, joints[1:])]
        assert all(-0.5 <= s <= 0.5 for s in steps), steps  # one timeline through the robot's clock coming in
        assert 0.0 < joints[10] - joints[9] <= 0.5, joints[8:12]
        actions = {m["phase"]: m["stamp"] for k, m in taken if k == "action"}
        assert joints[5] <= actions["start"] <= joints[6] + 0.5 and joints[40] <= actions["end"] <= joints[41] + 0.5
        warned = source.warnings()
        assert len(warned) == 1 and "first 10 joint states had no stamp" in warned[0], warned
        # the robot's own clock, for what the twin stamps (/tf): the simulation's 12.1 s where its stamps began
        assert source.robot_time(joints[10] - source.t0) == pytest.approx(12.1, abs=1e-6)
        from types import SimpleNamespace

        from conductor.ros2_out import Ros2Out

        out = Ros2Out(session, 0, 0.01).attach(SimpleNamespace(taps=[], origin_ns=0), source)
        try:
            tick = round((joints[30] - source.t0) / 0.01)
            assert out._stamp_ns(tick) * 1e-9 == pytest.approx(12.3, abs=0.011)  # (its tick's 10 ms)
        finally:
            out.close()
    finally:
        source.close()
        if robot_session is not None:
            robot_session.close()
        session.close()


def test_a_ros2_robot_of_an_early_rmw_zenoh_on_sim_time_whose_action_comes_first():
    """rmw_zenoh's first releases put a keyed attachment (each value after its name, 77 bytes) on every message: the
    twin took them all for malformed and left every one out. And a robot on sim time whose action annotation came
    before its first joint state: the action was stamped by the wall clock, which made the run's time 0, so every
    joint state was taken at once and the action's end left out as behind its start. Now the keyed attachment is
    read (its sequence numbers checked), an attachment the twin cannot read only loses its metadata (a note), and
    an action before the first joint state is stamped on that joint state's clock. Real Zenoh."""
    from protocol.config import ZenohOptions

    session, endpoint = open_router()
    source = ros2_source.Ros2Source(session, Keys("keyed"), domain=0, republish=False, wait_first=0.5)
    robot_session = None
    try:
        robot_session = ZenohOptions(mode="client", connect=[endpoint]).open()
        robot = RosNode(robot_session, 0, keyed=True)
        time.sleep(0.3)
        robot.action("pick", "start")
        assert wait_until(lambda: source._last_arrival is not None, timeout=10)
        # (an action held for the first joint state does not begin the run: its time 0 is not known yet)
        with pytest.raises(RunAborted, match="1 action annotations came, but no joint state within 0.5 s"):
            source.wait_for_data(threading.Event())
        sim0 = 12_000_000_000
        for i in range(50):
            if i == 25:
                robot.seq["js"] += 1  # one publication lost on the way
            robot.joint_state(["j1"], [0.01 * i], [], [], stamp_ns=sim0 + i * 10_000_000)
            if i == 40:
                robot.action("pick", "end")
            time.sleep(0.01)
        robot.pubs["js"].put(cdr_joint_state(12, 500_000_000, ["j1"], [0.5], [], []), attachment=b"\x01\x02")
        assert wait_until(lambda: sum(source.queued.values()) + sum(source.left_out.values()) >= 53, timeout=10)
        robot.close()
        taken = source.due(1e9)
        assert source.left_out == {}, source.left_out
        assert [k for k, _ in taken].count("action") == 2 and [k for k, _ in taken].count("joint_state") == 51
        actions = {m["phase"]: m["stamp"] for k, m in taken if k == "action"}
        assert taken[0][0] == "action" and source.t0 == actions["start"], taken[:2]
        assert 12.0 - 10 < actions["start"] < 12.0 and 12.4 <= actions["end"] <= 12.4 + 0.5, actions
        assert source.dropped == 1 and source.unread_attachments == 1
        warned = source.warnings()
        assert len(warned) == 1 and "1 of the robot's ROS 2 publication never came" in warned[0], warned
        assert any("1 of the robot's ROS 2 publication carried an attachment the twin could not read" in n
                   for n in source.notes()), source.notes()
    finally:
        source.close()
        if robot_session is not None:
            robot_session.close()
        session.close()


def test_a_live_action_annotation_is_checked_as_a_replayed_one():
    """An operation that is not a name (5, ""), or params that are a list of pairs, were taken live (``str(5)``,
    ``dict(pairs)``) and refused in a replay of the same bag; one check now, with the recording's words."""
    def decode(obj) -> dict:
        return ros2.decode_action(cdr_string(json.dumps(obj)), 2_000_000_000)

    assert decode({"operation": "grip"}) == {"stamp": 2.0, "operation": "grip", "phase": "start", "params": {}}
    for bad, why in (({"operation": 5}, "without an 'operation' name"), ({"operation": ""}, "without an 'operation'"),
                     ({"operation": "grip", "params": [["a", 1]]}, "params are not a map"),
                     ({"operation": "grip", "phase": "middle"}, "phase is not 'start' or 'end'")):
        with pytest.raises(ValueError, match=why):
            decode(bad)
    with pytest.raises(ValueError, match="not JSON"):
        ros2.decode_action(cdr_string("{grip"), None)
