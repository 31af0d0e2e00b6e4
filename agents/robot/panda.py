"""Shared facts about the Franka Panda as pybullet loads it (``franka_panda/panda.urdf``).

Small on purpose: the URDF's path, the telemetry joint names, the force limits the physics drives
the joints with, and a lookup of a loaded body's joints and links by name. Models that need the
Panda in a pybullet client of their own use it so that every process names things the same way.

Example::

    import pybullet as p
    from agents.robot.panda import PandaIndex, urdf_path

    cid = p.connect(p.DIRECT)
    robot = p.loadURDF(urdf_path(), useFixedBase=True, physicsClientId=cid)
    idx = PandaIndex(robot, cid)
    idx.joint["panda_finger_joint1"]   # -> 9
    idx.link["panda_hand"]              # -> 8 (pybullet link index; -1 is the base, panda_link0)
"""
from __future__ import annotations

import os
from pathlib import Path

ARM_JOINTS: tuple[str, ...] = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS: tuple[str, ...] = ("panda_finger_joint1", "panda_finger_joint2")
JOINTS: tuple[str, ...] = ARM_JOINTS + FINGER_JOINTS
"""The nine telemetry joint names, arm first (rad), then the two fingers (m, 0 = closed, 0.04 = open)."""

HAND_LINK = "panda_hand"
FINGER_LINKS: tuple[str, ...] = ("panda_leftfinger", "panda_rightfinger")
TIP_LINK = "panda_grasptarget"
"""A massless link of the URDF at the fingertip centre, 0.105 m along ``panda_hand``'s z axis."""
FINGERTIP_OFFSET = 0.105

ARM_FORCE_LIMITS: tuple[float, ...] = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
"""Torque limits (Nm) of joints 1..7, as in the URDF and Franka's datasheet."""
FINGER_FORCE = 70.0
"""Force (N) per finger: the Franka Hand's continuous grasping force. The URDF's finger ``effort``
limit says 20 N, which is lower than the real hand; the physics exposes it as a parameter."""
FINGER_OPEN = 0.04
READY: tuple[float, ...] = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, FINGER_OPEN, FINGER_OPEN)
"""Franka's 'ready' posture (arm joints 1..7, then both fingers open): hand down above the table."""

DEFAULT_URDF = "franka_panda/panda.urdf"


def urdf_path(name: str | None = None) -> str:
    """Absolute path of a robot URDF: ``name`` as given if it exists, else relative to
    ``pybullet_data`` (default ``franka_panda/panda.urdf``). Raises FileNotFoundError otherwise."""
    import pybullet_data

    name = name or DEFAULT_URDF
    if os.path.isabs(name) and os.path.exists(name):
        return name
    for base in (Path.cwd(), Path(pybullet_data.getDataPath())):
        cand = base / name
        if cand.exists():
            return str(cand)
    raise FileNotFoundError(f"robot URDF {name!r} not found (absolute, relative to the working directory "
                            f"or to pybullet_data)")


class PandaIndex:
    """Joint and link indices of a loaded robot body, by name.

    ``joint``: movable joints' names -> pybullet joint index; ``link``: every link's name -> link
    index (the base link is -1); ``lower`` / ``upper`` / ``max_force``: each movable joint's URDF limits.
    Works for any URDF; the Panda's names are the constants of this module.
    """

    def __init__(self, body: int, client: int):
        import pybullet as p

        self.body = body
        self.joint: dict[str, int] = {}
        self.link: dict[str, int] = {}
        self.lower: dict[str, float] = {}
        self.upper: dict[str, float] = {}
        self.max_force: dict[str, float] = {}
        base = p.getBodyInfo(body, physicsClientId=client)[0].decode()
        self.link[base] = -1
        for j in range(p.getNumJoints(body, physicsClientId=client)):
            info = p.getJointInfo(body, j, physicsClientId=client)
            name = info[1].decode()
            self.link[info[12].decode()] = j
            if info[2] != p.JOINT_FIXED:
                self.joint[name] = j
                self.lower[name], self.upper[name] = float(info[8]), float(info[9])
                self.max_force[name] = float(info[10])

    @property
    def num_links(self) -> int:
        """Links including the base (pybullet link indices -1 .. num_links - 2)."""
        return len(self.link)
