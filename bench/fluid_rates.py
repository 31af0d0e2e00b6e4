"""Step rates of the fluid and in_hand models in-process (no Zenoh): what each model costs by itself.

    .venv/bin/python -m bench.fluid_rates [--seconds 3] [--repeat 3] [--json FILE | --json -]

Fluid: a cup of N particles stepped at 60 Hz (``dt = 1/60``, substeps of ``time_step``) for
``--seconds`` simulated seconds, once standing still (every particle resting on others: the most
contacts) and once tipped by 120° over one second (particles pouring out onto the table). The
real-time factor is simulated seconds per wall second. Configurations follow the paper's Table 1:
50 and 100 particles at 1.5 × 1/240 s, and 100 particles at 1/240 s.

in_hand: one grasped object, synthetic Panda telemetry (a swinging arm with noisy joints, fingers
in contact), stepped at 60 Hz; also the cost of its forward kinematics alone.

Prints a table, and the figures as JSON to ``--json FILE`` (``-``: standard output after the
table). Medians over ``--repeat`` runs.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.models.fluid import DEFAULT_TIME_STEP, Fluid
from agents.models.in_hand import InHand
from agents.robot.kinematics import RobotKinematics, compose, quat_slerp
from protocol.geometry import quat_from_axis_angle
from protocol.robot import resolve_robot

ROOT = Path(__file__).resolve().parent.parent

RATE = 60.0
CUP_POSE = [0.5, 0.0, 0.25, 0.0, 0.0, 0.0, 1.0]
TIPPED = quat_from_axis_angle([1, 0, 0], math.radians(120))


def _defaults(cls) -> dict:
    return {k: p.default for k, p in cls.params.items()}


def fluid_run(n: int, time_step: float, tip: bool, seconds: float) -> dict:
    m = Fluid()
    m.owned = {("fluid", "pose")}
    params = _defaults(Fluid) | {"particles": n, "time_step": time_step}
    scene = {"entities": {"cup": {"shape": {"type": "container", "style": "cup"}, "pose": CUP_POSE},
                          "fluid": {"shape": {"type": "sphere", "radius": 0.008}, "pose": CUP_POSE}}}
    t0 = time.perf_counter()
    m.init(params, scene)
    init_s = time.perf_counter() - t0
    dt = 1.0 / RATE
    steps = int(seconds * RATE)
    tel: dict[str, Any] = {"joints": None, "actions": []}
    t0 = time.perf_counter()
    for k in range(steps):
        t = k * dt
        s = min(1.0, max(0.0, t - 0.5)) if tip else 0.0
        q = quat_slerp([0, 0, 0, 1], TIPPED, s)
        m._outputs, m._events = {}, []
        m.step(k, t, dt, tel, {"cup": {"pose": [*CUP_POSE[:3], *q]}})
    wall = time.perf_counter() - t0
    out = {"particles": n, "time_step": time_step, "scenario": "tipped 120°" if tip else "upright",
           "steps_per_s": steps / wall, "substeps_per_s": m.substeps / wall, "rtf": steps * dt / wall,
           "init_s": init_s, "spilled": m.spilled}
    m.close()
    return out


def in_hand_run(seconds: float) -> dict:
    robot = resolve_robot(None)
    ARM_JOINTS, FINGER_JOINTS = robot.arm, robot.gripper.joints
    fk = RobotKinematics(robot)
    q_home = np.array([0.0, 0.2, 0.0, -2.0, 0.0, 2.2, 0.785])
    amp = np.array([0.3, 0.15, 0.2, 0.25, 0.2, 0.2, 0.3])
    names = list(ARM_JOINTS) + list(FINGER_JOINTS)
    rng = np.random.default_rng(0)
    dt = 1.0 / RATE
    steps = int(seconds * RATE)
    qs = [q_home + amp * math.sin(2 * math.pi * 0.4 * k * dt) for k in range(steps)]
    T_ho = [0.0, -0.004, 0.105, 0, 0, 0, 1]
    world0 = compose(list(fk.link_pose(dict(zip(ARM_JOINTS, qs[0])))), T_ho)
    # FK alone
    t0 = time.perf_counter()
    for q in qs:
        fk.link_pose(dict(zip(ARM_JOINTS, q)))
    fk_us = (time.perf_counter() - t0) / steps * 1e6
    fk.close()
    m = InHand()
    m.owned = {("ball", "pose")}
    m.init(_defaults(InHand), {"entities": {"ball": {"shape": {"type": "sphere", "radius": 0.033},
                                                     "pose": list(world0)}}, "robot": {}})
    tels = []
    for k, q in enumerate(qs):
        pos = list(q + rng.normal(0, 5e-4, 7)) + [0.029 + rng.normal(0, 3e-4), 0.037 + rng.normal(0, 3e-4)]
        eff = list(rng.normal(5, 2, 7)) + [20 + rng.normal(0, 0.3), 20 + rng.normal(0, 0.3)]
        tels.append({"joints": {"stamp": k * dt, "name": names, "position": pos, "velocity": [0.0] * 9,
                                "effort": eff}, "actions": []})
    t0 = time.perf_counter()
    for k, tel in enumerate(tels):
        m._outputs, m._events = {}, []
        m.step(k, k * dt, dt, tel, {})
    wall = time.perf_counter() - t0
    est = m._outputs["estimate"]["ball"]
    m.close()
    return {"steps_per_s": steps / wall, "step_us": wall / steps * 1e6, "fk_us": fk_us,
            "rtf_at_60hz": steps * dt / wall, "sigma_mm": est["sigma"] * 1e3}


def main(argv=None) -> int:
    from bench.common import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=3, help="runs per configuration (median reported)")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON ('-': standard output)")
    args = ap.parse_args(argv)

    configs = [(50, DEFAULT_TIME_STEP), (100, DEFAULT_TIME_STEP), (100, 1.0 / 240.0)]
    fluid_rows = []
    for n, ts in configs:
        for tip in (False, True):
            runs = [fluid_run(n, ts, tip, args.seconds) for _ in range(args.repeat)]
            row = dict(runs[0])
            for k in ("steps_per_s", "substeps_per_s", "rtf", "init_s"):
                row[k] = round(statistics.median(r[k] for r in runs), 3)
            row["rtf_all"] = [round(r["rtf"], 3) for r in runs]
            fluid_rows.append(row)
    ih_runs = [in_hand_run(args.seconds) for _ in range(args.repeat)]
    in_hand = {k: round(statistics.median(r[k] for r in ih_runs), 3) for k in ih_runs[0]}

    print(f"fluid model alone, stepped at {RATE:.0f} Hz for {args.seconds} s simulated (median of {args.repeat})")
    print(f"{'particles':>9} {'substep (s)':>12} {'scenario':>12} {'steps/s':>9} {'substeps/s':>11} {'RTF':>7} "
          f"{'spilled':>8}")
    for r in fluid_rows:
        print(f"{r['particles']:>9} {r['time_step']:>12.5f} {r['scenario']:>12} {r['steps_per_s']:>9.0f} "
              f"{r['substeps_per_s']:>11.0f} {r['rtf']:>7.2f} {r['spilled']:>8}")
    print(f"\nin_hand (one object, 60 Hz): {in_hand['steps_per_s']:.0f} steps/s ({in_hand['step_us']:.0f} µs/step, "
          f"of which FK {in_hand['fk_us']:.0f} µs), real-time factor {in_hand['rtf_at_60hz']:.0f}")
    out = {"machine": machine_info(),
           "rate_hz": RATE, "seconds": args.seconds, "repeat": args.repeat,
           "fluid": fluid_rows, "in_hand": in_hand}
    if args.json == "-":
        print(json.dumps(out, indent=2))
    elif args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=2))
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
