"""The insertion scenario: insert a DIP (plug) into the SPU's chamfered socket under impedance control."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from protocol.geometry import quat_from_axis_angle, quat_mul

from .common import (
    GENERATOR,
    REALITIES,
    SIM_RATE,
    SOLVER_ITERATIONS,
    TELEMETRY_RATE,
    TIP,
    Progress,
    SynthResult,
    _command,
    _contact,
    _noise_levels,
    _perceive,
    _r,
    _rot,
    _scale_durations,
    _yaw_quat,
    hand_down,
)
from .reality import Material, Telemetry, _finish, _reality_generation
from .robot import Planner, Robot, linear_move
from .worlds import make_world

# The SPU of the insertion scenario: a 6 x 6 cm block, 8 cm high, with an octagonal hole on top
# (apothem 7.5 mm for a 6 mm-radius DIP), 20 mm deep, whose upper 6 mm are a 45-degree chamfer. Its
# frame is the block's centre (as for any box), so the DIP's ideal pose -- centre of a 5 cm DIP
# resting on the hole's bottom -- is SPU_CONNECTION_OFFSET above it (the insertion scene's
# connector uses the same [0, 0, 0.045]).
SPU_SIZE = (0.06, 0.06, 0.08)


SPU_HOLE_HALF = 0.0075


SPU_HOLE_DEPTH = 0.020


SPU_CHAMFER = 0.006


DIP_RADIUS = 0.006


DIP_LENGTH = 0.05


SPU_CONNECTION_OFFSET = (0.0, 0.0, SPU_SIZE[2] / 2 - SPU_HOLE_DEPTH + DIP_LENGTH / 2)


CONNECT_LATERAL_TOL = 0.003


CONNECT_DEPTH_TOL = 0.004


# -------------------------------------------------------------------------------------- insertion
INSERT_DURATIONS = {"settle": 0.4, "approach": 2.4, "align": 0.8, "insert": 2.0, "hold": 0.8, "tail": 0.4}


def _octagon_ring(apothem: float, half: float, z0: float, z1: float) -> list[dict]:
    """Boxes filling a square of half size ``half`` minus a centred octagonal opening, from z0 to z1."""
    h, zc, a = z1 - z0, (z0 + z1) / 2, apothem
    one = [0.0, 0.0, 0.0, 1.0]
    parts = [{"size": [2 * half, half - a, h], "pos": [0, (half + a) / 2, zc], "quat": one},
             {"size": [2 * half, half - a, h], "pos": [0, -(half + a) / 2, zc], "quat": one},
             {"size": [half - a, 2 * a, h], "pos": [(half + a) / 2, 0, zc], "quat": one},
             {"size": [half - a, 2 * a, h], "pos": [-(half + a) / 2, 0, zc], "quat": one}]
    # the square's corners inside the opening: one box per diagonal side of the octagon
    th = (math.sqrt(2) - 1) * a + 0.001
    side = 2 * a * math.tan(math.pi / 8) + 2 * th
    for k in range(4):
        yaw = math.pi / 4 + k * math.pi / 2
        rc = a + th / 2
        parts.append({"size": [th, side, h], "pos": [rc * math.cos(yaw), rc * math.sin(yaw), zc],
                      "quat": _yaw_quat(yaw)})
    return parts


def spu_parts() -> list[dict]:
    """The SPU's boxes in its frame (block centre): a base, an octagonal hole, a 45-degree chamfer.

    From the bottom: a solid block up to the hole's bottom; walls round an octagonal hole (apothem
    SPU_HOLE_HALF) up to the chamfer; eight slabs tilted 45 degrees whose upper faces form the
    chamfer, from the hole's apothem to SPU_HOLE_HALF + SPU_CHAMFER at the top; a top ring round it.
    A DIP whose lower face lands on the chamfer slides into the hole; one that lands on the flat top
    (more than about SPU_HOLE_HALF + SPU_CHAMFER - DIP_RADIUS off the axis) is blocked there.
    """
    sx, sy, H = SPU_SIZE
    half = min(sx, sy) / 2
    a, d, e = SPU_HOLE_HALF, SPU_HOLE_DEPTH, SPU_CHAMFER
    z0 = -H / 2
    zb = z0 + H - d  # the hole's bottom
    parts = [{"size": [sx, sy, H - d], "pos": [0, 0, (z0 + zb) / 2], "quat": [0, 0, 0, 1]}]
    parts += _octagon_ring(a, half, zb, z0 + H - e)
    parts += _octagon_ring(a + e, half, z0 + H - e, z0 + H)
    t = e  # slab thickness: enough to fill the wedge under the slope
    b = a + e
    width = 2 * b * math.tan(math.pi / 8) + 0.001
    for k in range(8):
        yaw = k * math.pi / 4
        mid_r, mid_z = a + e / 2, z0 + H - e / 2
        n_r, n_z = -1 / math.sqrt(2), 1 / math.sqrt(2)  # slope normal: up and towards the axis
        cr, cz = mid_r - n_r * t / 2, mid_z - n_z * t / 2
        q = quat_mul(_yaw_quat(yaw), quat_from_axis_angle([0, 1, 0], -math.pi / 4))
        parts.append({"size": [e * math.sqrt(2), width, t], "pos": [cr * math.cos(yaw), cr * math.sin(yaw), cz],
                      "quat": q})
    return parts


def synth_insertion(seed: int, out: str | Path, localization_error: float = 0.002, time_scale: float = 1.0,
                    progress: Progress | None = None, reality: str = "pybullet") -> SynthResult:
    """Generate one insertion recording (see the package docstring); returns what was measured."""
    if not 0.0 <= localization_error <= 0.1:
        raise ValueError(f"localization error must be within [0, 0.1] m, got {localization_error}")
    if reality not in REALITIES:
        raise ValueError(f"reality must be one of {', '.join(REALITIES)}, got {reality!r}")
    wall0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    contact = _contact(rng)
    noise = _noise_levels(rng)
    dip = {"mass": float(rng.uniform(0.015, 0.03)), "friction": float(rng.uniform(0.25, 0.4)),
           "radius": DIP_RADIUS, "length": DIP_LENGTH}
    spu_friction = float(rng.uniform(0.2, 0.35))
    r, th = rng.uniform(0.45, 0.62), rng.uniform(-0.8, 0.8)
    spu_yaw = float(rng.uniform(-math.pi / 4, math.pi / 4))
    spu_pose = [r * math.cos(th), r * math.sin(th), SPU_SIZE[2] / 2, *_yaw_quat(spu_yaw)]
    err_dir = float(rng.uniform(-math.pi, math.pi))
    srng = np.random.default_rng([seed, 1])
    dur = _scale_durations(srng, INSERT_DURATIONS, time_scale)
    grip_force = float(srng.uniform(25.0, 40.0))
    kp = float(srng.uniform(0.08, 0.15))
    hover = float(srng.uniform(0.03, 0.05))
    push = float(srng.uniform(0.006, 0.010))
    grip_dz = float(srng.uniform(0.010, 0.014))  # DIP centre below the fingertip centre
    start_tip = np.array([rng.uniform(0.35, 0.5), rng.uniform(-0.15, 0.15), rng.uniform(0.30, 0.40)])
    imp = {"k": float(srng.uniform(350, 500)), "k_rot": float(srng.uniform(15, 25)), "k_null": 2.0, "d_null": 0.5}
    imp["d"] = 2 * math.sqrt(imp["k"] * 1.5)
    imp["d_rot"] = 2 * math.sqrt(imp["k_rot"] * 0.01) * 1.5
    prng = np.random.default_rng([seed, 2])

    belief = list(spu_pose)
    belief[0] += localization_error * math.cos(err_dir)
    belief[1] += localization_error * math.sin(err_dir)

    world = make_world(reality, contact)
    planner = Planner()
    try:
        w = world
        w.static_boxes(spu_parts(), spu_pose, spu_friction, 0.1)
        yaw_h = spu_yaw  # hand aligned with the SPU's sides
        rest = planner.rest_for(start_tip[:2], yaw_h)
        start_q = planner.tip_pose_ik(start_tip, yaw_h, rest, rest)
        cfg = {"start_q": start_q, "start_fingers": DIP_RADIUS, "grip_force": grip_force, "kp": kp,
               "impedance": imp}
        telem = Telemetry(np.random.default_rng([seed, 3]), noise)
        robot = Robot(w, planner, telem, cfg, max_time=30.0 * max(time_scale, 1.0), progress=progress)
        # the DIP between the closed fingers, axis along the hand's z
        hand_pos, hand_quat = w.hand()
        R = _rot(hand_quat)
        tip = hand_pos + R[:, 2] * TIP
        dip_pos = tip + R[:, 2] * grip_dz
        dip_id = w.cylinder(DIP_RADIUS, DIP_LENGTH, dip_pos, mass=dip["mass"], quat=[float(v) for v in hand_quat],
                            material=Material(dip["friction"], rolling=1e-4, spinning=1e-3, restitution=0.05))
        w.set_finger_friction(contact["finger_friction"])
        robot.finger_ref = 0.0
        robot.recording = False
        robot.wait(dur["settle"])
        telem.t0 = w.t  # the log starts now
        robot.recording = True

        def say(msg: str) -> None:
            if progress:
                progress(f"{msg} (t = {w.t - telem.t0:.1f} s)")

        dip0 = w.pose(dip_id)
        dip_seen = _perceive(prng, dip0, noise["perception_m"] / 3)
        spu_seen = _perceive(prng, belief, noise["perception_m"] / 3)
        # the robot's plan: believed hole axis, the DIP hanging grip_dz below the fingertips
        hole_top = np.array(belief[:3]) + [0, 0, SPU_SIZE[2] / 2]
        tip_goal = hole_top + [0, 0, DIP_LENGTH / 2 + grip_dz - SPU_HOLE_DEPTH - push]
        tip_hover = hole_top + [0, 0, DIP_LENGTH / 2 + grip_dz + hover]
        tip_pre = tip_hover + [0, 0, 0.06]
        rest = planner.rest_for(hole_top[:2], yaw_h)
        say("approach the SPU")
        robot.move_to(planner.tip_pose_ik(tip_pre, yaw_h, robot.q_ref, rest), dur["approach"], "above_spu")
        robot.follow(linear_move(planner, robot.q_ref, tip_pre, tip_hover, yaw_h, dur["align"], rest), "align")
        say("insert (compliant)")
        robot.compliant_move(tip_hover, tip_goal, hand_down(yaw_h), dur["insert"], dur["hold"], "insert",
                             mode="compliant")
        robot.wait(dur["tail"])
        robot.recording = False
        # measure in the SPU's frame
        dp = w.pose(dip_id)
        local = _rot(spu_pose[3:]).T @ (dp[:3] - np.array(spu_pose[:3]))
        ideal = np.array(SPU_CONNECTION_OFFSET)
        lateral = float(math.hypot(local[0] - ideal[0], local[1] - ideal[1]))
        depth_err = float(local[2] - ideal[2])  # > 0: not fully in
        axis = _rot(dp[3:])[:, 2]
        tilt = math.degrees(math.acos(min(1.0, abs(float(axis[2])))))
        connected = lateral < CONNECT_LATERAL_TOL and depth_err < CONNECT_DEPTH_TOL and tilt < 10.0
        gt = {"connected": "true" if connected else "false", "lateral_error_m": json.dumps(round(lateral, 5)),
              "depth_error_m": json.dumps(round(depth_err, 5)), "tilt_deg": json.dumps(round(tilt, 2))}
        scene = {"entities": {
            "spu": {"pose": _r(spu_seen), "shape": {"type": "box", "size": list(SPU_SIZE)}},
            "dip": {"pose": _r(dip_seen), "shape": {"type": "cylinder", "radius": DIP_RADIUS, "length": DIP_LENGTH},
                    "mass": 0.02},
        }}
        gen = {"generator": GENERATOR, "scenario": "insertion", "seed": int(seed),
               "localization_error": float(localization_error), "localization_direction_rad": err_dir,
               "time_scale": float(time_scale), "sim_rate_hz": SIM_RATE, "telemetry_rate_hz": TELEMETRY_RATE,
               "solver_iterations": SOLVER_ITERATIONS, "contact": contact, "noise": noise, "dip": dip,
               "spu": {"pose": spu_pose, "believed_pose": belief, "friction": spu_friction, "size": list(SPU_SIZE),
                       "hole_half_width": SPU_HOLE_HALF, "hole_depth": SPU_HOLE_DEPTH, "chamfer": SPU_CHAMFER,
                       "connection_offset": list(SPU_CONNECTION_OFFSET)},
               "perceived": scene["entities"], "durations": dur, "grip_force_n": grip_force, "position_gain": kp,
               "impedance": imp, "hover": hover, "push": push, "grip_dz": grip_dz, "start_tip": start_tip.tolist(),
               "tolerance": {"lateral_m": CONNECT_LATERAL_TOL, "depth_m": CONNECT_DEPTH_TOL, "tilt_deg": 10.0}}
        _reality_generation(gen, w)
        gen["command"] = _command(gen)
        return _finish(out, telem, gt, scene, gen, w, wall0,
                       {"lateral": lateral, "depth_error": depth_err, "tilt_deg": tilt, "connected": connected})
    finally:
        planner.close()
        world.close()
