"""The robot the reality plays: a shipped robot description plus what the scripts need to move it.

Everything robot-specific of the generator is here, read from the robot's description
(:mod:`protocol.robot`: URDF, arm and gripper joints, hand link, force limits) and its URDF (the tip point in
the hand frame, the gripper's finger geometry), plus two script facts per robot that are not in a
description: the HOME posture the scripts start from and return to (hand down above the table) and the
wrist joint that turns the hand about its approach axis (for IK rest postures).

    arm = synth_arm("xarm6")
    arm.names           # telemetry joint names: the arm's, then the gripper's
    arm.grip(0.0)       # gripper joint positions fully closed (1.0: fully open)
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from agents.robot.kinematics import GripperGeometry, RobotKinematics, compose, invert
from protocol.errors import SynthError
from protocol.robot import Robot, read_urdf, resolve_robot

ROBOTS = ("panda", "xarm6")

# HOME: hand down above the table, in front of the robot; wrist: (index in the arm's joints, the joint's
# value when the hand's yaw is 0 with joint 1 at 0, +1 / -1: the wrist turns the hand's yaw up / down);
# reach: the farthest (m, horizontally) the fingertips go with the hand down at carrying height (the xArm's
# measured with the planner's IK: 0.625 m with the tip 0.25 m up, 0.575 m at 0.35 m)
_SCRIPT: dict[str, dict[str, Any]] = {
    "panda": {"home": [0.0, -0.55, 0.0, -2.35, 0.0, 1.80, 0.785], "wrist": (6, 0.785, 1.0), "reach": 0.78},
    "xarm6": {"home": [0.0, -0.35, -0.95, 0.0, 1.30, 0.0], "wrist": (5, 0.0, -1.0), "reach": 0.58},
}


@dataclass(frozen=True)
class SynthArm:
    """A robot as the generator drives it (see the module docstring)."""

    robot: Robot
    home: np.ndarray
    wrist: tuple[int, float, float]
    tip: float  # the fingertip centre's distance along the hand's z axis (m)
    geometry: GripperGeometry
    reach: float  # m: see _SCRIPT

    @property
    def name(self) -> str:
        return self.robot.name

    @property
    def n(self) -> int:
        """Number of arm joints."""
        return len(self.robot.arm)

    @property
    def names(self) -> tuple[str, ...]:
        return self.robot.joints

    @property
    def torque_limits(self) -> np.ndarray:
        return np.asarray(self.robot.arm_force, float)

    def grip(self, opening: float) -> list[float]:
        """Gripper joint positions at ``opening`` (0 closed, 1 fully open), linear in each joint."""
        g = self.robot.gripper
        return [c + opening * (o - c) for o, c in zip(g.open, g.closed, strict=True)]

    @property
    def prismatic_fingers(self) -> bool:
        """Each finger on a prismatic joint of its own (the Panda's): a joint's force is its finger's."""
        g = self.robot.gripper
        return len(g.joints) == 2 and read_urdf(self.robot.urdf_file).joints[g.joints[0]]["type"] == "prismatic"

    def grip_effort(self, force: float, q: list[float]) -> float:
        """The joint effort limit that lets each finger press with ``force`` newtons at joint positions ``q``."""
        g = self.robot.gripper
        if self.prismatic_fingers:
            return float(force)
        qs = dict(zip(g.joints, q, strict=True))
        share = sum(abs(self.geometry.slope(i, qs[g.driver(i)])) for i in range(2) if g.driver(i) == g.joints[0])
        return float(force) * max(share, 1e-6)


@cache
def synth_arm(name: str = "panda") -> SynthArm:
    """The generator's view of a shipped robot (SynthError for a robot it has no script facts for)."""
    if name not in _SCRIPT:
        raise SynthError(f"the recording generator has no script for robot {name!r} (robots: {', '.join(ROBOTS)})")
    robot = resolve_robot({"use": name})
    fk = RobotKinematics(robot, base=[0, 0, 0, 0, 0, 0, 1])
    try:
        g = robot.gripper
        hand = fk.link_pose(robot.ready_positions(), g.hand)
        tip = compose(invert(hand), compose(fk.link_pose(None, g.tip), [*g.tip_offset, 0, 0, 0, 1]))
    finally:
        fk.close()
    if abs(tip[0]) > 1e-4 or abs(tip[1]) > 1e-4:
        raise SynthError(f"{name}: the tip is not on the hand's z axis ({np.round(tip[:3], 4).tolist()})")
    s = _SCRIPT[name]
    # pybullet keeps link frames in single precision: the tip to a micrometre (the Panda's is 0.105 m exactly)
    k, zero, sign = s["wrist"]
    return SynthArm(robot, np.asarray(s["home"], float), (int(k), float(zero), float(sign)),
                    round(float(tip[2]), 6), GripperGeometry(robot), float(s["reach"]))
