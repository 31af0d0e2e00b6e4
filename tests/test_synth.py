"""`twin record synth`: recordings from the simulated realities (pybullet, MuJoCo) open in rosbags and in
the twin's reader, carry the nine Panda joints at 250 Hz, annotated actions and parseable metadata, are
reproducible, and their ground truth is what the reality run physically produced."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from conductor.scene import load_scene
from conductor.sources.recording import load_recording
from protocol.geometry import validate_shape
from recordings.synth import JOINT_NAMES, SPU_CONNECTION_OFFSET, synthesize

ROOT = Path(__file__).resolve().parent.parent
FAST = 0.6  # --time-scale for tests: shorter scripts, same physics


def _rosbags_messages(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {"/joint_states": "sensor_msgs/msg/JointState", "/action": "std_msgs/msg/String"}
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    return out


def _actions(rec) -> list[dict]:
    return [m for _, kind, m in rec.items if kind == "action"]


def _joints(rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    js = [m for _, kind, m in rec.items if kind == "joint_state"]
    return (np.array([m["stamp"] for m in js]), np.array([m["position"] for m in js]),
            np.array([m["effort"] for m in js]))


def _width_after(rec, operation: str, phase: str, command: str | None = None, delay: float = 0.0) -> float:
    """Finger opening (q1 + q2) at ``delay`` seconds after the first matching annotation."""
    stamps, pos, _ = _joints(rec)
    for a in _actions(rec):
        if (a["operation"] == operation and a["phase"] == phase
                and (command is None or a["params"].get("command") == command)):
            i = min(int(np.searchsorted(stamps, a["stamp"] + delay)), len(stamps) - 1)
            return float(pos[i, 7] + pos[i, 8])
    raise AssertionError(f"no {operation} {phase} {command or ''} annotation")


def _check_pairs(actions: list[dict]) -> None:
    """Every start has a later end of the same operation, and every end a start before it."""
    open_ops: dict[str, float] = {}
    for a in actions:
        key = a["operation"]
        if a["phase"] == "start":
            assert key not in open_ops, f"{key} started twice without an end"
            open_ops[key] = a["stamp"]
        else:
            assert a["phase"] == "end", a
            assert key in open_ops, f"{key} ended without a start"
            assert a["stamp"] >= open_ops.pop(key)
    assert not open_ops, f"operations without an end: {sorted(open_ops)}"


@pytest.fixture(scope="module")
def success_bin(tmp_path_factory) -> Path:
    """A ball_drop success recording made through the command line."""
    out = tmp_path_factory.mktemp("synth") / "bd_success.mcap"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "record", "synth", "--scenario", "ball_drop",
                        "--seed", "3", "--container", "bin", "--outcome", "success", "--time-scale", str(FAST),
                        "--out", str(out), "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "in_container=" in r.stdout
    return out


def test_ball_drop_opens_in_rosbags_with_nine_joints_at_250_hz(success_bin):
    """rosbags reads the bare .mcap; every joint state names the nine Panda joints, ~250 Hz with jitter."""
    msgs = _rosbags_messages(success_bin)
    js = msgs["/joint_states"]
    assert len(js) > 1000
    for _, m in js:
        assert list(m.name) == list(JOINT_NAMES)
        assert len(m.position) == len(m.velocity) == len(m.effort) == 9
        assert np.all(np.isfinite(m.position)) and np.all(np.isfinite(m.effort))
    stamps = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in js])
    dt = np.diff(stamps)
    assert np.all(dt > 0), "joint-state stamps must increase"
    assert 0.0039 < float(np.median(dt)) < 0.0041
    assert 1e-5 < float(np.std(dt)) < 1e-3, "a little timing jitter, not none and not chaos"
    for _, m in msgs["/action"]:
        a = json.loads(m.data)
        assert set(a) == {"operation", "phase", "params"}
    # file size: well under 1 MB
    assert success_bin.stat().st_size < 1_000_000


def test_ball_drop_actions_and_metadata(success_bin):
    """load_recording sees paired move_arm/move_hand/release annotations and parseable metadata."""
    rec = load_recording(success_bin)
    acts = _actions(rec)
    _check_pairs(acts)
    ops = {(a["operation"], a["phase"]) for a in acts}
    for op in ("move_arm", "move_hand", "release"):
        assert (op, "start") in ops and (op, "end") in ops, op
    hand = [a for a in acts if a["operation"] == "move_hand"]
    assert {a["params"]["command"] for a in hand} == {"open", "close"}
    assert all(a["params"]["hand"] == "hand" for a in hand)
    assert all(len(a["params"]["target"]) == 7 for a in acts if a["operation"] == "move_arm")
    # the order of the task
    starts = [a["operation"] + ":" + a["params"].get("command", a["params"].get("name", "")) for a in acts
              if a["phase"] == "start"]
    assert starts.index("move_hand:close") < starts.index("move_arm:lift") < starts.index("release:")

    gt = rec.ground_truth()
    assert isinstance(gt["in_container"], bool)
    scene = json.loads(rec.metadata["twin.scene"]["json"])
    ents = scene["entities"]
    assert set(ents) == {"ball", "stand", "container"}
    for name, e in ents.items():
        assert len(e["pose"]) == 7, name
        assert validate_shape(e["shape"]) is None, name
    assert ents["container"]["shape"] == {"type": "container", "style": "bin"}
    gen = rec.metadata["twin.generation"]
    full = json.loads(gen["json"])
    assert (full["seed"], full["scenario"], full["container"], full["outcome"]) == (3, "ball_drop", "bin", "success")
    assert full["time_scale"] == FAST
    for key in ("contact", "noise", "ball", "positions", "durations", "heights"):
        assert key in full, key
    assert gen["command"].startswith("twin record synth --scenario ball_drop --seed 3")
    # perception: within a few mm of the truth
    assert np.linalg.norm(np.array(ents["ball"]["pose"][:3]) - np.array(full["positions"]["ball"])) < 0.015
    # the conductor places the scene's entities where the robot perceived them
    sc = load_scene(ROOT / "scenes" / "ball_drop.yaml")
    sc.apply_perception(scene)
    assert sc.entities["container"].pose == pytest.approx(ents["container"]["pose"])


def test_success_lands_in_the_container(success_bin):
    """The success script physically drops the ball into the container (measured, not asserted by the script)."""
    rec = load_recording(success_bin)
    gt = rec.metadata["twin.ground_truth"]
    assert gt["in_container"] == "true", (
        f"seed 3 bin success measured in_container={gt['in_container']} (ball at {gt['ball_final_position']}): "
        "the success script is unreliable")
    assert gt["ball_held_after_carry"] == "true"
    # the fingers closed on the ball: the opening stays near its 66-68 mm diameter
    assert 0.060 < _width_after(rec, "move_hand", "end", "close") < 0.072


def test_empty_grasp_and_early_release_are_false(tmp_path):
    """An empty grasp closes the fingers on nothing, an early release opens far from the container:
    both leave the ball outside, as the reality measures it."""
    empty = synthesize("ball_drop", 4, tmp_path / "empty.mcap", container="cup", outcome="empty_grasp",
                       time_scale=FAST)
    assert empty.ground_truth["in_container"] == "false", (
        f"empty_grasp (seed 4, cup) measured {empty.ground_truth}: the empty-grasp script is unreliable")
    rec = load_recording(empty.path)
    assert _width_after(rec, "move_hand", "end", "close") < 0.01, "the fingers must close on nothing"
    assert empty.ground_truth["ball_held_after_lift"] == "false"

    early = synthesize("ball_drop", 5, tmp_path / "early.mcap", container="bowl", outcome="released_early",
                       time_scale=FAST)
    assert early.ground_truth["in_container"] == "false", (
        f"released_early (seed 5, bowl) measured {early.ground_truth}: the early-release script is unreliable")
    rec = load_recording(early.path)
    acts = _actions(rec)
    carry_end = next(a["stamp"] for a in acts if a["operation"] == "move_arm" and a["phase"] == "end"
                     and a["params"]["name"] == "above_container")
    release = next(a["stamp"] for a in acts if a["operation"] == "release" and a["phase"] == "start")
    assert release < carry_end, "the early release happens during the carry"
    assert early.ground_truth["ball_held_after_lift"] == "true"
    assert early.ground_truth["ball_held_after_carry"] == "false"


def test_insertion_connects_or_is_blocked(tmp_path):
    """A small localization error ends connected; a large one leaves the DIP blocked on the SPU's top."""
    good = synthesize("insertion", 21, tmp_path / "ins_good.mcap", localization_error=0.0005, time_scale=FAST)
    assert good.ground_truth["connected"] == "true", f"0.5 mm error (seed 21) measured {good.ground_truth}"
    bad = synthesize("insertion", 21, tmp_path / "ins_bad.mcap", localization_error=0.012, time_scale=FAST)
    assert bad.ground_truth["connected"] == "false", f"12 mm error (seed 21) measured {bad.ground_truth}"
    assert float(bad.ground_truth["depth_error_m"]) > 0.015, "blocked on the top, not half-way in"

    rec = load_recording(good.path)
    stamps, pos, eff = _joints(rec)
    assert pos.shape[1] == 9
    assert 0.0039 < float(np.median(np.diff(stamps))) < 0.0041
    # the DIP is held from the start: fingers at its 12 mm diameter, squeezing
    assert 0.008 < pos[0, 7] + pos[0, 8] < 0.014
    assert eff[0, 7] < -5 and eff[0, 8] < -5
    acts = _actions(rec)
    _check_pairs(acts)
    assert any(a["operation"] == "move_arm" and a["params"].get("mode") == "compliant" for a in acts)
    ents = json.loads(rec.metadata["twin.scene"]["json"])["entities"]
    assert set(ents) == {"spu", "dip"}
    gen = json.loads(rec.metadata["twin.generation"]["json"])
    # the scene shows the SPU where the robot believes it is: the localization error away from the truth
    believed, true = np.array(gen["spu"]["believed_pose"][:3]), np.array(gen["spu"]["pose"][:3])
    assert np.linalg.norm(believed - true) == pytest.approx(0.0005, abs=1e-6)
    assert gen["spu"]["connection_offset"] == pytest.approx(list(SPU_CONNECTION_OFFSET))
    assert np.linalg.norm(np.array(ents["spu"]["pose"][:3]) - believed) < 0.005
    assert math.isclose(ents["dip"]["shape"]["radius"], 0.006)


def test_same_arguments_give_the_same_file(tmp_path):
    """Determinism: generating twice with the same arguments writes identical bytes."""
    a = synthesize("ball_drop", 8, tmp_path / "a.mcap", container="box", outcome="missed", time_scale=FAST)
    b = synthesize("ball_drop", 8, tmp_path / "b.mcap", container="box", outcome="missed", time_scale=FAST)
    assert a.path.read_bytes() == b.path.read_bytes()
    c = synthesize("ball_drop", 9, tmp_path / "c.mcap", container="box", outcome="missed", time_scale=FAST)
    assert c.generation["positions"] != a.generation["positions"], "another seed, another case"


def test_cli_rejects_options_of_the_other_scenario(tmp_path):
    """--container/--outcome belong to ball_drop and --localization-error to insertion."""
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "record", "synth", "--scenario", "insertion",
                        "--seed", "1", "--outcome", "missed", "--out", str(tmp_path / "x.mcap")],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "ball_drop only" in r.stderr
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.parametrize("name", ["ball_drop_00", "insertion_00"])
def test_shipped_recording_is_reproduced_byte_for_byte(tmp_path, name):
    """The command stored in a shipped recording's metadata makes exactly that file again (make
    recordings is deterministic; a change to the reality or its random draws shows up here).

    Exactly, on a machine whose OpenBLAS picks the kernels of the one that made the shipped set (an Intel Xeon with
    AVX-512: SkylakeX). The insertion reality's small matrix products round differently with other kernels (an AMD
    EPYC's, or ``OPENBLAS_CORETYPE=Sandybridge`` on the Xeon), and contact makes the last digits grow: the bytes
    differ there. Then the same command must still make the same file twice on this machine, from the same random
    draws (every generation parameter), with the same outcome and the same messages' count."""
    shipped = ROOT / "recordings" / f"{name}.mcap"
    cmd = load_recording(shipped).metadata["twin.generation"]["command"].split()
    assert cmd[:3] == ["twin", "record", "synth"]

    def make(out: Path) -> Path:
        argv = [*cmd[1:]]
        argv[argv.index("FILE.mcap")] = str(out)
        r = subprocess.run([sys.executable, "-m", "conductor.cli", *argv, "-q"], capture_output=True, text=True,
                           timeout=300, cwd=ROOT)
        assert r.returncode == 0, r.stderr[-2000:]
        return out

    out = make(tmp_path / f"{name}.mcap")
    if out.read_bytes() == shipped.read_bytes():
        return
    assert name.startswith("insertion"), f"{name}: not the shipped file (only insertion's reality goes through BLAS)"
    assert make(tmp_path / f"{name}_again.mcap").read_bytes() == out.read_bytes(), "not deterministic here"
    ours, theirs = load_recording(out), load_recording(shipped)
    assert ours.metadata["twin.generation"] == theirs.metadata["twin.generation"]  # the same random draws
    assert ours.metadata["twin.ground_truth"]["connected"] == theirs.metadata["twin.ground_truth"]["connected"]
    assert [k for _, k, _ in ours.items] == [k for _, k, _ in theirs.items]
    warnings.warn(f"{name}: the same outcome and draws as the shipped file, not the same bytes (this machine's BLAS "
                  "kernels round the reality's matrix products differently)", stacklevel=1)


# ------------------------------------------------------------------------------ both realities
# (reality, outcome, container, seed): one short recording per reality and outcome; the assertions
# say what the outcome physically produces, checked against what the reality measured
BALL_CASES = [
    ("pybullet", "slipped", "bin", 21), ("pybullet", "knocked", "box", 22),
    ("mujoco", "success", "bowl", 23), ("mujoco", "released_early", "cup", 24), ("mujoco", "missed", "bin", 25),
    ("mujoco", "empty_grasp", "box", 26), ("mujoco", "slipped", "cup", 27), ("mujoco", "knocked", "bin", 28),
]


def _stand_and_ball(gen: dict) -> tuple[np.ndarray, float, float]:
    return np.array(gen["positions"]["stand"][:2]), float(gen["stand"]["radius"]), float(gen["ball"]["radius"])


def _carry_window(acts: list[dict]) -> tuple[float, float]:
    """From the end of the close to the start of the first release (or open) after it."""
    close_end = next(a["stamp"] for a in acts if a["operation"] == "move_hand" and a["phase"] == "end"
                     and a["params"]["command"] == "close")
    after = [a for a in acts if a["stamp"] > close_end and a["phase"] == "start"
             and (a["operation"] == "release" or (a["operation"] == "move_hand" and a["params"]["command"] == "open"))]
    return close_end, after[0]["stamp"]


@pytest.mark.slow
@pytest.mark.parametrize("reality,outcome,container,seed", BALL_CASES)
def test_ball_drop_outcome_is_what_the_reality_measured(tmp_path, reality, outcome, container, seed):
    res = synthesize("ball_drop", seed, tmp_path / "bd.mcap", container=container, outcome=outcome,
                     time_scale=FAST, reality=reality)
    gt, gen = res.ground_truth, res.generation
    rec = load_recording(res.path)
    acts = _actions(rec)
    _check_pairs(acts)
    stamps, pos, eff = _joints(rec)
    final = np.array(json.loads(gt["ball_final_position"]))
    stand_xy, stand_r, ball_r = _stand_and_ball(gen)
    on_table = abs(final[2] - ball_r) < 0.003
    assert (gen.get("reality") or "pybullet") == reality
    assert gen["command"].startswith(f"twin record synth --scenario ball_drop --seed {seed}")
    assert ("--reality mujoco" in gen["command"]) == (reality == "mujoco")
    width = _width_after(rec, "move_hand", "end", "close")
    if outcome == "success":
        assert gt["in_container"] == "true" and gt["ball_held_after_carry"] == "true", gt
        assert 0.060 < width < 0.072, "the fingers closed on the ball"
    elif outcome == "released_early":
        assert gt["in_container"] == "false" and gt["ball_held_after_lift"] == "true", gt
        assert gt["ball_held_after_carry"] == "false" and on_table, gt
    elif outcome == "missed":
        assert gt["in_container"] == "false" and gt["ball_held_after_carry"] == "true" and on_table, gt
    elif outcome == "empty_grasp":
        assert gt["in_container"] == "false" and gt["ball_held_after_lift"] == "false", gt
        assert width < 0.01, "the fingers closed on nothing"
        assert np.linalg.norm(final - np.array(gen["positions"]["ball"])) < 0.01, "the ball stays on its stand"
    elif outcome == "slipped":
        assert gt["in_container"] == "false" and gt["ball_held_after_lift"] == "true", gt
        assert gt["ball_held_after_carry"] == "false" and on_table, gt
        assert 0.060 < width < 0.072, "the grip held at first"
        t0, t1 = _carry_window(acts)
        assert t1 == next(a["stamp"] for a in acts if a["operation"] == "release" and a["phase"] == "start"), (
            "the robot commands the grasp until its release at the container")
        window = (stamps > t0) & (stamps < t1)
        squeeze = -eff[window][:, 7:9].mean(axis=1)
        assert squeeze[0] > 5 and squeeze[-1] < 2.5, "the gripper's force fails during the carry"
    elif outcome == "knocked":
        assert gt["in_container"] == "false" and gt["ball_held_after_lift"] == "false", gt
        assert width < 0.01, "the fingers closed on nothing"
        assert on_table and np.linalg.norm(final[:2] - stand_xy) > stand_r, "knocked off its stand"
        assert any(a["operation"] == "move_hand" and a["params"]["command"] == "close" for a in acts)
        assert any(a["operation"] == "release" for a in acts), "the robot carried on with its script"


@pytest.mark.slow
@pytest.mark.parametrize("reality", ["pybullet", "mujoco"])
def test_insertion_over_the_range_of_localization_error(tmp_path, reality):
    """Small errors connect, medium ones stop on the rim or top of the SPU about 20 mm higher, large
    ones (6 cm) go down beside it; the joint positions show where the arm stopped."""
    from recordings.synth.robot import Planner

    ends = {}
    for label, err in (("small", 0.002), ("medium", 0.012), ("large", 0.06)):
        res = synthesize("insertion", 31, tmp_path / f"{label}.mcap", localization_error=err, time_scale=FAST,
                         reality=reality)
        stamps, pos, eff = _joints(load_recording(res.path))
        ends[label] = (res.ground_truth, pos[-1], eff[-1])
    small, medium, large = (ends[k][0] for k in ("small", "medium", "large"))
    assert small["connected"] == "true" and abs(float(small["depth_error_m"])) < 0.004, small
    assert medium["connected"] == "false" and 0.015 < float(medium["depth_error_m"]) < 0.025, medium
    assert large["connected"] == "false" and float(large["depth_error_m"]) < -0.003, large
    assert float(large["lateral_error_m"]) > 0.05
    planner = Planner()
    try:
        tip_z = {k: float(planner.tip(v[1][:7])[2]) for k, v in ends.items()}
    finally:
        planner.close()
    assert tip_z["medium"] - tip_z["small"] == pytest.approx(0.02, abs=0.006), tip_z
    assert tip_z["large"] < tip_z["small"] - 0.003, tip_z
    # the SPU's top holds up the pushing hand: the shoulder's effort differs from the free descent beside it
    assert abs(ends["medium"][2][1] - ends["large"][2][1]) > 3.0


def test_mujoco_recording_is_reproduced_from_its_stored_command(tmp_path):
    """Determinism in MuJoCo: the command stored in the metadata makes the same bytes again."""
    first = tmp_path / "first.mcap"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "record", "synth", "--scenario", "insertion",
                        "--seed", "5", "--localization-error", "0.004", "--reality", "mujoco", "--time-scale", "0.4",
                        "--out", str(first), "-q"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    gen = load_recording(first).metadata["twin.generation"]
    assert gen["reality"] == "mujoco" and json.loads(gen["json"])["engine"]["engine"].startswith("mujoco ")
    cmd = gen["command"].split()
    again = tmp_path / "again.mcap"
    cmd[cmd.index("FILE.mcap")] = str(again)
    r = subprocess.run([sys.executable, "-m", "conductor.cli", *cmd[1:], "-q"], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert again.read_bytes() == first.read_bytes()
