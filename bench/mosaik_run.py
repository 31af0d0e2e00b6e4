"""Run mosaik 3 with N trivial simulator processes for T steps; prints 'TICKS_PER_S x'."""
import sys
import time
from pathlib import Path

import mosaik


def main():
    n, ticks = int(sys.argv[1]), int(sys.argv[2])
    sim = Path(__file__).with_name("mosaik_sim.py")
    world = mosaik.World({"Trivial": {"cmd": f"{sys.executable} {sim} %(addr)s"}}, debug=False)
    for _ in range(n):
        world.start("Trivial").Model.create(1)
    t0 = time.perf_counter()
    world.run(until=ticks, print_progress=False)
    print(f"TICKS_PER_S {ticks / (time.perf_counter() - t0)}")
    world.shutdown() if hasattr(world, "shutdown") else None


if __name__ == "__main__":
    main()
