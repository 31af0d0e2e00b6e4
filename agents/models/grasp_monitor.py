"""The grasp monitor: an observer deciding from finger telemetry whether a hand holds something.

A parallel gripper that holds an object cannot close: its fingers stop apart and press on the
object with the grip force, and they stay still. Closing on nothing, they run to the closed end
stop and the force vanishes; opening, they push outwards. So, per hand, a telemetry sample counts
as *pressing* when, on both fingers,

- the squeezing force ``effort_sign * effort`` exceeds ``effort_on`` (N),
- the finger is neither fully closed (``position > closed_position``, m) nor fully open
  (``position < open_position``: nothing wider than the hand's opening can be held),

and the fingers are still: the grip width ``q1 + q2`` changes slower than ``max_speed`` (m/s;
from the telemetry velocities, or a finite difference of the widths when the stream has none).
A sample counts as *released* when either finger's squeezing force is below ``effort_off``, either
finger is fully closed, or the width runs faster than ``max_speed`` (the object slipped out and
the fingers close on nothing, or the hand opens). The decision has hysteresis: ``samples_on``
consecutive pressing samples start a grasp, ``samples_off`` consecutive released samples end it,
and samples in between (a force between the two thresholds) keep the current decision, so sensor
noise and single-sample spikes never toggle it. Repeated samples (same stamp) are not counted.

Finger positions and forces are read through the robot's gripper geometry
(:class:`agents.robot.kinematics.GripperGeometry`, from the scene's robot block and its URDF): a finger's
*position* here is its opening (m, 0 = closed; the Panda's finger joint positions as they are, the xArm's
drive angle turned into how far each finger stands from closed), and its *effort* the finger force (N)
the gripper joint's effort makes by virtual work, negative when it squeezes. The thresholds below are
in those units, so they hold for any parallel gripper.

What the pybullet Panda produces (``franka_panda/panda.urdf``, fingers under ``POSITION_CONTROL``
with a force limit F of 20–70 N, measured at 240 Hz and 1 kHz time steps, sampled every step):

- closing on a tennis ball (r = 33 mm): both efforts settle at −F (saturated: −20.0 N at
  F = 20, −70.0 N at F = 70) with the fingers at 31.6–33.4 mm (the soft pads give 0–1.7 mm)
  and still; while the arm then swings the ball, the efforts stay at −F and the fingers shift
  together (one 23 mm, the other 40 mm: the ball slides between them, the width stays constant);
- closing on nothing: the fingers reach 0.0 mm and the efforts fall to |e| ≤ 0.2 N; during the
  first ≤ 28 ms of closing the motor saturates (−F, and up to +33 N at 1 kHz) while the fingers
  run at 0.4–3 m/s, which is what the speed condition rejects;
- opening: the efforts are positive (up to +F for ≤ 30 ms) or ~0 and drop below 0.1 N once
  open, so a sign-aware threshold never sees a grasp there.

Hence the defaults: ``effort_sign`` −1 (squeezing is a negative effort), ``effort_on`` 5 N,
``effort_off`` 2.5 N (a grasp presses with 20–70 N; an empty, still hand shows under 0.2 N;
telemetry noise is 0.1–0.5 N), ``closed_position`` 1 mm, ``max_speed`` 0.05 m/s, two samples
each way (at 15 Hz a grasp is confirmed 67–133 ms after the fingers settle). ``effort_sign`` 0
uses the effort's magnitude, for robots that report squeezing as positive or unsigned.

A stream that never carries a non-zero finger effort (a real Franka's ``joint_states`` often
report none) is handled without efforts (``use_efforts: auto``; ``always`` / ``never`` force a
choice): a sample is then pressing when the last ``move_hand`` command for the hand was
``close`` (from its start) and both fingers are still (the width also within ``steady_width``, 0.5 mm, over the
last ``steady_window``, 0.1 s: fingers closing slowly on nothing, under ``max_speed`` sample by sample, counted as
a grasp; the recordings' finger widths move by 0.1–0.2 mm at rest), neither fully closed nor fully open, and
released when a
finger is fully closed, the width runs, or the hand is commanded open / to ``release``.

Params: ``hands`` maps a hand name to its two finger joint names, read as two prismatic fingers in metres
(default: one hand, ``hand``, the scene robot's gripper through its geometry), and the thresholds above;
``open_position`` 0 means just under the gripper's own full opening. Outputs (every step):
``grasped`` (bool, the hand named ``hand``, else the first hand) and ``grasped_by_hand``
{hand: bool}. Events: ``grasp_started`` / ``grasp_lost`` {hand, width, forces}. Evaluators:
``hand_free(hand="hand")`` -> bool, ``grasped(hand="hand")`` -> bool, ``grip(hand="hand")`` ->
{grasped, width, forces, positions, efforts_used}.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from protocol.robot import resolve_robot

from ..model import Model, Param, evaluator
from ..robot.kinematics import GripperGeometry

USE_EFFORTS = ("auto", "always", "never")


@dataclass
class Hand:
    """Decision state of one hand."""

    name: str
    fingers: tuple[str, ...]  # the joints read: two prismatic fingers, or the robot gripper's joints
    geometry: GripperGeometry | None = None  # the robot's gripper (None: ``fingers`` are prismatic, in m)
    grasped: bool = False
    run_on: int = 0  # consecutive pressing samples
    run_off: int = 0  # consecutive released samples
    commanded_closed: bool = False
    width: float | None = None
    stamp: float | None = None
    forces: list[float] = field(default_factory=lambda: [0.0, 0.0])
    positions: list[float] = field(default_factory=lambda: [0.0, 0.0])
    widths: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=256))  # (stamp, width)


class GraspMonitor(Model):
    """Per-hand grasp decision from finger positions and efforts (see the module docstring)."""

    kind = "grasp_monitor"
    role = "observer"
    params = {
        "hands": Param(dict, {}, "hand name -> [finger joint 1, finger joint 2] (prismatic, m; default: the "
                                 "scene robot's gripper as the hand 'hand')"),
        "effort_on": Param(float, 5.0, "squeezing force (N) both fingers must exceed to count as pressing"),
        "effort_off": Param(float, 2.5, "squeezing force (N) under which a finger counts as released"),
        "effort_sign": Param(float, -1.0, "sign of a squeezing effort in the telemetry (0: use |effort|)"),
        "closed_position": Param(float, 0.001, "a finger at or below this position (m) is fully closed"),
        "open_position": Param(float, 0.0, "a finger at or above this opening (m) is fully open (0: 0.5 mm under "
                                           "the gripper's full opening)"),
        "max_speed": Param(float, 0.05, "grip width speed (m/s) above which the fingers are moving"),
        "steady_window": Param(float, 0.1, "without efforts: the span (s) over which the grip width must stay..."),
        "steady_width": Param(float, 0.0005, "... within this (m) for the fingers to count as pressing on something"),
        "samples_on": Param(int, 2, "consecutive pressing samples that start a grasp"),
        "samples_off": Param(int, 2, "consecutive released samples that end a grasp"),
        "use_efforts": Param(str, "auto", "auto | always | never: decide from efforts, or from positions and commands",
                             choices=USE_EFFORTS),
    }
    outputs = ("grasped", "grasped_by_hand")
    events = ("grasp_started", "grasp_lost")

    def init(self, params: dict, scene: dict) -> None:
        self.prm = params
        if params["use_efforts"] not in USE_EFFORTS:
            raise ValueError(f"use_efforts must be one of {', '.join(USE_EFFORTS)}, got {params['use_efforts']!r}")
        if not params["effort_off"] < params["effort_on"]:
            raise ValueError("effort_off must be below effort_on (hysteresis)")
        hands = params["hands"] or {}
        self.hands: dict[str, Hand] = {}
        self.open_position = float(params["open_position"])
        for name, fingers in hands.items():
            if not isinstance(fingers, (list, tuple)) or len(fingers) != 2:
                raise ValueError(f"hands.{name} must list two finger joint names, got {fingers!r}")
            self.hands[name] = Hand(name, (str(fingers[0]), str(fingers[1])))
        if not hands:
            geo = GripperGeometry.of(resolve_robot(scene.get("robot") or None))
            self.hands["hand"] = Hand("hand", geo.gripper.joints, geo)
            if not self.open_position:
                self.open_position = min(geo.open_opening) - 0.0005
        elif not self.open_position:
            self.open_position = 0.0395  # prismatic fingers of a Panda-sized hand (4 cm stroke)
        self.main_hand = "hand" if "hand" in self.hands else next(iter(self.hands))
        self.efforts_seen = False
        self._names: list | None = None
        self._index: dict[str, tuple[int, ...] | None] = {}

    # ------------------------------------------------------------------ step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        for a in telemetry.get("actions") or ():
            self._command(a)
        js = telemetry.get("joints")
        if js is not None:
            self._sample(js)
        self.output("grasped", self.hands[self.main_hand].grasped)
        self.output("grasped_by_hand", {n: h.grasped for n, h in self.hands.items()})

    def _command(self, action: dict) -> None:
        op, phase = action.get("operation"), action.get("phase")
        params = action.get("params") or {}
        hand = params.get("hand")
        targets = [self.hands[hand]] if hand in self.hands else list(self.hands.values())
        if op == "move_hand" and phase == "start" and params.get("command") in ("close", "open"):
            for h in targets:
                h.commanded_closed = params["command"] == "close"
        elif op == "release" and phase == "start":
            for h in targets:
                h.commanded_closed = False

    def _sample(self, js: dict) -> None:
        """Take one joint state: per hand (each sample once), its grip reading, then the decision."""
        names = js.get("name") or []
        if names != self._names:
            self._reindex(names)
        position, velocity, effort = js.get("position") or [], js.get("velocity") or [], js.get("effort") or []
        stamp = js.get("stamp")
        n = len(names)
        for h in self.hands.values():
            ij = self._index.get(h.name)
            if ij is None or (stamp is not None and stamp == h.stamp):
                continue
            q, rates, forces = self._reading(h, ij, position, velocity if len(velocity) == n else [],
                                             effort if len(effort) == n else [])
            width = q[0] + q[1]
            speed = abs(rates[0] + rates[1]) if rates is not None else self._speed(h, width, stamp)
            h.stamp, h.width, h.forces, h.positions = stamp, width, forces, q
            if stamp is not None:
                h.widths.append((float(stamp), width))
            self._decide(h, *self._judge(h, q, forces, speed))

    def _reading(self, h: Hand, ij: tuple[int, ...], position: list, velocity: list,
                 effort: list) -> tuple[list[float], tuple[float, float] | None, list[float]]:
        """One hand's sample: finger openings (m), their speeds (m/s; None without velocities) and squeezing
        forces (N, ``effort_sign`` applied; zeros without efforts). A non-zero effort tells ``use_efforts:
        auto`` that the stream carries efforts."""
        if h.geometry is None:  # two prismatic fingers in metres
            q = [float(position[ij[0]]), float(position[ij[1]])]
            rates = (float(velocity[ij[0]]), float(velocity[ij[1]])) if velocity else None
            e = [float(effort[ij[0]]), float(effort[ij[1]])] if effort else [0.0, 0.0]
        else:
            qs = {j: float(position[i]) for j, i in zip(h.fingers, ij, strict=True)}
            q = list(h.geometry.openings(qs))
            rates = h.geometry.rates(qs, {j: float(velocity[i]) for j, i in zip(h.fingers, ij, strict=True)}) \
                if velocity else None
            e = list(h.geometry.forces(qs, {j: float(effort[i]) for j, i in zip(h.fingers, ij, strict=True)})) \
                if effort else [0.0, 0.0]
        if e[0] != 0.0 or e[1] != 0.0:
            self.efforts_seen = True
        sign = float(self.prm["effort_sign"])
        return q, rates, [sign * x if sign else abs(x) for x in e]

    def _reindex(self, names: list) -> None:
        """Where each hand's joints are in the joint states (None: not all there)."""
        self._names = list(names)
        pos = {n: i for i, n in enumerate(names)}
        self._index = {h.name: (tuple(pos[f] for f in h.fingers) if all(f in pos for f in h.fingers) else None)
                       for h in self.hands.values()}

    @staticmethod
    def _speed(h: Hand, width: float, stamp: float | None) -> float:
        """How fast the grip width changes (m/s) without velocities in the stream: the finite difference to
        the hand's last sample (0 for the first one)."""
        if h.width is not None and h.stamp is not None and stamp is not None and stamp > h.stamp:
            return abs(width - h.width) / (stamp - h.stamp)
        return 0.0

    def _efforts_used(self) -> bool:
        mode = self.prm["use_efforts"]
        return mode == "always" or (mode == "auto" and self.efforts_seen)

    def _judge(self, h: Hand, q: list[float], forces: list[float], speed: float) -> tuple[bool, bool]:
        """(pressing, released) for one sample of a hand (see the module docstring)."""
        p = self.prm
        closed = min(q) <= p["closed_position"]
        apart = not closed and max(q) < self.open_position
        moving = speed > p["max_speed"]
        if self._efforts_used():
            return (apart and not moving and min(forces) > p["effort_on"],
                    closed or moving or min(forces) < p["effort_off"])
        return (h.commanded_closed and apart and not moving and self._steady(h),
                closed or moving or not h.commanded_closed)

    def _steady(self, h: Hand) -> bool:
        """Without efforts: the grip width has stayed within ``steady_width`` over the last ``steady_window`` s, as
        fingers stopped by an object do (a held ball moves it by under 1 mm/s). Fingers closing slowly on nothing
        (a Franka grasp at 20 mm/s a finger) ran under ``max_speed`` sample by sample and counted as a grasp."""
        p, widths = self.prm, h.widths
        if not widths:
            return False
        now, window = widths[-1][0], float(p["steady_window"])
        if now - widths[0][0] < window - 1e-9:
            return False  # (not yet that long a history: nothing says the fingers stopped)
        lo = hi = widths[-1][1]
        for s, w in reversed(widths):
            if now - s > window + 1e-9:
                break
            lo, hi = min(lo, w), max(hi, w)
        return hi - lo <= p["steady_width"]

    def _decide(self, h: Hand, pressing: bool, released: bool) -> None:
        """Hysteresis: a run of ``samples_on`` pressing samples starts a grasp, a run of
        ``samples_off`` released samples ends it; anything else breaks the runs."""
        h.run_on = h.run_on + 1 if pressing else 0
        h.run_off = h.run_off + 1 if released else 0
        if not h.grasped and h.run_on >= int(self.prm["samples_on"]):
            h.grasped = True
            h.run_off = 0
            self.emit("grasp_started", hand=h.name, width=h.width, forces=list(h.forces))
        elif h.grasped and h.run_off >= int(self.prm["samples_off"]):
            h.grasped = False
            h.run_on = 0
            self.emit("grasp_lost", hand=h.name, width=h.width, forces=list(h.forces))

    # ------------------------------------------------------------- evaluators
    def _hand(self, hand: str) -> Hand:
        h = self.hands.get(hand)
        if h is None:
            raise KeyError(f"unknown hand {hand!r} (hands: {', '.join(self.hands)})")
        return h

    @evaluator("hand_free")
    def hand_free(self, hand: str = "hand") -> bool:
        """True when the hand holds nothing."""
        return not self._hand(hand).grasped

    @evaluator("grasped")
    def is_grasped(self, hand: str = "hand") -> bool:
        """True when the hand holds something."""
        return self._hand(hand).grasped

    @evaluator("grip")
    def grip(self, hand: str = "hand") -> dict:
        """The hand's decision and the last sample it was taken from."""
        h = self._hand(hand)
        return {"grasped": h.grasped, "width": h.width, "forces": list(h.forces), "positions": list(h.positions),
                "efforts_used": self._efforts_used()}
