"""A run log stands alone: it carries the scene's text, the perception the run used, where its input came from
and the twin's version, and ``twin run --from-log RUN.mcap`` re-runs the run from the log alone (its own joint
states and actions) to the same handovers and answer."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conductor.runlog import read_metadata

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def twin(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                          timeout=600, env=ENV, cwd=ROOT)


def outcome(summary_file: Path) -> tuple:
    s = json.loads(summary_file.read_text())
    return (s["status"], s["semantic_state"], s["final_ownership"],
            [(h["tick"], h["entity"], h["attribute"], h["from"], h["to"], h["trigger"]) for h in s["handovers"]])


@pytest.mark.slow
@pytest.mark.parametrize("scene, recording", [("ball_drop", "ball_drop_03.mcap"), ("insertion", "insertion_01.mcap")])
def test_a_run_is_rerun_from_its_log_alone(tmp_path, scene, recording):
    rec = ROOT / "recordings" / recording
    r = twin("run", f"scenes/{scene}.yaml", "--recording", str(rec), "--run-dir", str(tmp_path / "first"),
             "--summary", str(tmp_path / "first.json"))
    assert r.returncode == 0, r.stdout + r.stderr
    log = tmp_path / "first" / "run.mcap"
    meta = read_metadata(log)
    assert meta["twin.scene_text"]["yaml"] == (ROOT / "scenes" / f"{scene}.yaml").read_text()
    assert meta["twin.recording"]["sha256"] == hashlib.sha256(rec.read_bytes()).hexdigest()
    assert meta["twin.version"]["twin"] and "twin.summary" in meta  # the summary joins, nothing is overwritten
    perceived = json.loads(meta["twin.perception"]["json"])["entities"]
    recorded = json.loads(json.loads(json.dumps(read_metadata(rec)["twin.scene"]))["json"])["entities"]
    for name, ent in recorded.items():  # what the run used: where the robot perceived each object
        assert perceived[name]["pose"][:3] == pytest.approx(ent["pose"][:3])

    moved = tmp_path / "elsewhere" / "run.mcap"  # the log alone, away from the scene and the recording
    moved.parent.mkdir()
    moved.write_bytes(log.read_bytes())
    r = twin("run", "--from-log", str(moved), "--run-dir", str(tmp_path / "again"),
             "--summary", str(tmp_path / "again.json"))
    assert r.returncode == 0, r.stdout + r.stderr
    first, again = outcome(tmp_path / "first.json"), outcome(tmp_path / "again.json")
    assert first == again
    assert first[0] == "complete" and first[3], "the run should move a responsibility"


def test_a_log_that_does_not_stand_alone_is_refused_in_one_line(tmp_path):
    r = twin("run", "--from-log", str(ROOT / "recordings" / "ball_drop_00.mcap"), "--run-dir", str(tmp_path))
    assert r.returncode == 1
    assert r.stderr.strip().count("\n") == 0 and "not a self-contained run log" in r.stderr
