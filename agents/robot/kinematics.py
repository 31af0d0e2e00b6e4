"""Forward kinematics of the Franka Panda, and the small pose algebra the models share.

:class:`PandaKinematics` keeps a private pybullet ``DIRECT`` client holding only the robot
(``franka_panda/panda.urdf`` from ``pybullet_data``, fixed base). Setting joint positions and
reading a link's frame costs about 50 µs; no simulation step is ever taken, so the client is a
pure kinematic calculator and never disturbs a physics world living in the same process.

Poses are ``[x, y, z, qx, qy, qz, qw]`` (metres, quaternion xyzw), as everywhere in the twin.

Example::

    fk = PandaKinematics(base=[0, 0, 0, 0, 0, 0, 1])
    T_wh = fk.link_pose({"panda_joint1": 0.1, ...}, "panda_hand")   # world <- hand
    T_wo = compose(T_wh, [0, 0, 0.105, 0, 0, 0, 1])                 # a point between the fingertips
    fk.close()
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

Vec = Sequence[float] | npt.NDArray[np.float64]
"""A vector, quaternion or pose: a sequence of numbers or a float array."""

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
HAND_LINK = "panda_hand"
FINGERTIP_OFFSET = 0.105  # panda_grasptarget: fingertip centre along the hand's z axis (m)
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
class PandaKinematics:
    """Forward kinematics of one Panda in a private pybullet ``DIRECT`` client.

    ``base`` is the robot's base pose in the world (the scene's ``robot: {base: ...}``), ``urdf``
    a path relative to ``pybullet_data`` or absolute. Unknown joint names in the inputs are ignored;
    joints missing from the inputs keep their last value (zero at start).
    """

    def __init__(self, base: Vec | None = None, urdf: str = "franka_panda/panda.urdf"):
        import pybullet as p
        import pybullet_data

        self._p = p
        self.client = p.connect(p.DIRECT)
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=self.client)
        pose = as_pose(base if base is not None else IDENTITY)
        self.robot = p.loadURDF(urdf, pose[:3].tolist(), pose[3:].tolist(), useFixedBase=True,
                                physicsClientId=self.client)
        self.joints: dict[str, int] = {}
        self.links: dict[str, int] = {}
        for j in range(p.getNumJoints(self.robot, physicsClientId=self.client)):
            info = p.getJointInfo(self.robot, j, physicsClientId=self.client)
            if info[2] != p.JOINT_FIXED:
                self.joints[info[1].decode()] = j
            self.links[info[12].decode()] = j
        self._q: dict[str, float] = {n: 0.0 for n in self.joints}

    def set_joints(self, positions: Mapping[str, float]) -> None:
        """Set the robot's joint positions (rad / m) by name; only changed joints are written."""
        p, c, r = self._p, self.client, self.robot
        for name, value in positions.items():
            j = self.joints.get(name)
            if j is None:
                continue
            value = float(value)
            if self._q[name] != value:
                p.resetJointState(r, j, value, physicsClientId=c)
                self._q[name] = value

    def link_pose(self, positions: Mapping[str, float] | None = None, link: str = HAND_LINK) -> np.ndarray:
        """World pose of ``link``'s URDF frame (not its centre of mass) at ``positions``."""
        if positions is not None:
            self.set_joints(positions)
        idx = self.links.get(link)
        if idx is None:
            raise KeyError(f"the Panda has no link {link!r} (links: {', '.join(self.links)})")
        st = self._p.getLinkState(self.robot, idx, computeForwardKinematics=1, physicsClientId=self.client)
        out = np.array([*st[4], *st[5]], float)
        out[3:] = quat_normalize(out[3:])  # pybullet's quaternions are single-precision
        return out

    def hand_pose(self, names: Sequence[str], position: Vec) -> np.ndarray:
        """``panda_hand`` pose from a telemetry joint state's ``name`` and ``position`` lists."""
        return self.link_pose(dict(zip(names, position, strict=False)), HAND_LINK)

    def close(self) -> None:
        if self.client is not None:
            try:
                self._p.disconnect(physicsClientId=self.client)
            except Exception:  # already gone (interpreter shutdown)
                pass
            self.client = None
