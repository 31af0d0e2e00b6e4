"""The scene's robot in a pybullet world, following the telemetry's joint positions.

:class:`BulletRobot` loads the robot's URDF (:class:`protocol.robot.Robot`: fixed base at the robot's base pose)
into a pybullet client and drives every joint the telemetry names with ``POSITION_CONTROL``: arm joints at
the description's torque limits, gripper joints (and the URDF's mimic joints that follow them, as the
xArm's linkage does) at the gripper's force. The gains are pybullet's share of the position error
corrected per step, given at a 1/240 s step and scaled with the time step so that the tracking time
constant does not depend on it. The first joint state is written with ``resetJointState`` (the robot
starts where the recording starts, without a swing); until then the robot holds its ready posture.

    arm = BulletRobot(p, cid, robot, time_step=1 / 240, finger_force=0.0, gains=(0.1, 0.3, 1.0), initial=[])
    arm.drive(joint_state)          # each step, before stepping the world
"""
from __future__ import annotations

from typing import Any

from protocol.joints import joint_state_key
from protocol.robot import Robot

from ..robot.index import BodyIndex
from ..robot.kinematics import base_link_frame, compose


def couple_mimic(p: Any, client: int, body: int, index: BodyIndex, robot: Robot, max_force: float = 1000.0) -> None:
    """Make the URDF's mimic joints follow their leader rigidly (gear constraints), as the linkage they stand
    for does: a pybullet body is a tree, so without them an object pushing on a finger could bend the
    linkage and the drive's angle would no longer say where the fingers are. The followers' own motors are
    switched off: the gripper has one motor, its drive (six motors pushing would squeeze six times as hard).
    Only an offset of 0 (the xArm's) can be a gear."""
    for follower, (leader, mult, off) in robot.gripper.mimic.items():
        if off != 0.0:
            raise ValueError(f"mimic joint {follower}: an offset ({off}) cannot be a pybullet gear constraint")
        p.setJointMotorControl2(body, index.joint[follower], p.VELOCITY_CONTROL, force=0.0, physicsClientId=client)
        c = p.createConstraint(body, index.joint[leader], body, index.joint[follower], p.JOINT_GEAR, [1, 0, 0],
                               [0, 0, 0], [0, 0, 0], physicsClientId=client)
        p.changeConstraint(c, gearRatio=-float(mult), erp=0.2, maxForce=max_force, physicsClientId=client)


class BulletRobot:
    """One robot body of a pybullet world, driven from joint states (see the module docstring)."""

    def __init__(self, p: Any, client: int, robot: Robot, *, time_step: float, finger_force: float,
                 gains: tuple[float, float, float], initial: list[float]):
        self.p, self.cid, self.spec = p, client, robot
        g = robot.gripper
        self.body = p.loadURDF(robot.urdf_file, list(robot.base[:3]), list(robot.base[3:]), useFixedBase=True,
                               flags=p.URDF_USE_INERTIA_FROM_FILE | p.URDF_IGNORE_VISUAL_SHAPES, physicsClientId=client)
        self.index = BodyIndex(self.body, client)
        couple_mimic(p, client, self.body, self.index, robot)
        self.fingers = [self.index.link[n] for n in g.fingers]
        self.hand = self.index.link[g.hand]
        self.tip = self.index.link[g.tip]
        self.tip_offset = [*g.tip_offset, 0.0, 0.0, 0.0, 1.0]
        finger_gain, arm_gain, self.velocity_gain = gains
        gripper_joints = set(g.joints)
        limits = dict(zip(robot.arm, robot.arm_force, strict=True))
        limits.update({n: finger_force or g.force for n in gripper_joints})
        self.joint_force = {n: limits.get(n, self.index.max_force[n]) for n in self.index.joint}
        scale = time_step * 240.0
        self.joint_gain = {n: min(1.0, scale * (finger_gain if n in gripper_joints else arm_gain))
                           for n in self.index.joint}
        hold = dict(zip(robot.joints, robot.posture(initial), strict=True))
        for n, v in robot.with_mimic(hold).items():
            p.resetJointState(self.body, self.index.joint[n], v, physicsClientId=client)
        self.command(list(hold), list(hold.values()), None)
        self.telemetry_seen = False
        self._last_key: tuple[Any, ...] | None = None  # the joint state last driven by
        self._last_q: tuple[Any, list[float]] | None = None
        self._names_seen: list[str] | None = None
        self._map: tuple[list[int], list[str]] = ([], [])

    def command(self, names: list[str], positions: list[float], velocities: list[float] | None) -> None:
        """Position targets (and target velocities, else zero) for these joints."""
        idx = [self.index.joint[n] for n in names]
        self.p.setJointMotorControlArray(
            self.body, idx, self.p.POSITION_CONTROL, targetPositions=positions,
            targetVelocities=velocities if velocities is not None else [0.0] * len(idx),
            forces=[self.joint_force[n] for n in names], positionGains=[self.joint_gain[n] for n in names],
            velocityGains=[self.velocity_gain] * len(idx), physicsClientId=self.cid)

    def drive(self, js: dict[str, Any] | None) -> None:
        """Position targets from the latest joint state (only when a new one arrived)."""
        if js is None:
            return
        stamp, key = js.get("stamp"), joint_state_key(js)
        if key == self._last_key and self.telemetry_seen:
            return
        self._last_key = key
        names = js["name"]
        if names != self._names_seen:
            self._names_seen = list(names)
            # the URDF's mimic joints are not driven: they follow their leader through gear constraints
            sel = [i for i, n in enumerate(names) if n in self.index.joint and n not in self.spec.gripper.mimic]
            self._map = (sel, [names[i] for i in sel])
        sel, jn = self._map
        if not sel or (not self.telemetry_seen and not set(self.spec.arm) <= set(jn)):
            # (the first joint state that names the whole arm sets it: one naming the gripper alone, from a driver
            # that publishes them apart, left the arm at its ready posture, to swing from there under the servos)
            return
        pos = js["position"]
        q = [float(pos[i]) for i in sel]
        qd = self._velocities(js, sel, q, stamp)
        self._last_q = (stamp, q)
        if not self.telemetry_seen:
            for n, v in self.spec.with_mimic(dict(zip(jn, q, strict=True))).items():
                self.p.resetJointState(self.body, self.index.joint[n], v, physicsClientId=self.cid)
            self.telemetry_seen = True
        self.command(jn, q, qd)

    def _velocities(self, js: dict[str, Any], sel: list[int], q: list[float], stamp: Any) -> list[float] | None:
        """The joint state's velocities, else a finite difference of the last two joint states (None at first)."""
        vel = js.get("velocity")
        if vel is not None and len(vel) == len(js["name"]):
            return [float(vel[i]) for i in sel]
        last = self._last_q
        if last is not None and len(last[1]) == len(q) and stamp is not None and stamp > last[0]:
            h = stamp - last[0]
            return [(a - b) / h for a, b in zip(q, last[1], strict=True)]
        return None

    def link_pose(self, li: int) -> list[float]:
        """World pose of a link's URDF frame (-1: the base)."""
        if li < 0:
            return [float(v) for v in base_link_frame(self.p, self.body, self.cid)]
        s = self.p.getLinkState(self.body, li, computeForwardKinematics=1, physicsClientId=self.cid)
        return [*s[4], *s[5]]

    def tip_point(self) -> list[float]:
        """The point between the fingertips (the gripper's tip link and offset), in the world."""
        return [float(v) for v in compose(self.link_pose(self.tip), self.tip_offset)[:3]]
