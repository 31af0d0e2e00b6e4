"""The insertion scenario: insert a DIP (plug) into the SPU's chamfered socket under impedance control."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from protocol.geometry import socket_parts

from .common import (
    GENERATOR,
    REALITIES,
    SIM_RATE,
    SOLVER_ITERATIONS,
    TELEMETRY_RATE,
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


SPU_SHAPE = {"type": "socket", "size": list(SPU_SIZE), "hole": SPU_HOLE_HALF, "depth": SPU_HOLE_DEPTH,
             "chamfer": SPU_CHAMFER}
"""The SPU as a scene shape: the one geometry definition of the reality and of the twin's scenes."""
STATED_POSITION_SIGMA = 0.005
"""The position uncertainty (m, one standard deviation) the robot's perception states for what it localizes: a
fixed claim of the perception system, not this run's error (which the twin must never be told)."""


CONNECT_LATERAL_TOL = 0.003


CONNECT_DEPTH_TOL = 0.004


# -------------------------------------------------------------------------------------- insertion
INSERT_DURATIONS = {"settle": 0.4, "approach": 2.4, "align": 0.8, "insert": 2.0, "hold": 0.8, "tail": 0.4}


def spu_parts() -> list[dict]:
    """The SPU's boxes in its frame (block centre): :func:`protocol.geometry.socket_parts` of :data:`SPU_SHAPE`,
    the same definition every scene of the twin models the SPU with."""
    return socket_parts(SPU_SHAPE)


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
        cfg = {"start_q": start_q, "start_fingers": [DIP_RADIUS, DIP_RADIUS], "grip_force": grip_force, "kp": kp,
               "impedance": imp}
        telem = Telemetry(np.random.default_rng([seed, 3]), noise)
        robot = Robot(w, planner, telem, cfg, max_time=30.0 * max(time_scale, 1.0), progress=progress)
        # the DIP between the closed fingers, axis along the hand's z
        hand_pos, hand_quat = w.hand()
        R = _rot(hand_quat)
        tip = hand_pos + R[:, 2] * w.arm.tip
        dip_pos = tip + R[:, 2] * grip_dz
        dip_id = w.cylinder(DIP_RADIUS, DIP_LENGTH, dip_pos, mass=dip["mass"], quat=[float(v) for v in hand_quat],
                            material=Material(dip["friction"], rolling=1e-4, spinning=1e-3, restitution=0.05))
        w.set_finger_friction(contact["finger_friction"])
        robot.finger_ref = robot.arm.grip(0.0)
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
            "spu": {"pose": _r(spu_seen), "shape": dict(SPU_SHAPE), "position_sigma": STATED_POSITION_SIGMA},
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
