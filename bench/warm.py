"""Warm against cold ``twin evaluate``, side by side in one run: the same recordings and configurations through
the warm service (serially, and ``--parallel N``) and with fresh processes per run (``--cold``), interleaved
in rounds; wall times, their ratios, recordings interpreted per minute, and whether every interpretation and
handover is the same in all three. ``tick_loops_s`` sums the runs' tick loops (their summaries' ``wall_s``):
a serial evaluation cannot take less, so ``speedup_bound_serial`` (cold time / the warm run's tick loops) is
the most any warm service running one run at a time could gain over cold.

``--limit`` times the same runs without the framework too (:func:`bench.limit.limit_evaluation`: every model in
one process, no Zenoh, no agent processes, no run log), in one process and in ``--parallel`` processes side by
side: how fast the models themselves interpret the recordings on this machine, so what is left between a warm
evaluation and that floor is the framework's. Its answers are compared with the cold evaluation's.

    python -m bench.warm --every 4 --rounds 1 --json docs/results/warm.json
    python -m bench.warm --every 8 --configs ensemble,baseline1,baseline2,baseline3 --limit
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import machine_info

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = "ensemble,baseline1,baseline2,baseline3,mujoco_grasp,mujoco"


def evaluate(recs: Path, mode: list[str], out: Path, configs: str) -> tuple[float, dict[str, Any]]:
    """Wall seconds of one ``twin evaluate`` (a process, as a user runs it) and its results."""
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "evaluate", "--recordings", str(recs), "--configs",
                        configs, "--json", str(out), "--run-dir", str(out.with_suffix("")), *mode],
                       capture_output=True, text=True, cwd=ROOT, timeout=7200)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise RuntimeError(f"twin evaluate {' '.join(mode)} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    return wall, json.loads(out.read_text())


def limit(recs: Path, parts: int, out: Path, configs: str) -> tuple[float, dict[str, Any]]:
    """Wall seconds of the limit (:func:`bench.limit.limit_evaluation`: the same runs in one process, without the
    framework) over the same recordings and configurations, in ``parts`` processes side by side, each taking every
    ``parts``-th recording; and their results merged."""
    t = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-m", "bench.limit", "--evaluation", str(recs), "--configs", configs,
                               "--part", f"{i}/{parts}", "--json", str(out.with_suffix(f".{i}.json"))],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
             for i in range(1, parts + 1)]
    errors = [p.communicate(timeout=7200)[1] for p in procs]
    wall = time.perf_counter() - t
    if any(p.returncode for p in procs):
        raise RuntimeError("the limit failed:\n" + "\n".join(e[-2000:] for e in errors))
    merged: dict[str, Any] = {"runs": {}, "skipped": {}, "loops_s": 0.0, "inits_s": 0.0}
    for i in range(1, parts + 1):
        part = json.loads(out.with_suffix(f".{i}.json").read_text())
        merged["runs"].update(part["runs"])
        merged["skipped"].update(part["skipped"])
        merged["loops_s"] += part["loops_s"]
        merged["inits_s"] += part["inits_s"]
    return wall, merged


def limit_differences(twin: dict[str, Any], lim: dict[str, Any]) -> list[str]:
    """Runs whose semantic state the limit found otherwise than the twin, or did not make at all though it was not
    among those it cannot make (``skipped``, said apart) ([]: none). The semantic state only: the limit keeps no
    handovers."""
    out = []
    for r in twin["runs"]:
        for cfg, sem in r["interpretations"].items():
            key = f"{Path(r['recording']).name}/{cfg}"
            got = lim["runs"].get(key)
            if got is None and key not in lim["skipped"]:
                out.append(f"{key}: the limit made no such run")
            elif got is not None and got["semantic_state"] != sem:
                out.append(f"{key}: twin {sem}, limit {got['semantic_state']}")
    return out


def answers(result: dict[str, Any]) -> dict[str, Any]:
    return {Path(r["recording"]).name: {k: r[k] for k in ("interpretations", "handovers", "status")}
            for r in result["runs"]}


def by_config(result: dict[str, Any]) -> dict[str, float]:
    """The tick loops of one evaluation summed per configuration (seconds)."""
    out: dict[str, float] = {}
    for r in result["runs"]:
        for cfg, v in (r.get("wall_s_by_config") or {}).items():
            out[cfg] = out.get(cfg, 0.0) + v
    return {cfg: round(v, 2) for cfg, v in out.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recordings", default=str(ROOT / "recordings"))
    ap.add_argument("--every", type=int, default=1, help="take every k-th recording (default all)")
    ap.add_argument("--configs", default=CONFIGS)
    ap.add_argument("--parallel", type=int, default=2, help="the warm parallel variant's --parallel (default 2)")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--limit", action="store_true",
                    help="also time the limit on the same runs (bench.limit --evaluation: the models in one process, "
                         "without the framework), one process and --parallel processes side by side")
    ap.add_argument("--json", metavar="FILE")
    a = ap.parse_args(argv)
    load_before = os.getloadavg()  # another user of the machine shows here (the ratios are side by side anyway)
    work = Path(tempfile.mkdtemp(prefix="twin-warm-"))
    recs = work / "recordings"
    recs.mkdir()
    chosen = sorted(Path(a.recordings).glob("*.mcap"))[::a.every]
    for p in chosen:
        (recs / p.name).symlink_to(p.resolve())
    modes = {"cold": ["--cold"], "warm": ["--parallel", "1"],
             f"warm_parallel{a.parallel}": ["--parallel", str(a.parallel)]}
    limits = {"limit": 1, f"limit_parallel{a.parallel}": a.parallel} if a.limit else {}
    walls: dict[str, list[float]] = {m: [] for m in [*modes, *limits]}
    rounds: dict[str, list[dict[str, Any]]] = {m: [] for m in [*modes, *limits]}  # each round's result
    try:
        for rnd in range(a.rounds):
            order = [*modes, *limits]
            for m in (order if rnd % 2 == 0 else reversed(order)):  # ABC, CBA, ...
                if m in limits:
                    wall, res = limit(recs, limits[m], work / f"{m}-{rnd}.json", a.configs)
                else:
                    wall, res = evaluate(recs, modes[m], work / f"{m}-{rnd}.json", a.configs)
                walls[m].append(wall)
                rounds[m].append(res)
                print(f"round {rnd + 1}: {m:16s} {wall:7.1f} s", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    cold = rounds["cold"][0]
    runs = sum(len(r["status"]) for r in cold["runs"])
    # every round of every mode against the first cold one (the cold rounds among themselves too)
    same = {m: all(answers(res) == answers(cold) for res in rounds[m]) for m in modes}
    med = {m: statistics.median(w) for m, w in walls.items()}
    # the tick loops alone: what no service can take away from a serial evaluation (medians over the rounds)
    loops = {m: round(statistics.median(sum(by_config(res).values()) for res in rounds[m]), 2) for m in modes}
    per_config = {m: {cfg: round(statistics.median(by_config(res)[cfg] for res in rounds[m]), 2)
                      for cfg in by_config(rounds[m][0])} for m in modes}
    lim_diffs = sorted({d for m in limits for res in rounds[m] for d in limit_differences(cold, res)})
    out = {"recordings": len(chosen), "every": a.every, "configs": a.configs.split(","), "runs": runs,
           "rounds": a.rounds, "wall_s": walls, "median_wall_s": med,
           "tick_loops_s": loops, "tick_loop_share": {m: round(loops[m] / med[m], 3) for m in modes},
           "tick_loops_by_config_s": per_config,
           "speedup_bound_serial": round(med["cold"] / loops["warm"], 2) if loops["warm"] else None,
           "speedup_vs_cold": {m: round(med["cold"] / med[m], 2) for m in modes if m != "cold"},
           # (each round's own: cold and the mode of one round, side by side; one value when --rounds 1)
           "speedup_vs_cold_per_round": {m: [round(c / w, 2) for c, w in zip(walls["cold"], walls[m])]
                                         for m in modes if m != "cold"},
           "recordings_per_minute": {m: round(len(chosen) / med[m] * 60, 1) for m in modes},
           "identical_interpretations_and_handovers": same, "machine": machine_info(),
           **({"limit": {"speedup_vs_cold": {m: round(med["cold"] / med[m], 2) for m in limits},
                         "loops_s": round(statistics.median(res["loops_s"] for res in rounds["limit"]), 2),
                         "inits_s": round(statistics.median(res["inits_s"] for res in rounds["limit"]), 2),
                         "runs": len(rounds["limit"][0]["runs"]), "skipped": rounds["limit"][0]["skipped"],
                         "compared": "semantic state (the limit keeps no handovers)",
                         "differences_from_cold": lim_diffs}}
              if limits else {}),
           "load_average": {"before": [round(x, 2) for x in load_before],
                            "after": [round(x, 2) for x in os.getloadavg()]}}
    print(json.dumps({k: out[k] for k in ("speedup_vs_cold", "recordings_per_minute", "tick_loops_s", "tick_loop_share",
                                           "tick_loops_by_config_s",
                                           "speedup_bound_serial", "identical_interpretations_and_handovers")
                      if k in out} | ({"limit": out["limit"]} if limits else {}),
                     indent=2))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0 if all(same.values()) and not lim_diffs else 1


if __name__ == "__main__":
    sys.exit(main())
