"""End to end, as a user evaluates the twin: make one short recording per scenario with
`twin record synth` (a fresh seed, not one of the shipped recordings), then `twin evaluate` runs the
ensemble and a baseline on them (real agent processes, real pybullet, real Zenoh) and compares each
interpretation with the ground truth the reality run measured."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def twin(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, f"twin {' '.join(args)}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


@pytest.mark.slow
def test_fresh_recordings_are_interpreted_end_to_end(tmp_path):
    recs = tmp_path / "recordings"
    recs.mkdir()
    twin("record", "synth", "--scenario", "ball_drop", "--seed", "1000", "--container", "bowl",
         "--outcome", "success", "--time-scale", "0.7", "--out", str(recs / "ball_drop_fresh.mcap"), "-q")
    twin("record", "synth", "--scenario", "insertion", "--seed", "1001", "--localization-error", "0.002",
         "--time-scale", "0.7", "--out", str(recs / "insertion_fresh.mcap"), "-q")
    out = tmp_path / "t2.json"
    r = twin("evaluate", "--recordings", str(recs), "--configs", "ensemble,baseline1", "--json", str(out),
             "--table", str(tmp_path / "t2.md"), "--run-dir", str(tmp_path / "runs"), timeout=600)
    result = json.loads(out.read_text())
    assert len(result["runs"]) == 2, r.stdout
    by = {r["scenario"]: r for r in result["runs"]}
    assert set(by) == {"ball_drop", "insertion"}
    for scenario, predicate, truth_key in (("ball_drop", "in(container, ball)", "in_container"),
                                           ("insertion", "connected(dip, spu)", "connected")):
        run = by[scenario]
        assert run["errors"] == {} or not any(run["errors"].values()), run["errors"]
        truth = run["ground_truth"][truth_key]
        assert isinstance(truth, bool)
        got = run["interpretations"]["ensemble"][predicate]
        assert got == truth, f"{scenario}: ensemble says {predicate}={got}, the reality run measured {truth}"
        assert run["correct"]["ensemble"] is True
        assert run["handovers"]["ensemble"], f"{scenario}: the ensemble never moved a responsibility"
        assert run["rtf_by_config"]["ensemble"] > 0 and run["rtf_by_config"]["baseline1"] > 0
    table = (tmp_path / "t2.md").read_text()
    assert "| ball_drop |" in table and "| insertion |" in table
