"""The ball_drop scenario: pick a ball from a stand and drop it into a container (or fail to)."""
from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from protocol.errors import SynthError
from protocol.geometry import container_params, container_parts, inside_container

from .arm import SynthArm, synth_arm
from .common import (
    CONTAINERS,
    GENERATOR,
    OUTCOMES,
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
    _scale_durations,
    _yaw_quat,
)
from .reality import Material, Telemetry, _finish, _reality_generation
from .robot import JointMove, Planner, Robot, _settle, linear_move
from .worlds import make_world


def _container_radius(shape: dict) -> float:
    """Horizontal radius of the container's footprint (outer)."""
    p = container_params(shape)
    if p["style"] in ("bin", "box"):
        return math.hypot(p["size"][0], p["size"][1]) / 2
    return float(p["radius"]) + float(p["wall"])


def _container_height(shape: dict) -> float:
    p = container_params(shape)
    return float(p["size"][2]) if p["style"] in ("bin", "box") else float(p["height"])


def _container_extent(shape: dict, yaw: float, direction) -> float:
    """Distance from the container's centre to its outer side along a world direction."""
    p = container_params(shape)
    if p["style"] in ("bin", "box"):
        c, s = math.cos(yaw), math.sin(yaw)
        ux, uy = c * direction[0] + s * direction[1], -s * direction[0] + c * direction[1]
        return abs(ux) * p["size"][0] / 2 + abs(uy) * p["size"][1] / 2
    return float(p["radius"]) + float(p["wall"])


def _container_inner(shape: dict) -> float:
    """Radius of the largest horizontal disc inside the container's opening."""
    p = container_params(shape)
    if p["style"] in ("bin", "box"):
        return min(p["size"][0], p["size"][1]) / 2 - p["wall"]
    return float(p["radius"]) - float(p["wall"])


# -------------------------------------------------------------------------------------- ball drop
# "open" is no phase any more, but its random draw stays: every duration is drawn from the seed in
# this order, and the shipped recordings (make recordings) must come out byte for byte the same
BALL_DURATIONS = {"settle": 0.3, "open": 0.4, "approach": 2.0, "descend": 1.2, "lift": 1.0, "carry": 2.2,
                  "lower": 0.8, "retreat": 0.8, "home": 1.4}


def _place_ball_drop(rng: np.random.Generator, shape: dict, reach: float | None = None) -> dict:
    """Stand and container within the Panda's reach, apart enough for the fingers and an early release.

    ``reach``: another arm's (m, :attr:`SynthArm.reach`): a container whose centre, where the hand opens over it,
    lies beyond it is drawn again (None: the Panda's, whose draws all reach).
    """
    Rc = _container_radius(shape)
    for _ in range(2000):
        rs, ths = rng.uniform(0.40, 0.60), rng.uniform(-1.05, 1.05)
        rc, thc = rng.uniform(0.42, 0.64), rng.uniform(-1.1, 1.1)
        if reach is not None and rc > reach:
            continue
        stand = np.array([rs * math.cos(ths), rs * math.sin(ths)])
        cont = np.array([rc * math.cos(thc), rc * math.sin(thc)])
        if np.linalg.norm(stand - cont) < Rc + 0.22:
            continue
        if rc - Rc < 0.2 or rc + Rc > 0.86:
            continue
        return {"stand_xy": stand, "container_xy": cont, "container_yaw": float(rng.uniform(-math.pi, math.pi))}
    raise SynthError(f"cannot place a {shape.get('style')} container and a stand within reach")


def _draw_world(rng: np.random.Generator, shape: dict, reach: float | None = None) -> dict:
    """The physical world of a seed (drawn first, in a fixed order: the same for every outcome and reality;
    ``reach``: see :func:`_place_ball_drop`)."""
    contact = _contact(rng)
    noise = _noise_levels(rng)
    ball = {"radius": float(rng.uniform(0.0325, 0.0340)), "mass": float(rng.uniform(0.056, 0.059)),
            "friction": float(rng.uniform(0.6, 0.9)), "rolling_friction": float(rng.uniform(2e-4, 6e-4)),
            "spinning_friction": float(rng.uniform(5e-4, 2e-3)), "restitution": float(rng.uniform(0.75, 0.85))}
    stand = {"radius": float(rng.uniform(0.02, 0.03)), "length": float(rng.uniform(0.05, 0.12))}
    cprops = {"friction": float(rng.uniform(0.4, 0.7)), "restitution": float(rng.uniform(0.35, 0.55))}
    place = _place_ball_drop(rng, shape, reach)
    return {"contact": contact, "noise": noise, "ball": ball, "stand": stand, "cprops": cprops, "place": place}


def _draw_script(srng: np.random.Generator, time_scale: float, arm: SynthArm) -> dict:
    """The script's choices (its own stream; the order of the draws is fixed for reproducibility)."""
    s = {"dur": _scale_durations(srng, BALL_DURATIONS, time_scale), "grip_force": float(srng.uniform(20.0, 35.0)),
         "kp": float(srng.uniform(0.08, 0.15)), "pre_grasp": float(srng.uniform(0.08, 0.14)),
         "grasp_dz": float(srng.uniform(-0.006, 0.004))}
    s["carry_clear"] = float(srng.uniform(0.06, 0.10))
    s["release_clear"] = float(srng.uniform(0.02, 0.05))
    s["yaw_grasp_dev"] = float(srng.uniform(-0.4, 0.4))
    s["start_q"] = arm.home + srng.normal(0, 0.05, arm.n)
    s["early_frac"] = float(srng.uniform(0.2, 0.35))
    s["miss_gap"] = float(srng.uniform(0.04, 0.07))
    s["miss_dir"] = float(srng.uniform(-math.pi, math.pi))
    s["empty_mode"] = str(srng.choice(["mislocated", "too_high"]))
    s["empty_offset"] = float(srng.uniform(0.065, 0.09)) * float(srng.choice([-1.0, 1.0]))
    s["empty_high"] = float(srng.uniform(0.025, 0.045))
    s["release_off"] = srng.uniform(-1, 1, 2)
    return s


def _draw_faults(frng: np.random.Generator) -> dict:
    """The failures the reality inflicts (a stream of its own, so the older outcomes keep their draws).

    slipped: partway through the carry the gripper's force falls, within ``ramp_s``, to
    ``residual_force_n`` per finger -- too little for friction to hold a 57 g ball (2 mu F < m g
    with mu <= 1.3 needs F < 0.2 N) -- while the robot still commands the grasp. A linkage gripper's
    drive (the xArm's) also gives way by ``slip_give`` of its stroke (see :meth:`Robot.weaken_grip`).
    knocked: the robot believes the ball ``offset`` (m, 30-40 mm either way) from its real place
    along the fingers' closing line. The open fingers' inner faces are 40 mm from the hand's axis
    and their tips 14 mm thick, so one fingertip comes down on the top of the ball instead of
    beside it: it presses the ball onto the stand until the torque-limited arm yields sideways,
    and the closing fingers push the ball off the stand. (Less offset and the fingertip pushes the
    ball between the fingers, which then grasp it; more and the back-drivable finger yields and the
    ball stays. A finger closing at gripper speed cannot knock a ball off a 2-3 cm wide stand by
    squeezing it from the side: it moves it a few mm.) The robot carries on.
    """
    return {"slip_fraction": float(frng.uniform(0.1, 0.4)), "slip_ramp_s": float(frng.uniform(0.05, 0.3)),
            "slip_residual_force_n": float(frng.uniform(0.03, 0.12)),
            "knock_offset": float(frng.uniform(0.030, 0.040)) * float(frng.choice([-1.0, 1.0])),
            "slip_give": float(frng.uniform(0.12, 0.2))}  # (drawn last: the Panda's draws before it stay)


def _release_xy(outcome: str, shape: dict, cont_seen, stand_seen, s: dict, radius: float,
                reach: float = 0.78) -> np.ndarray:
    """Where the hand opens: over the believed container (within its slack), or beside it (missed)."""
    cxy = np.array(cont_seen[:2])
    if outcome != "missed":
        inner = _container_inner(shape)
        slack = max(0.0, inner - radius - 0.01)
        return cxy + s["release_off"] * 0.4 * slack
    c_yaw = 2 * math.atan2(cont_seen[5], cont_seen[6])
    for k in range(64):
        a = s["miss_dir"] + k * 0.41
        u = np.array([math.cos(a), math.sin(a)])
        xy = cxy + u * (_container_extent(shape, c_yaw, u) + radius + s["miss_gap"])
        r = float(np.linalg.norm(xy))
        if 0.32 < r < reach and np.linalg.norm(xy - np.array(stand_seen[:2])) > 0.12:
            return xy
    raise SynthError("no reachable release point beside the container")


def synth_ball_drop(seed: int, out: str | Path, container: str = "bin", outcome: str = "success",
                    time_scale: float = 1.0, progress: Progress | None = None,
                    reality: str = "pybullet", arm_name: str = "panda") -> SynthResult:
    """Generate one ball_drop recording (see the package docstring); returns what was measured."""
    if container not in CONTAINERS:
        raise ValueError(f"container must be one of {', '.join(CONTAINERS)}, got {container!r}")
    if outcome not in OUTCOMES:
        raise ValueError(f"outcome must be one of {', '.join(OUTCOMES)}, got {outcome!r}")
    if reality not in REALITIES:
        raise ValueError(f"reality must be one of {', '.join(REALITIES)}, got {reality!r}")
    wall0 = time.perf_counter()
    shape = {"type": "container", "style": container}
    arm = synth_arm(arm_name)
    wd = _draw_world(np.random.default_rng(seed), shape, None if arm.name == "panda" else arm.reach)
    ball, stand, place = wd["ball"], wd["stand"], wd["place"]
    s = _draw_script(np.random.default_rng([seed, 1]), time_scale, arm)
    faults = _draw_faults(np.random.default_rng([seed, 4]))
    dur = s["dur"]
    prng = np.random.default_rng([seed, 2])  # perception noise
    h_c = _container_height(shape)

    stand_pose = [*place["stand_xy"], stand["length"] / 2, 0.0, 0.0, 0.0, 1.0]
    ball_pos = np.array([*place["stand_xy"], stand["length"] + ball["radius"] - 0.0003])
    cont_pose = [*place["container_xy"], 0.0, *_yaw_quat(place["container_yaw"])]

    world = make_world(reality, wd["contact"], arm)
    planner = Planner(arm)
    try:
        w = world
        w.cylinder(stand["radius"], stand["length"], stand_pose[:3],
                   material=Material(0.7, rolling=1e-3, spinning=1e-3, restitution=0.3))
        w.static_boxes(container_parts(shape), cont_pose, wd["cprops"]["friction"], wd["cprops"]["restitution"])
        ball_id = w.sphere(ball["radius"], ball_pos, ball["mass"],
                           Material(ball["friction"], rolling=ball["rolling_friction"],
                                    spinning=ball["spinning_friction"], restitution=ball["restitution"], damping=0.01))
        # perception: what the robot believes (true poses + a few mm of noise)
        noise = wd["noise"]
        ball_seen = _perceive(prng, list(ball_pos) + [0, 0, 0, 1], noise["perception_m"])
        stand_seen = _perceive(prng, stand_pose, noise["perception_m"])
        cont_seen = _perceive(prng, cont_pose, noise["perception_m"], noise["perception_yaw_rad"])
        yaw_g = math.atan2(ball_seen[1], ball_seen[0]) + s["yaw_grasp_dev"]
        # the robot believes the ball is beside its real place: along the hand's x axis (across the
        # fingers' closing line) beyond the pads (empty grasp), or along the closing line under a finger (knocked)
        side = np.array([math.cos(yaw_g), math.sin(yaw_g)])
        if outcome == "empty_grasp" and s["empty_mode"] == "mislocated":
            ball_seen[0] += s["empty_offset"] * side[0]
            ball_seen[1] += s["empty_offset"] * side[1]
        elif outcome == "knocked":
            closing = np.array([math.sin(yaw_g), -math.cos(yaw_g)])  # the hand's y axis: the fingers' travel
            ball_seen[0] += faults["knock_offset"] * closing[0]
            ball_seen[1] += faults["knock_offset"] * closing[1]

        telem = Telemetry(np.random.default_rng([seed, 3]), noise, arm=arm)
        cfg = {"start_q": s["start_q"], "start_fingers": arm.grip(0.5), "grip_force": s["grip_force"], "kp": s["kp"]}
        robot = Robot(w, planner, telem, cfg, max_time=40.0 * max(time_scale, 1.0), progress=progress)
        robot.recording = False
        robot.wait(dur["settle"])  # the world at rest before the log starts
        telem.t0 = w.t  # the log starts now
        robot.recording = True

        def say(msg: str) -> None:
            if progress:
                progress(f"{msg} (t = {w.t - telem.t0:.1f} s)")

        bx, by, bz = ball_seen[:3]
        grasp_tip = np.array([bx, by, bz + s["grasp_dz"]])
        if outcome == "empty_grasp" and s["empty_mode"] == "too_high":
            grasp_tip[2] = bz + ball["radius"] + s["empty_high"]
        above_tip = grasp_tip + [0, 0, s["pre_grasp"]]
        rest_g = planner.rest_for(grasp_tip[:2], yaw_g)

        say("open hand")
        robot.hand("open")
        say("approach the ball")
        q_above = planner.tip_pose_ik(above_tip, yaw_g, rest_g, rest_g)
        robot.move_to(q_above, dur["approach"], "above_ball")
        say("descend")
        robot.follow(linear_move(planner, robot.q_ref, above_tip, grasp_tip, yaw_g, dur["descend"], rest_g),
                     "grasp_ball")
        say("grasp")
        robot.hand("close")
        # carry height: the ball's bottom well above the rim, and above the stand
        z_carry = max(h_c + ball["radius"] + s["carry_clear"], grasp_tip[2] + 0.08)
        lift_tip = np.array([grasp_tip[0], grasp_tip[1], z_carry])
        say("lift")
        robot.follow(linear_move(planner, robot.q_ref, grasp_tip, lift_tip, yaw_g, dur["lift"], rest_g), "lift")
        held_after_lift = bool(np.linalg.norm(w.pose(ball_id)[:3] - w.tip()) < 0.03)

        cxy = np.array(cont_seen[:2])
        z_rel = h_c + ball["radius"] + s["release_clear"]
        rel_xy = _release_xy(outcome, shape, cont_seen, stand_seen, s, ball["radius"], arm.reach)
        yaw_c = math.atan2(rel_xy[1], rel_xy[0]) + s["yaw_grasp_dev"]
        carry_tip = np.array([rel_xy[0], rel_xy[1], z_carry])
        rest_c = planner.rest_for(rel_xy, yaw_c)
        q_carry = planner.tip_pose_ik(carry_tip, yaw_c, robot.q_ref, rest_c)
        carry = JointMove(robot.q_ref, q_carry, dur["carry"])
        during: list[tuple[float, Callable[[], object]]] = []
        early_frac = s["early_frac"]
        if outcome == "released_early":
            # open where the hand is still far from the container (checked on the planned path)
            for f in np.linspace(early_frac, 0.15, 8):
                tip = planner.tip(carry.at(f * carry.duration)[0])
                if np.linalg.norm(tip[:2] - cxy) > _container_radius(shape) + 0.15:
                    early_frac = float(f)
                    break
            def release_early() -> None:
                say("release (early)")
                robot.release("ball", wait=False)

            during.append((early_frac, release_early))
        elif outcome == "slipped":
            # the reality's fault, not the robot's command: the grasp stays commanded
            during.append((faults["slip_fraction"], lambda: robot.weaken_grip(
                faults["slip_residual_force_n"], faults["slip_ramp_s"], faults["slip_give"])))
        say("carry")
        robot.follow(carry, "above_container" if outcome != "missed" else "beside_container", during=during)
        held_after_carry = bool(np.linalg.norm(w.pose(ball_id)[:3] - w.tip()) < 0.03)
        if outcome == "slipped" and held_after_carry:  # (no recording that says slipped of a ball carried on)
            raise SynthError(f"slipped: the ball is still in the {arm.name}'s hand after the carry (seed {seed}): "
                             "the gripper's fault did not let it go")
        if outcome != "released_early":
            rel_tip = np.array([rel_xy[0], rel_xy[1], z_rel])
            robot.follow(linear_move(planner, robot.q_ref, carry_tip, rel_tip, yaw_c, dur["lower"], rest_c),
                         "release_pose")
            say("release")
            robot.release("ball")
            top_tip = rel_tip
        else:
            top_tip = carry_tip
        say("retreat")
        up = top_tip + [0, 0, 0.10]
        robot.follow(linear_move(planner, robot.q_ref, top_tip, up, yaw_c, dur["retreat"], rest_c), "retreat")
        robot.move_to(arm.home, dur["home"], "home")
        # keep logging until the ball is at rest (at most 2 s), then measure without logging
        _settle(w, robot, ball_id, max_s=2.0 * max(1.0, time_scale))
        robot.recording = False
        _settle(w, robot, ball_id, max_s=4.0, still_s=0.5)
        final = w.pose(ball_id)
        inside = inside_container(shape, cont_pose, final[:3])
        gt = {"in_container": "true" if inside else "false",
              "ball_final_position": json.dumps(_r(final[:3].tolist(), 4)),
              "ball_speed_at_measurement": json.dumps(round(w.speed(ball_id), 4)),
              "ball_held_after_lift": "true" if held_after_lift else "false",
              "ball_held_after_carry": "true" if held_after_carry else "false"}
        scene = {"entities": {
            "ball": {"pose": _r(ball_seen), "shape": {"type": "sphere", "radius": 0.033}, "mass": 0.057},
            "stand": {"pose": _r(stand_seen), "shape": {"type": "cylinder", "radius": _r(stand["radius"], 4),
                                                       "length": _r(stand["length"], 4)}},
            "container": {"pose": _r(cont_seen), "shape": dict(shape)},
        }}
        gen = {"generator": GENERATOR, "scenario": "ball_drop", "seed": int(seed), "container": container,
               "outcome": outcome, "time_scale": float(time_scale), "sim_rate_hz": SIM_RATE,
               "telemetry_rate_hz": TELEMETRY_RATE, "solver_iterations": SOLVER_ITERATIONS,
               "contact": wd["contact"], "noise": noise, "ball": ball, "stand": stand,
               "container_props": wd["cprops"],
               "positions": {"ball": ball_pos.tolist(), "stand": stand_pose, "container": cont_pose},
               "perceived": scene["entities"], "durations": dur, "grip_force_n": s["grip_force"],
               "position_gain": s["kp"],
               "heights": {"pre_grasp": s["pre_grasp"], "grasp_dz": s["grasp_dz"], "carry_z": z_carry,
                           "release_z": z_rel},
               "release_xy": rel_xy.tolist(), "start_q": s["start_q"].tolist()}
        if arm.name != "panda":  # the Panda, the default, is named by no key
            gen["robot"] = arm.name
        _outcome_generation(gen, outcome, s, faults, early_frac, arm)
        _reality_generation(gen, w)
        gen["command"] = _command(gen)
        return _finish(out, telem, gt, scene, gen, w, wall0,
                       {"ball_final": final[:3].tolist(), "inside": inside, "held_after_lift": held_after_lift,
                        "held_after_carry": held_after_carry})
    finally:
        planner.close()
        world.close()


def _outcome_generation(gen: dict, outcome: str, s: dict, faults: dict, early_frac: float, arm: SynthArm) -> None:
    """The parameters of the chosen outcome, for the generation metadata."""
    if outcome == "released_early":
        gen["early_fraction"] = early_frac
    if outcome == "missed":
        gen["miss_gap"] = s["miss_gap"]
    if outcome == "empty_grasp":
        mode = s["empty_mode"]
        gen["empty_grasp_mode"] = mode
        gen["empty_grasp_offset" if mode == "mislocated" else "empty_grasp_height"] = (
            s["empty_offset"] if mode == "mislocated" else s["empty_high"])
    if outcome == "slipped":
        gen["slip"] = {k: faults[k] for k in ("slip_fraction", "slip_ramp_s", "slip_residual_force_n")}
        if not arm.prismatic_fingers:  # (a linkage's drive gives way: Robot.weaken_grip)
            gen["slip"]["slip_give"] = faults["slip_give"]
    if outcome == "knocked":
        gen["knock_offset"] = faults["knock_offset"]
