"""A robot is data: the Panda is one robot description among others, the xArm 6 runs end to end, and a
recording that does not fit the scene's robot says so (a one-line error, or a warning and a degraded run)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conductor.sources.recording import load_recording
from protocol.robot import description, resolve_robot
from recordings.rosbag import RecordingWriter

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def twin(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=ENV)


def test_no_panda_name_in_the_models():
    """Every Panda joint and link name lives in its description (protocol/robots/panda.yaml), none in agents/."""
    d = description("panda")
    g = d["gripper"]
    names = {*d["arm"], *g["joints"], *g["fingers"], g["hand"], g["tip"]}
    names |= {f"panda_link{i}" for i in range(9)}
    pattern = re.compile("|".join(re.escape(n) for n in sorted(names, key=len, reverse=True)))
    found = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}" for p in sorted((ROOT / "agents").rglob("*.py"))
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if pattern.search(line)]
    assert found == []
    assert len(names) >= 13  # the test looks for something


def test_a_third_arm_needs_only_a_robot_block():
    """The shipped descriptions resolve with their URDF's mimic joints; the xArm's gripper is one drive joint."""
    x = resolve_robot({"use": "xarm6"})
    assert x.joints == ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "drive_joint")
    assert len(x.gripper.mimic) == 5 and all(lead == "drive_joint" for lead, _, _ in x.gripper.mimic.values())
    p = resolve_robot(None)
    assert p.name == "panda" and p.gripper.mimic == {}  # both finger joints are reported: neither is a follower


def _rewrite(src: Path, dst: Path, rename: dict[str, str] | None = None, drop: tuple[str, ...] = ()) -> Path:
    """A copy of a recording with joints renamed or left out (actions and metadata kept)."""
    rec = load_recording(src)
    rename = rename or {}
    with RecordingWriter(dst) as w:
        for t, kind, m in rec.items:
            if kind == "joint_state":
                keep = [i for i, n in enumerate(m["name"]) if n not in drop]
                w.joint_state(t, [rename.get(m["name"][i], m["name"][i]) for i in keep],
                              *([v[i] for i in keep] if v else [] for v in (m["position"], m["velocity"], m["effort"])))
            else:
                w.action(t, m["operation"], m["phase"], **m["params"])
        for name, data in rec.metadata.items():
            w.metadata(name, data)
    return dst


def test_no_matching_joint_name_is_a_one_line_error(tmp_path):
    rec = _rewrite(ROOT / "recordings" / "ball_drop_00.mcap", tmp_path / "other.mcap",
                   rename={f"panda_joint{i}": f"arm_{i}" for i in range(1, 8)} | {
                       "panda_finger_joint1": "grip_l", "panda_finger_joint2": "grip_r"})
    r = twin("run", "scenes/ball_drop.yaml", "--recording", str(rec), "--run-dir", str(tmp_path / "run"))
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "none of its joint names (arm_1, arm_2" in lines[0] and "robot panda" in lines[0]
    assert "joints: {arm_1: panda_joint1" in lines[0]  # the map to write
    assert not (tmp_path / "run").exists() or not list((tmp_path / "run").glob("*.log")), "no agent started"


@pytest.mark.slow
def test_a_joint_map_fits_a_renamed_bag_and_a_partial_one_degrades(tmp_path):
    """Renamed joints with the scene's ``joints:`` map run as the original does; a bag without the wrist joint
    runs, warns naming it, and ends degraded (exit 3)."""
    src = ROOT / "recordings" / "ball_drop_00.mcap"
    rename = {f"panda_joint{i}": f"fr3_joint{i}" for i in range(1, 8)}
    renamed = _rewrite(src, tmp_path / "renamed.mcap", rename=rename)
    scene = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    mapping = ", ".join(f"{b}: {a}" for a, b in rename.items())
    scene = scene.replace("robot: {urdf: franka_panda/panda.urdf, base: [0, 0, 0, 0, 0, 0, 1]}",
                          f"robot: {{use: panda, joints: {{{mapping}}}}}")
    assert "fr3_joint1: panda_joint1" in scene
    (tmp_path / "mapped.yaml").write_text(scene)
    r = twin("run", str(tmp_path / "mapped.yaml"), "--recording", str(renamed), "--summary", str(tmp_path / "a.json"),
             "--run-dir", str(tmp_path / "a"))
    assert r.returncode == 0, r.stdout + r.stderr
    a = json.loads((tmp_path / "a.json").read_text())
    assert a["semantic_state"]["in(container, ball)"] is True
    assert [h["to"] for h in a["handovers"]] == ["in_hand", "physics"]

    partial = _rewrite(src, tmp_path / "partial.mcap", drop=("panda_joint7",))
    r = twin("run", "scenes/ball_drop.yaml", "--recording", str(partial), "--summary", str(tmp_path / "b.json"),
             "--run-dir", str(tmp_path / "b"))
    assert r.returncode == 3, r.stdout + r.stderr
    b = json.loads((tmp_path / "b.json").read_text())
    assert b["status"] == "degraded"
    assert any("panda_joint7" in reason and "not in the telemetry" in reason for reason in b["status_reasons"])


@pytest.mark.slow
@pytest.mark.parametrize("name, truth", [("ball_drop_xarm_success_cup", True), ("ball_drop_xarm_slipped_bin", False)])
def test_xarm_ball_drop_is_interpreted(tmp_path, name, truth):
    """The xArm 6 ensemble on shipped xArm recordings: the grasp goes to in_hand and comes back, and the
    answer matches what the reality measured."""
    rec = ROOT / "recordings" / f"{name}.mcap"
    assert load_recording(rec).ground_truth()["in_container"] is truth
    r = twin("run", "scenes/xarm_ball_drop.yaml", "--recording", str(rec), "--summary", str(tmp_path / "s.json"),
             "--run-dir", str(tmp_path / "run"))
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["semantic_state"]["in(container, ball)"] is truth
    hs = [(h["from"], h["to"]) for h in s["handovers"]]
    assert hs[0] == ("physics", "in_hand") and hs[-1] == ("in_hand", "physics"), hs


def test_twin_check_says_whether_a_bag_fits_before_running(tmp_path):
    ok = twin("check", "scenes/xarm_ball_drop.yaml", "--recording", "recordings/ball_drop_xarm_success_bin.mcap")
    assert ok.returncode == 0 and "robot joints reported: 7 of 7" in ok.stdout, ok.stdout + ok.stderr
    wrong = twin("check", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_xarm_success_bin.mcap")
    assert wrong.returncode == 2 and "none of its joint names (joint1, joint2" in wrong.stderr
    assert "joints: {joint1: panda_joint1" in wrong.stderr
    partial = _rewrite(ROOT / "recordings" / "ball_drop_00.mcap", tmp_path / "p.mcap", drop=("panda_finger_joint2",))
    some = twin("check", "scenes/ball_drop.yaml", "--recording", str(partial))
    assert some.returncode == 3 and "panda_finger_joint2" in some.stderr, some.stdout + some.stderr
    assert "robot joints reported: 8 of 9" in some.stdout
    broken = sorted((ROOT / "tests" / "scenes" / "broken").glob("*.yaml"))[0]
    bad = twin("check", str(broken))
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def test_a_robot_block_whose_numbers_or_names_cannot_hold_is_refused():
    """Values that passed as numbers but could not work: a zero torque limit (the arm never moved, and the run said
    complete), a negative inertia, a quaternion of length 0 (every physics value NaN), a joint named twice, two
    recorded names on one URDF joint, a ready posture outside the URDF's limits, a name that is not a string."""
    from protocol.robot import check_robot

    def problems(**block):
        return {".".join(p): m for p, m in check_robot({"use": "panda", **block})}

    assert problems() == {}
    assert "each above 0" in problems(arm_force=[87, 87, 87, 0, 12, 12, 12])["robot.arm_force"]
    assert "each 0 or more" in problems(arm_inertia=[1, 1, 1, 1, 1, 1, -0.1])["robot.arm_inertia"]
    assert "is all zero" in problems(base=[0, 0, 0, 0, 0, 0, 0])["robot.base"]
    arm = [f"panda_joint{i}" for i in (1, 2, 3, 4, 5, 6, 6)]
    assert problems(arm=arm)["robot.arm"] == "panda_joint6: named twice among the arm's and the gripper's joints"
    two = problems(joints={"a1": "panda_joint1", "b1": "panda_joint1"})
    assert set(two) == {"robot.joints.a1", "robot.joints.b1"} and "another recorded name" in two["robot.joints.a1"]
    assert problems(ready=[0, -0.785, 0, -2.356, 0, 1.571, 4.0, 0.04, 0.04])["robot.ready"] == \
        "panda_joint7 at 4 is outside its URDF limits [-2.9671, 2.9671]"
    assert "outside its URDF limits" in problems(gripper={"open": [0.2, 0.2]})["robot.gripper.open"]
    assert "name must be a string" in problems(name=[1, 2])["robot.name"]
