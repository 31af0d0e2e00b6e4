"""Step rates of single models, called in-process (no Zenoh): what each model costs by itself.

    .venv/bin/python -m bench.model_rates OUT.json [--seconds 4] [--repeat 3] [--only physics,grasp_monitor]

Every model has one function registered with :func:`bench` that builds the model on a realistic
scene, steps it through ``model.step`` exactly as the agent runtime does (outputs and events
cleared each step, owned values read back with ``model.read``), and returns table rows. Adding a
model is one more decorated function (see ``grasp_monitor_rates`` for the smallest example).

- ``physics``: the ball-drop world (Panda, table, ball on a stand, a bin) following telemetry of a
  smooth arm motion with the fingers closing and opening, at 240 Hz and 1 kHz time steps with one
  substep per step (the raw pybullet figure of PLATFORM.md is per substep) and at the scenes'
  setting (1/240 s substeps, stepped at 120 Hz). Each row also measures, in the same run and the
  same pybullet world, the *raw* loop the model wraps: joint targets, ``stepSimulation``, one body
  pose read; ``model/raw`` is the cost of the model's own work (state extraction, link poses,
  contact events) on top of it.
- ``grasp_monitor``: 15 Hz steps on 250 Hz finger telemetry (one new sample per step).
- ``mujoco``: the same world and telemetry in MuJoCo, as the main model and as an idle hand model.
- ``fmu``: the cooling unit (FMI 3 through FMPy) at 10 Hz and 1 kHz.

Rates are medians over ``--repeat`` runs, interleaved (model, raw, model, raw, ...) so machine load
hits both alike. The JSON holds every row plus the machine.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from agents.models.grasp_monitor import GraspMonitor
from agents.models.physics import Physics
from protocol.robot import resolve_robot

PANDA = resolve_robot({"use": "panda"})
JOINTS, READY = PANDA.joints, PANDA.ready


ROOT = Path(__file__).resolve().parent.parent

BENCHES: dict[str, Callable[[argparse.Namespace], list[dict]]] = {}

BALL_DROP = {
    "stand": {"shape": {"type": "cylinder", "radius": 0.025, "length": 0.10}, "pose": [0.45, -0.25, 0.05],
              "tags": ["static"]},
    "ball": {"shape": {"type": "sphere", "radius": 0.033}, "pose": [0.45, -0.25, 0.133], "tags": ["graspable"],
             "mass": 0.057},
    "container": {"shape": {"type": "container", "style": "bin"}, "pose": [0.45, 0.25, 0.0], "tags": ["static"]},
}


def bench(name: str):
    """Register ``fn(args) -> rows`` as the benchmark of model ``name``."""

    def deco(fn):
        BENCHES[name] = fn
        return fn

    return deco


def defaults(cls) -> dict:
    return {k: p.default for k, p in cls.params.items()}


def telemetry(seconds: float, rate: float = 250.0) -> list[dict]:
    """Joint states of a smooth multi-joint swing; fingers close at 1/3 and open at 2/3 of the run."""
    amp = np.array([0.4, 0.2, 0.3, 0.3, 0.3, 0.3, 0.5])
    out = []
    for i in range(int(seconds * rate) + 1):
        t = i / rate
        q = np.asarray(READY[:7]) + amp * math.sin(2 * math.pi * 0.25 * t)
        qd = amp * 2 * math.pi * 0.25 * math.cos(2 * math.pi * 0.25 * t)
        f = 0.04 if t < seconds / 3 or t > 2 * seconds / 3 else 0.0
        out.append({"stamp": t, "name": list(JOINTS), "position": [*q, f, f], "velocity": [*qd, 0.0, 0.0],
                    "effort": [0.0] * 9})
    return out


def _latest(tel: list[dict], t: float, i: int) -> int:
    while i + 1 < len(tel) and tel[i + 1]["stamp"] <= t + 1e-9:
        i += 1
    return i


def physics_once(time_step: float, dt: float, seconds: float, tel: list[dict], params: dict | None = None) -> dict:
    """Step the physics model for ``seconds`` at ``dt``; then the raw pybullet loop on its world."""
    m = Physics()
    m.owned = {(n, "pose") for n in BALL_DROP}
    prm = defaults(Physics) | {"time_step": time_step} | (params or {})
    m.init(prm, {"entities": BALL_DROP, "robot": {}})
    steps = int(round(seconds / dt))
    owned = sorted(m.owned)
    i = 0
    t0 = time.perf_counter()
    for k in range(steps):
        t = k * dt
        i = _latest(tel, t, i)
        m._outputs, m._events = {}, []
        m.tick, m.t = k, t
        m.step(k, t, dt, {"joints": tel[i], "actions": []}, {})
        for e, a in owned:
            m.read(e, a)
    wall = time.perf_counter() - t0
    substeps = steps * max(1, int(round(dt / time_step)))
    # the raw loop on the same world: targets, stepSimulation, one pose read
    p, c, robot, ball = m.p, m.cid, m.robot, m.bodies["ball"].id
    idx = [m.arm.index.joint[n] for n in JOINTS]
    forces = [m.arm.joint_force[n] for n in JOINTS]
    i = 0
    t0 = time.perf_counter()
    for k in range(substeps):
        t = k * time_step
        i = _latest(tel, t, i)
        p.setJointMotorControlArray(robot, idx, p.POSITION_CONTROL, targetPositions=tel[i]["position"],
                                    forces=forces, physicsClientId=c)
        p.stepSimulation(physicsClientId=c)
        p.getBasePositionAndOrientation(ball, physicsClientId=c)
    raw_wall = time.perf_counter() - t0
    m.close()
    return {"steps_per_s": steps / wall, "substeps_per_s": substeps / wall, "rtf": seconds / wall,
            "raw_substeps_per_s": substeps / raw_wall}


@bench("physics")
def physics_rates(args: argparse.Namespace) -> list[dict]:
    tel = telemetry(args.seconds)
    configs = [("240 Hz, 1 substep/step", 1 / 240, 1 / 240, None),
               ("1 kHz, 1 substep/step", 1 / 1000, 1 / 1000, None),
               ("240 Hz substeps, stepped at 120 Hz", 1 / 240, 1 / 120, None),
               ("240 Hz, no contact events", 1 / 240, 1 / 240, {"contact_events": False}),
               ("240 Hz, grasp_binding force", 1 / 240, 1 / 240, {"grasp_binding": "force"})]
    rows = []
    for label, ts, dt, extra in configs:
        runs = [physics_once(ts, dt, args.seconds, tel, extra) for _ in range(args.repeat)]
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        rows.append({"model": "physics", "config": label, "time_step": ts, "dt": dt, "params": extra or {},
                     "steps_per_s": round(med["steps_per_s"], 1), "substeps_per_s": round(med["substeps_per_s"], 1),
                     "rtf": round(med["rtf"], 2), "raw_substeps_per_s": round(med["raw_substeps_per_s"], 1),
                     "raw_over_model": round(med["raw_substeps_per_s"] / med["substeps_per_s"], 2),
                     "runs": [{k: round(v, 1) for k, v in r.items()} for r in runs]})
    return rows


@bench("grasp_monitor")
def grasp_monitor_rates(args: argparse.Namespace) -> list[dict]:
    rate = 15.0
    tel = telemetry(args.seconds)
    rng = np.random.default_rng(0)
    for js in tel:  # a grasp in the middle third: the fingers stop at 32 mm and press with 30 N
        if js["position"][7] == 0.0:
            js["position"][7:] = [0.032 + rng.normal(0, 3e-5), 0.032 + rng.normal(0, 3e-5)]
            js["effort"][7:] = [-30 + rng.normal(0, 0.4), -30 + rng.normal(0, 0.4)]
    runs = []
    for _ in range(args.repeat):
        m = GraspMonitor()
        m.init(defaults(GraspMonitor), {"entities": {}})
        dt = 1 / rate
        reps = 50  # a 15 Hz run is short: go through it many times for a measurable wall time
        steps = int(args.seconds * rate)
        seq, i = [], 0
        for k in range(steps):
            i = _latest(tel, k * dt, i)
            seq.append(tel[i])
        feed = [{"joints": dict(js, stamp=r * 1000.0 + js["stamp"]), "actions": []} for r in range(reps) for js in seq]
        t0 = time.perf_counter()
        for k, tl in enumerate(feed):
            m._outputs, m._events = {}, []
            m.step(k, k * dt, dt, tl, {})
        wall = time.perf_counter() - t0
        runs.append({"steps_per_s": steps * reps / wall, "rtf": steps * reps * dt / wall,
                     "grasped_end": m.hands["hand"].grasped})
    return [{"model": "grasp_monitor", "config": "15 Hz on 250 Hz telemetry",
             "steps_per_s": round(statistics.median(r["steps_per_s"] for r in runs), 1),
             "rtf": round(statistics.median(r["rtf"] for r in runs), 1)}]


def _step_model(m, steps: int, dt: float, tel: list[dict] | None, inputs: dict | None = None) -> float:
    """Step ``m`` as the runtime does for ``steps`` steps of ``dt``; the wall time."""
    owned = sorted(m.owned)
    i = 0
    t0 = time.perf_counter()
    for k in range(steps):
        t = k * dt
        tl: dict = {"actions": []}
        if tel is not None:
            i = _latest(tel, t, i)
            tl["joints"] = tel[i]
        m._outputs, m._events = {}, []
        m.tick, m.t = k, t
        m.step(k, t, dt, tl, inputs or {})
        for e, a in owned:
            m.read(e, a)
    return time.perf_counter() - t0


@bench("mujoco")
def mujoco_rates(args: argparse.Namespace) -> list[dict]:
    """The ball-drop world in MuJoCo following the same telemetry, as the main model (simulating every step)
    and as a hand model that owns no pose (idle: kinematic), at the scenes' 1 ms step stepped at 120 Hz."""
    from agents.models.mujoco import MuJoCo

    tel = telemetry(args.seconds)
    rows = []
    for label, owned, extra in (("main model, 1 ms steps at 120 Hz", {(n, "pose") for n in BALL_DROP}, {}),
                                ("owning nothing, idle: kinematic", set(), {"idle": "kinematic"})):
        runs = []
        for _ in range(args.repeat):
            m = MuJoCo()
            m.owned = set(owned)
            m.init(defaults(MuJoCo) | {"time_step": 0.001} | extra, {"entities": BALL_DROP, "robot": {}})
            dt = 1 / 120
            steps = int(round(args.seconds / dt))
            wall = _step_model(m, steps, dt, tel)
            runs.append({"steps_per_s": steps / wall, "rtf": args.seconds / wall})
        rows.append({"model": "mujoco", "config": label,
                     "steps_per_s": round(statistics.median(r["steps_per_s"] for r in runs), 1),
                     "rtf": round(statistics.median(r["rtf"] for r in runs), 1)})
    return rows


@bench("fmu")
def fmu_rates(args: argparse.Namespace) -> list[dict]:
    """The cooling unit of scenes/units/cooling.py (FMI 3, pythonfmu3) stepped at 10 Hz and 1 kHz through FMPy,
    its output read back every step."""
    from agents.registry import resolve_kind

    cls = resolve_kind(f"fmu:{ROOT / 'scenes' / 'units' / 'cooling.py'}")
    rows = []
    for rate in (10.0, 1000.0):
        runs = []
        for _ in range(args.repeat):
            m = cls()
            m.owned = {("coffee", "temperature")}
            m.init(defaults(cls), {"entities": {}})
            dt = 1 / rate
            steps = max(200, int(round(args.seconds * rate)))
            wall = _step_model(m, steps, dt, None)
            m.close()
            runs.append({"steps_per_s": steps / wall, "rtf": steps * dt / wall})
        rows.append({"model": "fmu", "config": f"cooling unit at {rate:g} Hz",
                     "steps_per_s": round(statistics.median(r["steps_per_s"] for r in runs), 1),
                     "rtf": round(statistics.median(r["rtf"] for r in runs), 1)})
    return rows


def main(argv=None) -> int:
    from bench.common import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON file to write")
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=3, help="runs per configuration (median reported)")
    ap.add_argument("--only", default="", help="comma-separated model names (default: all: "
                                               + ", ".join(BENCHES) + ")")
    args = ap.parse_args(argv)
    names = [n for n in args.only.split(",") if n] or list(BENCHES)
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        ap.error(f"unknown model(s) {unknown}; known: {', '.join(BENCHES)}")
    rows = []
    for n in names:
        rows += BENCHES[n](args)
    print(f"single models in-process, {args.seconds} s simulated per run, median of {args.repeat}")
    print(f"{'model':<14} {'configuration':<36} {'steps/s':>9} {'substeps/s':>11} {'RTF':>8} {'raw/s':>9} "
          f"{'raw/model':>9}")
    for r in rows:
        sub = f"{r['substeps_per_s']:>11.0f}" if "substeps_per_s" in r else f"{'':>11}"
        raw = (f"{r['raw_substeps_per_s']:>9.0f} {r['raw_over_model']:>9.2f}" if "raw_substeps_per_s" in r
               else f"{'':>9} {'':>9}")
        print(f"{r['model']:<14} {r['config']:<36} {r['steps_per_s']:>9.0f} {sub} {r['rtf']:>8.1f} {raw}")
    out = {"machine": machine_info(),
           "seconds": args.seconds, "repeat": args.repeat, "rows": rows}
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
