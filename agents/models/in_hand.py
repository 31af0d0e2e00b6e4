"""In-hand localization: owns a grasped object's pose while the grasp lasts (paper §4.1, [18]).

A general physics engine tends to lose or crush an object held between two fingers; this model
instead assumes the object *is* grasped and estimates where it sits in the hand. It keeps, per
owned entity, an extended Kalman filter (:class:`Ekf`) over the object's position in the hand frame
(the robot gripper's hand link) and the width the fingers grip it at:

    x = [p_x, p_y, p_z, w]        (metres, hand frame; w = grasped width along the finger axis)

*Prediction.* The object is glued to the hand, but may slip: a random walk of ``slip_sigma``
m/√s on every axis, plus ``loose_slip_sigma`` m/√s along gravity (expressed in the hand frame)
scaled by how weak the grip is once a contact was made (``c`` below; before the first contact the
object still rests where it was handed over). The width follows its own random walk (``width_sigma``)::

    x = F x          F = I
    P = F P Fᵀ + Q   Q = dt · (σ_s² I + (1 - c) σ_l² ĝ ĝᵀ  ⊕  σ_w²)

*Update.* The fingers of a parallel gripper stand ``q1`` (left pad at +q1 along the hand's y axis) and
``q2`` (right pad at -q2) from closed: the robot's gripper geometry turns its joint positions into these
openings, and its joint efforts into finger forces (:class:`agents.robot.kinematics.GripperGeometry`).
Squeezing an object of width ``w`` centred at lateral
offset ``p_y``::

    z = [q1, q2],   h(x) = [p_y + w/2,  -p_y + w/2]      (+ ``finger_gap_offset`` / 2 each)
    K = P Hᵀ (H P Hᵀ + R)⁻¹,   x = x + K (z - h(x))

so the lateral offset is observed as (q1 - q2)/2 and the width as q1 + q2. The finger efforts
say whether the reading can be trusted: the contact quality ``c`` rises from 0 at
``contact_effort`` to 1 at ``firm_effort`` (N) and the reading's noise is
``R = finger_sigma² / c``; below contact the update is skipped. A stream that never reports a
non-zero effort is treated as effort-less: contact then means "the gap fits the object". The
pads are flat, so ``p_x`` and ``p_z`` are not observed: they keep the seeded value and their
variance grows with the slip noise (the reported ``sigma`` says so). h is linear for flat pads,
so the EKF reduces to a Kalman filter here; a shape-dependent contact model would plug in its
own ``h`` and Jacobian.

*Seeding.* On ``acquire(entity, "pose", world_pose, extra)`` the hand pose ``T_wh`` comes from
this model's own forward kinematics (:mod:`agents.robot.kinematics`) at the latest telemetry joint
positions, and the object's pose in the hand is ``T_ho = T_wh⁻¹ ∘ T_wo`` (its orientation in
the hand stays fixed: a rigid grasp). Entities this model owns from the scene's start (the
insertion scene's DIP, already grasped) are seeded from their scene pose and the first
telemetry. The world pose it publishes is ``T_wh(t) ∘ [x_p, q_ho]``.

*Loss.* Unless the hand was commanded open (``move_hand`` with ``command: open`` or a
``release`` action; the scene's triggers then take the object back), the grasp is lost when,
for ``lost_steps`` consecutive steps, the fingers have closed narrower than the object allows
(``q1 + q2 < width_from_scene_shape - gap_tolerance``), or, after a contact was made, the efforts
vanished while the fingers kept closing (the gap shrank by more than ``closing_margin`` over
``closing_window`` seconds).
The model then raises ``lost`` and stops updating the entity: its pose stays where it was lost,
and a trigger (``on: {event: in_hand.lost}``) gives it back to the physics.

*Release.* ``release`` returns the world pose and ``{"velocity": [vx, vy, vz, wx, wy, wz]}``,
a finite difference of the object's world pose (where the hand holds it now) over the last
``velocity_window`` seconds of telemetry, so a ball let go while the arm swings flies on in the physics.
Asked between two of its steps (a 60 Hz model, a trigger on a 120 Hz tick), the pose is carried on at that
velocity to the handover's time: the pose of its last step was up to a step old (5 mm at 0.6 m/s).

*Slack grip.* Two fingers hold an object only by the friction their squeeze makes. When, after a
contact, the mean squeezing effort falls below ``contact_effort`` while the hand is still
commanded closed (a weakening gripper, an object slipping out), the object has been in free fall
since that sample, whatever the command says: the grasp monitor and the scene's triggers notice
it a sample or two later. So a release during a slack grip hands over the object where free fall
from the last held pose has taken it since the grip went slack, ``p + v Δ + ½ g Δ²`` with
velocity ``v + g Δ`` (Δ capped at ``max_free_fall`` s), not where the hand is: the physics then
lets it drop from the right place at the right speed instead of catching it again between its
closing fingers. A grip that firms up again before the release clears it (:data:`REGRIP_SAMPLES` samples in a
row). Without efforts, a grasp lost while the hand is not commanded open went where the fingers' gap last held
steady at the width it held before it moved (a slipping ball pushes the fingers apart, then lets them close).
The fall stops where the object
would first meet what is below it (the table, or the top of a scene entity whose footprint is under it, a
container's floor), at the speed it has then: the physics lets it land there (handed over under the table or
inside a stand, it was thrown back up out of it).

Params: see :attr:`InHand.params`. Outputs: ``estimate`` {entity: {pose, position_hand,
covariance (3×3), sigma (√trace of the position covariance, m), width, gap, contact, lost,
stamp}}. Events: ``lost`` {entity, reason, gap, effort, width}. Evaluators: ``estimate(entity)``,
``holding()`` (entities held and not lost).
"""
from __future__ import annotations

import copy
import math
from collections import deque
from typing import Any

import numpy as np

from protocol.joints import joint_state_key
from protocol.robot import resolve_robot

from ..model import Model, Param, evaluator
from ..robot.kinematics import (
    GripperGeometry,
    RobotKinematics,
    advanced,
    as_pose,
    compose,
    invert,
    quat_conj,
    quat_matrix,
    quat_mul,
    rotation_vector,
)


def grasp_width(shape: dict | None, q_ho) -> float | None:
    """Extent (m) of an entity's shape along the hand's y axis (the finger axis) when its
    orientation in the hand frame is ``q_ho``; None for shapes without a simple extent."""
    if not shape:
        return None
    R = quat_matrix(q_ho)  # columns: the object's axes in the hand frame
    t = shape.get("type")
    if t == "sphere":
        return 2.0 * float(shape["radius"])
    if t == "box":
        return float(sum(abs(R[1, i]) * float(s) for i, s in enumerate(shape["size"])))
    if t == "cylinder":
        u = min(1.0, abs(R[1, 2]))  # the cylinder's axis is its z axis
        return 2.0 * float(shape["radius"]) * math.sqrt(1.0 - u * u) + float(shape["length"]) * u
    if t == "container":
        from protocol.geometry import container_params

        p = container_params(shape)
        if "size" in p and p["style"] in ("bin", "box"):
            sx, sy, _ = map(float, p["size"])
            return abs(R[1, 0]) * sx + abs(R[1, 1]) * sy
        return 2.0 * float(p["radius"])
    return None


def reach(shape: dict | None) -> float:
    """The radius (m) of a sphere round an entity's shape centred at its pose (0 without a shape): how far below
    its centre its lowest point can be, and how far sideways its footprint can reach."""
    if not shape:
        return 0.0
    t = shape.get("type")
    if t == "sphere":
        return float(shape["radius"])
    if t == "box":
        return 0.5 * math.sqrt(sum(float(s) ** 2 for s in shape["size"]))
    if t == "cylinder":
        return math.hypot(float(shape["radius"]), 0.5 * float(shape["length"]))
    if t == "container":
        from protocol.geometry import container_params

        p = container_params(shape)
        if "size" in p and p["style"] in ("bin", "box"):
            return 0.5 * math.hypot(float(p["size"][0]), float(p["size"][1]))
        return float(p["radius"])
    return 0.0


def support_below(entities: dict[str, Any], held: str, xy: Any) -> float:
    """The height (m) of the highest surface under the point ``xy`` that a falling object could land on: the table
    (0), the top of a scene entity whose footprint (the circle of its :func:`reach`) holds ``xy``, a container's
    floor. Generous: it may stop a fall a little early, never let one pass through a surface."""
    top = 0.0
    for name, ent in entities.items():
        shape, pose = ent.get("shape") or {}, ent.get("pose")
        if name == held or pose is None or "virtual" in (ent.get("tags") or ()):
            continue
        pose = as_pose(pose)
        if math.hypot(float(xy[0]) - pose[0], float(xy[1]) - pose[1]) > reach(shape):
            continue
        if shape.get("type") == "container":
            from protocol.geometry import container_params

            top = max(top, float(pose[2]) + float(container_params(shape)["wall"]))  # (its floor: it falls in)
        else:
            top = max(top, float(pose[2]) + reach(shape))
    return top


class Ekf:
    """An extended Kalman filter: state ``x`` (column), covariance ``P``, transition ``F``, process noise ``Q``.

    ``update`` uses the Joseph form ``P = (I - K H) P (I - K H)^T + K R K^T`` (stable for any gain). Written here
    rather than taken from filterpy, whose import pulls in scipy.stats (a second of every agent's start-up);
    ``tests/test_in_hand.py`` checks it against filterpy's ``ExtendedKalmanFilter`` step by step.
    """

    def __init__(self, dim_x: int) -> None:
        self.x = np.zeros((dim_x, 1))
        self.P = np.eye(dim_x)
        self.F = np.eye(dim_x)
        self.Q = np.eye(dim_x)
        self.y = np.zeros((0, 1))
        self._I = np.eye(dim_x)

    def predict(self) -> None:
        self.x = self.F @ self.x
        self.P = self.F @ self.P @ self.F.T + self.Q

    def update(self, z: np.ndarray, jacobian, h, R: np.ndarray, args: tuple = (), hx_args: tuple = ()) -> None:
        """Correct with measurement ``z``: ``h(x, *hx_args)`` predicts it, ``jacobian(x, *args)`` is dh/dx."""
        H = jacobian(self.x, *args)
        PHT = self.P @ H.T
        K = PHT @ np.linalg.inv(H @ PHT + R)
        self.y = z - h(self.x, *hx_args)
        self.x = self.x + K @ self.y
        I_KH = self._I - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T


STEADY_SAMPLES = 3
"""Samples in a row within :data:`STEADY_BAND` (or three usual deviations) of the held gap that make it steady."""
STEADY_BAND = 0.0002
"""The least band (m) round the held gap: a finger reading's quantisation and noise at rest (0.1 mm in the
recordings' fingers while they hold a ball)."""
REGRIP_SAMPLES = 3
"""Samples in a row that say the fingers hold the object again before a slack grip counts as firm (an xArm's finger
force, its drive torque's 0.11 N m noise through the linkage, crossed ``contact_effort`` on one sample in twelve:
three in a row by chance, one in two thousand)."""


class _Track:
    """The filter and bookkeeping of one grasped entity."""

    def __init__(self, entity: str, T_ho: np.ndarray, width: float | None, gap: float | None,
                 seed_sigma: float, width_sigma0: float):
        self.entity = entity
        self.q_ho = T_ho[3:].copy()
        self.shape_width = width
        ekf = Ekf(dim_x=4)
        w0 = width if width is not None else (gap if gap is not None else 0.0)
        ekf.x = np.array([[T_ho[0]], [T_ho[1]], [T_ho[2]], [w0]])
        ekf.F = np.eye(4)
        # P: handover uncertainty of the position; the width starts at the scene shape's
        ekf.P = np.diag([seed_sigma ** 2] * 3 + [width_sigma0 ** 2 if width is not None else 0.02 ** 2])
        self.ekf = ekf
        self.lost = False
        self.lost_reason = ""
        self.bad_steps = 0
        self.contact = 0.0
        self.had_contact = False
        self.gap: float | None = gap
        self.innovation: list[float] = [0.0, 0.0]
        self.world = np.zeros(7)
        self.history: deque = deque(maxlen=64)  # (stamp, the hand's world pose)
        self.gaps: deque = deque(maxlen=64)     # (stamp, gap)
        self.velocity = [0.0] * 6
        self.stamp: float | None = None
        # the grip went slack at this stamp, holding the object here at this velocity (None: not slack)
        self.slack: tuple[float, np.ndarray, list[float]] | None = None
        self.regrip = 0  # samples in a row since then that say the fingers hold it again

    @property
    def T_ho(self) -> np.ndarray:
        return np.concatenate([self.ekf.x[:3, 0], self.q_ho])


def _H(x, offset):  # Jacobian of h: constant for flat parallel pads
    return _H_CONST


_H_CONST = np.array([[0.0, 1.0, 0.0, 0.5], [0.0, -1.0, 0.0, 0.5]])


def _hx(x, offset):
    # q1 = p_y + (w - offset)/2, q2 = -p_y + (w - offset)/2 (offset: gap when the finger joints read 0)
    py, w = x[1, 0], x[3, 0]
    return np.array([[py + (w - offset) / 2], [-py + (w - offset) / 2]])


class InHand(Model):
    """Kalman in-hand localization of grasped objects (see the module docstring)."""

    kind = "in_hand"
    role = "simulation"
    params = {
        "seed_sigma": Param(float, 0.005, "std (m) of the handed-over position, per axis, at seeding"),
        "width_sigma0": Param(float, 0.004, "std (m) of the object's width from the scene shape"),
        "finger_sigma": Param(float, 0.0005, "std (m) of one finger joint reading at firm contact"),
        "slip_sigma": Param(float, 0.001, "random walk of the object in the hand (m/√s)"),
        "loose_slip_sigma": Param(float, 0.02, "extra random walk along gravity at zero grip (m/√s)"),
        "width_sigma": Param(float, 0.002, "random walk of the grasped width (m/√s): squeezing"),
        "contact_effort": Param(float, 2.0, "mean finger effort (N) below which the fingers touch nothing"),
        "firm_effort": Param(float, 10.0, "mean finger effort (N) at which a reading gets full weight"),
        "gap_tolerance": Param(float, 0.01, "how much narrower (m) than the object the fingers may close"),
        "closing_margin": Param(float, 0.002, "gap decrease (m) that counts as 'the fingers kept closing'"),
        "closing_window": Param(float, 0.1, "time window (s) of that gap decrease"),
        "lost_steps": Param(int, 3, "consecutive steps a loss condition must hold before 'lost'"),
        "velocity_window": Param(float, 0.05, "finite-difference window (s) of the release velocity"),
        "max_free_fall": Param(float, 0.3, "longest free fall (s) a release after a slack grip accounts for"),
        "finger_gap_offset": Param(float, 0.0, "gap (m) between the pads when both finger joints read 0"),
        "hand_link": Param(str, "", "link of the hand frame (default: the robot gripper's hand)"),
    }
    attributes = ("pose",)
    outputs = ("estimate",)
    events = ("lost",)
    owner_events = ("lost",)  # it loses only what it holds

    def init(self, params: dict, scene: dict) -> None:
        self.p = params
        robot = resolve_robot(scene.get("robot") or None)
        self.fk = RobotKinematics.lease(robot)
        self.arm = tuple(robot.arm)
        self.hand_link = params["hand_link"] or robot.gripper.hand
        self.gripper = GripperGeometry.of(robot)
        if self.hand_link == robot.gripper.hand and self.gripper.axis[1] < 0.98:
            raise ValueError(f"the fingers of {robot.name} close along {self.gripper.axis.round(3).tolist()} in the "
                             f"{self.hand_link} frame; this model needs them along its y axis (left finger at +y)")
        self.entities = scene.get("entities", {})
        self.tracks: dict[str, _Track] = {}
        self.pending: dict[str, np.ndarray] = {}  # owned but not yet seeded: world pose
        for ent, attr in self.owned:
            if attr == "pose":
                self.pending[ent] = as_pose(self.entities[ent]["pose"])
        self.T_wh: np.ndarray | None = None
        self._fk_stale = False
        self.q: dict[str, float] = {}
        self.effort: dict[str, float] = {}
        self.stamp: float | None = None
        self._joints_key: tuple | None = None  # the joint state last taken (stamp, names, positions)
        self.efforts_reported = False
        self.opening = False

    # ------------------------------------------------------------------ step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        for a in telemetry.get("actions") or ():
            self._on_action(a)
        js = telemetry.get("joints")
        fresh = False
        if js is not None:
            stamp = float(js.get("stamp", t))
            key = joint_state_key(js)
            if key != self._joints_key or not self.q:
                self._joints_key = key
                fresh = True
                names = js["name"]
                self.q = dict(zip(names, js["position"], strict=False))
                eff = js.get("effort") or []
                self.effort = dict(zip(names, eff, strict=True)) if len(eff) == len(names) else {}
                if not self.efforts_reported and any(abs(float(e)) > 0.0 for e in self.effort.values()):
                    self.efforts_reported = True
                self._fk_stale = True
                self.stamp = stamp
        if not self.tracks and not self.pending:
            return  # holding nothing: the hand's pose is worked out when something is handed over
        if self._hand() is None:
            return  # no telemetry yet: owned entities stay where the scene put them
        for ent in list(self.pending):
            if (ent, "pose") in self.owned:
                self._seed(ent, self.pending.pop(ent))
        out = {}
        for ent, tr in self.tracks.items():
            if not tr.lost:
                self._predict(tr, dt)
                if fresh:
                    self._measure(tr)
            if not tr.lost and self.T_wh is not None:
                tr.world = compose(self.T_wh, tr.T_ho)
                if fresh:
                    tr.history.append((self.stamp, self.T_wh.copy()))
                    tr.velocity = self._velocity(tr)
            out[ent] = self._describe(tr)
        if out:
            self.output("estimate", out)

    def _on_action(self, a: dict) -> None:
        op, params = a.get("operation"), a.get("params") or {}
        if op == "release" and a.get("phase") == "start":
            self.opening = True
        elif op == "move_hand":
            cmd = params.get("command")
            if cmd == "open":
                self.opening = True
            elif cmd == "close":
                self.opening = False

    def _fingers(self) -> tuple[float, float] | None:
        """Both fingers' openings (m) from the latest joint state (None until it has the gripper's joints)."""
        try:
            return self.gripper.openings(self.q)
        except KeyError:
            return None

    def _grip(self) -> tuple[float | None, float | None]:
        """The gap between the pads (m) and the mean squeezing force of the fingers (N; None without efforts)."""
        o = self._fingers()
        gap = None if o is None else o[0] + o[1] + self.p["finger_gap_offset"]
        effort = None
        if o is not None and self.efforts_reported and all(j in self.effort for j in self.gripper.gripper.joints):
            f = self.gripper.forces(self.q, self.effort)
            effort = (abs(f[0]) + abs(f[1])) / 2
        return gap, effort

    def _hand(self) -> np.ndarray | None:
        """The hand's world pose from the latest joint positions (forward kinematics, computed
        only when needed: nothing to do while the model holds nothing)."""
        # (a joint state naming the gripper alone, a driver's that publishes them apart, put the hand of an arm
        # at all-zero joints: wait for the arm's)
        if self._fk_stale and self.q and all(j in self.q for j in self.arm):
            self.T_wh = self.fk.link_pose(self.q, self.hand_link)
            self._fk_stale = False
        return self.T_wh

    def _seed(self, ent: str, world: np.ndarray) -> None:
        assert self.T_wh is not None, "acquire computes the hand pose first"
        T_ho = compose(invert(self.T_wh), world)
        gap, _ = self._grip()
        width = grasp_width(self.entities.get(ent, {}).get("shape"), T_ho[3:])
        tr = _Track(ent, T_ho, width, gap, self.p["seed_sigma"], self.p["width_sigma0"])
        tr.world = world.copy()
        tr.stamp = self.stamp
        tr.history.append((self.stamp, self.T_wh.copy()))
        self.tracks[ent] = tr

    def _predict(self, tr: _Track, dt: float) -> None:
        p = self.p
        assert self.T_wh is not None, "a track is predicted only with a hand pose"
        g = quat_matrix(self.T_wh[3:]).T @ np.array([0.0, 0.0, -1.0])  # gravity direction in the hand
        Q = np.zeros((4, 4))
        # Q = dt (σ_s² I + (1 - c) σ_l² ĝ ĝᵀ ⊕ σ_w²); before the first contact nothing pulls the object
        # out of the hand (it still rests where it was handed over), so the loose term waits for it
        loose = (1.0 - tr.contact) if tr.had_contact else 0.0
        Q[:3, :3] = dt * (p["slip_sigma"] ** 2 * np.eye(3) + loose * p["loose_slip_sigma"] ** 2 * np.outer(g, g))
        Q[3, 3] = dt * p["width_sigma"] ** 2
        tr.ekf.Q = Q
        tr.ekf.predict()

    def _measure(self, tr: _Track) -> None:
        p = self.p
        gap, effort = self._grip()
        if gap is None:
            return
        tr.gap = gap
        tr.gaps.append((self.stamp, gap))
        fits = tr.shape_width is None or gap >= tr.shape_width - p["gap_tolerance"]
        if effort is not None:
            span = max(1e-9, p["firm_effort"] - p["contact_effort"])
            c = min(1.0, max(0.0, (effort - p["contact_effort"]) / span))
        else:
            c = 1.0 if fits and abs(gap - float(tr.ekf.x[3, 0])) <= p["gap_tolerance"] else 0.0
        tr.contact = c
        self._slack(tr, effort)
        tr.had_contact = tr.had_contact or c > 0.0
        if not self.opening:
            reason = self._loss(tr, gap, effort, fits)
            tr.bad_steps = tr.bad_steps + 1 if reason else 0
            if reason and tr.bad_steps >= p["lost_steps"]:
                tr.lost, tr.lost_reason = True, reason
                self.emit("lost", entity=tr.entity, reason=reason, gap=gap, effort=effort,
                          width=tr.shape_width)
                return
        else:
            tr.bad_steps = 0
        if c <= 0.0 or not fits or self.opening:
            return
        o = self._fingers()
        if o is None:
            return
        z = np.array([[o[0]], [o[1]]])
        R = np.eye(2) * (p["finger_sigma"] ** 2 / max(c, 0.05))
        off = p["finger_gap_offset"]
        tr.ekf.update(z, _H, _hx, R=R, args=(off,), hx_args=(off,))
        tr.innovation = [float(v) for v in tr.ekf.y[:, 0]]

    def _slack(self, tr: _Track, effort: float | None) -> None:
        """Note when the squeeze that held the object went (see *Slack grip*): the last held pose and
        velocity, kept until the grip firms up again (for :data:`REGRIP_SAMPLES` samples in a row: a noisy force,
        an xArm's through its linkage, crossed ``contact_effort`` for one sample now and then, and the fall began
        again from there) or the hand is commanded open. Without efforts, :meth:`_departed` says it when the
        grasp is lost."""
        stamp = self.stamp
        if stamp is None or self.opening or not tr.had_contact:
            tr.slack, tr.regrip = None, 0
            return
        if effort is None:  # (said from the fingers' gap when the grasp is lost: :meth:`_departed`)
            return
        if effort >= self.p["contact_effort"]:
            tr.regrip += 1
            if tr.regrip >= REGRIP_SAMPLES:
                tr.slack = None
        else:
            tr.regrip = 0
            if tr.slack is None:
                tr.slack = (float(stamp), tr.world.copy(), list(tr.velocity))

    def _departed(self, tr: _Track) -> tuple[float, np.ndarray, list[float]] | None:
        """Without efforts, for a grasp lost with the hand not commanded open: the stamp, pose and velocity where
        the fingers' gap last held steady at the width it held (:data:`STEADY_SAMPLES` samples in a row within
        three of its usual deviations) before it moved, as a ball that slips out first pushes the fingers apart,
        then lets them close; there the grip went. None if it never moved. (The effort-less monitor sees the
        grasp lost a few samples after the gap moves: the object, handed over where the hand held it then, was
        caught again between the closing fingers.)"""
        gaps = list(tr.gaps)
        if len(gaps) < 2 * STEADY_SAMPLES:
            return None
        values = np.array([g for _, g in gaps])
        held = float(np.median(values))
        band = max(3.0 * 1.4826 * float(np.median(np.abs(values - held))), STEADY_BAND)
        steady = np.abs(values - held) <= band
        last = next((i for i in range(len(gaps) - 1, STEADY_SAMPLES - 2, -1)
                     if steady[i - STEADY_SAMPLES + 1:i + 1].all()), None)
        if last is None or last == len(gaps) - 1:
            return None
        since = float(gaps[last][0])
        hand = next((h for s, h in reversed(tr.history) if s == since), None)
        world = compose(hand, tr.T_ho) if hand is not None else tr.world.copy()
        return since, world, list(tr.velocity)

    def _free_fall(self, tr: _Track, ahead: float = 0.0) -> tuple[np.ndarray, list[float]]:
        """Where the object is ``ahead`` seconds after the last telemetry if it has fallen freely since its grip
        went slack (or where it first met what is below it: :func:`support_below`)."""
        assert tr.slack is not None and self.stamp is not None
        since, pose, vel = tr.slack
        dt = min(max(0.0, float(self.stamp) + ahead - since), float(self.p["max_free_fall"]))
        v0 = np.array(vel[:3])
        g = np.array([0.0, 0.0, -9.81])
        ent = self.entities.get(tr.entity) or {}
        ends = [pose[:2], pose[:2] + v0[:2] * dt]  # (where it starts and where it would be: the higher support)
        floor = max(support_below(self.entities, tr.entity, xy) for xy in ends) + reach(ent.get("shape"))
        if pose[2] + v0[2] * dt + 0.5 * g[2] * dt * dt < floor:  # it meets that support first: at what time
            gap = max(0.0, float(pose[2]) - floor)  # z(t) = z0 + vz t - g t²/2 falls to the floor
            dt = min(dt, (v0[2] + math.sqrt(v0[2] ** 2 + 2 * 9.81 * gap)) / 9.81)
        out = pose.copy()
        out[:3] = pose[:3] + v0 * dt + 0.5 * g * dt * dt
        return out, [float(x) for x in (*(v0 + g * dt), *vel[3:])]

    def _loss(self, tr: _Track, gap: float, effort: float | None, fits: bool) -> str:
        if not fits:
            return "closed past the object"
        if tr.had_contact and effort is not None and effort < self.p["contact_effort"]:
            old = [g for s, g in tr.gaps if self.stamp - s >= self.p["closing_window"] - 1e-9]
            if old and old[-1] - gap > self.p["closing_margin"]:
                return "no contact force while the fingers close"
        return ""

    def _velocity(self, tr: _Track) -> list[float]:
        """The object's velocity as the hand carries it: the hand's motion over the window, with the object where
        the filter puts it in the hand now (the filter's own corrections, its first firm reading moving the
        estimate by the whole handover offset, are no motion: read as one, 17 ms after an 8 mm correction a still
        hand's object was released at 0.48 m/s)."""
        newest_s, newest_hand = tr.history[-1]
        base = tr.history[-1]
        for s, hand in reversed(tr.history):
            base = (s, hand)
            if newest_s - s >= self.p["velocity_window"] - 1e-9:
                break
        s0, hand0 = base
        span = newest_s - s0
        if span <= 0:
            return tr.velocity
        newest, pose0 = compose(newest_hand, tr.T_ho), compose(hand0, tr.T_ho)
        v = (newest[:3] - pose0[:3]) / span
        # ω from the orientation change: q_new = Δq ⊗ q_old
        w = rotation_vector(quat_mul(newest[3:], quat_conj(pose0[3:]))) / span
        return [float(x) for x in (*v, *w)]

    def _describe(self, tr: _Track) -> dict:
        P = tr.ekf.P
        return {
            "pose": [float(v) for v in tr.world],
            "position_hand": [float(v) for v in tr.ekf.x[:3, 0]],
            "covariance": [[float(P[i, j]) for j in range(3)] for i in range(3)],
            "sigma": float(math.sqrt(max(0.0, P[0, 0] + P[1, 1] + P[2, 2]))),
            "width": float(tr.ekf.x[3, 0]),
            "shape_width": tr.shape_width,
            "gap": tr.gap,
            "contact": float(tr.contact),
            "lost": tr.lost,
            "stamp": self.stamp,
        }

    # ----------------------------------------------------------- ownership
    def read(self, entity: str, attribute: str):
        tr = self.tracks.get(entity)
        if tr is not None:
            return [float(v) for v in tr.world]
        if entity in self.pending:
            return [float(v) for v in self.pending[entity]]
        raise KeyError(f"in_hand does not hold {entity}")

    def acquire(self, entity: str, attribute: str, value, extra: dict) -> None:
        world = as_pose(value if value is not None else self.entities[entity]["pose"])
        self.tracks.pop(entity, None)
        self.opening = False  # a handover to in_hand means a new grasp
        if self._hand() is None:
            self.pending[entity] = world
        else:
            self._seed(entity, world)

    def release(self, entity: str, attribute: str):
        tr = self.tracks.pop(entity, None)
        if tr is None:
            pose = self.pending.pop(entity, None)
            if pose is None:
                raise KeyError(f"in_hand does not hold {entity}")
            return [float(v) for v in pose], {"velocity": [0.0] * 6}
        ahead = max(0.0, float(self.now) - float(self.t))  # asked between two of its steps: from its last on
        if tr.slack is None and not self.opening and self._grip()[1] is None:
            tr.slack = self._departed(tr)
        if tr.slack is not None:
            pose, velocity = self._free_fall(tr, ahead)
            return [float(v) for v in pose], {"velocity": velocity, "free_fall_since": tr.slack[0]}
        return [float(v) for v in advanced(tr.world, tr.velocity, ahead)], {"velocity": list(tr.velocity)}

    # ------------------------------------------------------- stepping back
    _STATE = ("tracks", "pending", "T_wh", "_fk_stale", "q", "effort", "stamp", "_joints_key", "efforts_reported",
              "opening")
    """Everything its steps change (the kinematics it leases follows ``q`` whenever ``_fk_stale`` says so)."""

    def snapshot(self) -> dict[str, Any]:
        return copy.deepcopy({k: getattr(self, k) for k in self._STATE})

    def restore(self, state: dict[str, Any]) -> None:
        for k, v in state.items():
            setattr(self, k, v)

    def close(self) -> None:
        fk = getattr(self, "fk", None)
        if fk is not None:
            fk.give_back()  # the next run on this agent takes it (it is closed when the process ends)
            del self.fk

    # ---------------------------------------------------------- evaluators
    @evaluator("estimate", names={"entity": "entity"})
    def estimate(self, entity: str):
        tr = self.tracks.get(entity)
        return None if tr is None else self._describe(tr)

    @evaluator("holding")
    def holding(self):
        return sorted(e for e, tr in self.tracks.items() if not tr.lost)
