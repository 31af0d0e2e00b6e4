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
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "not a self-contained run log" in r.stderr


def test_a_log_damaged_in_the_middle_replays_up_to_the_damage_degraded(tmp_path):
    """A whole run log with a chunk damaged in its middle used to be read quietly up to the damage: the re-run ended
    complete, with an answer about the first part of the robot's work. It now ends degraded, saying where."""
    from mcap.reader import make_reader

    r = twin("run", "scenes/ball_drop.yaml", "--recording", str(ROOT / "recordings" / "ball_drop_00.mcap"),
             "--run-dir", str(tmp_path / "first"))
    assert r.returncode == 0, r.stdout + r.stderr
    log = tmp_path / "first" / "run.mcap"
    with open(log, "rb") as f:
        chunks = sorted(c.chunk_start_offset for c in make_reader(f).get_summary().chunk_indexes)
    data, middle = log.read_bytes(), chunks[len(chunks) // 2]
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data[:middle + 1] + b"\xff" * 8 + data[middle + 9:])  # the chunk's length
    again = twin("run", "--from-log", str(damaged), "--run-dir", str(tmp_path / "again"), "--summary",
                 str(tmp_path / "again.json"))
    assert again.returncode == 3, again.stdout + again.stderr
    s = json.loads((tmp_path / "again.json").read_text())
    assert s["status"] == "degraded" and any("a run log damaged near byte" in w for w in s["status_reasons"]), s
    # and the re-run's own log, viewed, says how that run ended
    view = twin("view", str(tmp_path / "again" / "run.mcap"))
    assert view.returncode == 0 and "the run ended DEGRADED: input: " in view.stdout, view.stdout + view.stderr


def test_the_log_of_a_run_stopped_early_replays_degraded_and_says_why(tmp_path):
    """The log of a run cut short by --max-ticks holds only what that run was given: re-run from it (--from-log,
    or given as the recording) the run goes to the end of the log but ends degraded, saying so (it used to end
    complete with an answer about a moment of the robot's work, not its end), and twin check warns (exit 3)."""
    rec = ROOT / "recordings" / "ball_drop_00.mcap"
    r = twin("run", "scenes/ball_drop.yaml", "--recording", str(rec), "--max-ticks", "200", "--run-dir",
             str(tmp_path / "part"))
    assert r.returncode == 4, r.stdout + r.stderr
    log = tmp_path / "part" / "run.mcap"
    for argv in (["run", "--from-log", str(log)], ["run", "scenes/ball_drop.yaml", "--recording", str(log)]):
        again = twin(*argv, "--run-dir", str(tmp_path / "again"), "--summary", str(tmp_path / "again.json"))
        assert again.returncode == 3, again.stdout + again.stderr
        s = json.loads((tmp_path / "again.json").read_text())
        assert s["status"] == "degraded" and "the log of a run that ended truncated" in s["status_reasons"][0], s
    check = twin("check", "scenes/ball_drop.yaml", "--recording", str(log))
    assert check.returncode == 3 and "the log of a run that ended truncated" in check.stderr, check.stderr
