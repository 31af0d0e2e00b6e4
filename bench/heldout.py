"""The team's held-out recordings: made with seeds that no shipped recording, test or tuning ever used, to see
whether what the ensemble does on the shipped set carries over to recordings nobody looked at first.

32 recordings, seeds 7001-7032 in this order: per reality (pybullet, then MuJoCo), every ball_drop outcome
with the bin and then the cup (12), then insertion at 3, 8, 15 and 40 mm of localization error (4).

    python -m bench.heldout --out runs/heldout            # generate (about 2 minutes)
    twin evaluate --recordings runs/heldout --json docs/results/heldout.json --table docs/results/heldout.md
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from recordings.synth import OUTCOMES, synth_ball_drop, synth_insertion

FIRST_SEED = 7001
REALITIES = ("pybullet", "mujoco")
CONTAINERS = ("bin", "cup")
ERRORS = (0.003, 0.008, 0.015, 0.04)


def plan(first_seed: int = FIRST_SEED) -> list[tuple[str, int, dict[str, Any]]]:
    """(file name, seed, arguments) of every held-out recording, in seed order."""
    out: list[tuple[str, int, dict[str, Any]]] = []
    seed = first_seed
    for reality in REALITIES:
        for outcome in OUTCOMES:
            for container in CONTAINERS:
                out.append((f"ho_bd_{reality}_{outcome}_{container}.mcap", seed,
                            {"scenario": "ball_drop", "reality": reality, "outcome": outcome, "container": container}))
                seed += 1
        for err in ERRORS:
            out.append((f"ho_ins_{reality}_{err}.mcap", seed,
                        {"scenario": "insertion", "reality": reality, "localization_error": err}))
            seed += 1
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.heldout", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/heldout", help="folder for the recordings (default runs/heldout)")
    ap.add_argument("--first-seed", type=int, default=FIRST_SEED,
                    help=f"the first of the 32 seeds (default {FIRST_SEED}: the set in docs/results/heldout.*; another "
                         "makes a fresh set nobody has looked at)")
    a = ap.parse_args(argv)
    folder = Path(a.out)
    folder.mkdir(parents=True, exist_ok=True)
    todo = plan(a.first_seed)
    for i, (name, seed, args) in enumerate(todo, 1):
        t0 = time.perf_counter()
        kw = dict(args)
        scenario = kw.pop("scenario")
        if scenario == "ball_drop":
            res = synth_ball_drop(seed, folder / name, **kw)
        else:
            res = synth_insertion(seed, folder / name, **kw)
        truth = ", ".join(f"{k}={v}" for k, v in res.ground_truth.items() if k in ("in_container", "connected"))
        print(f"[{i}/{len(todo)}] {name} (seed {seed}): {truth} ({time.perf_counter() - t0:.1f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
