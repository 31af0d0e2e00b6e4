"""The reality: a world of its own at 1 kHz that plays the real robot, and the telemetry it records.

:class:`World` is what the scripts ask of a reality (bodies, the Panda's joint commands and
sensors, stepping); :class:`Reality` is the pybullet one. The MuJoCo one is
:class:`recordings.synth.mujoco_reality.MujocoReality`.
"""
from __future__ import annotations

import json
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents.engines.pybullet_robot import couple_mimic
from agents.robot.index import BodyIndex
from protocol.errors import SynthError

from ..rosbag import RecordingWriter
from .arm import SynthArm, synth_arm
from .common import (
    REALITIES,
    SIM_RATE,
    SOLVER_ITERATIONS,
    TELEMETRY_RATE,
    SynthResult,
    _metadata_generation,
    _r,
    _rot,
)


class _Client:
    """A pybullet client of its own: every call gets this client's ``physicsClientId``.

    (pybullet_utils' BulletClient passes ``options=''`` to ``connect``, which prints ``argv[0]=``.)
    """

    def __init__(self, p):
        self._p = p
        self._id = p.connect(p.DIRECT)

    def __getattr__(self, name: str):
        fn = getattr(self._p, name)
        if callable(fn):
            cid = self._id
            return lambda *a, **k: fn(*a, physicsClientId=cid, **k)
        return fn

    def disconnect(self) -> None:
        if self._id >= 0:
            self._p.disconnect(physicsClientId=self._id)
            self._id = -1


def _bullet(p) -> _Client:
    return _Client(p)


# -------------------------------------------------------------------------------------- telemetry
class Telemetry:
    """Samples the reality's joints at 250 Hz with Gaussian noise and timing jitter; collects actions."""

    def __init__(self, rng: np.random.Generator, noise: dict[str, float], rate: float = TELEMETRY_RATE,
                 arm: SynthArm | None = None):
        self.arm = arm or synth_arm()
        self.rng = rng
        self.noise = noise
        self.period = 1.0 / rate
        self.k = 0
        self.next_t = self._acq(0)
        self.last_stamp = -1.0
        self.t0 = 0.0  # reality time at which the log starts
        self.joint_states: list[tuple[float, list, list, list]] = []
        self.actions: list[tuple[float, str, str, dict]] = []

    def _acq(self, k: int) -> float:
        j = float(np.clip(self.rng.normal(0.0, self.noise["jitter_s"]), -2.5 * self.noise["jitter_s"],
                          2.5 * self.noise["jitter_s"]))
        return max(0.0, k * self.period + j)

    def due(self, t: float, dt: float) -> bool:
        return t - self.t0 + dt / 2 >= self.next_t

    def sample(self, q, qd, tau) -> None:
        n = self.noise
        k, g = self.arm.n, len(self.arm.robot.gripper.joints)
        pos = np.asarray(q, float) + np.concatenate([self.rng.normal(0, n["position_rad"], k),
                                                     self.rng.normal(0, n["finger_position_m"], g)])
        eff = np.asarray(tau, float) + np.concatenate([self.rng.normal(0, n["effort_nm"], k),
                                                       self.rng.normal(0, n["finger_effort_n"], g)])
        stamp = max(self.next_t, self.last_stamp + 1e-4)
        self.last_stamp = stamp
        self.joint_states.append((stamp, pos.tolist(), np.asarray(qd, float).tolist(), eff.tolist()))
        self.k += 1
        self.next_t = self._acq(self.k)

    def action(self, t: float, operation: str, phase: str, params: dict) -> None:
        self.actions.append((t - self.t0, operation, phase, _r(params)))

    def write(self, path: Path, metadata: dict[str, dict]) -> None:
        items: list[tuple[float, int, tuple]] = [(s, 0, ("js", s, p, v, e)) for s, p, v, e in self.joint_states]
        items += [(t, 1, ("act", t, op, ph, pr)) for t, op, ph, pr in self.actions]
        items.sort(key=lambda x: (x[0], x[1]))
        with RecordingWriter(path) as w:
            for _, _, it in items:
                if it[0] == "js":
                    w.joint_state(it[1], list(self.arm.names), it[2], it[3], it[4])
                else:
                    w.action(it[1], it[2], it[3], **it[4])
            for name, data in metadata.items():
                w.metadata(name, data)

    @property
    def duration(self) -> float:
        return self.joint_states[-1][0] if self.joint_states else 0.0


# ---------------------------------------------------------------------------------------- reality
@dataclass(frozen=True)
class Material:
    """How a body's surface touches others, in engine-neutral terms.

    ``friction``: sliding (Coulomb) coefficient; ``rolling``/``spinning``: rolling and torsional
    friction (lengths, m: resisting torque per newton of normal force); ``restitution``: the share
    of the normal speed a bounce keeps; ``damping``: linear and angular velocity damping of a free
    body (air drag). None leaves the engine's default. Each reality maps these to its own contact
    model (pybullet multiplies two bodies' friction and restitution, MuJoCo takes the larger
    friction and mixes the contacts' spring-dampers).
    """

    friction: float
    rolling: float | None = None
    spinning: float | None = None
    restitution: float | None = None
    damping: float | None = None


class World(ABC):
    """What a scripted task needs from a reality: a table at z = 0, the robot (``arm``) fixed at the origin,
    bodies, the robot's joint-level commands and sensors, stepping at 1 kHz.

    Bodies are opaque handles returned by the builders. Poses are [x, y, z, qx, qy, qz, qw].
    Joint vectors hold the arm joints, then the gripper joints (``arm.names``). Commands hold
    until replaced; :meth:`step` advances the world by ``dt`` with the commands in force.
    """

    name: str = ""
    arm: SynthArm
    dt: float = 1.0 / SIM_RATE
    t: float = 0.0
    steps: int = 0

    # -- building
    @abstractmethod
    def static_boxes(self, parts: list[dict], pose, friction: float, restitution: float) -> list:
        """Static bodies made of boxes ``{size, pos, quat}`` given in the frame ``pose``."""

    @abstractmethod
    def cylinder(self, radius: float, length: float, pos, mass: float = 0.0, quat=(0, 0, 0, 1),
                 material: Material | None = None):
        """A cylinder along its z axis (static when ``mass`` is 0)."""

    @abstractmethod
    def sphere(self, radius: float, pos, mass: float, material: Material | None = None):
        """A free sphere."""

    # -- the robot
    @abstractmethod
    def reset_arm(self, q, fingers) -> None:
        """Put the arm joints at ``q`` and the fingers at ``fingers``, at rest."""

    @abstractmethod
    def set_finger_friction(self, friction: float) -> None:
        """The finger pads' sliding friction coefficient from now on."""

    @abstractmethod
    def command_arm_position(self, q, qd, gain: float, limits) -> None:
        """Joint position servo of the arm towards ``q`` with velocity ``qd``, torques within ``limits``.

        ``gain`` is the robot's position gain as pybullet's motors take it (the share of the error
        removed per step); an engine whose servo gains are set when it is built may ignore it.
        """

    @abstractmethod
    def arm_torque_mode(self) -> None:
        """Switch the arm's joint servos off: from now on :meth:`command_arm_torque` drives it."""

    @abstractmethod
    def command_arm_torque(self, tau) -> None:
        """Joint torques of the arm (its controller's complete output, gravity included)."""

    @abstractmethod
    def command_fingers(self, target: list[float], force: float) -> None:
        """The gripper joints towards ``target``, each finger pressing with at most ``force`` (N)."""

    @abstractmethod
    def joints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and efforts of the arm's and the gripper's joints.

        Efforts are what a robot's joint torque sensors report: the torque (N m) or force (N) its
        actuators apply, the support of the arm's own weight included; squeezing fingers are negative.
        """

    @abstractmethod
    def hand(self) -> tuple[np.ndarray, np.ndarray]:
        """Position and orientation of the robot's hand link."""

    def tip(self) -> np.ndarray:
        """The fingertip centre (``arm.tip`` along the hand's z axis)."""
        pos, quat = self.hand()
        return pos + _rot(quat)[:, 2] * self.arm.tip

    @abstractmethod
    def tip_dynamics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a Cartesian impedance controller needs, at the current state.

        Returns the fingertip centre, the hand's orientation, the 6 x n Jacobian of the fingertip
        point (linear over angular, world frame) and the bias torques of the arm (gravity,
        Coriolis and centrifugal: the torques that hold the arm at its current velocity).
        """

    # -- bodies and time
    @abstractmethod
    def pose(self, body) -> np.ndarray:
        """[x, y, z, qx, qy, qz, qw] of a body."""

    @abstractmethod
    def speed(self, body) -> float:
        """Linear speed of a body (m/s)."""

    @abstractmethod
    def step(self) -> None:
        """Advance by ``dt``."""

    def describe(self) -> dict:
        """The engine's own settings, for the recording's metadata (empty: nothing beyond the defaults)."""
        return {}

    @abstractmethod
    def close(self) -> None:
        """Free the engine's resources."""


class Reality(World):
    """The pybullet reality: DIRECT at 1 kHz, table plane at z = 0, the robot fixed at the origin."""

    name = "pybullet"

    def __init__(self, contact: dict[str, float], arm: SynthArm | None = None):
        import pybullet as p

        self.arm = arm = arm or synth_arm()
        self.p = p
        self.pb = _bullet(p)
        self.dt = 1.0 / SIM_RATE
        self.t = 0.0
        self.steps = 0
        pb = self.pb
        pb.setGravity(0, 0, -9.81)
        pb.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSolverIterations=SOLVER_ITERATIONS, numSubSteps=0,
                                     enableConeFriction=1, deterministicOverlappingPairs=1,
                                     restitutionVelocityThreshold=0.05, contactBreakingThreshold=0.005,
                                     solverResidualThreshold=1e-9)
        self.table = pb.createMultiBody(0, pb.createCollisionShape(p.GEOM_PLANE))
        pb.changeDynamics(self.table, -1, lateralFriction=contact["table_friction"],
                          restitution=contact["table_restitution"], rollingFriction=1e-4, spinningFriction=1e-4)
        self.robot = pb.loadURDF(arm.robot.urdf_file, useFixedBase=True)
        idx = BodyIndex(self.robot, pb._id)
        g = arm.robot.gripper
        self.ARM = [idx.joint[n] for n in arm.robot.arm]
        self.FINGERS = [idx.joint[n] for n in g.joints]  # the telemetry's gripper joints
        # the joints the gripper's motor drives (the URDF's mimic joints follow them through gear constraints);
        # reset_arm also puts the followers (target = multiplier q + offset)
        self.grip_drive = [(idx.joint[n], g.joints.index(n), 1.0, 0.0) for n in g.joints]
        self.grip_follow = [(idx.joint[f], g.joints.index(lead), mult, off) for f, (lead, mult, off) in g.mimic.items()]
        self.PADS = [idx.link[n] for n in g.fingers]
        self.HAND = idx.link[g.hand]
        self.MOVABLE = list(idx.joint.values())
        for f in self.PADS:
            # the URDF's pads are already soft (stiffness 3e4, damping 1e3, friction anchor)
            pb.changeDynamics(self.robot, f, lateralFriction=contact["finger_friction"],
                              spinningFriction=contact["finger_spinning"], rollingFriction=1e-4,
                              contactStiffness=contact["finger_stiffness"], contactDamping=contact["finger_damping"],
                              frictionAnchor=True)
        for j in range(pb.getNumJoints(self.robot)):
            pb.changeDynamics(self.robot, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.02)
        if len(self.FINGERS) == 2:
            # two finger joints coupled by one motor (the Panda's rack): keep them symmetric with a gear constraint
            gear = pb.createConstraint(self.robot, self.FINGERS[0], self.robot, self.FINGERS[1], p.JOINT_GEAR,
                                       [1, 0, 0], [0, 0, 0], [0, 0, 0])
            pb.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=100)
        couple_mimic(p, pb._id, self.robot, idx, arm.robot)  # a linkage gripper (the xArm's) stays a linkage

    def reset_arm(self, q, fingers) -> None:
        for j, v in zip(self.ARM, q, strict=True):
            self.pb.resetJointState(self.robot, j, float(v))
        for j, k, mult, off in self.grip_drive + self.grip_follow:
            self.pb.resetJointState(self.robot, j, mult * float(fingers[k]) + off)

    def _material(self, body: int, m: Material | None) -> None:
        if m is None:
            return
        kw = {"lateralFriction": m.friction}
        for key, v in (("rollingFriction", m.rolling), ("spinningFriction", m.spinning),
                       ("restitution", m.restitution), ("linearDamping", m.damping), ("angularDamping", m.damping)):
            if v is not None:
                kw[key] = v
        self.pb.changeDynamics(body, -1, **kw)

    def static_boxes(self, parts: list[dict], pose, friction: float, restitution: float) -> list[int]:
        """Static compound bodies of boxes ``{size, pos, quat}`` given in the frame ``pose``.

        pybullet keeps at most 16 children per compound shape, so larger sets become several bodies.
        """
        p, pb = self.p, self.pb
        bodies = []
        for k in range(0, len(parts), 16):
            chunk = parts[k:k + 16]
            shape = pb.createCollisionShapeArray(
                shapeTypes=[p.GEOM_BOX] * len(chunk),
                halfExtents=[[s / 2 for s in part["size"]] for part in chunk],
                collisionFramePositions=[list(map(float, part["pos"])) for part in chunk],
                collisionFrameOrientations=[list(map(float, part["quat"])) for part in chunk])
            body = pb.createMultiBody(0, shape, basePosition=list(map(float, pose[:3])),
                                      baseOrientation=list(map(float, pose[3:7])))
            pb.changeDynamics(body, -1, lateralFriction=friction, restitution=restitution,
                              rollingFriction=1e-4, spinningFriction=1e-4)
            if len(pb.getCollisionShapeData(body, -1)) != len(chunk):
                raise SynthError(f"pybullet built {len(pb.getCollisionShapeData(body, -1))} of {len(chunk)} boxes")
            bodies.append(body)
        return bodies

    def cylinder(self, radius: float, length: float, pos, mass: float = 0.0, quat=(0, 0, 0, 1),
                 material: Material | None = None) -> int:
        pb = self.pb
        shape = pb.createCollisionShape(self.p.GEOM_CYLINDER, radius=radius, height=length)
        body = pb.createMultiBody(mass, shape, basePosition=list(map(float, pos)), baseOrientation=list(quat))
        self._material(body, material)
        return body

    def sphere(self, radius: float, pos, mass: float, material: Material | None = None) -> int:
        pb = self.pb
        body = pb.createMultiBody(mass, pb.createCollisionShape(self.p.GEOM_SPHERE, radius=radius),
                                  basePosition=list(map(float, pos)))
        self._material(body, material)
        return body

    def set_finger_friction(self, friction: float) -> None:
        for f in self.PADS:
            self.pb.changeDynamics(self.robot, f, lateralFriction=friction)

    def command_arm_position(self, q, qd, gain: float, limits) -> None:
        n = len(self.ARM)
        self.pb.setJointMotorControlArray(self.robot, self.ARM, self.p.POSITION_CONTROL, targetPositions=list(q),
                                          targetVelocities=list(qd), forces=list(limits),
                                          positionGains=[gain] * n, velocityGains=[1.0] * n)

    def arm_torque_mode(self) -> None:
        # pybullet's joints carry velocity motors until their force is set to zero
        self.pb.setJointMotorControlArray(self.robot, self.ARM, self.p.VELOCITY_CONTROL, forces=[0.0] * len(self.ARM))

    def command_arm_torque(self, tau) -> None:
        self.pb.setJointMotorControlArray(self.robot, self.ARM, self.p.TORQUE_CONTROL, forces=list(tau))

    def command_fingers(self, target: list[float], force: float) -> None:
        q = [] if self.arm.prismatic_fingers else [
            float(s[0]) for s in self.pb.getJointStates(self.robot, self.FINGERS)]
        effort = self.arm.grip_effort(force, q)
        joints = [j for j, _, _, _ in self.grip_drive]
        n = len(joints)
        self.pb.setJointMotorControlArray(self.robot, joints, self.p.POSITION_CONTROL,
                                          targetPositions=[m * float(target[k]) + o for _, k, m, o in self.grip_drive],
                                          forces=[effort] * n, positionGains=[0.05] * n,
                                          targetVelocities=[0.0] * n, velocityGains=[1.0] * n)

    def joints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        st = self.pb.getJointStates(self.robot, self.ARM + self.FINGERS)
        return (np.array([s[0] for s in st]), np.array([s[1] for s in st]), np.array([s[3] for s in st]))

    def hand(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.pb.getLinkState(self.robot, self.HAND, computeForwardKinematics=True)
        return np.array(s[4]), np.array(s[5])

    def tip_dynamics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        pb, n = self.pb, len(self.ARM)
        st_all = pb.getJointStates(self.robot, self.MOVABLE)  # pybullet's Jacobian takes every movable joint
        q, qd = [s[0] for s in st_all], [s[1] for s in st_all]
        st = pb.getLinkState(self.robot, self.HAND, computeLinkVelocity=True, computeForwardKinematics=True)
        com_pos, com_quat = np.array(st[0]), np.array(st[1])
        hand_pos, hand_quat = np.array(st[4]), np.array(st[5])
        tip = hand_pos + _rot(hand_quat)[:, 2] * self.arm.tip
        # pybullet's Jacobian takes the point in the link's centre-of-mass frame
        local = _rot(com_quat).T @ (tip - com_pos)
        zeros = [0.0] * len(q)
        jl, ja = pb.calculateJacobian(self.robot, self.HAND, list(local), q, qd, zeros)
        J = np.vstack([np.array(jl)[:, :n], np.array(ja)[:, :n]])
        bias = np.array(pb.calculateInverseDynamics(self.robot, q, qd, zeros))[:n]
        return tip, hand_quat, J, bias

    def pose(self, body: int) -> np.ndarray:
        pos, quat = self.pb.getBasePositionAndOrientation(body)
        return np.array(list(pos) + list(quat))

    def speed(self, body: int) -> float:
        lin, ang = self.pb.getBaseVelocity(body)
        return float(np.linalg.norm(lin))

    def step(self) -> None:
        self.pb.stepSimulation()
        self.steps += 1
        self.t = self.steps * self.dt

    def close(self) -> None:
        try:
            self.pb.disconnect()
        except Exception:
            pass


def _reality_generation(gen: dict, world: World) -> None:
    """Name the reality in the generation metadata (pybullet, the default, is named by no key)."""
    if world.name != REALITIES[0]:
        gen.pop("solver_iterations", None)  # pybullet's
        gen["reality"] = world.name
        gen["engine"] = world.describe()


def _finish(out, telem: Telemetry, gt: dict, scene: dict, gen: dict, world: World, wall0: float,
            measured: dict) -> SynthResult:
    out = Path(out)
    telem.write(out, {"twin.ground_truth": gt, "twin.scene": {"json": json.dumps(scene, sort_keys=True)},
                      "twin.generation": _metadata_generation(gen)})
    return SynthResult(path=out, ground_truth=gt, generation=gen, duration=telem.duration,
                       joint_states=len(telem.joint_states), actions=len(telem.actions), sim_steps=world.steps,
                       wall_s=time.perf_counter() - wall0, size_bytes=out.stat().st_size, measured=measured)
