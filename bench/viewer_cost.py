"""What the live Rerun sink costs the conductor: real-time factor of one replay with and without it.

    .venv/bin/python -m bench.viewer_cost [--rounds 5] [--seconds 20] [--json FILE | --json -]
    .venv/bin/python -m bench.viewer_cost --scene scenes/ball_drop.yaml --recording recordings/ball_drop_00.mcap

Each round replays the same recording twice on a fresh embedded router with fresh agent processes,
as ``twin run`` does: once without a sink and once with ``ViewerSink`` in save mode (an .rrd in a
temporary folder), in alternating order (ABBA) so drift of the machine hits both alike. The replay
runs as fast as the models allow; the real-time factor is the conductor's own (simulated seconds
per wall second of its tick loop). Reports medians, the ratio with/without, and the per-round
ratios. Default: the core scene (tests/core_scene.yaml, test models, handovers) on a synthetic
recording of ``--seconds``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def one_run(scene_path: Path, recording: Path, with_sink: bool, workdir: Path, mode: str) -> dict:
    from conductor.core import Conductor, RunOptions
    from conductor.launch import AgentProcs, agent_command, open_router
    from conductor.scene import load_scene
    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource
    from conductor.viewer import start_sink
    from protocol.keys import Keys

    scene = load_scene(scene_path)
    rec = load_recording(recording)
    if "twin.scene" in rec.metadata:
        scene.apply_perception(json.loads(rec.metadata["twin.scene"].get("json", "{}")))
    workdir.mkdir(parents=True, exist_ok=True)
    session, endpoint = open_router()
    procs = AgentProcs(workdir)
    keys = Keys("bench")
    sink = None
    try:
        c = Conductor(scene, session, keys, ReplaySource(rec), RunOptions(run_log=str(workdir / "run.mcap"),
                                                                          register_timeout=60))
        for name, spec in scene.models.items():
            procs.spawn(name, agent_command(spec.kind, name, endpoint, keys.ensemble))
        if with_sink:
            sink = start_sink(session, keys, scene, mode, workdir, tap=c.run_log)
        cpu0 = time.process_time()
        try:
            s = c.run()
        finally:
            c.close()
        cpu = time.process_time() - cpu0
        out = {"rtf": s["rtf"], "ticks": s["ticks"], "wall_s": s["wall_s"], "handovers": len(s["handovers"]),
               "errors": len(s["errors"]), "conductor_process_cpu_s": round(cpu, 3)}
        if sink is not None:
            t0 = time.perf_counter()
            sink.close()
            out["sink_close_s"] = round(time.perf_counter() - t0, 3)
            out["sink_worker_cpu_s"] = round(sink.worker_cpu_s, 3)
            counts = sink._started().counts
            out["sink_poses"] = counts["poses"]
            out["sink_messages"] = counts["messages"]
            out["rrd_kib"] = round((workdir / "run.rrd").stat().st_size / 1024, 1)
        return out
    finally:
        procs.stop()
        session.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(ROOT / "tests" / "core_scene.yaml"))
    ap.add_argument("--recording", help="recording to replay (default: a synthetic one for the core scene)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the synthetic recording")
    ap.add_argument("--rounds", type=int, default=5, help="rounds of (without, with) pairs")
    ap.add_argument("--mode", default="save", help="sink mode measured (save; serve works too)")
    ap.add_argument("--json", help="write the figures as JSON to FILE ('-' = standard output)")
    args = ap.parse_args(argv)

    from bench.common import machine_info

    with tempfile.TemporaryDirectory(prefix="twin-viewer-cost-") as tmp:
        d = Path(tmp)
        if args.recording:
            recording = Path(args.recording)
        else:
            from recordings.simple import core_recording

            recording = core_recording(d / "rec.mcap", seconds=args.seconds)
        runs: dict[str, list[dict[str, Any]]] = {"without": [], "with": []}
        for r in range(args.rounds):
            order = (False, True) if r % 2 == 0 else (True, False)
            for with_sink in order:
                key = "with" if with_sink else "without"
                res = one_run(Path(args.scene), recording, with_sink, d / f"r{r}-{key}", args.mode)
                runs[key].append(res)
                print(f"round {r + 1}/{args.rounds} {key:7s} sink: real-time factor {res['rtf']:.2f} "
                      f"({res['ticks']} ticks in {res['wall_s']:.2f} s)", flush=True)
    rtf_without = [x["rtf"] for x in runs["without"]]
    rtf_with = [x["rtf"] for x in runs["with"]]
    med_without, med_with = statistics.median(rtf_without), statistics.median(rtf_with)
    pair = [w / o for w, o in zip(rtf_with, rtf_without)]
    result = {
        "benchmark": "viewer_cost",
        "scene": str(Path(args.scene).resolve().relative_to(ROOT)) if Path(args.scene).resolve().is_relative_to(ROOT)
        else args.scene,
        "recording": args.recording or f"synthetic core recording, {args.seconds} s",
        "mode": args.mode,
        "rounds": args.rounds,
        "rtf_without_sink": rtf_without,
        "rtf_with_sink": rtf_with,
        "median_rtf_without_sink": round(med_without, 3),
        "median_rtf_with_sink": round(med_with, 3),
        "ratio_of_medians": round(med_with / med_without, 4),
        "median_of_round_ratios": round(statistics.median(pair), 4),
        "cost_percent": round(100 * (1 - med_with / med_without), 2),
        "runs_without_sink": runs["without"],
        "runs_with_sink": runs["with"],
        "machine": machine_info(),
    }
    print(f"\nmedian real-time factor: {med_without:.2f} without the sink, {med_with:.2f} with it "
          f"(ratio {result['ratio_of_medians']:.3f}; cost {result['cost_percent']:.1f} % of the real-time factor)")
    if args.json:
        text = json.dumps(result, indent=2)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(text + "\n")
            print(f"figures: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
