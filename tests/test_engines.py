"""Heterogeneous for real: three engines in one ensemble, through a real `twin run` (real agent processes, real
pybullet, MuJoCo and an FMI unit built with pythonfmu3, real Zenoh, a real Rerun recording).

scenes/coffee.yaml on a shipped ball_drop recording: the cup's pose goes pybullet -> MuJoCo (the grasp) ->
pybullet (the release); the coffee's temperature goes from one FMU (the mug) to another (the spill) when the
cup is emptied over the bin."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conductor.runlog import read_run_log

from .test_viewer import read_rrd, state_at, verify

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


@pytest.mark.slow
def test_three_engines_one_scene(tmp_path):
    run_dir = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/coffee.yaml", "--recording",
                        "recordings/ball_drop_00.mcap", "--rerun", "save", "--run-dir", str(run_dir)],
                       capture_output=True, text=True, timeout=600, cwd=ROOT, env=ENV)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["status"] == "complete" and s["invariant_violations"] == 0, s["status_reasons"]
    assert s["rerun_stream"] == {"mode": "save", "rrd": str(run_dir / "run.rrd"), "url": None, "delivered": None}
    moves = [(h["entity"], h["attribute"], h["from"], h["to"]) for h in s["handovers"]]
    assert moves == [("cup", "pose", "physics", "hand"), ("cup", "pose", "hand", "physics"),
                     ("coffee", "temperature", "mug", "spill")], moves
    assert s["semantic_state"]["in(container, cup)"] is True and s["semantic_state"]["poured(coffee)"] is True
    # the spill started where the mug had got to, and both cooled by Newton's law from 85 degC
    t_pour = s["handovers"][2]["t"]
    mug, spill = s["semantic_state"]["mug temperature (degC)"], s["semantic_state"]["poured coffee temperature (degC)"]
    assert mug == pytest.approx(20 + 65 * math.exp(-s["sim_s"] / 1500), abs=0.02)
    poured_at = 20 + 65 * math.exp(-t_pour / 1500)
    assert spill == pytest.approx(20 + (poured_at - 20) * math.exp(-(s["sim_s"] - t_pour) / 120), abs=0.05)
    unit = ROOT / "scenes" / "units" / "cooling.py"
    assert (f"running coffee (physics:physics, grasp_monitor:grasp_monitor, hand:mujoco, mug:fmu:{unit}, "
            f"spill:fmu:{unit})") in r.stdout, r.stdout[:500]

    # one owner per attribute in every ownership message of the run log, and the owners span three engines
    owners_seen: dict[str, set[str]] = {}
    versions = []
    for key, _, msg in read_run_log(s["run_log"]):
        if key.endswith("/ownership") and isinstance(msg, dict):
            versions.append(msg["version"])
            for ent, attrs in msg["owners"].items():
                for attr, owner in attrs.items():
                    assert isinstance(owner, str) and owner, (ent, attr, owner)
                    owners_seen.setdefault(f"{ent}.{attr}", set()).add(owner)
    assert versions == sorted(versions) and len(versions) == 1 + len(moves)
    assert owners_seen["cup.pose"] == {"physics", "hand"} and owners_seen["coffee.temperature"] == {"mug", "spill"}

    # the Rerun recording shows each handover at its tick: the ownership lane switches there
    rrd = run_dir / "run.rrd"
    verify(rrd)
    rows = read_rrd(rrd)
    for h in s["handovers"]:
        lane = rows[f"/ownership/{h['entity']}/{h['attribute']}"]
        assert state_at(lane, h["tick"]) == h["to"] and state_at(lane, h["tick"] - 1) == h["from"], h
    assert len(rows["/log/handovers"]) == len(moves)


def test_check_says_what_has_no_model_to_fall_back_to():
    """The coffee's temperature is owned by FMUs, and physics, the main model, cannot own a temperature: were its
    owner lost, it would stay where it was. twin check says so (a note: the scene is valid), ball_drop has none."""
    def check(scene: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "conductor.cli", "check", scene], capture_output=True,
                              text=True, timeout=300, cwd=ROOT, env=ENV)

    r = check("scenes/coffee.yaml")
    assert r.returncode == 0, r.stdout + r.stderr
    assert ("note: the main model physics cannot own coffee.temperature: if the model that owns it is lost, it "
            "stays where it was") in r.stdout, r.stdout
    r = check("scenes/ball_drop.yaml")
    assert r.returncode == 0 and "cannot own" not in r.stdout, r.stdout + r.stderr
