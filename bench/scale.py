"""``twin bench scale``: the conductor's tick rate as agents multiply and spread over hosts.

For every (hosts, agents) pair, three measurements in one run, with the same placement of processes:

* twin: the conductor (in this process, with the router) stepping N trivial service-stepped agents;
* raw query: this process issuing N concurrent Zenoh gets per round to N bare queryable processes, then
  collecting every reply (the baseline of ``twin bench overhead``);
* raw pub/sub: one put per round answered by a put from each of N bare subscriber processes (the
  transport shape the conductor's step broadcast uses).

``hosts = 1`` puts every process on this machine (loopback); ``hosts = H > 1`` spreads the agents
round-robin over H emulated machines, network namespaces joined by a bridge (bench/netns.py; needs root),
so each step crosses a veth pair and the bridge. The router and the conductor stay on this machine.
"""
from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from conductor.core import Conductor, RunOptions
from conductor.launch import AgentProcs, agent_command, free_port, open_router
from conductor.scene import parse_scene
from protocol.config import ZenohOptions
from protocol.keys import Keys

from .common import ROOT, machine_info, pubsub_rounds, query_rounds, wait_tokens
from .netns import Net, available


def _placement(hosts: int, logdir: Path):
    """(spawn(label, cmd, i), listen endpoint host, cleanup) for this many hosts."""
    if hosts <= 1:
        procs = AgentProcs(logdir)
        return (lambda label, cmd, i: procs.spawn(label, cmd)), "127.0.0.1", procs.stop

    net = Net(logdir)
    try:
        machines = [net.add_host(f"h{k}") for k in range(hosts)]
        ip = net.attach_root()
    except Exception:
        net.close()
        raise
    return (lambda label, cmd, i: machines[i % hosts].spawn(label, cmd)), ip, net.close


def _router(ip: str):
    port = free_port()
    return open_router(options=ZenohOptions(mode="router", listen=[f"tcp/{ip}:{port}"]))


def bench_twin(n: int, hosts: int, ticks: int, logdir: Path) -> dict:
    models = "\n".join(f"  m{i}: {{kind: trivial, step: service, rate: 1000}}" for i in range(n))
    # one step message per tick (batch 1): compared round for round with raw Zenoh queries
    scene = parse_scene(f"name: scale\nclock: {{rate: 1000, batch: 1}}\nmain: m0\nmodels:\n{models}\n", "<scale>")
    spawn, ip, cleanup = _placement(hosts, logdir)
    session = None
    try:
        session, endpoint = _router(ip)
        ens = f"scale{n}x{hosts}"
        t0 = time.perf_counter()
        for i, name in enumerate(scene.models):
            spawn(name, agent_command("trivial", name, endpoint, ens), i)
        with Conductor(scene, session, Keys(ens), None, RunOptions(max_ticks=ticks, register_timeout=300)) as c:
            s = c.run()
        models = s["models"].values()
        return {"ticks_per_s": round(s["ticks"] / s["wall_s"], 1),
                "setup_s": round(time.perf_counter() - t0 - s["wall_s"], 2),
                "steps": sum(m["steps"] for m in models), "errors": sum(m["errors"] for m in models)}
    finally:
        if session is not None:
            session.close()
        cleanup()


def bench_raw(n: int, hosts: int, ticks: int, logdir: Path) -> float:
    """Rounds per second of N concurrent gets to N bare queryables (placed as the agents are)."""
    spawn, ip, cleanup = _placement(hosts, logdir)
    session = None
    try:
        session, endpoint = _router(ip)
        keys = [f"bench/raw/{i}/step" for i in range(n)]
        for i, k in enumerate(keys):
            spawn(f"raw{i}", [sys.executable, str(ROOT / "bench" / "raw_queryable.py"), endpoint, k], i)
        wait_tokens(session, "bench/raw/*/alive", n, timeout=300)
        return query_rounds(session, keys, ticks)
    finally:
        if session is not None:
            session.close()
        cleanup()


def bench_raw_pubsub(n: int, hosts: int, ticks: int, logdir: Path) -> float:
    """Rounds per second of one put answered by a put from each of N bare subscribers."""
    spawn, ip, cleanup = _placement(hosts, logdir)
    session = None
    try:
        session, endpoint = _router(ip)
        for i in range(n):
            spawn(f"ps{i}", [sys.executable, str(ROOT / "bench" / "raw_subscriber.py"), endpoint, str(i)], i)
        wait_tokens(session, "bench/ps/alive/*", n, timeout=300)
        return pubsub_rounds(session, n, ticks)
    finally:
        if session is not None:
            session.close()
        cleanup()


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
    for j, h in enumerate(sorted({r["hosts"] for r in out["results"]})):
        rs = sorted((r for r in out["results"] if r["hosts"] == h and "ticks_per_s" in r), key=lambda r: r["agents"])
        if not rs:
            continue
        x = [r["agents"] for r in rs]
        c = colors[j % len(colors)]
        where = "one host (loopback)" if h == 1 else f"{h} hosts (netns + bridge)"
        ax.plot(x, [r["ticks_per_s"] for r in rs], "o-", color=c, label=f"twin, {where}")
        ax.plot(x, [r["raw_ticks_per_s"] for r in rs], "s--", color=c, alpha=0.7, label=f"raw Zenoh query, {where}")
        ax.plot(x, [r["raw_pubsub_ticks_per_s"] for r in rs], "^:", color=c, alpha=0.7,
                label=f"raw Zenoh pub/sub, {where}")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("service-stepped agents (one process each)")
    ax.set_ylabel("ticks (rounds) per second")
    cpus = out["machine"].get("cpus")
    ax.set_title(f"Conductor tick rate vs agents ({cpus} cores, {out['ticks']} ticks per point)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def cmd_scale(args) -> int:
    agents = [int(x) for x in args.agents.split(",") if x]
    hosts = [int(x) for x in args.hosts.split(",") if x]
    logdir = Path(args.logdir)
    results: list[dict[str, Any]] = []
    for h in hosts:
        if h > 1:
            reason = available()
            if reason:
                print(f"hosts={h}: skipped ({reason})", file=sys.stderr)
                results.extend({"hosts": h, "agents": n, "skipped": reason} for n in agents)
                continue
        for n in agents:
            twin, raw, rawps, extra = [], [], [], {}
            for rep in range(args.repeat):
                tag = f"{h}x{n}-{rep}"
                r = bench_twin(n, h, args.ticks, logdir / f"twin-{tag}")
                twin.append(r["ticks_per_s"])
                extra = {"setup_s": r["setup_s"], "errors": r["errors"]}
                raw.append(bench_raw(n, h, args.ticks, logdir / f"raw-{tag}"))
                rawps.append(bench_raw_pubsub(n, h, args.ticks, logdir / f"ps-{tag}"))
                print(f"  hosts={h} agents={n:3d} rep {rep + 1}: twin {twin[-1]:8.1f} ticks/s, raw query "
                      f"{raw[-1]:8.1f}, raw pub/sub {rawps[-1]:8.1f}", file=sys.stderr, flush=True)
            row = {"hosts": h, "agents": n, "ticks": args.ticks, "repeats": args.repeat,
                   "ticks_per_s": round(statistics.median(twin), 1),
                   "raw_ticks_per_s": round(statistics.median(raw), 1),
                   "raw_pubsub_ticks_per_s": round(statistics.median(rawps), 1),
                   "overhead_ratio": round(statistics.median(raw) / statistics.median(twin), 3),
                   "overhead_ratio_vs_pubsub": round(statistics.median(rawps) / statistics.median(twin), 3),
                   **extra}
            results.append(row)
            print(f"hosts={h} agents={n:3d}: twin {row['ticks_per_s']:8.1f} ticks/s, raw query "
                  f"{row['raw_ticks_per_s']:8.1f} (x{row['overhead_ratio']}), raw pub/sub "
                  f"{row['raw_pubsub_ticks_per_s']:8.1f}", flush=True)
    out = {"machine": machine_info(), "ticks": args.ticks, "results": results,
           "method": "medians over --repeat runs in one process. twin = the conductor (with the Zenoh router, "
                     "in this process) stepping N trivial service-stepped agent processes (step broadcast + "
                     "done/<id>), ticks per second of its loop; raw query = this process issuing N concurrent "
                     "gets per round to N bare queryable processes; raw pub/sub = one put per round answered by "
                     "one put from each of N bare subscriber processes. hosts=1: every process on this machine "
                     "over loopback; hosts=H: the N processes round-robin on H network namespaces joined to "
                     "this machine by veth pairs and a Linux bridge."}
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")
    png = Path(args.plot) if args.plot else path.with_suffix(".png")
    try:
        plot(out, png)
        print(f"wrote {path} and {png}")
    except ImportError:
        print(f"wrote {path} (no plot: matplotlib is not installed)")
    return 0
