"""Forward kinematics of the scene's robot, and the small pose algebra the models share.

:class:`RobotKinematics` keeps a private pybullet ``DIRECT`` client holding only the robot (the
URDF of the scene's robot block, :class:`protocol.robot.Robot`, fixed base). Setting joint positions and
reading a link's frame costs about 50 µs; no simulation step is ever taken, so the client is a
pure kinematic calculator and never disturbs a physics world living in the same process.
:class:`GripperGeometry` tabulates, once, how far each finger of the robot's parallel gripper stands
from its closed position for every gripper joint position, from the same URDF: the models read finger
openings (m) and squeezing forces (N) from it whatever the gripper's joints are (two prismatic fingers,
or one revolute drive moving a linkage).

Poses are ``[x, y, z, qx, qy, qz, qw]`` (metres, quaternion xyzw), as everywhere in the twin.

Example::

    robot = resolve_robot({"use": "panda"})
    fk = RobotKinematics(robot)
    T_wh = fk.link_pose(dict(zip(robot.joints, robot.ready)), robot.gripper.hand)   # world <- hand
    fk.close()
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol.geometry import quat_from_axis_angle
from protocol.robot import Robot

Vec = Sequence[float] | npt.NDArray[np.float64]
"""A vector, quaternion or pose: a sequence of numbers or a float array."""

IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


# ------------------------------------------------------------------ pose algebra
def quat_normalize(q: Vec) -> np.ndarray:
    """``q`` scaled to unit length (the identity for a zero quaternion)."""
    a = np.asarray(q, float)
    n = float(np.linalg.norm(a))
    return a / n if n > 0 else np.array([0.0, 0.0, 0.0, 1.0])


def quat_mul(a: Vec, b: Vec) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of xyzw quaternions (apply ``b`` first, then ``a``)."""
    x1, y1, z1, w1 = a
    x2, y2, z2, w2 = b
    return np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                     w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])


def quat_conj(q: Vec) -> np.ndarray:
    """The conjugate (the inverse rotation of a unit quaternion)."""
    return np.array([-q[0], -q[1], -q[2], q[3]], float)


def quat_matrix(q: Vec) -> np.ndarray:
    """Rotation matrix of a unit xyzw quaternion."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quat_angle(a: Vec, b: Vec) -> float:
    """Angle (rad) of the rotation taking orientation ``a`` to orientation ``b``."""
    d = abs(float(np.dot(quat_normalize(a), quat_normalize(b))))
    return 2.0 * math.acos(min(1.0, d))


def quat_slerp(a: Vec, b: Vec, s: float) -> np.ndarray:
    """Spherical interpolation from ``a`` (s = 0) to ``b`` (s = 1) along the short arc."""
    qa, qb = quat_normalize(a), quat_normalize(b)
    d = float(np.dot(qa, qb))
    if d < 0:
        qb, d = -qb, -d
    if d > 0.9995:
        return quat_normalize(qa + s * (qb - qa))
    th = math.acos(d)
    out: np.ndarray = (math.sin((1 - s) * th) * qa + math.sin(s * th) * qb) / math.sin(th)
    return out


def rotation_vector(q: Vec) -> np.ndarray:
    """Axis × angle of a unit quaternion (the log map), short arc."""
    u = quat_normalize(q)
    if u[3] < 0:
        u = -u
    s = float(np.linalg.norm(u[:3]))
    if s < 1e-12:
        out: np.ndarray = 2.0 * u[:3]
        return out
    out = u[:3] / s * (2.0 * math.atan2(s, u[3]))
    return out


def advanced(pose: Vec, velocity: Vec, dt: float) -> np.ndarray:
    """``pose`` moved on for ``dt`` seconds at the twist ``velocity`` ([vx, vy, vz, wx, wy, wz], world frame)."""
    p, v = np.asarray(pose, float), np.asarray(velocity, float)
    out = p[:7].copy()
    out[:3] += v[:3] * dt
    angle = float(np.linalg.norm(v[3:6])) * dt
    if angle > 1e-12:
        out[3:] = quat_normalize(quat_mul(quat_from_axis_angle(v[3:6], angle), p[3:7]))
    return out


def compose(a: Vec, b: Vec) -> np.ndarray:
    """``a ∘ b``: the pose ``b`` (expressed in frame ``a``) in the frame ``a`` is expressed in."""
    pa = np.asarray(a, float)
    pb = np.asarray(b, float)
    out = np.empty(7)
    out[:3] = pa[:3] + quat_matrix(pa[3:7]) @ pb[:3]
    out[3:] = quat_normalize(quat_mul(pa[3:7], pb[3:7]))
    return out


def invert(a: Vec) -> np.ndarray:
    """The inverse pose: ``compose(invert(a), a)`` is the identity."""
    pa = np.asarray(a, float)
    qi = quat_conj(pa[3:7])
    out = np.empty(7)
    out[:3] = -(quat_matrix(qi) @ pa[:3])
    out[3:] = qi
    return out


def base_link_frame(p: Any, body: int, client: int) -> np.ndarray:
    """World pose of a pybullet body's base link *frame* (its URDF origin): pybullet reports where the base's
    centre of mass is, which is the frame only when the URDF puts the inertial origin there."""
    pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=client)
    inertial = p.getDynamicsInfo(body, -1, physicsClientId=client)[3:5]
    return compose([*pos, *orn], invert([*inertial[0], *inertial[1]]))


def as_pose(v: Vec) -> np.ndarray:
    """A 3- or 7-vector as a 7-vector pose (identity orientation if none is given)."""
    nums = [float(x) for x in v]
    if len(nums) == 3:
        nums += [0.0, 0.0, 0.0, 1.0]
    if len(nums) != 7:
        raise ValueError(f"a pose is [x, y, z] or [x, y, z, qx, qy, qz, qw], got {len(nums)} numbers")
    out = np.asarray(nums)
    out[3:] = quat_normalize(out[3:])
    return out


# ------------------------------------------------------------------ kinematics
class RobotKinematics:
    """Forward kinematics of the scene's robot in a private pybullet ``DIRECT`` client.

    ``base`` overrides the robot's base pose in the world (default: the robot block's). Unknown joint
    names in the inputs are ignored; joints missing from the inputs keep their last value (zero at start).
    """

    def __init__(self, robot: Robot, base: Vec | None = None):
        import pybullet as p

        self._p = p
        self.robot_spec = robot
        self.client = p.connect(p.DIRECT)
        pose = as_pose(base if base is not None else robot.base)
        self.robot = p.loadURDF(robot.urdf_file, pose[:3].tolist(), pose[3:].tolist(), useFixedBase=True,
                                flags=p.URDF_IGNORE_VISUAL_SHAPES, physicsClientId=self.client)
        self.joints: dict[str, int] = {}
        self.links: dict[str, int] = {p.getBodyInfo(self.robot, physicsClientId=self.client)[0].decode(): -1}
        for j in range(p.getNumJoints(self.robot, physicsClientId=self.client)):
            info = p.getJointInfo(self.robot, j, physicsClientId=self.client)
            if info[2] != p.JOINT_FIXED:
                self.joints[info[1].decode()] = j
            self.links[info[12].decode()] = j
        self._q: dict[str, float] = {n: 0.0 for n in self.joints}

    def set_joints(self, positions: Mapping[str, float]) -> None:
        """Set the robot's joint positions (rad / m) by name, and the URDF's mimic joints that follow
        them; only changed joints are written."""
        p, c, r = self._p, self.client, self.robot
        for name, value in self.robot_spec.with_mimic(positions).items():
            j = self.joints.get(name)
            if j is None:
                continue
            value = float(value)
            if self._q[name] != value:
                p.resetJointState(r, j, value, physicsClientId=c)
                self._q[name] = value

    def link_pose(self, positions: Mapping[str, float] | None = None, link: str | None = None) -> np.ndarray:
        """World pose of ``link``'s URDF frame (not its centre of mass; default the hand) at ``positions``."""
        if positions is not None:
            self.set_joints(positions)
        link = link or self.robot_spec.gripper.hand
        idx = self.links.get(link)
        if idx is None:
            raise KeyError(f"the robot has no link {link!r} (links: {', '.join(self.links)})")
        if idx < 0:
            return base_link_frame(self._p, self.robot, self.client)
        st = self._p.getLinkState(self.robot, idx, computeForwardKinematics=1, physicsClientId=self.client)
        out = np.array([*st[4], *st[5]], float)
        out[3:] = quat_normalize(out[3:])  # pybullet's quaternions are single-precision
        return out

    def hand_pose(self, names: Sequence[str], position: Vec) -> np.ndarray:
        """The hand link's pose from a telemetry joint state's ``name`` and ``position`` lists."""
        return self.link_pose(dict(zip(names, position, strict=False)), self.robot_spec.gripper.hand)

    @classmethod
    def lease(cls, robot: Robot) -> RobotKinematics:
        """The robot's kinematics at its own base, every joint at zero as loaded: one given back
        (:meth:`give_back`) by an earlier user in this process if there is one, else loaded now. A warm agent
        initialised again for every run of the same robot loads its URDF once (about 50 ms for the Panda)."""
        idle = _IDLE_KINEMATICS.get(_robot_key(robot))
        if not idle:
            return cls(robot)
        fk = idle.pop()
        for name, j in fk.joints.items():
            fk._p.resetJointState(fk.robot, j, 0.0, physicsClientId=fk.client)
            fk._q[name] = 0.0
        return fk

    def give_back(self) -> None:
        """Done with a leased instance (:meth:`lease`): the next lease of the same robot takes it."""
        if self.client is not None:
            _IDLE_KINEMATICS.setdefault(_robot_key(self.robot_spec), []).append(self)

    def close(self) -> None:
        if self.client is not None:
            try:
                self._p.disconnect(physicsClientId=self.client)
            except Exception:  # already gone (interpreter shutdown)
                pass
            self.client = None


_IDLE_KINEMATICS: dict[str, list[RobotKinematics]] = {}  # robot description -> instances given back, at its base
_GEOMETRIES: dict[str, GripperGeometry] = {}


def _robot_key(robot: Robot) -> str:
    return json.dumps(robot.as_dict(), sort_keys=True, default=str)


class GripperGeometry:
    """How far each finger of the robot's gripper stands from its closed position, by gripper joint position.

    Tabulated once (``samples`` positions from open to closed, every gripper joint moved alike and the
    URDF's mimic joints following) from the fingers' link frames in the hand frame, projected on the
    finger axis (the direction from the right finger to the left one, open). Finger ``i`` is moved by
    joint :meth:`protocol.robot.Gripper.driver` ``(i)``; its *opening* is 0 closed and grows as it opens
    (the Panda's: the finger joint's own position in metres). A joint effort ``tau`` on a driver becomes
    a finger force by virtual work, ``F = tau / sum_k d opening_k / d q`` over the fingers it drives: so a
    squeeze is a negative force whichever way the joint turns to close.
    """

    def __init__(self, robot: Robot, samples: int = 81):
        g = robot.gripper
        self.gripper = g
        fk = RobotKinematics(robot, base=IDENTITY)
        try:
            cs = np.linspace(0.0, 1.0, samples)
            ys = []
            for c in cs:
                q = {j: o + c * (cl - o) for j, o, cl in zip(g.joints, g.open, g.closed, strict=True)}
                T_hw = invert(fk.link_pose(q, g.hand))
                ys.append([compose(T_hw, fk.link_pose(None, f))[:3] for f in g.fingers])
        finally:
            fk.close()
        y = np.asarray(ys)  # samples x 2 fingers x 3
        axis = y[0, 0] - y[0, 1]
        n = float(np.linalg.norm(axis))
        if n < 1e-6:
            raise ValueError(f"the gripper's fingers {g.fingers[0]} and {g.fingers[1]} are at the same place when open")
        self.axis = axis / n
        """The finger axis in the hand frame (unit; from the right finger to the left one)."""
        self.closed_gap = float(abs(np.dot(y[-1, 0] - y[-1, 1], self.axis)))
        """Distance (m) between the two finger link frames along the axis when fully closed."""
        self._q: list[np.ndarray] = []
        self._o: list[np.ndarray] = []
        for i in range(2):
            d = g.joints.index(g.driver(i))
            qs = g.open[d] + cs * (g.closed[d] - g.open[d])
            o = np.abs((y[:, i] - y[-1, i]) @ self.axis)
            order = np.argsort(qs)
            self._q.append(qs[order])
            self._o.append(o[order])
        self.open_opening = (float(self._o[0].max()), float(self._o[1].max()))
        """Each finger's opening (m) fully open."""

    @classmethod
    def of(cls, robot: Robot) -> GripperGeometry:
        """The geometry of ``robot``'s gripper, tabulated once per process and description (a warm agent is
        initialised again for every run of the same robot; the table is read-only)."""
        key = _robot_key(robot)
        geo = _GEOMETRIES.get(key)
        if geo is None:
            geo = _GEOMETRIES[key] = cls(robot)
        return geo

    def openings(self, q: Mapping[str, float]) -> tuple[float, float]:
        """Both fingers' openings (m) at gripper joint positions ``q`` (by name; KeyError if a driver is missing)."""
        g = self.gripper
        return (float(np.interp(float(q[g.driver(0)]), self._q[0], self._o[0])),
                float(np.interp(float(q[g.driver(1)]), self._q[1], self._o[1])))

    def slope(self, i: int, qi: float) -> float:
        """d opening_i / d q of finger ``i``'s driver at ``qi`` (m per joint unit)."""
        qs, os_ = self._q[i], self._o[i]
        k = int(np.clip(np.searchsorted(qs, qi), 1, len(qs) - 1))
        return float((os_[k] - os_[k - 1]) / (qs[k] - qs[k - 1]))

    def rates(self, q: Mapping[str, float], qd: Mapping[str, float]) -> tuple[float, float]:
        """Both fingers' opening speeds (m/s) from the drivers' joint velocities."""
        g = self.gripper
        return (self.slope(0, float(q[g.driver(0)])) * float(qd[g.driver(0)]),
                self.slope(1, float(q[g.driver(1)])) * float(qd[g.driver(1)]))

    def forces(self, q: Mapping[str, float], effort: Mapping[str, float]) -> tuple[float, float]:
        """Both fingers' forces (N; negative squeezes) from the drivers' joint efforts."""
        g = self.gripper
        out = []
        for i in range(2):
            d = g.driver(i)
            share = sum(self.slope(k, float(q[d])) for k in range(2) if g.driver(k) == d)
            out.append(float(effort[d]) / share if abs(share) > 1e-9 else 0.0)
        return out[0], out[1]
