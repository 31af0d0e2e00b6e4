"""Start-up waits across network namespaces: how long a Zenoh session takes to open on one emulated host when the
router is on another (a router opening, an agent's client session, a peer), with the twin's own options. Before
the scouting delay went, a router's open alone took 0.5 s.

    python -m bench.startup_netns --json docs/results/startup_netns.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench.netns import Net, available

ROOT = Path(__file__).resolve().parent.parent
PROBE = """
import json, sys, time
sys.path.insert(0, {root!r})
from protocol.config import ZenohOptions
out = {{}}
for mode, kw in (("router", dict(listen=["tcp/0.0.0.0:7450"])), ("client", dict(connect=[{ep!r}])),
                 ("peer", dict(connect=[{ep!r}]))):
    times = []
    for _ in range({n}):
        t = time.perf_counter()
        s = ZenohOptions(mode=mode, **kw).open()
        times.append(time.perf_counter() - t)
        s.close()
    out[mode] = times
print(json.dumps(out))
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", metavar="FILE")
    a = ap.parse_args(argv)
    why = available()
    if why:
        print(f"bench.startup_netns: {why}", file=sys.stderr)
        return 2
    net = Net(Path(tempfile.mkdtemp(prefix="twin-startup-")))
    try:
        router, agent = net.add_host("router"), net.add_host("agent")
        router.spawn("router", [sys.executable, "-m", "conductor.cli", "router", "--listen", "tcp/0.0.0.0:7447"],
                     cwd=str(ROOT))
        net.wait_reachable(agent, router)
        time.sleep(1.0)  # the router process is up
        r = agent.run(sys.executable, "-c", PROBE.format(root=str(ROOT), ep=f"tcp/{router.ip}:7447", n=a.repeat),
                      timeout=120)
        if r.returncode != 0:
            print(r.stdout + r.stderr, file=sys.stderr)
            return 1
        times = json.loads(r.stdout.strip().splitlines()[-1])
    finally:
        net.close()
    out = {mode: {"median_ms": round(1e3 * statistics.median(ts), 2), "max_ms": round(1e3 * max(ts), 2),
                  "runs": len(ts)} for mode, ts in times.items()}
    print(json.dumps(out, indent=2))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
