"""The scripted robot: an IK planner, smooth joint trajectories and the controller that plays them in the reality."""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from agents.robot.index import BodyIndex
from protocol.errors import SynthError

from .arm import SynthArm, synth_arm
from .common import (
    Progress,
    _quat_error,
    _quintic,
    _rot,
    hand_down,
)
from .reality import Telemetry, World, _bullet


# ---------------------------------------------------------------------------------------- planner
class Planner:
    """The robot's motion planner: its own kinematic pybullet client with the robot (never stepped).

    pybullet's IK starts from the body's current joint state, so the planner resets its private
    robot to a seed before every query and refines the answer until the hand is within 0.2 mm.
    """

    def __init__(self, arm: SynthArm | None = None):
        import pybullet as p

        self.arm = arm = arm or synth_arm()
        self.pb = _bullet(p)
        self.robot = self.pb.loadURDF(arm.robot.urdf_file, useFixedBase=True)
        idx = BodyIndex(self.robot, self.pb._id)
        self.ARM = [idx.joint[n] for n in arm.robot.arm]
        self.HAND = idx.link[arm.robot.gripper.hand]
        movable = list(idx.joint)  # pybullet's IK answers for every movable joint, in this order
        self.lo = np.array([idx.lower[n] for n in movable])
        self.hi = np.array([idx.upper[n] for n in movable])
        half = arm.robot.with_mimic(dict(zip(arm.robot.gripper.joints, arm.grip(0.5), strict=True)))
        self.rest_tail = [half.get(n, 0.0) for n in movable[arm.n:]]  # the gripper half open (and its mimics)

    def _set(self, q) -> None:
        for j, v in zip(self.ARM, q, strict=True):
            self.pb.resetJointState(self.robot, j, float(v))

    def fk(self, q) -> tuple[np.ndarray, np.ndarray]:
        """The hand link's position and orientation for arm joints ``q``."""
        self._set(q)
        s = self.pb.getLinkState(self.robot, self.HAND, computeForwardKinematics=True)
        return np.array(s[4]), np.array(s[5])

    def tip(self, q) -> np.ndarray:
        pos, quat = self.fk(q)
        return pos + _rot(quat)[:, 2] * self.arm.tip

    def ik(self, pos, quat, seed, rest=None, tol: float = 1e-4) -> np.ndarray:
        """Arm joints putting the hand link at ``pos``/``quat``; raises SynthError if unreachable.

        One null-space solve (biased towards ``rest``) picks the posture; plain solves from there
        remove the residual the null-space bias leaves (about 1 mm).
        """
        seed = np.asarray(seed, float)
        rest = np.asarray(rest if rest is not None else seed, float)
        pos, quat = [float(v) for v in pos], [float(v) for v in quat]
        self._set(seed)
        sol = self.pb.calculateInverseKinematics(
            self.robot, self.HAND, pos, quat, lowerLimits=list(self.lo), upperLimits=list(self.hi),
            jointRanges=list(self.hi - self.lo), restPoses=list(rest) + self.rest_tail,
            maxNumIterations=50, residualThreshold=1e-4)
        n = self.arm.n
        q = np.clip(np.array(sol[:n]), self.lo[:n], self.hi[:n])
        err = ang = float("inf")
        for _ in range(8):
            p_, q_ = self.fk(q)
            err = float(np.linalg.norm(p_ - np.asarray(pos)))
            ang = float(np.linalg.norm(_quat_error(quat, q_)))
            if err < tol and ang < 2e-3:
                return q
            sol = self.pb.calculateInverseKinematics(self.robot, self.HAND, pos, quat, maxNumIterations=50,
                                                     residualThreshold=1e-6)
            q = np.clip(np.array(sol[:n]), self.lo[:n], self.hi[:n])
        if err < 2e-3 and ang < 0.02:
            return q
        raise SynthError(f"no IK solution for {self.arm.robot.gripper.hand} at {np.round(pos, 3).tolist()} "
                         f"(residual {err * 1000:.1f} mm, {math.degrees(ang):.1f} deg)")

    def tip_pose_ik(self, tip, yaw: float, seed, rest=None) -> np.ndarray:
        """Arm joints putting the fingertip centre at ``tip`` with the hand down, turned by ``yaw``."""
        quat = hand_down(yaw)
        hand = np.asarray(tip, float) - _rot(quat)[:, 2] * self.arm.tip
        return self.ik(hand, quat, seed, rest)

    def rest_for(self, xy, yaw: float) -> np.ndarray:
        """A comfortable posture to bias IK: joint 1 towards the target, the wrist joint for the yaw."""
        a = math.atan2(xy[1], xy[0])
        r = self.arm.home.copy()
        r[0] = a
        k, zero, sign = self.arm.wrist
        r[k] = (zero + sign * yaw - sign * a + math.pi) % (2 * math.pi) - math.pi  # (this order: shipped recordings)
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


# ------------------------------------------------------------------------------------------ robot
class Robot:
    """Runs the script on the reality: controllers, annotations, telemetry; one 1 kHz step at a time.

    Arm: position control with the Panda's torque limits (tracking a trajectory's positions and
    velocities), or a Cartesian impedance controller in torque mode (``compliant``). Fingers:
    position control with a force limit (the grip force) -- unless the reality inflicts a gripper
    fault (:meth:`weaken_grip`), which changes what the gripper delivers, never the robot's commands.
    Works on any :class:`World`; in torque mode the joint efforts logged are the commanded torques.
    """

    def __init__(self, world: World, planner: Planner, telem: Telemetry, cfg: dict, max_time: float,
                 progress: Progress | None = None):
        self.w, self.pl, self.tm, self.cfg = world, planner, telem, cfg
        self.arm = arm = world.arm
        self.q_ref = np.asarray(cfg["start_q"], float)
        self.qd_ref = np.zeros(arm.n)
        self.finger_ref = [float(v) for v in cfg["start_fingers"]]  # the gripper joints' targets
        self.finger_force = float(cfg["grip_force"])
        self.grip_fault: Callable[[float], float] | None = None  # reality time -> force the gripper delivers
        self.grip_given: list[float] | None = None  # where a faulty gripper's drive gave way to (else finger_ref)
        self.fault_ends_on_command = False  # the fault ends at the robot's next command of the hand
        self.mode = "position"
        self.tau = np.zeros(arm.n)
        self.imp_target: tuple[np.ndarray, np.ndarray] | None = None
        self.imp_rest = self.q_ref.copy()
        self.hooks: list[Callable[[], bool]] = []
        self.max_time = max_time
        self.progress = progress
        self.recording = True
        self._last_report = -1.0
        self.w.reset_arm(self.q_ref, self.finger_ref)

    # -- one step
    def step(self) -> None:
        w = self.w
        if self.mode == "position":
            w.command_arm_position(self.q_ref, self.qd_ref, self.cfg["kp"], self.arm.torque_limits)
        else:
            self.tau = self._impedance_torques()
            w.command_arm_torque(self.tau)
        if self.grip_fault is None:
            w.command_fingers(self.finger_ref, self.finger_force)
        else:
            w.command_fingers(self.grip_given or self.finger_ref, self.grip_fault(w.t))
        w.step()
        if self.recording and self.tm.due(w.t, w.dt):
            q, qd, tau = w.joints()
            if self.mode != "position":
                tau[:self.arm.n] = self.tau
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
        return {"name": name, "target": list(pos) + list(quat), "link": self.arm.robot.gripper.hand}

    def follow(self, move, name: str, during: list[tuple[float, Callable[[], object]]] | None = None,
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
        self.qd_ref = np.zeros(self.arm.n)
        for _ in range(int(settle_max / self.w.dt)):
            q, _, _ = self.w.joints()
            if np.max(np.abs(q[:self.arm.n] - self.q_ref)) < settle_tol:
                break
            self.step()
        self.annotate("move_arm", "end", **params)

    def move_to(self, q, duration: float, name: str, **kw) -> None:
        self.follow(JointMove(self.q_ref, q, duration), name, **kw)

    # -- hand
    def _finger_done_hook(self, on_done: Callable[[bool], None], min_t: float = 0.15, max_t: float = 1.5,
                          reach: bool = False):
        """A step hook that calls ``on_done(reached)`` once the fingers have stopped (30 steps still, after
        ``min_t``) -- with ``reach``, stopped within a tenth of their stroke of their target -- or ``max_t``
        passed. ``reached`` is False only when ``reach`` and they did not get there (fingers that never
        opened made no release)."""
        t0 = self.w.t
        still = [0]
        g = self.arm.robot.gripper
        tol = 0.1 * np.abs(np.asarray(g.open, float) - np.asarray(g.closed, float))

        def hook() -> bool:
            q, qd, _ = self.w.joints()
            el = self.w.t - t0
            still[0] = still[0] + 1 if float(np.max(np.abs(qd[self.arm.n:]))) < 2e-3 else 0
            there = not reach or bool(np.all(np.abs(q[self.arm.n:] - self.finger_ref) <= tol))
            if (el >= min_t and still[0] >= 30 and there) or el >= max_t:
                on_done(there)
                return True
            return False

        return hook

    def hand(self, command: str, operation: str = "move_hand", extra: dict | None = None, wait: bool = True) -> None:
        """Close or open the fingers; annotate ``operation`` start now and end when the fingers stop."""
        params = {"hand": "hand", "command": command} if operation == "move_hand" else {"hand": "hand", **(extra or {})}
        self.annotate(operation, "start", **params)
        self.finger_ref = self.arm.grip(0.0 if command == "close" else 1.0)
        if self.fault_ends_on_command:  # (a fault that lets the drive give way: see weaken_grip)
            self.grip_fault, self.grip_given, self.fault_ends_on_command = None, None, False
        done = [False]

        def finish(reached: bool) -> None:
            if reached:
                self.annotate(operation, "end", **params)
            else:  # the fingers did not get there: the robot's gripper reports the command failed
                self.annotate(operation, "end", **params, failed=True)
                if self.progress:
                    self.progress(f"{operation}: the fingers did not reach their target")
            done[0] = True

        # an opening ends when the fingers are open. (Not in the MuJoCo reality, whose shipped recordings were
        # made before: its fingers wait up to 0.4 s before they open, and a release ends as they stop, 0.15 s in)
        reach = command != "close" and self.w.name != "mujoco"
        self.hooks.append(self._finger_done_hook(finish, reach=reach))
        if wait:
            for _ in range(int(2.0 / self.w.dt)):
                if done[0]:
                    break
                self.step()

    def weaken_grip(self, residual: float, ramp: float, give: float = 0.0) -> None:
        """A gripper fault: from now on its force falls linearly, within ``ramp`` seconds, to ``residual``
        newtons per finger, whatever the robot commands (its commands and annotations are unchanged).

        Fingers on a linkage (the xArm's) grasping a ball stay where they are in this reality however little
        the drive squeezes (with no force at all, too), the ball held between them, and the residual force
        cannot open them at the release: there the fault is also the drive giving way, the fingers let open
        by ``give`` of their stroke, and it ends at the robot's next command of the hand (its release, which
        then opens them). Fingers on their own prismatic joints (the Panda's) let a ball slide out and open
        with the residual force: there the fault lasts (``give`` unused).
        """
        t0, f0 = self.w.t, self.finger_force
        if not self.arm.prismatic_fingers:
            q = self.w.joints()[0][self.arm.n:]
            g = self.arm.robot.gripper
            self.grip_given = [float(v) + give * (o - c) for v, o, c in zip(q, g.open, g.closed, strict=True)]
            self.fault_ends_on_command = True

        def delivered(t: float) -> float:
            a = min(1.0, (t - t0) / max(ramp, 1e-3))
            return f0 + (residual - f0) * a

        self.grip_fault = delivered

    def release(self, obj: str, wait: bool = True) -> None:
        self.hand("open", operation="release", extra={"object": obj}, wait=wait)

    # -- compliance
    def _impedance_torques(self) -> np.ndarray:
        """tau = J^T [K (x_d - x) - D v; K_r e_r - D_r w] + g(q) + null-space posture term."""
        c = self.cfg["impedance"]
        tip, hand_quat, J, g = self.w.tip_dynamics()
        q, qd, _ = self.w.joints()
        n = self.arm.n
        v = J @ qd[:n]
        assert self.imp_target is not None, "compliant_move sets the target first"
        x_d, quat_d = self.imp_target
        f = c["k"] * (x_d - tip) - c["d"] * v[:3]
        m = c["k_rot"] * _quat_error(quat_d, hand_quat) - c["d_rot"] * v[3:]
        tau = J.T @ np.concatenate([f, m]) + g
        # null space: pull gently towards the posture the move started from
        Jp = np.linalg.pinv(J)
        N = np.eye(n) - J.T @ Jp.T
        tau += N @ (c["k_null"] * (self.imp_rest - q[:n]) - c["d_null"] * qd[:n])
        return np.clip(tau, -self.arm.torque_limits, self.arm.torque_limits)

    def compliant_move(self, tip0, tip1, quat, duration: float, hold: float, name: str, **extra) -> None:
        """Move the impedance set point along a straight line (move_arm annotated), then hold it."""
        w = self.w
        if self.mode != "impedance":
            w.arm_torque_mode()
            self.mode = "impedance"
            self.imp_rest = w.joints()[0][:self.arm.n].copy()
        quat = np.asarray(quat, float)
        hand1 = np.asarray(tip1) - _rot(quat)[:, 2] * self.arm.tip
        params = {"name": name, "target": list(hand1) + list(quat), "link": self.arm.robot.gripper.hand, **extra}
        self.annotate("move_arm", "start", **params)
        tip0, tip1 = np.asarray(tip0, float), np.asarray(tip1, float)
        n = int(round(duration / w.dt))
        for i in range(1, n + 1):
            s, _ = _quintic(i / n)
            self.imp_target = (tip0 + (tip1 - tip0) * s, quat)
            self.step()
        self.wait(hold)
        self.annotate("move_arm", "end", **params)


def _settle(world: World, robot: Robot | None, body: int, max_s: float, still_s: float = 0.3,
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
