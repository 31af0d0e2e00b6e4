"""``make demo``: run the most complete scenario there is, end to end, on the embedded router."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from recordings.simple import core_recording

from ..sources.recording import load_recording
from .main import main as twin_main

ROOT = Path(__file__).resolve().parents[2]


def _stamp(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def main() -> int:
    ball = ROOT / "scenes" / "ball_drop.yaml"
    rec = ROOT / "recordings" / "ball_drop_00.mcap"
    if ball.exists() and rec.exists():
        summary = Path("runs/demo/summary.json")
        earlier = _stamp(summary)
        rc = twin_main(["run", str(ball), "--recording", str(rec), "--run-dir", "runs/demo",
                        "--summary", str(summary), "--rerun", "save"])
        s = json.loads(summary.read_text()) if summary.exists() and _stamp(summary) != earlier else {}
        if s.get("ticks"):  # this run's (an earlier run's is not its answer), and it ran (one that did not start: said)
            truth = load_recording(rec).ground_truth().get("in_container")
            said = s["semantic_state"].get("in(container, ball)")
            status = str(s.get("status", "unknown"))
            print(f"\ninterpretation: in(container, ball) = {said};  ground truth of the recording: "
                  f"in_container = {truth}  -> {'CORRECT' if said == truth else 'WRONG'}"
                  + ("" if status == "complete" else f"  (the run ended {status.upper()}: see above)"))
            print("watch it:  .venv/bin/rerun runs/demo/run.rrd   (or: twin run ... --rerun serve for the web viewer)")
            print("or open runs/demo/run.mcap in Foxglove / Lichtblick with the layout docs/foxglove/ball_drop.json")
        return rc
    Path("runs/demo").mkdir(parents=True, exist_ok=True)
    core_recording("runs/demo/core.mcap")
    return twin_main(["run", str(ROOT / "scenes" / "core_demo.yaml"), "--recording", "runs/demo/core.mcap",
                      "--run-dir", "runs/demo", "--summary", "runs/demo/summary.json"])


if __name__ == "__main__":
    sys.exit(main())
