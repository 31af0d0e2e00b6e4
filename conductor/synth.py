"""Synthetic robot recordings: a separate, higher-fidelity *reality* that plays the real robot.

``twin record synth`` runs a scripted Franka Panda task in a pybullet world of its own and records
what a real robot would log: ``/joint_states`` of the nine Panda joints at 250 Hz (with sensor noise
and timing jitter) and ``/action`` annotations (``move_arm``, ``move_hand``, ``release``, phases
``start``/``end``), as MCAP in rosbag2 layout (:class:`conductor.rosbag.RecordingWriter`). It then
measures what really happened and stores it as the recording's ground truth.

The reality is deliberately *not* the ensemble's physics model: it is its own pybullet DIRECT
world stepped at 1 kHz with more solver iterations, cone friction, rolling and spinning friction,
restitution, the URDF's soft finger pads, and randomized friction, masses and sizes. Nothing here
imports ``agents/``.

Two scenarios, each computed with pybullet IK on ``panda_hand`` (hand pointing down) by a separate
kinematic planner client, played as smooth (quintic) joint trajectories under position control with
the Panda's torque limits:

- ``ball_drop``: pick a tennis ball from a stand and drop it into a container (``bin``, ``box``,
  ``bowl``, ``cup``). Outcomes: ``success``; ``released_early`` (the hand opens on the way, well
  before the container); ``missed`` (it opens beside the container); ``empty_grasp`` (the fingers
  close on nothing -- the ball is not where the robot believes, or the hand stops too high -- and
  the robot carries on with its script). Ground truth ``in_container``: the ball's settled position
  inside the container's interior (:func:`protocol.geometry.inside_container`).
- ``insertion``: the DIP (plug) starts grasped; the SPU (socket: a static body with a chamfered
  square hole) stands on the table. The robot moves the DIP above where it *believes* the SPU is
  (true pose + ``localization_error`` in a random horizontal direction) and inserts it downwards
  under a Cartesian impedance controller (torque control with gravity compensation, so a
  misaligned DIP is stopped on the SPU's top or guided by the chamfer). Ground truth
  ``connected``: the DIP ends within 3 mm of the hole's axis and inserted to within 4 mm of the
  hole's bottom.

Every random choice (positions, friction, masses, noise levels, jitter, durations, heights) comes
from ``numpy.random.default_rng(seed)``; the same arguments give the same file. Metadata:
``twin.ground_truth``, ``twin.scene`` (what the robot perceived) and ``twin.generation`` (every
parameter). See ``docs/recordings.md``.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from protocol.geometry import (CONTAINER_DEFAULTS, container_params, container_parts, inside_container,
                               quat_from_axis_angle, quat_mul, quat_to_matrix)

from .rosbag import RecordingWriter

__all__ = ["JOINT_NAMES", "SCENARIOS", "CONTAINERS", "OUTCOMES", "SynthError", "SynthResult", "synthesize",
           "synth_ball_drop", "synth_insertion", "SPU_SIZE", "SPU_CONNECTION_OFFSET"]

JOINT_NAMES = tuple(f"panda_joint{i}" for i in range(1, 8)) + ("panda_finger_joint1", "panda_finger_joint2")
SCENARIOS = ("ball_drop", "insertion")
CONTAINERS = tuple(CONTAINER_DEFAULTS)
OUTCOMES = ("success", "released_early", "missed", "empty_grasp")
GENERATOR = "twin.synth/1"

SIM_RATE = 1000.0  # reality steps per second
TELEMETRY_RATE = 250.0  # joint states per second
SOLVER_ITERATIONS = 150
ARM = (0, 1, 2, 3, 4, 5, 6)  # pybullet joint indices of panda_joint1..7
FINGERS = (9, 10)
HAND = 8  # panda_hand link
TIP = 0.105  # fingertip centre along panda_hand's z axis
TORQUE_LIMITS = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
FINGER_OPEN = 0.04
HAND_DOWN = (1.0, 0.0, 0.0, 0.0)  # panda_hand z axis pointing at the table
HOME = np.array([0.0, -0.55, 0.0, -2.35, 0.0, 1.80, 0.785])

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

Progress = Callable[[str], None]


class SynthError(RuntimeError):
    """A script could not be planned or executed (unreachable pose, time limit)."""


@dataclass
class SynthResult:
    """What one generation produced: the file, the measured ground truth and some figures."""

    path: Path
    ground_truth: dict[str, str]
    generation: dict[str, Any]
    duration: float  # recorded seconds
    joint_states: int
    actions: int
    sim_steps: int
    wall_s: float
    size_bytes: int = 0
    measured: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------ math
def _yaw_quat(yaw: float) -> list[float]:
    return quat_from_axis_angle([0, 0, 1], yaw)


def hand_down(yaw: float) -> list[float]:
    """Orientation of panda_hand pointing down, turned by ``yaw`` about the world z axis."""
    return [float(v) for v in quat_mul(_yaw_quat(yaw), list(HAND_DOWN))]


def _rot(q) -> np.ndarray:
    return quat_to_matrix(q)


def _quintic(tau: float) -> tuple[float, float]:
    """Minimum-jerk time scaling s(tau) and ds/dtau on [0, 1]."""
    tau = min(max(tau, 0.0), 1.0)
    return (10 * tau**3 - 15 * tau**4 + 6 * tau**5, 30 * tau**2 - 60 * tau**3 + 30 * tau**4)


def _quat_error(q_target, q) -> np.ndarray:
    """Rotation vector taking orientation ``q`` to ``q_target`` (world frame)."""
    x1, y1, z1, w1 = q_target
    x2, y2, z2, w2 = -q[0], -q[1], -q[2], q[3]  # conjugate of q
    e = np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                  w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                  w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                  w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])
    if e[3] < 0:
        e = -e
    s = np.linalg.norm(e[:3])
    if s < 1e-12:
        return np.zeros(3)
    return e[:3] / s * 2 * math.atan2(s, e[3])


def _r(v, nd: int = 5):
    """Round floats (also inside lists/dicts) for compact, stable metadata."""
    if isinstance(v, dict):
        return {k: _r(x, nd) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_r(x, nd) for x in v]
    if isinstance(v, (float, np.floating)):
        return round(float(v), nd)
    if isinstance(v, np.integer):
        return int(v)
    return v


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


def _panda_path() -> str:
    import pybullet_data

    return str(Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf")


# ---------------------------------------------------------------------------------------- planner
class Planner:
    """The robot's motion planner: its own kinematic pybullet client with the Panda (never stepped).

    pybullet's IK starts from the body's current joint state, so the planner resets its private
    Panda to a seed before every query and refines the answer until the hand is within 0.2 mm.
    """

    def __init__(self):
        import pybullet as p

        self.pb = _bullet(p)
        self.robot = self.pb.loadURDF(_panda_path(), useFixedBase=True)
        lo, hi = [], []
        for j in list(ARM) + list(FINGERS):
            info = self.pb.getJointInfo(self.robot, j)
            lo.append(info[8])
            hi.append(info[9])
        self.lo, self.hi = np.array(lo), np.array(hi)

    def _set(self, q) -> None:
        for j, v in zip(ARM, q):
            self.pb.resetJointState(self.robot, j, float(v))

    def fk(self, q) -> tuple[np.ndarray, np.ndarray]:
        """panda_hand position and orientation for arm joints ``q``."""
        self._set(q)
        s = self.pb.getLinkState(self.robot, HAND, computeForwardKinematics=True)
        return np.array(s[4]), np.array(s[5])

    def tip(self, q) -> np.ndarray:
        pos, quat = self.fk(q)
        return pos + _rot(quat)[:, 2] * TIP

    def ik(self, pos, quat, seed, rest=None, tol: float = 1e-4) -> np.ndarray:
        """Arm joints putting panda_hand at ``pos``/``quat``; raises SynthError if unreachable.

        One null-space solve (biased towards ``rest``) picks the posture; plain solves from there
        remove the residual the null-space bias leaves (about 1 mm).
        """
        seed = np.asarray(seed, float)
        rest = np.asarray(rest if rest is not None else seed, float)
        pos, quat = [float(v) for v in pos], [float(v) for v in quat]
        self._set(seed)
        sol = self.pb.calculateInverseKinematics(
            self.robot, HAND, pos, quat, lowerLimits=list(self.lo), upperLimits=list(self.hi),
            jointRanges=list(self.hi - self.lo), restPoses=list(rest) + [0.02, 0.02],
            maxNumIterations=50, residualThreshold=1e-4)
        q = np.clip(np.array(sol[:7]), self.lo[:7], self.hi[:7])
        err = ang = float("inf")
        for _ in range(8):
            p_, q_ = self.fk(q)
            err = float(np.linalg.norm(p_ - np.asarray(pos)))
            ang = float(np.linalg.norm(_quat_error(quat, q_)))
            if err < tol and ang < 2e-3:
                return q
            sol = self.pb.calculateInverseKinematics(self.robot, HAND, pos, quat, maxNumIterations=50,
                                                     residualThreshold=1e-6)
            q = np.clip(np.array(sol[:7]), self.lo[:7], self.hi[:7])
        if err < 2e-3 and ang < 0.02:
            return q
        raise SynthError(f"no IK solution for panda_hand at {np.round(pos, 3).tolist()} "
                         f"(residual {err * 1000:.1f} mm, {math.degrees(ang):.1f} deg)")

    def tip_pose_ik(self, tip, yaw: float, seed, rest=None) -> np.ndarray:
        """Arm joints putting the fingertip centre at ``tip`` with the hand down, turned by ``yaw``."""
        quat = hand_down(yaw)
        hand = np.asarray(tip, float) - _rot(quat)[:, 2] * TIP
        return self.ik(hand, quat, seed, rest)

    def rest_for(self, xy, yaw: float) -> np.ndarray:
        """A comfortable posture to bias IK: joint 1 towards the target, joint 7 for the yaw."""
        a = math.atan2(xy[1], xy[0])
        r = HOME.copy()
        r[0] = a
        r[6] = (0.785 + yaw - a + math.pi) % (2 * math.pi) - math.pi
        return r

    def close(self) -> None:
        try:
            self.pb.disconnect()
        except Exception:
            pass


# ---------------------------------------------------------------------------------- trajectories
class JointMove:
    """Quintic joint-space move from ``q0`` to ``q1`` in ``duration`` seconds."""

    def __init__(self, q0, q1, duration: float):
        self.q0, self.q1 = np.asarray(q0, float), np.asarray(q1, float)
        self.duration = max(float(duration), 1e-3)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        s, ds = _quintic(t / self.duration)
        d = self.q1 - self.q0
        return self.q0 + d * s, d * ds / self.duration


class SampledMove:
    """Joint trajectory through IK solutions sampled along a Cartesian path (linear between samples)."""

    def __init__(self, times, qs):
        self.times = np.asarray(times, float)
        self.qs = np.asarray(qs, float)
        self.duration = float(self.times[-1])
        self.q1 = self.qs[-1]
        self.vs = np.gradient(self.qs, self.times, axis=0) if len(self.times) > 1 else np.zeros_like(self.qs)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        t = min(max(t, 0.0), self.duration)
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        i = min(max(i, 0), len(self.times) - 2)
        t0, t1 = self.times[i], self.times[i + 1]
        a = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
        return (self.qs[i] + a * (self.qs[i + 1] - self.qs[i]), self.vs[i] + a * (self.vs[i + 1] - self.vs[i]))


def linear_move(planner: Planner, q_start, tip0, tip1, yaw: float, duration: float, rest=None,
                sample_dt: float = 0.02) -> SampledMove:
    """A straight fingertip path with minimum-jerk timing, hand down (IK every ``sample_dt``)."""
    n = max(2, int(math.ceil(duration / sample_dt)) + 1)
    times = np.linspace(0.0, duration, n)
    q = np.asarray(q_start, float)
    qs = []
    tip0, tip1 = np.asarray(tip0, float), np.asarray(tip1, float)
    for t in times:
        s, _ = _quintic(t / duration)
        q = planner.tip_pose_ik(tip0 + (tip1 - tip0) * s, yaw, q, rest if rest is not None else q)
        qs.append(q)
    return SampledMove(times, qs)


# -------------------------------------------------------------------------------------- telemetry
class Telemetry:
    """Samples the reality's joints at 250 Hz with Gaussian noise and timing jitter; collects actions."""

    def __init__(self, rng: np.random.Generator, noise: dict[str, float], rate: float = TELEMETRY_RATE):
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
        pos = np.asarray(q, float) + np.concatenate([self.rng.normal(0, n["position_rad"], 7),
                                                     self.rng.normal(0, n["finger_position_m"], 2)])
        eff = np.asarray(tau, float) + np.concatenate([self.rng.normal(0, n["effort_nm"], 7),
                                                       self.rng.normal(0, n["finger_effort_n"], 2)])
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
                    w.joint_state(it[1], JOINT_NAMES, it[2], it[3], it[4])
                else:
                    w.action(it[1], it[2], it[3], **it[4])
            for name, data in metadata.items():
                w.metadata(name, data)

    @property
    def duration(self) -> float:
        return self.joint_states[-1][0] if self.joint_states else 0.0


# ---------------------------------------------------------------------------------------- reality
class Reality:
    """The real world: pybullet DIRECT at 1 kHz, table plane at z = 0, the Panda fixed at the origin."""

    def __init__(self, contact: dict[str, float]):
        import pybullet as p

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
        self.robot = pb.loadURDF(_panda_path(), useFixedBase=True)
        for f in FINGERS:
            # the URDF's pads are already soft (stiffness 3e4, damping 1e3, friction anchor)
            pb.changeDynamics(self.robot, f, lateralFriction=contact["finger_friction"],
                              spinningFriction=contact["finger_spinning"], rollingFriction=1e-4,
                              contactStiffness=contact["finger_stiffness"], contactDamping=contact["finger_damping"],
                              frictionAnchor=True)
        for j in range(pb.getNumJoints(self.robot)):
            pb.changeDynamics(self.robot, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.02)
        # the Panda's fingers are coupled (one motor, a rack): keep them symmetric with a gear constraint
        gear = pb.createConstraint(self.robot, FINGERS[0], self.robot, FINGERS[1], p.JOINT_GEAR, [1, 0, 0],
                                   [0, 0, 0], [0, 0, 0])
        pb.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=100)

    def reset_arm(self, q, fingers) -> None:
        for j, v in zip(ARM, q):
            self.pb.resetJointState(self.robot, j, float(v))
        for j, v in zip(FINGERS, fingers):
            self.pb.resetJointState(self.robot, j, float(v))

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

    def cylinder(self, radius: float, length: float, pos, mass: float = 0.0, quat=(0, 0, 0, 1)) -> int:
        pb = self.pb
        shape = pb.createCollisionShape(self.p.GEOM_CYLINDER, radius=radius, height=length)
        return pb.createMultiBody(mass, shape, basePosition=list(map(float, pos)), baseOrientation=list(quat))

    def sphere(self, radius: float, pos, mass: float) -> int:
        pb = self.pb
        return pb.createMultiBody(mass, pb.createCollisionShape(self.p.GEOM_SPHERE, radius=radius),
                                  basePosition=list(map(float, pos)))

    def pose(self, body: int) -> np.ndarray:
        pos, quat = self.pb.getBasePositionAndOrientation(body)
        return np.array(list(pos) + list(quat))

    def speed(self, body: int) -> float:
        lin, ang = self.pb.getBaseVelocity(body)
        return float(np.linalg.norm(lin))

    def joints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        st = self.pb.getJointStates(self.robot, list(ARM) + list(FINGERS))
        return (np.array([s[0] for s in st]), np.array([s[1] for s in st]), np.array([s[3] for s in st]))

    def hand(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.pb.getLinkState(self.robot, HAND, computeForwardKinematics=True)
        return np.array(s[4]), np.array(s[5])

    def tip(self) -> np.ndarray:
        pos, quat = self.hand()
        return pos + _rot(quat)[:, 2] * TIP

    def step(self) -> None:
        self.pb.stepSimulation()
        self.steps += 1
        self.t = self.steps * self.dt

    def close(self) -> None:
        try:
            self.pb.disconnect()
        except Exception:
            pass


# ------------------------------------------------------------------------------------------ robot
class Robot:
    """Runs the script on the reality: controllers, annotations, telemetry; one 1 kHz step at a time.

    Arm: position control with the Panda's torque limits (tracking a trajectory's positions and
    velocities), or a Cartesian impedance controller in torque mode (``compliant``). Fingers:
    position control with a force limit (the grip force).
    """

    def __init__(self, world: Reality, planner: Planner, telem: Telemetry, cfg: dict, max_time: float,
                 progress: Progress | None = None):
        self.w, self.pl, self.tm, self.cfg = world, planner, telem, cfg
        self.q_ref = np.asarray(cfg["start_q"], float)
        self.qd_ref = np.zeros(7)
        self.finger_ref = float(cfg["start_fingers"])
        self.finger_force = float(cfg["grip_force"])
        self.mode = "position"
        self.tau = np.zeros(7)
        self.imp_target: tuple[np.ndarray, np.ndarray] | None = None
        self.imp_rest = self.q_ref.copy()
        self.hooks: list[Callable[[], bool]] = []
        self.max_time = max_time
        self.progress = progress
        self.recording = True
        self._last_report = -1.0
        self.w.reset_arm(self.q_ref, [self.finger_ref] * 2)

    # -- one step
    def step(self) -> None:
        w, pb, p = self.w, self.w.pb, self.w.p
        if self.mode == "position":
            pb.setJointMotorControlArray(w.robot, list(ARM), p.POSITION_CONTROL, targetPositions=list(self.q_ref),
                                         targetVelocities=list(self.qd_ref), forces=list(TORQUE_LIMITS),
                                         positionGains=[self.cfg["kp"]] * 7, velocityGains=[1.0] * 7)
        else:
            self.tau = self._impedance_torques()
            pb.setJointMotorControlArray(w.robot, list(ARM), p.TORQUE_CONTROL, forces=list(self.tau))
        pb.setJointMotorControlArray(w.robot, list(FINGERS), p.POSITION_CONTROL, targetPositions=[self.finger_ref] * 2,
                                     forces=[self.finger_force] * 2, positionGains=[0.05] * 2,
                                     targetVelocities=[0.0, 0.0], velocityGains=[1.0] * 2)
        w.step()
        if self.recording and self.tm.due(w.t, w.dt):
            q, qd, tau = w.joints()
            if self.mode != "position":
                tau[:7] = self.tau
            self.tm.sample(q, qd, tau)
        for h in list(self.hooks):
            if h():
                self.hooks.remove(h)
        if w.t > self.max_time:
            raise SynthError(f"script exceeded its time limit of {self.max_time:.0f} s")
        if self.progress and self.recording and w.t - self._last_report >= 1.0:
            self._last_report = w.t
            self.progress(f"t = {w.t - self.tm.t0:4.1f} s")

    def wait(self, seconds: float) -> None:
        for _ in range(int(round(seconds / self.w.dt))):
            self.step()

    def annotate(self, operation: str, phase: str, **params) -> None:
        if self.recording:
            self.tm.action(self.w.t, operation, phase, params)

    # -- arm
    def target_params(self, name: str, q) -> dict:
        pos, quat = self.pl.fk(q)
        return {"name": name, "target": list(pos) + list(quat), "link": "panda_hand"}

    def follow(self, move, name: str, during: list[tuple[float, Callable[[], None]]] | None = None,
               settle_tol: float = 0.004, settle_max: float = 0.5) -> None:
        """Play a joint trajectory (move_arm start/end annotations); ``during`` = [(time fraction, fn)]."""
        params = self.target_params(name, move.q1)
        self.annotate("move_arm", "start", **params)
        pending = sorted(during or [], key=lambda x: x[0])
        n = int(round(move.duration / self.w.dt))
        for i in range(1, n + 1):
            t = i * self.w.dt
            self.q_ref, self.qd_ref = move.at(t)
            while pending and t >= pending[0][0] * move.duration:
                pending.pop(0)[1]()
            self.step()
        self.qd_ref = np.zeros(7)
        for _ in range(int(settle_max / self.w.dt)):
            q, _, _ = self.w.joints()
            if np.max(np.abs(q[:7] - self.q_ref)) < settle_tol:
                break
            self.step()
        self.annotate("move_arm", "end", **params)

    def move_to(self, q, duration: float, name: str, **kw) -> None:
        self.follow(JointMove(self.q_ref, q, duration), name, **kw)

    # -- hand
    def _finger_done_hook(self, on_done: Callable[[], None], min_t: float = 0.15, max_t: float = 1.5):
        t0 = self.w.t
        still = [0]

        def hook() -> bool:
            _, qd, _ = self.w.joints()
            el = self.w.t - t0
            still[0] = still[0] + 1 if max(abs(qd[7]), abs(qd[8])) < 2e-3 else 0
            if (el >= min_t and still[0] >= 30) or el >= max_t:
                on_done()
                return True
            return False

        return hook

    def hand(self, command: str, operation: str = "move_hand", extra: dict | None = None, wait: bool = True) -> None:
        """Close or open the fingers; annotate ``operation`` start now and end when the fingers stop."""
        params = {"hand": "hand", "command": command} if operation == "move_hand" else {"hand": "hand", **(extra or {})}
        self.annotate(operation, "start", **params)
        self.finger_ref = 0.0 if command == "close" else FINGER_OPEN
        done = [False]

        def finish() -> None:
            self.annotate(operation, "end", **params)
            done[0] = True

        self.hooks.append(self._finger_done_hook(finish))
        if wait:
            for _ in range(int(2.0 / self.w.dt)):
                if done[0]:
                    break
                self.step()

    def release(self, obj: str, wait: bool = True) -> None:
        self.hand("open", operation="release", extra={"object": obj}, wait=wait)

    # -- compliance
    def _impedance_torques(self) -> np.ndarray:
        """tau = J^T [K (x_d - x) - D v; K_r e_r - D_r w] + g(q) + null-space posture term."""
        w, pb, c = self.w, self.w.pb, self.cfg["impedance"]
        q, qd, _ = w.joints()
        st = pb.getLinkState(w.robot, HAND, computeLinkVelocity=True, computeForwardKinematics=True)
        com_pos, com_quat = np.array(st[0]), np.array(st[1])
        hand_pos, hand_quat = np.array(st[4]), np.array(st[5])
        tip = hand_pos + _rot(hand_quat)[:, 2] * TIP
        local = _rot(com_quat).T @ (tip - com_pos)
        zeros = [0.0] * 9
        jl, ja = pb.calculateJacobian(w.robot, HAND, list(local), list(q), list(qd), zeros)
        J = np.vstack([np.array(jl)[:, :7], np.array(ja)[:, :7]])
        v = J @ qd[:7]
        x_d, quat_d = self.imp_target
        f = c["k"] * (x_d - tip) - c["d"] * v[:3]
        m = c["k_rot"] * _quat_error(quat_d, hand_quat) - c["d_rot"] * v[3:]
        g = np.array(pb.calculateInverseDynamics(w.robot, list(q), list(qd), zeros))[:7]
        tau = J.T @ np.concatenate([f, m]) + g
        # null space: pull gently towards the posture the move started from
        Jp = np.linalg.pinv(J)
        N = np.eye(7) - J.T @ Jp.T
        tau += N @ (c["k_null"] * (self.imp_rest - q[:7]) - c["d_null"] * qd[:7])
        return np.clip(tau, -TORQUE_LIMITS, TORQUE_LIMITS)

    def compliant_move(self, tip0, tip1, quat, duration: float, hold: float, name: str, **extra) -> None:
        """Move the impedance set point along a straight line (move_arm annotated), then hold it."""
        w, pb, p = self.w, self.w.pb, self.w.p
        if self.mode != "impedance":
            pb.setJointMotorControlArray(w.robot, list(ARM), p.VELOCITY_CONTROL, forces=[0.0] * 7)
            self.mode = "impedance"
            self.imp_rest = w.joints()[0][:7].copy()
        quat = np.asarray(quat, float)
        hand1 = np.asarray(tip1) - _rot(quat)[:, 2] * TIP
        params = {"name": name, "target": list(hand1) + list(quat), "link": "panda_hand", **extra}
        self.annotate("move_arm", "start", **params)
        tip0, tip1 = np.asarray(tip0, float), np.asarray(tip1, float)
        n = int(round(duration / w.dt))
        for i in range(1, n + 1):
            s, _ = _quintic(i / n)
            self.imp_target = (tip0 + (tip1 - tip0) * s, quat)
            self.step()
        self.wait(hold)
        self.annotate("move_arm", "end", **params)


# ------------------------------------------------------------------------------------ generation
def _noise_levels(rng: np.random.Generator) -> dict[str, float]:
    return {"position_rad": float(rng.uniform(5e-5, 2e-4)), "finger_position_m": float(rng.uniform(1e-5, 5e-5)),
            "effort_nm": float(rng.uniform(0.05, 0.3)), "finger_effort_n": float(rng.uniform(0.1, 0.5)),
            "jitter_s": float(rng.uniform(5e-5, 3e-4)), "perception_m": float(rng.uniform(0.001, 0.003)),
            "perception_yaw_rad": float(rng.uniform(0.005, 0.02))}


def _contact(rng: np.random.Generator) -> dict[str, float]:
    return {"finger_friction": float(rng.uniform(0.9, 1.3)), "finger_spinning": float(rng.uniform(0.02, 0.1)),
            "finger_stiffness": float(rng.uniform(2.5e4, 4e4)), "finger_damping": float(rng.uniform(600, 1200)),
            "table_friction": float(rng.uniform(0.45, 0.8)), "table_restitution": float(rng.uniform(0.55, 0.7))}


def _scale_durations(rng: np.random.Generator, base: dict[str, float], time_scale: float) -> dict[str, float]:
    return {k: float(v * time_scale * rng.uniform(0.85, 1.15)) for k, v in base.items()}


def _perceive(rng: np.random.Generator, pose, sigma: float, yaw_sigma: float = 0.0) -> list[float]:
    pose = list(map(float, pose))
    out = [pose[0] + rng.normal(0, sigma), pose[1] + rng.normal(0, sigma), pose[2] + rng.normal(0, sigma / 2)]
    q = pose[3:7] if len(pose) >= 7 else [0.0, 0.0, 0.0, 1.0]
    if yaw_sigma:
        q = quat_mul(_yaw_quat(rng.normal(0, yaw_sigma)), q)
    return out + [float(v) for v in q]


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


def _metadata_generation(gen: dict) -> dict[str, str]:
    out = {k: (v if isinstance(v, str) else json.dumps(_r(v, 7), sort_keys=True)) for k, v in gen.items()}
    out["json"] = json.dumps(_r(gen, 7), sort_keys=True)
    return out


def _command(gen: dict) -> str:
    cmd = f"twin record synth --scenario {gen['scenario']} --seed {gen['seed']}"
    if gen["scenario"] == "ball_drop":
        cmd += f" --container {gen['container']} --outcome {gen['outcome']}"
    else:
        cmd += f" --localization-error {gen['localization_error']}"
    if gen.get("time_scale", 1.0) != 1.0:
        cmd += f" --time-scale {gen['time_scale']}"
    return cmd + " --out FILE.mcap"


def _settle(world: Reality, robot: Robot | None, body: int, max_s: float, still_s: float = 0.3,
            v_tol: float = 0.01) -> float:
    """Step until ``body`` has been still for ``still_s`` (or ``max_s`` passed); returns the time spent."""
    t0 = world.t
    still = 0.0
    while world.t - t0 < max_s:
        if robot is not None:
            robot.step()
        else:
            world.step()
        still = still + world.dt if world.speed(body) < v_tol else 0.0
        if still >= still_s:
            break
    return world.t - t0


# -------------------------------------------------------------------------------------- ball drop
# "open" is no phase any more, but its random draw stays: every duration is drawn from the seed in
# this order, and the shipped recordings (make recordings) must come out byte for byte the same
BALL_DURATIONS = {"settle": 0.3, "open": 0.4, "approach": 2.0, "descend": 1.2, "lift": 1.0, "carry": 2.2,
                  "lower": 0.8, "retreat": 0.8, "home": 1.4}


def _place_ball_drop(rng: np.random.Generator, shape: dict) -> dict:
    """Stand and container within the Panda's reach, apart enough for the fingers and an early release."""
    Rc = _container_radius(shape)
    for _ in range(2000):
        rs, ths = rng.uniform(0.40, 0.60), rng.uniform(-1.05, 1.05)
        rc, thc = rng.uniform(0.42, 0.64), rng.uniform(-1.1, 1.1)
        stand = np.array([rs * math.cos(ths), rs * math.sin(ths)])
        cont = np.array([rc * math.cos(thc), rc * math.sin(thc)])
        if np.linalg.norm(stand - cont) < Rc + 0.22:
            continue
        if rc - Rc < 0.2 or rc + Rc > 0.86:
            continue
        return {"stand_xy": stand, "container_xy": cont, "container_yaw": float(rng.uniform(-math.pi, math.pi))}
    raise SynthError(f"cannot place a {shape.get('style')} container and a stand within reach")


def synth_ball_drop(seed: int, out: str | Path, container: str = "bin", outcome: str = "success",
                    time_scale: float = 1.0, progress: Progress | None = None) -> SynthResult:
    """Generate one ball_drop recording (see the module docstring); returns what was measured."""
    if container not in CONTAINERS:
        raise ValueError(f"container must be one of {', '.join(CONTAINERS)}, got {container!r}")
    if outcome not in OUTCOMES:
        raise ValueError(f"outcome must be one of {', '.join(OUTCOMES)}, got {outcome!r}")
    wall0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    # --- the world (drawn first, in a fixed order: the same seed gives the same world for every outcome)
    contact = _contact(rng)
    noise = _noise_levels(rng)
    ball = {"radius": float(rng.uniform(0.0325, 0.0340)), "mass": float(rng.uniform(0.056, 0.059)),
            "friction": float(rng.uniform(0.6, 0.9)), "rolling_friction": float(rng.uniform(2e-4, 6e-4)),
            "spinning_friction": float(rng.uniform(5e-4, 2e-3)), "restitution": float(rng.uniform(0.75, 0.85))}
    stand = {"radius": float(rng.uniform(0.02, 0.03)), "length": float(rng.uniform(0.05, 0.12))}
    shape = {"type": "container", "style": container}
    cprops = {"friction": float(rng.uniform(0.4, 0.7)), "restitution": float(rng.uniform(0.35, 0.55))}
    place = _place_ball_drop(rng, shape)
    # --- the script's choices
    srng = np.random.default_rng([seed, 1])
    dur = _scale_durations(srng, BALL_DURATIONS, time_scale)
    grip_force = float(srng.uniform(20.0, 35.0))
    kp = float(srng.uniform(0.08, 0.15))
    pre_grasp = float(srng.uniform(0.08, 0.14))
    grasp_dz = float(srng.uniform(-0.006, 0.004))
    h_c = _container_height(shape)
    carry_clear = float(srng.uniform(0.06, 0.10))
    release_clear = float(srng.uniform(0.02, 0.05))
    yaw_grasp_dev = float(srng.uniform(-0.4, 0.4))
    start_q = HOME + srng.normal(0, 0.05, 7)
    early_frac = float(srng.uniform(0.2, 0.35))
    miss_gap = float(srng.uniform(0.04, 0.07))
    miss_dir = float(srng.uniform(-math.pi, math.pi))
    empty_mode = str(srng.choice(["mislocated", "too_high"]))
    empty_offset = float(srng.uniform(0.065, 0.09)) * float(srng.choice([-1.0, 1.0]))
    empty_high = float(srng.uniform(0.025, 0.045))
    release_off = srng.uniform(-1, 1, 2)
    prng = np.random.default_rng([seed, 2])  # perception noise

    stand_pose = [*place["stand_xy"], stand["length"] / 2, 0.0, 0.0, 0.0, 1.0]
    ball_pos = np.array([*place["stand_xy"], stand["length"] + ball["radius"] - 0.0003])
    cont_pose = [*place["container_xy"], 0.0, *_yaw_quat(place["container_yaw"])]

    world = Reality(contact)
    planner = Planner()
    try:
        w, pb = world, world.pb
        stand_id = w.cylinder(stand["radius"], stand["length"], stand_pose[:3])
        pb.changeDynamics(stand_id, -1, lateralFriction=0.7, restitution=0.3, rollingFriction=1e-3,
                          spinningFriction=1e-3)
        cont_id = w.static_boxes(container_parts(shape), cont_pose, cprops["friction"], cprops["restitution"])
        ball_id = w.sphere(ball["radius"], ball_pos, ball["mass"])
        pb.changeDynamics(ball_id, -1, lateralFriction=ball["friction"], rollingFriction=ball["rolling_friction"],
                          spinningFriction=ball["spinning_friction"], restitution=ball["restitution"],
                          linearDamping=0.01, angularDamping=0.01)
        # perception: what the robot believes (true poses + a few mm of noise)
        ball_seen = _perceive(prng, list(ball_pos) + [0, 0, 0, 1], noise["perception_m"])
        stand_seen = _perceive(prng, stand_pose, noise["perception_m"])
        cont_seen = _perceive(prng, cont_pose, noise["perception_m"], noise["perception_yaw_rad"])
        yaw_g = math.atan2(ball_seen[1], ball_seen[0]) + yaw_grasp_dev
        if outcome == "empty_grasp" and empty_mode == "mislocated":
            # the robot believes the ball is beside its real place, across the fingers' closing line
            side = np.array([math.cos(yaw_g), math.sin(yaw_g)])  # hand x axis: across the closing axis
            ball_seen[0] += empty_offset * side[0]
            ball_seen[1] += empty_offset * side[1]

        telem = Telemetry(np.random.default_rng([seed, 3]), noise)
        cfg = {"start_q": start_q, "start_fingers": 0.02, "grip_force": grip_force, "kp": kp}
        robot = Robot(w, planner, telem, cfg, max_time=40.0 * max(time_scale, 1.0), progress=progress)
        robot.recording = False
        robot.wait(dur["settle"])  # the world at rest before the log starts
        # the log starts now: re-base its clock
        telem.t0 = w.t  # the log starts now
        robot.recording = True

        def say(msg: str) -> None:
            if progress:
                progress(f"{msg} (t = {w.t - telem.t0:.1f} s)")

        bx, by, bz = ball_seen[:3]
        grasp_tip = np.array([bx, by, bz + grasp_dz])
        if outcome == "empty_grasp" and empty_mode == "too_high":
            grasp_tip[2] = bz + ball["radius"] + empty_high
        above_tip = grasp_tip + [0, 0, pre_grasp]
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
        z_carry = max(h_c + ball["radius"] + carry_clear, grasp_tip[2] + 0.08)
        lift_tip = np.array([grasp_tip[0], grasp_tip[1], z_carry])
        say("lift")
        robot.follow(linear_move(planner, robot.q_ref, grasp_tip, lift_tip, yaw_g, dur["lift"], rest_g), "lift")
        held_after_lift = bool(np.linalg.norm(w.pose(ball_id)[:3] - w.tip()) < 0.03)

        # where to open the hand
        cxy = np.array(cont_seen[:2])
        c_yaw = 2 * math.atan2(cont_seen[5], cont_seen[6])
        z_rel = h_c + ball["radius"] + release_clear
        inner = _container_inner(shape)
        slack = max(0.0, inner - ball["radius"] - 0.01)
        if outcome == "missed":
            rel_xy = None
            for k in range(64):
                a = miss_dir + k * 0.41
                u = np.array([math.cos(a), math.sin(a)])
                xy = cxy + u * (_container_extent(shape, c_yaw, u) + ball["radius"] + miss_gap)
                r = float(np.linalg.norm(xy))
                if 0.32 < r < 0.78 and np.linalg.norm(xy - np.array(stand_seen[:2])) > 0.12:
                    rel_xy = xy
                    break
            if rel_xy is None:
                raise SynthError("no reachable release point beside the container")
        else:
            rel_xy = cxy + release_off * 0.4 * slack
        yaw_c = math.atan2(rel_xy[1], rel_xy[0]) + yaw_grasp_dev
        carry_tip = np.array([rel_xy[0], rel_xy[1], z_carry])
        rest_c = planner.rest_for(rel_xy, yaw_c)
        q_carry = planner.tip_pose_ik(carry_tip, yaw_c, robot.q_ref, rest_c)
        carry = JointMove(robot.q_ref, q_carry, dur["carry"])
        during = []
        if outcome == "released_early":
            # open where the hand is still far from the container (checked on the planned path)
            frac = early_frac
            for f in np.linspace(early_frac, 0.15, 8):
                tip = planner.tip(carry.at(f * carry.duration)[0])
                if np.linalg.norm(tip[:2] - cxy) > _container_radius(shape) + 0.15:
                    frac = float(f)
                    break
            early_frac = frac
            during.append((frac, lambda: (say("release (early)"), robot.release("ball", wait=False))))
        say("carry")
        robot.follow(carry, "above_container" if outcome != "missed" else "beside_container", during=during)
        held_after_carry = bool(np.linalg.norm(w.pose(ball_id)[:3] - w.tip()) < 0.03)
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
        robot.move_to(HOME, dur["home"], "home")
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
               "contact": contact, "noise": noise, "ball": ball, "stand": stand, "container_props": cprops,
               "positions": {"ball": ball_pos.tolist(), "stand": stand_pose, "container": cont_pose},
               "perceived": scene["entities"], "durations": dur, "grip_force_n": grip_force, "position_gain": kp,
               "heights": {"pre_grasp": pre_grasp, "grasp_dz": grasp_dz, "carry_z": z_carry, "release_z": z_rel},
               "release_xy": rel_xy.tolist(), "start_q": start_q.tolist()}
        if outcome == "released_early":
            gen["early_fraction"] = early_frac
        if outcome == "missed":
            gen["miss_gap"] = miss_gap
        if outcome == "empty_grasp":
            gen["empty_grasp_mode"] = empty_mode
            gen["empty_grasp_offset" if empty_mode == "mislocated" else "empty_grasp_height"] = (
                empty_offset if empty_mode == "mislocated" else empty_high)
        gen["command"] = _command(gen)
        return _finish(out, telem, gt, scene, gen, w, wall0, {"ball_final": final[:3].tolist(), "inside": inside, "held_after_lift": held_after_lift,
                        "held_after_carry": held_after_carry})
    finally:
        planner.close()
        world.close()


def _finish(out, telem: Telemetry, gt: dict, scene: dict, gen: dict, world: Reality, wall0: float,
            measured: dict) -> SynthResult:
    out = Path(out)
    telem.write(out, {"twin.ground_truth": gt, "twin.scene": {"json": json.dumps(scene, sort_keys=True)},
                      "twin.generation": _metadata_generation(gen)})
    return SynthResult(path=out, ground_truth=gt, generation=gen, duration=telem.duration,
                       joint_states=len(telem.joint_states), actions=len(telem.actions), sim_steps=world.steps,
                       wall_s=time.perf_counter() - wall0, size_bytes=out.stat().st_size, measured=measured)


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
                    progress: Progress | None = None) -> SynthResult:
    """Generate one insertion recording (see the module docstring); returns what was measured."""
    if not 0.0 <= localization_error <= 0.1:
        raise ValueError(f"localization error must be within [0, 0.1] m, got {localization_error}")
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

    world = Reality(contact)
    planner = Planner()
    try:
        w, pb = world, world.pb
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
        dip_id = w.cylinder(DIP_RADIUS, DIP_LENGTH, dip_pos, mass=dip["mass"], quat=[float(v) for v in hand_quat])
        pb.changeDynamics(dip_id, -1, lateralFriction=dip["friction"], spinningFriction=1e-3, rollingFriction=1e-4,
                          restitution=0.05)
        for f in FINGERS:
            pb.changeDynamics(w.robot, f, lateralFriction=contact["finger_friction"])
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
        gen["command"] = _command(gen)
        return _finish(out, telem, gt, scene, gen, w, wall0,
                       {"lateral": lateral, "depth_error": depth_err, "tilt_deg": tilt, "connected": connected})
    finally:
        planner.close()
        world.close()


def synthesize(scenario: str, seed: int, out: str | Path, container: str = "bin", outcome: str = "success",
               localization_error: float = 0.002, time_scale: float = 1.0,
               progress: Progress | None = None) -> SynthResult:
    """Generate one recording of ``scenario`` (``ball_drop`` or ``insertion``)."""
    if not 0.25 <= time_scale <= 4.0:
        raise ValueError(f"time scale must be within [0.25, 4], got {time_scale}")
    if scenario == "ball_drop":
        return synth_ball_drop(seed, out, container, outcome, time_scale, progress)
    if scenario == "insertion":
        return synth_insertion(seed, out, localization_error, time_scale, progress)
    raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
