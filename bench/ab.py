"""Two checkouts of the twin side by side: the conductor's ticks per second with N trivial agents, measured
alternately (A, B, A, B, ...) in one run so machine load hits both alike.

    .venv/bin/python -m bench.ab --a /tmp/old --b . --agents 1,4,16 --ticks 2000 --rounds 3 [--json F]

Each measurement runs in a fresh process whose working directory is the checkout (so it imports that
checkout's code, and its agents are started from it too). Both batched (the default ``clock.batch``) and one
step message per tick (``batch: 1``) are measured. Reports medians and the ratio B / A.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

# the overhead benchmark's entry point moved between versions: use whichever the checkout has
PROBE = """
import json, sys
n, ticks, batch = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
batch = None if batch == "default" else int(batch)
try:
    from bench.overhead import bench_twin
    rate, extra = bench_twin(n, ticks, batch=batch)
except ImportError:
    from conductor.bench_cli import bench_twin
    rate, extra = bench_twin(n, ticks, batch=batch)
print("RESULT", json.dumps({"rate": rate, "errors": extra.get("errors", 0)}))
"""


def measure(checkout: Path, n: int, ticks: int, batch: str) -> float:
    out = subprocess.run([sys.executable, "-c", PROBE, str(n), str(ticks), batch], cwd=checkout,
                         capture_output=True, text=True, timeout=900)
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            res = json.loads(line[7:])
            if res["errors"]:
                raise RuntimeError(f"{checkout}: {res['errors']} step errors with N={n}")
            return float(res["rate"])
    raise RuntimeError(f"{checkout}: no result (N={n}, batch {batch})\n{out.stderr[-2000:]}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", required=True, help="first checkout (e.g. the code before a change)")
    ap.add_argument("--b", default=".", help="second checkout (default: this one)")
    ap.add_argument("--agents", default="1,4,16")
    ap.add_argument("--ticks", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", metavar="FILE", help="write every measurement")
    args = ap.parse_args(argv)
    a, b = Path(args.a).resolve(), Path(args.b).resolve()
    rows = []
    for n in [int(x) for x in args.agents.split(",")]:
        for batch in ("default", "1"):
            got: dict[str, list[float]] = {"a": [], "b": []}
            for _ in range(args.rounds):
                got["a"].append(measure(a, n, args.ticks, batch))
                got["b"].append(measure(b, n, args.ticks, batch))
            ma, mb = statistics.median(got["a"]), statistics.median(got["b"])
            rows.append({"agents": n, "batch": batch, "a_ticks_per_s": round(ma, 1), "b_ticks_per_s": round(mb, 1),
                         "ratio_b_over_a": round(mb / ma, 3), "a_all": got["a"], "b_all": got["b"]})
            print(f"N={n:3d} batch {batch:>7}: A {ma:9.1f}  B {mb:9.1f} ticks/s  B/A {mb / ma:.3f}  "
                  f"(A {[round(x) for x in got['a']]}, B {[round(x) for x in got['b']]})", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"a": str(a), "b": str(b), "ticks": args.ticks, "rows": rows},
                                              indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
