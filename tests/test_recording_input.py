"""Bad robot recordings and perception files: a clear error naming the file (and key), or the malformed
messages left out, counted and reported — never a traceback, a hang, or NaN passed on to the models."""
from __future__ import annotations

import json
import math
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from conductor.scene import check_perception
from conductor.scene.perception import load_perception
from conductor.sources.recording import load_recording
from protocol.errors import TwinError
from protocol.robot import resolve_robot
from recordings.rosbag import RecordingWriter

ROOT = Path(__file__).resolve().parent.parent
NAMES = ["j1", "finger"]


def write(path, n=100, namespace="", extra=None):
    """``n`` joint states at 100 Hz (the finger closes from 0.8 s to 2.0 s, as in the core scene's
    recording), a move_hand end at 0.5 s, and whatever ``extra`` adds."""
    with RecordingWriter(path, namespace=namespace) as w:
        for i in range(n):
            w.joint_state(i / 100, NAMES, [0.1, 0.2 if 0.8 < i / 100 < 2.0 else 1.0], [0.0, 0.0], [0.0, 0.0])
        w.action(0.5, "move_hand", "end", hand="right")
        if extra:
            extra(w)
    return path


def test_malformed_messages_are_left_out_counted_and_reported(tmp_path):
    def bad(w):
        w.joint_state(1.1, NAMES, [0.1], [0.0, 0.0], [0.0, 0.0])                   # lengths differ
        w.joint_state(1.2, NAMES, [float("nan"), 0.2], [], [])                     # NaN
        w.joint_state(1.3, NAMES, [0.1, float("inf")], [], [])                     # inf
        w.raw_action(1.4, '{"operation": "grasp", "phase": "middle"}')             # bad phase
        w.raw_action(1.5, '{"phase": "start"}')                                    # no operation
        w.raw_action(1.6, "not json")
        w.raw_action(1.7, "[" * 100_000 + "]" * 100_000)                           # nested too deep
        w.joint_state(1.8, NAMES, [0.3, 0.4], [], [])                              # fine (no velocity/effort)
    rec = load_recording(write(tmp_path / "r.mcap", extra=bad))
    js = [m for _, k, m in rec.items if k == "joint_state"]
    assert len(js) == 101 and js[-1]["position"] == [0.3, 0.4]
    assert all(all(v == v for v in m["position"]) for m in js)  # no NaN got through
    assert [m["operation"] for _, k, m in rec.items if k == "action"] == ["move_hand"]
    assert sum(rec.skipped.values()) == 7
    assert rec.skipped["joint states with NaN, infinite or non-numeric values"] == 2
    assert rec.skipped["action annotations that are not JSON"] == 2
    lines = rec.warnings()
    assert len(lines) == 6 and all(line.startswith(str(tmp_path / "r.mcap")) for line in lines)
    # the joint states left out leave a hole from 0.99 s to the good one at 1.8 s: said too
    assert "its joint states stop 1 time for more than 0.5 s (the longest 0.81 s from t=0.99 s)" in lines[-1]


def test_nan_efforts_leave_the_positions_in_use(tmp_path):
    """A gripper driver that reports NaN efforts (common) made every joint state be left out, and the run refused
    the bag for having no joint states with names. The positions are whole: a NaN effort (or velocity) is taken from
    the same joint's joint state before (a missing effort would read as a hand let go), and a note counts them; a
    NaN position still leaves the joint state out."""
    def bad(w):
        w.joint_state(1.1, NAMES, [0.1, 0.2], [0.0, 0.0], [5.0, float("nan")])    # a NaN effort: the one before
        w.joint_state(1.2, NAMES, [0.1, 0.2], [float("inf"), 0.5], [6.0, 7.0])    # an infinite velocity: the same
        w.joint_state(1.3, NAMES, [float("nan"), 0.2], [0.0, 0.0], [0.0, 0.0])    # a NaN position: left out
    rec = load_recording(write(tmp_path / "r.mcap", extra=bad))
    js = {round(m["stamp"], 3): m for _, k, m in rec.items if k == "joint_state"}
    assert js[1.1]["effort"] == [5.0, 0.0] and js[1.1]["velocity"] == [0.0, 0.0] and js[1.1]["position"] == [0.1, 0.2]
    assert js[1.2]["velocity"] == [0.0, 0.5] and js[1.2]["effort"] == [6.0, 7.0]
    assert 1.3 not in js and rec.skipped == {"joint states with NaN, infinite or non-numeric values": 1}
    notes = rec.notes()
    assert any("1 joint state with NaN or infinite efforts: each taken from the joint state before" in n
               for n in notes), notes
    assert any("1 joint state with NaN or infinite velocities" in n for n in notes), notes


def test_a_gripper_on_a_topic_of_its_own_is_pointed_at(tmp_path):
    """The arm on /joint_states, the fingers on /gripper/joint_states: the fingers are missing from what the twin
    reads, and the warning told the user to map joints the bag names exactly. It now names the topic it did not read
    and the --remap that merges it (which then fits)."""
    from conductor.sources.fit import check_fit

    panda = resolve_robot({"use": "panda"})
    path = tmp_path / "split.mcap"
    with RecordingWriter(path) as w:
        for i in range(50):
            w.joint_topic = "/joint_states"
            w.joint_state(i / 100, panda.arm, [0.0] * 7, [], [])
            w.joint_topic = "/gripper/joint_states"
            w.joint_state(i / 100 + 0.005, panda.gripper.joints, [0.04, 0.04], [], [])
    rec = load_recording(path)
    (why,) = check_fit(panda, rec.joints_in_order, str(path), rec)
    assert "panda_finger_joint1, panda_finger_joint2 are not in the telemetry" in why and "the bag has JointState " \
        "topics it did not read (/gripper/joint_states): if one carries them (not a commanded or desired state), " \
        "merge it with --remap /joint_states:=/joint_states --remap /joint_states:=TOPIC, or map them" in why, why
    merged = load_recording(path, remap=["/joint_states:=/joint_states", "/joint_states:=/gripper/joint_states"])
    assert check_fit(panda, merged.joints_in_order, str(path), merged) == []


def test_namespaced_robot_topics_are_found(tmp_path):
    rec = load_recording(write(tmp_path / "ns.mcap", namespace="/panda"))
    assert [k for _, k, _ in rec.items].count("joint_state") == 100
    assert [k for _, k, _ in rec.items].count("action") == 1


def test_corrupted_bytes_are_an_error_not_different_data(tmp_path):
    path = write(tmp_path / "c.mcap")
    data = bytearray(path.read_bytes())
    data[len(data) // 4] ^= 0x10  # inside the (compressed, CRC-checked) chunk of messages
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(TwinError, match="flipped.mcap: no usable .* 1 chunk of its messages cannot be read"):
        load_recording(bad)


def _unstamped(m: dict) -> dict:
    return {k: v for k, v in m.items() if k != "stamp"}  # (stamps count from the first message read)


def test_a_damaged_chunk_is_left_out_and_said_the_rest_replayed(tmp_path):
    """One byte flipped in a chunk of a recording (a bad disk block, a copy gone wrong) refused the whole file, though
    its other chunks were sound. That chunk's messages are now left out and said (its CRC fails: never read as other
    data), the rest replayed as the whole file has them; the run is degraded, twin check exits 3."""
    from mcap.reader import make_reader

    src = ROOT / "recordings" / "ball_drop_00.mcap"
    with open(src, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) == 2, "ball_drop_00 holds two chunks of messages"
    whole = load_recording(src)
    for k, chunk in enumerate(chunks):
        data = bytearray(src.read_bytes())
        data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x10
        bad = tmp_path / f"chunk{k}.mcap"
        bad.write_bytes(bytes(data))
        part = load_recording(bad)
        shift = (part.origin_ns - whole.origin_ns) * 1e-9  # (its first message is another when chunk 0 is lost)
        kept = [(s + shift, kind, _unstamped(m)) for s, kind, m in part.items]
        lost = ((chunk.message_start_time - whole.origin_ns) * 1e-9, (chunk.message_end_time - whole.origin_ns) * 1e-9)
        expect = [(s, kind, _unstamped(m)) for s, kind, m in whole.items
                  if not lost[0] - 1e-9 <= s <= lost[1] + 1e-9]
        assert 100 < len(kept) < len(whole.items) and [x[1:] for x in kept] == [x[1:] for x in expect]
        assert [x[0] for x in kept] == pytest.approx([x[0] for x in expect], abs=1e-6)
        said = [w for w in part.warnings() if "cannot be read" in w]
        assert len(said) == 1 and "CRCValidationError" in said[0], part.warnings()
        assert ("before the first message read" in said[0]) == (k == 0), said
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", str(ROOT / "scenes" / "ball_drop.yaml"),
                        "--recording", str(bad)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 3 and "t=8.65 to 9.88 s) cannot be read" in r.stderr, r.stdout + r.stderr


def test_log_times_from_two_clocks_are_an_error_not_a_day_long_replay(tmp_path):
    def far(w):
        w.joint_state(2e9 - 1.7e9 - 1, NAMES, [0.1, 0.2], [], [])  # a stamp from another clock
    with pytest.raises(TwinError, match="more than a day"):
        load_recording(write(tmp_path / "mixed.mcap", extra=far))


def test_bad_perception_is_an_error_naming_file_and_key(tmp_path):
    cases = {
        "null.json": "null",
        "list.json": "[]",
        "pose.json": json.dumps({"entities": {"ball": {"pose": "abc"}}}),
        "nan.yaml": "entities: {ball: {pose: [.nan, 0, 0.1]}}",
        "short.yaml": "entities: {ball: {pose: [1, 2]}}",
        "mass.yaml": "entities: {ball: {mass: heavy}}",
        "shape.yaml": "entities: {ball: {shape: {type: sphere, radius: -1}}}",
    }
    keys = {"pose.json": "entities.ball.pose", "nan.yaml": "entities.ball.pose", "short.yaml": "entities.ball.pose",
            "mass.yaml": "entities.ball.mass", "shape.yaml": "entities.ball.shape"}
    for name, text in cases.items():
        p = tmp_path / name
        p.write_text(text)
        with pytest.raises(TwinError) as e:
            load_perception(str(p))
        assert str(e.value).startswith(str(p)), str(e.value)
        assert keys.get(name, "entities") in str(e.value), str(e.value)
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"entities: {}\n\xff\xfe")
    with pytest.raises(TwinError, match="bin.yaml"):
        load_perception(str(binary))
    assert check_perception({"entities": {"ball": {"pose": [0.5, 0, 0.1], "mass": 0.05}}}, "x") is not None


def test_a_perception_as_python_writes_json_is_read(tmp_path):
    """``json.dumps`` writes 0.00001 as ``1e-05``, which YAML 1.1 reads as a string: the pose was refused as not
    numbers; and JSON indented with tabs was a YAML syntax error. A key given twice is still refused."""
    ok = tmp_path / "perceived.json"
    ok.write_text(json.dumps({"entities": {"ball": {"pose": [0.45, 1e-05, 0.135], "mass": 5e-2}}}, indent="\t"))
    assert load_perception(str(ok)) == {"entities": {"ball": {"pose": [0.45, 1e-05, 0.135], "mass": 0.05}}}
    twice = tmp_path / "twice.json"
    twice.write_text('{\n\t"entities": {"ball": {"pose": [1, 2, 3]}, "ball": {}}\n}')
    with pytest.raises(TwinError, match="twice.json: duplicate key 'ball'"):
        load_perception(str(twice))
    broken = tmp_path / "broken.json"
    broken.write_text('{\n\t"entities": {"ball": {"pose": [1, 2, 3]},}\n}')
    with pytest.raises(TwinError, match=r"broken.json: not valid JSON: .*line 2"):
        load_perception(str(broken))


def test_recording_with_broken_perception_metadata_is_a_clean_cli_error(tmp_path):
    rec = write(tmp_path / "meta.mcap", extra=lambda w: w.metadata("twin.scene", {"json": "{not json"}))
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "tests/core_scene.yaml", "--recording", str(rec),
                        "--run-dir", str(tmp_path / "run")], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    assert "meta.mcap: metadata 'twin.scene' is not valid JSON" in r.stderr + r.stdout


@pytest.mark.slow
def test_run_reports_left_out_messages_in_its_summary(tmp_path):
    def bad(w):
        for i in range(5):
            w.joint_state(1.0 + i / 100 + 0.005, NAMES, [float("nan"), 0.2], [], [])
    rec = write(tmp_path / "nan.mcap", n=300, extra=bad)
    out = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "tests/core_scene.yaml", "--recording", str(rec),
                        "--summary", str(out), "--run-dir", str(tmp_path / "run")], capture_output=True, text=True,
                       timeout=180, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]  # degraded: input was left out
    s = json.loads(out.read_text())
    assert s["errors"] == [] and s["semantic_state"] == {"in(bin, ball)": True}
    assert s["status"] == "degraded" and any("NaN" in why for why in s["status_reasons"])
    assert s["input_warnings"] == [f"{rec}: 5 joint states with NaN, infinite or non-numeric values, left out"]
    assert "input: " in r.stdout


@pytest.mark.parametrize("keep", [1 / 3, 0.9999])
def test_a_recording_cut_short_is_replayed_up_to_the_cut(tmp_path, keep):
    """The recorder killed (no summary, no end, the last chunk written in part): what was written is replayed, the
    same messages as the whole file's up to the cut, and said (the run is degraded, twin check exits 3)."""
    src = ROOT / "recordings" / "ball_drop_00.mcap"
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * keep)])
    whole, part = load_recording(src), load_recording(cut)
    assert 100 < len(part.items) <= len(whole.items) and (keep > 0.99 or len(part.items) < len(whole.items) / 2)
    assert part.items == whole.items[: len(part.items)]  # nothing altered, nothing skipped before the cut
    # this recorder writes its metadata last (as rosbag2 does at close): a cut in the messages loses it
    assert part.metadata == (whole.metadata if keep > 0.99 else {}) and not whole.cut_short
    assert "cut short" in part.cut_short and any("cut short" in w for w in part.warnings())
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", str(ROOT / "scenes" / "ball_drop.yaml"),
                        "--recording", str(cut)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 3 and "cut short" in r.stderr, r.stdout + r.stderr


def test_damage_before_the_cut_is_an_error_not_a_shorter_recording(tmp_path):
    data = bytearray((ROOT / "recordings" / "ball_drop_00.mcap").read_bytes())
    data[len(data) // 4] ^= 0x10  # inside the first chunk, which was written whole
    bad = tmp_path / "damaged_and_cut.mcap"
    bad.write_bytes(bytes(data[:-100]))
    with pytest.raises(TwinError, match="damaged_and_cut.mcap"):
        load_recording(bad)


def test_a_file_too_short_or_cut_before_its_messages_says_so(tmp_path):
    """An empty or few-byte file is 'too short to be an MCAP recording' (not a struct error), and a recording cut
    before its first whole chunk of joint states says it is cut short beside 'no usable messages'."""
    from protocol.errors import TwinError

    whole = (Path(__file__).resolve().parent.parent / "recordings" / "ball_drop_00.mcap").read_bytes()
    for name, data, said in (("empty.mcap", b"", "0 bytes: too short to be an MCAP recording"),
                             ("four.mcap", b"abcd", "4 bytes: too short to be an MCAP recording"),
                             ("scene.mcap", b"# a scene\nname: x\n", "not a recording: neither an MCAP file nor an "
                                                                    "SQLite rosbag2 file"),
                             ("cut.mcap", whole[:10000], "no usable /joint_states or /action messages; the "
                                                          "recording is cut short .* before any of them was whole$")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(TwinError, match=said):
            load_recording(tmp_path / name)


@pytest.mark.slow
def test_joint_states_in_degrees_make_the_run_degraded(tmp_path):
    """A bag whose arm joints are in degrees (a driver's, or an export's) used to be replayed as radians: the twin's
    Panda spun through poses no Panda can take and the run ended complete with whatever it knocked. Positions far
    outside the robot's URDF limits are now said, and the run is degraded (exit 3)."""
    import math

    src = load_recording(str(ROOT / "recordings" / "ball_drop_00.mcap"))
    deg = tmp_path / "degrees.mcap"
    with RecordingWriter(deg) as w:
        for t, kind, m in src.items:
            if kind == "joint_state":
                arm = [math.degrees(q) if n.startswith("panda_joint") else q for n, q in zip(m["name"], m["position"])]
                w.joint_state(t, m["name"], arm, m["velocity"], m["effort"])
            else:
                w.action(t, m["operation"], m["phase"], **m["params"])
        for name, data in src.metadata.items():
            w.metadata(name, data)
    out = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/ball_drop.yaml", "--recording", str(deg),
                        "--summary", str(out), "--run-dir", str(tmp_path / "run")], capture_output=True, text=True,
                       timeout=300, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    s = json.loads(out.read_text())
    (why,) = [w for w in s["status_reasons"] if "outside the robot's limits" in w]
    assert why.startswith(f"{deg}: joint positions far outside the robot's limits: panda_joint") and \
        "Degrees for radians" in why, why
    # and the shipped recording itself is within its robot's limits (the MuJoCo reality's fingers a little past)
    # twin check says so before a run (exit 3)
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", "scenes/ball_drop.yaml", "--recording",
                        str(deg)], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3 and why in r.stderr, r.stdout[-2000:] + r.stderr[-2000:]
    from conductor.scene import parse_scene
    from conductor.sources.fit import telemetry_warnings

    for path in sorted((ROOT / "recordings").glob("*.mcap")):
        scene = "xarm_ball_drop" if "xarm" in path.name else "insertion" if "insertion" in path.name else "ball_drop"
        robot = parse_scene((ROOT / "scenes" / f"{scene}.yaml").read_text(), f"{scene}.yaml").declared_robot
        assert telemetry_warnings(robot, load_recording(str(path))) == [], path.name


def live_panda(positions: list[list[float]], period: float, scene: Path = ROOT / "scenes" / "ball_drop.yaml",
               text: str | None = None, hole_after: int | None = None) -> list[str]:
    """What a live run of ``scene``'s robot (the ball_drop Panda) says of these joint states (every ``period``
    seconds; with ``hole_after``, a second without any after that many)."""
    from conductor.scene import parse_scene
    from conductor.sources.fit import JointFit

    robot = parse_scene(text or scene.read_text(), str(scene)).declared_robot
    said: list[str] = []
    fit = JointFit(robot, object(), said.extend)  # (a source with no recording: live)
    for i, q in enumerate(positions):
        hole = 1.0 if hole_after is not None and i >= hole_after else 0.0
        fit.take({"stamp": 1000.0 + i * period + hole, "name": list(robot.joints), "position": q, "velocity": [],
                  "effort": []})
    fit.finish()
    return said


def test_a_move_across_a_gap_is_said_as_the_gap_not_again_as_a_jump():
    """The robot stopped publishing for a second and moved meanwhile: the source says the gap (the twin held its
    joints), so the move across it is not counted again as a jump; the same move between two regular joint
    states is one."""
    moved = [0.4, *READY[1:]]
    (why,) = live_panda([READY] * 10 + [moved] * 10, 0.01)
    assert "the arm jumps between two joint states 1 time: panda_joint1 by up to 0.4" in why, why
    assert live_panda([READY] * 10 + [moved] * 10, 0.01, hole_after=10) == []


def test_the_xarm_s_limits_are_read_past_its_transmissions():
    """The xArm's URDF names each joint again in a <transmission> (no type, no limits), which overwrote the joint's
    limits: a bag in degrees was said only as jumps, pointing at the wrong cause."""
    ready = [0.0, -0.5, -0.8, 0.0, 1.3, 0.0, 0.0]
    degrees = [[math.degrees(q) for q in ready[:6]] + [0.0] for _ in range(50)]
    (why,) = live_panda(degrees, 0.01, ROOT / "scenes" / "xarm_ball_drop.yaml")
    assert "joint positions far outside the robot's limits: joint2 at -28.65" in why, why


def test_a_fast_wrist_and_a_continuous_joint_s_wrap_are_no_jump(tmp_path):
    """The last joint turning the hand in place at 2.5 rad/s, 50 joint states a second (0.05 rad each), moves the tip
    little: no jump (a fixed 0.05 rad limit for every joint called it one). A continuous joint reported within one
    turn wraps from pi to -pi: no jump either."""
    wrist = [[*READY[:6], -2.8 + 0.05 * i, *READY[7:]] for i in range(100)]
    assert live_panda(wrist, 0.02) == []
    urdf = Path(__import__("pybullet_data").getDataPath()) / "franka_panda" / "panda.urdf"
    own = tmp_path / "franka_panda"
    shutil.copytree(urdf.parent, own)
    text = (own / "panda.urdf").read_text()
    at = text.index('<joint name="panda_joint7" type="revolute">')
    (own / "panda.urdf").write_text(text[:at] + text[at:].replace('type="revolute"', 'type="continuous"', 1))
    scene = (ROOT / "scenes" / "ball_drop.yaml").read_text().replace("urdf: franka_panda/panda.urdf",
                                                                      f"urdf: {own / 'panda.urdf'}, use: panda")
    turning = [[*READY[:6], (1.0 * 0.02 * i + math.pi) % (2 * math.pi) - math.pi, *READY[7:]] for i in range(400)]
    assert live_panda(turning, 0.02, text=scene) == []
    assert live_panda(turning, 0.02) != []  # (the Panda's own joint7 is revolute: there the wrap is a jump)


READY = [0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.7, 0.04, 0.04]


def test_a_live_robot_s_joints_out_of_range_are_said_at_the_run_s_end():
    """The same check live: every joint state is checked as it comes, and the run's end says the worst of each."""
    ten_in_degrees = [[*READY[:3], -90.0 + i * 0.1, *READY[4:]] if 50 <= i < 60 else READY for i in range(200)]
    said = live_panda(ten_in_degrees, 0.01)
    (why,) = [w for w in said if "outside" in w]
    assert why.startswith("the live telemetry: joint positions far outside the robot's limits: panda_joint4 at -85 "
                          "(t=0.50 s; its limits -3.142 to 0) in 10 joint states"), why


def _thinned(src: Path, dst: Path, every: int) -> Path:
    """``src`` with only every ``every``-th joint state (every action and the metadata kept)."""
    rec = load_recording(str(src))
    with RecordingWriter(dst) as w:
        joints = 0
        for t, kind, m in rec.items:
            if kind == "action":
                w.action(t, m["operation"], m["phase"], **m["params"])
            elif joints % every == 0:
                w.joint_state(t, m["name"], m["position"], m["velocity"], m["effort"])
            joints += kind == "joint_state"
        for name, data in rec.metadata.items():
            w.metadata(name, data)
    return dst


def test_a_bag_that_stops_in_the_middle_of_the_task_ends_degraded(tmp_path):
    """ball_drop_00 cut at 5.5 s, while the arm carries the ball to the container: the run said complete, ball not
    in the container, exit 0. It now says the recording ends during the action move_arm, degraded (exit 3)."""
    rec = load_recording(str(ROOT / "recordings" / "ball_drop_00.mcap"))
    cut = tmp_path / "first5s.mcap"
    with RecordingWriter(cut) as w:
        for t, kind, m in rec.items:
            if t >= 5.5:
                continue
            if kind == "action":
                w.action(t, m["operation"], m["phase"], **m["params"])
            else:
                w.joint_state(t, m["name"], m["position"], m["velocity"], m["effort"])
        for name, data in rec.metadata.items():
            w.metadata(name, data)
    summary = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/ball_drop.yaml", "--recording", str(cut),
                        "--run-dir", str(tmp_path / "run"), "--summary", str(summary)], capture_output=True,
                       text=True, timeout=300, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    s = json.loads(summary.read_text())
    assert s["status"] == "degraded" and any(
        "it ends in the middle of the robot's task: its action move_arm (begun at t=4.48 s) never ends" in why
        for why in s["status_reasons"]), s["status_reasons"]


def test_a_warn_trigger_catches_a_bag_replayed_without_its_perception(tmp_path):
    """ball_drop_00 without the perception it carries (a real robot's own bag): the ball starts at the scene's pose,
    76 cm from where the robot grasped it, and the run ends complete with the ball not in the container. A scene
    trigger with a ``warn`` effect (the grasp monitor confirms a grasp with nothing graspable within reach of the
    twin's hand) makes it degraded, exit 3, saying why."""
    rec = load_recording(str(ROOT / "recordings" / "ball_drop_00.mcap"))
    bare = tmp_path / "no_perception.mcap"
    with RecordingWriter(bare) as w:
        for t, kind, m in rec.items:
            if kind == "action":
                w.action(t, m["operation"], m["phase"], **m["params"])
            else:
                w.joint_state(t, m["name"], m["position"], m["velocity"], m["effort"])
        for name, data in rec.metadata.items():
            if name != "twin.scene":
                w.metadata(name, data)
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    scene = tmp_path / "ball_drop_warned.yaml"
    scene.write_text(text.replace("  - name: grasp_lost\n", """  - name: grasp_out_of_reach
    on: {topic: grasp_monitor.grasped}
    let: {near: "closest('graspable', 'panda_hand')"}
    when: "value == true and (near.entity == null or near.distance >= 0.15)"
    do:
      - warn: "the grasp monitor says the hand holds something, but nothing graspable is within reach"
  - name: grasp_lost
""", 1))
    summary = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(scene), "--recording", str(bare),
                        "--run-dir", str(tmp_path / "run"), "--summary", str(summary)], capture_output=True,
                       text=True, timeout=300, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    s = json.loads(summary.read_text())
    assert s["status"] == "degraded" and s["status_reasons"] == [
        "trigger grasp_out_of_reach at t=3.33 s: the grasp monitor says the hand holds something, but nothing "
        "graspable is within reach (near = {'entity': 'ball', 'distance': 0.7596})"], s["status_reasons"]


def test_joint_states_too_sparse_for_the_arm_s_motion_are_a_warning(tmp_path):
    """ball_drop_00 (the ball lands in the container) with 4 joint states a second: the twin's hand leapt 20 cm at
    a time, the ball was never grasped, and the run said COMPLETE, in(container, ball) false, with a note of the
    rate. The arm's jumps between two joint states are now a warning (twin check exits 3; a run is degraded)."""
    slow = _thinned(ROOT / "recordings" / "ball_drop_00.mcap", tmp_path / "slow4hz.mcap", 62)  # (of 250 a second)
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", "scenes/ball_drop.yaml", "--recording",
                        str(slow)], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    assert f"{slow}: the arm jumps between two joint states 26 times: panda_joint2 by up to 0.23 at t=8.93 s, 6.3 " \
        "times its limit 0.0367" in r.stderr, r.stderr
    assert "its joint states come every 0.25 s (4.03 a second)" in r.stdout, r.stdout  # (the rate itself: a note)
    assert "out of time order" not in r.stderr


def test_a_stream_whose_stamps_run_fast_moves_the_arm_faster_than_it_can(tmp_path):
    """ball_drop_00 with its stamps squeezed ten times (a bag played back fast, or stamped on another clock): every
    check passed, and the run answered wrongly, complete. The arm's joints then move 2.8 times faster than the
    Panda's URDF allows: a warning (twin check exits 3); squeezed three times (1.2 of a limit) it is no warning."""
    rec = load_recording(str(ROOT / "recordings" / "ball_drop_00.mcap"))
    for k in (10, 3):
        with RecordingWriter(tmp_path / f"fast{k}.mcap") as w:
            for t, kind, m in rec.items:
                if kind == "action":
                    w.action(t / k, m["operation"], m["phase"], **m["params"])
                else:
                    w.joint_state(t / k, m["name"], m["position"], m["velocity"], m["effort"])
            for name, data in rec.metadata.items():
                w.metadata(name, data)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", "scenes/ball_drop.yaml", "--recording",
                        str(tmp_path / "fast10.mcap")], capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    assert "the arm moves faster than the robot can, in 3 stretches of 100 ms: panda_joint2 at up to 6.1 rad/s at " \
           "t=0.90 s, 2.8 times its URDF velocity limit 2.175 rad/s" in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", "scenes/ball_drop.yaml", "--recording",
                        str(tmp_path / "fast3.mcap")], capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert r.returncode == 0 and "faster than the robot can" not in r.stderr, r.stdout[-2000:] + r.stderr[-2000:]


def test_a_frozen_driver_republishing_its_last_joint_state_is_said(tmp_path):
    """ball_drop_00 with its joint-state driver stuck from 4 s on: the same message (the same header stamp) goes on
    being recorded, so by the log times the robot stands still while its actions go on. The run said complete, the
    ball not in the container. The header stamp that stays for more than 0.5 s is now said (degraded, exit 3)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    src, dst = ROOT / "recordings" / "ball_drop_00.mcap", tmp_path / "frozen.mcap"
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        summary = reader.get_summary()
        assert summary is not None
        w = Writer(f_out)
        w.start("ros2", "test")
        schemas = {sid: w.register_schema(sc.name, sc.encoding, sc.data) for sid, sc in summary.schemas.items()}
        channels = {cid: w.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], c.metadata)
                    for cid, c in summary.channels.items()}
        t0, stuck = None, None
        for _, channel, message in reader.iter_messages(log_time_order=True):
            t0 = message.log_time if t0 is None else t0
            data = message.data
            if channel.topic == "/joint_states":
                if message.log_time - t0 < 4e9:
                    stuck = data
                else:
                    data = stuck
            w.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        for meta in make_reader(open(src, "rb")).iter_metadata():
            w.add_metadata(meta.name, dict(meta.metadata))
        w.finish()
    rec = load_recording(str(dst))
    (warning,) = [h for h in rec.holes if "header stamp" in h]
    assert warning.startswith("its joint states repeat one header stamp 1 time for more than 0.5 s (the longest 5.88 s "
                              "from t=4.00 s)"), \
        warning
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", "scenes/ball_drop.yaml", "--recording",
                        str(dst)], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 3 and "repeat one header stamp" in r.stdout + r.stderr, r.stdout[-2000:] + r.stderr[-2000:]


def test_two_robots_on_one_stream_jump_back_and_forth():
    """Two arms publishing on one ensemble merge into one stream: the twin's arm flicks between them every message.
    Said as the arm's jumps (the twin cannot tell two robots' joint states apart)."""
    other = [0.3, *READY[1:]]
    (why,) = live_panda([READY if i % 2 else other for i in range(100)], 0.005)
    assert why.startswith("the live telemetry: the arm jumps between two joint states 99 times: panda_joint1 by up to "
                          "0.3 at t=0.00 s, 8.2 times its limit 0.0367"), why


def _bag(path, joints_type="sensor_msgs/msg/JointState", definition=None, log_ns=None, encode=None, **writer_options):
    """200 joint states at 100 Hz (and an action) written with mcap's own writer: ``log_ns(ns)`` gives a message's
    log time from its header stamp (default the same), ``writer_options`` what the MCAP format leaves open."""
    from mcap.writer import Writer

    from protocol.ros2 import JOINT_STATE_DEF, STRING_DEF, encode_joint_state, encode_string

    with open(path, "wb") as f:
        w = Writer(f, **writer_options)
        w.start("ros2", "test")
        js = w.register_schema(joints_type, "ros2msg", (definition or JOINT_STATE_DEF).encode())
        st = w.register_schema("std_msgs/msg/String", "ros2msg", STRING_DEF.encode())
        joints, actions = w.register_channel("/joint_states", "cdr", js), w.register_channel("/action", "cdr", st)
        for i in range(200):
            ns = 1_700_000_000_000_000_000 + i * 10_000_000
            at = log_ns(ns) if log_ns else ns
            data = encode() if encode else encode_joint_state(0, NAMES, [0.1, 1.0], [], [], stamp_ns=ns)
            w.add_message(joints, at, data, at, i)
            if i == 50:
                w.add_message(actions, at, encode_string(json.dumps({"operation": "move_hand", "phase": "end",
                                                                     "params": {}})), at, i)
        w.finish()
    return path


def test_recordings_the_format_allows_or_a_recorder_makes_are_read_or_said(tmp_path):
    """A helper's review of the input side, each reproduced:
    - a summary that does not repeat its channels (the MCAP format allows it) read as a file holding nothing;
    - log times all 0 (ros2 bag record with use_sim_time and no /clock) replayed the whole motion in one tick, and
      the run said complete;
    - a /joint_states of another type was said to be a file that cannot be read at all."""
    whole = load_recording(_bag(tmp_path / "ref.mcap"))
    sparse = load_recording(_bag(tmp_path / "norepeat.mcap", repeat_channels=False, repeat_schemas=False))
    assert len(sparse.items) == len(whole.items) == 201 and sparse.items == whole.items
    with pytest.raises(TwinError, match="its 200 joint states all have one log time"):
        load_recording(_bag(tmp_path / "zero.mcap", log_ns=lambda ns: 0))
    with pytest.raises(TwinError, match="/joint_states holds my_msgs/msg/Joints, not sensor_msgs/msg/JointState, and "
                                        "its messages cannot be read as such"):
        load_recording(_bag(tmp_path / "other.mcap", joints_type="my_msgs/msg/Joints", definition="float64[] q\n",
                            encode=lambda: b"\x00\x01\x00\x00" + struct.pack("<I4x2d", 2, 0.1, 1.0)))


def test_perception_none_keeps_the_scene_s_own_poses():
    """A fluid scene replays a ball drop recording for its arm alone: the recording's perception names none of the
    scene's entities, and the run was degraded for it, with no way to say 'none' but a file of empty entities."""
    from conductor.scene import load_scene
    from conductor.scene.perception import load_perception, perceive
    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource

    assert load_perception("none") == {"entities": {}}
    scene = load_scene(ROOT / "scenes" / "fluid_split_50.yaml")
    cup = list(scene.entities["cup"].pose)
    assert perceive(scene, ReplaySource(load_recording(ROOT / "recordings" / "ball_drop_00.mcap")), "none") is None
    assert list(scene.entities["cup"].pose) == cup and not scene.perception_notes and not scene.perception_missed
    degraded = load_scene(ROOT / "scenes" / "fluid_split_50.yaml")  # (without it: the ball drop's entities, said)
    perceive(degraded, ReplaySource(load_recording(ROOT / "recordings" / "ball_drop_00.mcap")))
    assert any("none of this scene's entities" in n for n in degraded.perception_missed), degraded.perception_missed
