"""``twin bench overhead``: the conductor's ticks per second with N trivial agents, beside raw Zenoh and mosaik 3."""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

from conductor.core import Conductor, RunOptions
from conductor.launch import AgentProcs, agent_command, open_router
from conductor.scene import parse_scene
from protocol.keys import Keys

from .common import ROOT, machine_info, pubsub_rounds, query_rounds, wait_tokens


def bench_raw(n: int, ticks: int) -> float:
    """One process issuing N concurrent gets per round to N queryable processes; rounds per second."""
    session, endpoint = open_router()
    procs = AgentProcs(Path("/tmp") / f"twin-bench-raw-{os.getpid()}")
    try:
        keys = [f"bench/raw/{i}/step" for i in range(n)]
        for i, k in enumerate(keys):
            procs.spawn(f"raw{i}", [sys.executable, str(ROOT / "bench" / "raw_queryable.py"), endpoint, k])
        wait_tokens(session, "bench/raw/*/alive", n)
        return query_rounds(session, keys, ticks)
    finally:
        procs.stop()
        session.close()


def bench_raw_pubsub(n: int, ticks: int) -> float:
    """One process publishing one message per round, N subscriber processes each answering with a put."""
    session, endpoint = open_router()
    procs = AgentProcs(Path("/tmp") / f"twin-bench-ps-{os.getpid()}")
    try:
        for i in range(n):
            procs.spawn(f"ps{i}", [sys.executable, str(ROOT / "bench" / "raw_subscriber.py"), endpoint, str(i)])
        wait_tokens(session, "bench/ps/alive/*", n)
        return pubsub_rounds(session, n, ticks)
    finally:
        procs.stop()
        session.close()


def bench_twin(n: int, ticks: int, batch: int | None = None) -> tuple[float, dict]:
    """The conductor stepping N trivial service-stepped agents (twin run topology); ``batch`` sets the
    scene's clock.batch (None: the default; 1: one step message per tick)."""
    models = "\n".join(f"  m{i}: {{kind: trivial, step: service, rate: 1000}}" for i in range(n))
    clock = "{rate: 1000}" if batch is None else f"{{rate: 1000, batch: {batch}}}"
    scene = parse_scene(f"name: overhead\nclock: {clock}\nmain: m0\nmodels:\n{models}\n", "<bench>")
    session, endpoint = open_router()
    procs = AgentProcs(Path("/tmp") / f"twin-bench-{os.getpid()}")
    ens = f"bench{os.getpid()}"
    try:
        for name in scene.models:
            procs.spawn(name, agent_command("trivial", name, endpoint, ens))
        with Conductor(scene, session, Keys(ens), None, RunOptions(max_ticks=ticks)) as c:
            s = c.run()  # warm-up ticks are part of max_ticks; the loop is measured as a whole, set-up apart
        rate = s["ticks"] / s["wall_s"]
        models = s["models"].values()
        return rate, {"steps": sum(m["steps"] for m in models), "errors": sum(m["errors"] for m in models),
                      "batch": scene.batch}
    finally:
        procs.stop()
        session.close()


def bench_mosaik(n: int, ticks: int) -> float | None:
    script = ROOT / "bench" / "mosaik_run.py"
    try:
        out = subprocess.run([sys.executable, str(script), str(n), str(ticks)], capture_output=True, text=True,
                             timeout=600)
    except subprocess.TimeoutExpired:
        return None
    for line in out.stdout.splitlines():
        if line.startswith("TICKS_PER_S"):
            return float(line.split()[1])
    print(out.stderr[-2000:], file=sys.stderr)
    return None


def cmd_overhead(args) -> int:
    ns = [int(x) for x in args.agents.split(",")]
    results = []
    faults: list[str] = []
    for n in ns:
        raw: list[float] = []
        rawps: list[float] = []
        twin: list[float] = []
        lock: list[float] = []
        mos: list[float] = []
        extra: dict[str, Any] = {}
        errors = steps = 0
        for rep in range(args.repeat):
            parts = ["raw", "twin", "lockstep", "pubsub", *([] if args.no_mosaik else ["mosaik"])]
            for part in (parts if rep % 2 == 0 else parts[::-1]):  # each repetition all of them, alternating order
                if part == "raw":
                    raw.append(bench_raw(n, args.ticks))
                elif part == "pubsub":
                    rawps.append(bench_raw_pubsub(n, args.ticks))
                elif part == "mosaik":
                    m = bench_mosaik(n, args.ticks)
                    if m:
                        mos.append(m)
                    else:  # (said, not dropped without a word)
                        faults.append(f"N={n} rep {rep + 1}: the mosaik run gave no figure")
                else:
                    t, got = bench_twin(n, args.ticks, **({"batch": 1} if part == "lockstep" else {}))
                    (lock if part == "lockstep" else twin).append(t)
                    errors, steps = errors + got["errors"], steps + got["steps"]
                    extra = got if part == "twin" else extra
            print(f"  N={n:3d} rep {rep + 1}: raw query {raw[-1]:7.1f} rounds/s, twin {twin[-1]:7.1f} ticks/s "
                  f"(one message per tick: {lock[-1]:7.1f}), raw pub/sub {rawps[-1]:7.1f}"
                  + (f", mosaik {mos[-1]:7.1f}" if mos else ""), file=sys.stderr, flush=True)
        if errors:
            faults.append(f"N={n}: {errors} step errors in the twin's runs")
        extra = {**extra, "errors": errors, "steps": steps}  # (summed over every twin run, not the last one's)
        r = {"agents": n, "ticks": args.ticks, "repeats": args.repeat,
             "ticks_per_s": round(statistics.median(twin), 1),
             "raw_ticks_per_s": round(statistics.median(raw), 1),
             "overhead_ratio": round(statistics.median(raw) / statistics.median(twin), 3),
             "ticks_per_s_all": [round(x, 1) for x in twin], "raw_ticks_per_s_all": [round(x, 1) for x in raw],
             "lockstep_ticks_per_s": round(statistics.median(lock), 1),
             "lockstep_overhead_ratio": round(statistics.median(raw) / statistics.median(lock), 3),
             "lockstep_ticks_per_s_all": [round(x, 1) for x in lock],
             "raw_pubsub_ticks_per_s": round(statistics.median(rawps), 1),
             "overhead_ratio_vs_pubsub": round(statistics.median(rawps) / statistics.median(twin), 3),
             **extra}
        if mos:
            r["mosaik_ticks_per_s_all"] = [round(x, 1) for x in mos]
            r["mosaik_ticks_per_s"] = round(statistics.median(mos), 1)
            r["vs_mosaik"] = round(r["ticks_per_s"] / r["mosaik_ticks_per_s"], 2)
            r["lockstep_vs_mosaik"] = round(r["lockstep_ticks_per_s"] / r["mosaik_ticks_per_s"], 2)
        results.append(r)
        print(f"N={n:3d}: twin {r['ticks_per_s']:8.1f} ticks/s "
              f"(one message per tick {r['lockstep_ticks_per_s']:8.1f}), "
              f"raw {r['raw_ticks_per_s']:8.1f}, overhead {r['overhead_ratio']:.3f} (one message per tick "
              f"{r['lockstep_overhead_ratio']:.3f})"
              + (f", mosaik {r['mosaik_ticks_per_s']:8.1f} (x{r['vs_mosaik']}, one message per tick "
                 f"x{r['lockstep_vs_mosaik']})" if mos else ""), flush=True)
    out = {"machine": machine_info(), "results": results,
           "faults": faults,
           "method": "medians of alternating runs in one process (each repetition runs every variant, in alternating "
                     "order). raw (raw_ticks_per_s) = one process issuing N "
                     "concurrent Zenoh gets per round to N queryable processes through the same in-process router; "
                     "raw pub/sub = one put per round answered by a put from each of N subscriber processes; "
                     "twin (ticks_per_s) = the conductor in the router process stepping N trivial service-stepped "
                     "agent processes with its defaults: step broadcast on twin/<e>/step, answers on "
                     "twin/<e>/done/<id>, up to clock.batch = 32 ticks per step message (nothing can intervene "
                     "between the ticks of trivial agents: no triggers, no reads); lockstep = the same with "
                     "clock.batch 1, one step message and one answer per model per tick; mosaik = mosaik 3 World "
                     "stepping N trivial time-based simulators started "
                     "with 'cmd' (one process each)"}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=2))
        print(f"wrote {args.out}")
    for why in faults:
        print(f"fault: {why}", file=sys.stderr)
    return 1 if faults else 0


