"""`twin record synth --robot xarm6`: a slipped ball leaves the xArm's hand during the carry and its release opens
the fingers, and the containers are placed within the xArm's reach (seeds whose container lay beyond it failed)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from conductor.sources.recording import load_recording
from protocol.geometry import inside_container

ROOT = Path(__file__).resolve().parent.parent
FAST = 0.6  # --time-scale for tests: shorter scripts, same physics


def synth(out: Path, seed: int, container: str, outcome: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "conductor.cli", "record", "synth", "--scenario", "ball_drop",
                           "--seed", str(seed), "--container", container, "--outcome", outcome, "--robot", "xarm6",
                           "--time-scale", str(FAST), "--out", str(out), "--quiet"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_xarm_slipped_ball_leaves_the_hand_and_the_release_opens_the_fingers(tmp_path):
    """The fault's residual force (0.03-0.12 N) held the xArm's linkage where it was: the ball rode back home in the
    hand (ball_held_after_carry true) and the release that never moved the fingers was logged as done."""
    out = tmp_path / "slipped.mcap"
    r = synth(out, 9101, "bin", "slipped")
    assert r.returncode == 0, r.stderr[-2000:]
    rec = load_recording(out)
    gt, gen = rec.metadata["twin.ground_truth"], rec.metadata["twin.generation"]
    assert gen["robot"] == "xarm6" and gen["outcome"] == "slipped"
    assert gt["ball_held_after_lift"] == "true" and gt["ball_held_after_carry"] == "false", gt
    final = json.loads(gt["ball_final_position"])
    assert abs(final[2] - json.loads(gen["ball"])["radius"]) < 0.003, "the ball ends on the table"
    pose = json.loads(gen["positions"])["container"]
    assert gt["in_container"] == ("true" if inside_container({"type": "container", "style": "bin"}, pose, final)
                                  else "false")
    names = [m for _, k, m in rec.items if k == "joint_state"][0]["name"]
    drive = names.index("drive_joint")
    js = [m for _, k, m in rec.items if k == "joint_state"]
    stamps = np.array([m["stamp"] for m in js])
    acts = [m for _, k, m in rec.items if k == "action" and m["operation"] == "release"]
    assert [a["phase"] for a in acts] == ["start", "end"], acts
    assert "failed" not in acts[1]["params"], acts[1]

    def drive_at(t: float) -> float:
        return float(js[min(int(np.searchsorted(stamps, t)), len(js) - 1)]["position"][drive])

    # the fingers opened (drive_joint 0 = open) between the release's start and its end
    assert drive_at(acts[0]["stamp"]) - drive_at(acts[1]["stamp"]) > 0.1, (drive_at(acts[0]["stamp"]),
                                                                            drive_at(acts[1]["stamp"]))
    assert drive_at(acts[1]["stamp"]) < 0.085, "open, within a tenth of the stroke"


def test_xarm_container_within_reach(tmp_path):
    """Seed 9073's box was drawn from the Panda's range, 0.64 m out: 'no IK solution' (exit 1) for the xArm."""
    out = tmp_path / "box.mcap"
    r = synth(out, 9073, "box", "success")
    assert r.returncode == 0, r.stderr[-2000:]
    rec = load_recording(out)
    gen = rec.metadata["twin.generation"]
    assert float(np.hypot(*json.loads(gen["positions"])["container"][:2])) < 0.58
    assert rec.metadata["twin.ground_truth"]["in_container"] == "true"
