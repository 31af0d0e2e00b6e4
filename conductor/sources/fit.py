"""Does the robot's telemetry fit the scene's robot? Checked before the first tick, and renamed on the way.

A recording names its joints as its robot's driver did; the scene's robot block says which URDF joints
those are (``joints:``, identity by default). :func:`check_fit` compares the two sets once the map is
applied: no recorded joint is a joint of the robot -> a one-line error naming both sets and the map to
write; some arm or gripper joints missing -> a warning that the run reports (its status is then
``degraded``: the robot moves, but not all of it). :func:`rename` applies the map to one joint state.
Every joint position is also checked against the URDF's limits (:data:`LIMIT_SLACK`: far outside them, the
telemetry is in other units or of another robot) and the arm's joints against their last positions
(:data:`JUMP_M`: joint states too sparse for its motion); the run says so (degraded).
"""
from __future__ import annotations

import collections
import difflib
import logging
import math
import os
import re
from collections.abc import Iterable
from types import SimpleNamespace
from typing import Any

from protocol.errors import InputError, RunAborted, TwinError
from protocol.robot import Robot, read_urdf, resolve_robot, shipped

from .live import GAP_RECENT, GAP_S, gap_threshold

log = logging.getLogger("twin.source")


def _few(names: Iterable[str], n: int = 8) -> str:
    names = list(names)
    return ", ".join(names[:n]) + (f", ... ({len(names)} in all)" if len(names) > n else "")


def check_fit(robot: Robot, recorded: Iterable[str], where: str, rec: Any = None) -> list[str]:
    """Warnings (empty when every arm and gripper joint is reported); InputError when none is. ``recorded`` in
    the bag's order (the suggested map pairs them with the robot's joints in order). ``rec``, the recording: its
    messages left out by reason are said when no joint state is left (the error then gives the real cause), and
    its JointState topics not read when joints are missing (a gripper on a topic of its own: the --remap to merge)."""
    recorded = list(dict.fromkeys(recorded))
    matched, missing = robot.fit(recorded)
    if not recorded:
        why = "; ".join(f"{n} {reason}" for reason, n in sorted((getattr(rec, "skipped", None) or {}).items()))
        raise InputError(f"{where}: it has no usable joint states with joint names"
                         + (f" (left out: {why})" if why else "")
                         + f", so nothing moves the scene's robot {robot.name}")
    renamed = robot.rename(recorded)
    twice = sorted({n for n in renamed if renamed.count(n) > 1})
    if twice:  # (a joint state would name a joint twice: refused, message by message, as malformed)
        said = "; ".join(f"{' and '.join(r for r, n in zip(recorded, renamed, strict=True) if n == x)} would both be "
                         f"{x}" for x in twice)
        raise InputError(f"{where}: the scene's joint map gives two of its joints one name ({said}): map the one "
                         "the map leaves as it is too, or take the other out of the map")
    if not matched:
        raise InputError(f"{where}: none of its joint names ({_few(recorded)}) is a joint of the scene's robot "
                        f"{robot.name} ({_few(robot.joints, 12)}): map them in the scene's robot block, e.g. "
                        f"{suggested_map(robot, recorded)}")
    if missing:
        others = list(getattr(rec, "other_joint_topics", None) or [])
        read = list((getattr(rec, "topics", None) or {}).get("/joint_states") or ["/joint_states"])
        merge = " ".join(f"--remap /joint_states:={t}" for t in [*read, "TOPIC"])
        return [f"{where}: the robot's joints {_few(missing)} are not in the telemetry (recorded: "
                f"{_few(recorded)}); they stay where they started: "
                + (f"the bag has JointState topics it did not read ({', '.join(others)}): if one carries them (not "
                   f"a commanded or desired state), merge it with {merge}, or " if others else "")
                + "map them in the scene's robot block (joints: {recorded_name: urdf_name})"]
    return []


GRIPPER_WORDS = ("finger", "grip", "drive", "jaw", "claw", "hand")
"""Parts of a recorded joint's name that say it moves the gripper (the xArm's ``drive_joint``, ``finger_joint``)."""


def suggested_map(robot: Robot, recorded: list[str]) -> str:
    """A joint map to start from: the recording's arm joints paired with the robot's arm joints, the ones whose
    names say gripper (:data:`GRIPPER_WORDS`) with its gripper joints (never a gripper joint with an arm joint), by
    name where the names tell (:func:`paired_by_name`), the rest in order; joints one side has more of are left
    out, and a note says so when the arms differ or a pair was made by order alone."""
    grip = [n for n in recorded if any(w in n.lower() for w in GRIPPER_WORDS)]
    arm = [n for n in recorded if n not in grip]
    arm_pairs, arm_guessed = paired_by_name(arm, list(robot.arm))
    grip_pairs, _ = paired_by_name(grip, list(robot.gripper.joints))  # (fingers that mirror each other)
    pairs = arm_pairs + grip_pairs
    text = "joints: {" + ", ".join(f"{a}: {b}" for a, b in pairs) + "}"
    if len(arm) != len(robot.arm):
        text += (f" (the recording has {len(arm)} arm joint{'s' if len(arm) != 1 else ''}, the robot "
                 f"{len(robot.arm)}: check the pairs)")
    elif arm_guessed:
        text += f" ({', '.join(arm_guessed)} paired by order alone: check them)"
    return text + _unlike_joints(robot, recorded, pairs)


def paired_by_name(recorded: list[str], urdf: list[str]) -> tuple[list[tuple[str, str]], list[str]]:
    """The recorded joints paired with the URDF's (in the URDF's order) by what their names say: the same name,
    else the same name once each side's common prefix is gone (``fr3_joint3`` and ``panda_joint3``), else the same
    number at the end; what is left, in order. Also the recorded joints paired by order alone (a driver that
    publishes its joints in another order than the URDF's had every one of them paired with another joint)."""
    def rest(names: list[str]) -> dict[str, str]:
        cut = len(os.path.commonprefix(names)) if len(names) > 1 else 0
        return {n: n[cut:] for n in names}

    def number(name: str) -> str | None:
        m = re.search(r"(\d+)$", name)
        return m.group(1).lstrip("0") or "0" if m else None

    pairs: dict[str, str] = {}  # urdf joint -> recorded joint
    def numbers(names: list[str]) -> dict[str, str | None]:
        return {n: number(n) for n in names}

    for key in (lambda names: {n: n for n in names}, rest, numbers):
        left_rec = [n for n in recorded if n not in pairs.values()]
        left_urdf = [n for n in urdf if n not in pairs]
        ours, theirs = key(left_rec), key(left_urdf)
        if key is numbers and None in (*ours.values(), *theirs.values()):
            continue  # (numbers pair only names that all end in one: w1 is no joint1 beside a shoulder_pan)
        for u in left_urdf:
            k = theirs[u]
            same = [r for r in left_rec if k is not None and ours[r] == k]
            if len(same) == 1 and list(theirs.values()).count(k) == 1:
                pairs[u] = same[0]
    left_rec = [n for n in recorded if n not in pairs.values()]
    guessed = list(zip(left_rec, [n for n in urdf if n not in pairs], strict=False))
    pairs.update({u: r for r, u in guessed})
    paired = [(pairs[u], u) for u in urdf if u in pairs]
    return paired, ([r for r, _ in guessed] if len(guessed) > 1 else [])


UNITS = {"prismatic": "m"}
"""A joint type's unit in joint states (rad for the rest: revolute, continuous)."""


def _unlike_joints(robot: Robot, recorded: list[str], pairs: list[tuple[str, str]]) -> str:
    """A note on the pairs that join a revolute joint (rad) with a prismatic one (m), when the recorded joints are
    those of a shipped robot (whose URDF says their types): a joint map renames, it does not convert."""
    other = next((n for n in shipped() if n != robot.name and set(recorded) <= set(resolve_robot({"use": n}).joints)),
                 None)
    if other is None:
        return ""
    theirs = read_urdf(resolve_robot({"use": other}).urdf_file).joints
    ours = read_urdf(robot.urdf_file).joints
    unlike = [(a, b) for a, b in pairs
              if UNITS.get(theirs[a]["type"], "rad") != UNITS.get(ours[b]["type"], "rad")]
    if not unlike:
        return ""
    said = "; ".join(f"{a} is {theirs[a]['type']} ({UNITS.get(theirs[a]['type'], 'rad')}), {b} {ours[b]['type']} "
                     f"({UNITS.get(ours[b]['type'], 'rad')})" for a, b in unlike)
    return (f" (but these are the {other}'s joints and {said}: a map renames, it does not convert; a scene for that "
            f"robot says robot: {{use: {other}}})")


def rename(robot: Robot, msg: dict[str, Any]) -> dict[str, Any]:
    """A joint state with its names as the URDF's (the same dict when the robot has no joint map)."""
    if not robot.joint_map:
        return msg
    return {**msg, "name": robot.rename(list(msg["name"]))}


def recorded_joints(items: Iterable[tuple[float, str, dict[str, Any]]]) -> list[str]:
    """Every joint name a recording's joint states carry, in the order they first come."""
    out: dict[str, None] = {}
    for _, kind, m in items:
        if kind == "joint_state":
            out.update(dict.fromkeys(m["name"]))
    return list(out)


LIVE_FIT_S = 1.0
"""Seconds of a live robot's joint states whose joint names are checked against the scene's robot together: an
arm's and a gripper's driver publishing apart each name only theirs, and the first message alone would be half
the robot."""


LIMIT_SLACK = 0.25
"""A joint position further outside its URDF limits than this share of the joint's range is out of range. A robot's
driver reports positions within its limits, or a little past them where the joint gives (the MuJoCo reality's
fingers read up to 4.4 mm past their 40 mm when the ball knocks them, 11 % of the range); positions in degrees
for radians or millimetres for metres, or another robot's, are off by far more (57 or 1000 times)."""


JUMP_M = 0.04
"""An arm joint jumps when its move between two joint states could leap the hand further than this: the twin holds
the last joints until the next, so its hand leaps, and what the real hand touched on the way is not simulated
(4 cm: more than the shipped ball's 3.3 cm radius). Each joint's limit is this over its lever arm to the gripper's
tip (:func:`jump_limits`): 0.037 rad for the Panda's first joint, 0.19 for its last, whose turn barely moves the
tip. The shipped and held-out recordings (250 joint states a second) move at most 0.26 of a limit; ball_drop_00
thinned to 10 a second 2.6 times it (its answer still right), to 4 a second 6.3 times (the wrong answer,
complete, before this check). A move across a gap in the joint states (the robot stopped publishing: the source
says so, :func:`~.live.gap_threshold`) is the gap's, not a jump: said once."""


SPEED_FACTOR = 2.0
"""An arm joint moves faster than the robot can when its speed over :data:`SPEED_WINDOW_S` is more than this many
times its URDF ``<limit velocity>``: a robot's driver keeps each joint within it, so such a stream's timestamps run
fast (played back faster than it was recorded, stamped on another clock), and the twin replays the motion at that
speed. The shipped and held-out recordings reach 0.88 of the limit (their synthetic robots' fastest moves), the
limit's own margin the rest; ball_drop_00's stamps squeezed ten times reach 2.8 times it, and answered wrongly,
complete, before this check. Gripper joints are not checked: the realities drive the fingers faster than the Panda
URDF's 0.2 m/s."""
SPEED_WINDOW_S = 0.1
"""Seconds over which a joint's speed is measured (from joint state to joint state at least this far apart), and
never over a leap (said as the arm's jump): long enough that messages a recorder got late, in a burst after a
stall of its own, seldom make a speed (a 0.2 s stall made 2.0 times the limit of a 50 ms window out of a motion at
0.43 of it; of a 0.1 s window, 1.3), short enough for the fast moves of a task (over 0.25 s, ball_drop_00 squeezed
ten times reached only 1.7 times the limit)."""


def speed_limits(robot: Robot) -> dict[str, float]:
    """arm joint -> its URDF velocity limit (rad/s, m/s), for those that have a finite one."""
    urdf = read_urdf(robot.urdf_file).joints
    return {j: float(urdf[j]["velocity"]) for j in robot.arm
            if j in urdf and math.isfinite(urdf[j].get("velocity", math.inf)) and urdf[j]["velocity"] > 0}


def joint_bounds(robot: Robot) -> dict[str, tuple[float, float, float, float]]:
    """joint -> (lowest position accepted, highest accepted, lower limit, upper limit) of the robot's joints with
    finite limits (accepted: within :data:`LIMIT_SLACK` of the range past a limit)."""
    limits = read_urdf(robot.urdf_file).joints
    out = {}
    for name in robot.joints:
        j = limits.get(name)
        if j is not None and math.isfinite(j["lower"]) and math.isfinite(j["upper"]) and j["upper"] > j["lower"]:
            slack = LIMIT_SLACK * (j["upper"] - j["lower"])
            out[name] = (j["lower"] - slack, j["upper"] + slack, j["lower"], j["upper"])
    return out


def jump_limits(robot: Robot) -> dict[str, float]:
    """arm joint -> how far it may move between two joint states before the hand could leap :data:`JUMP_M` (rad; m
    for a prismatic joint). The lever arm is bounded from above by the URDF's joint offsets from it to the gripper's
    tip and the tip's offset, summed (never less than the real lever, in any posture); a joint the tip does not hang
    from (another chain) gets the limit of a lever as long as the whole arm's."""
    urdf = read_urdf(robot.urdf_file)
    by_child = {child: (name, parent, length) for name, (parent, child, length) in urdf.tree.items()}
    tip = math.sqrt(sum(float(v) ** 2 for v in robot.gripper.tip_offset))
    levers: dict[str, float | None] = {}
    for joint in robot.arm:
        lever, link = tip, robot.gripper.tip
        while link in by_child and by_child[link][0] != joint:
            lever, link = lever + by_child[link][2], by_child[link][1]
        levers[joint] = lever if link in by_child else None
    longest = max([v for v in levers.values() if v is not None] + [1.0])
    return {j: JUMP_M if urdf.joints.get(j, {}).get("type") == "prismatic" else JUMP_M / max(lever or longest, JUMP_M)
            for j, lever in levers.items()}


def telemetry_warnings(robot: Robot, rec: Any) -> list[str]:
    """What recording ``rec``'s joint positions say against ``robot``: outside its limits, an arm that jumps between
    two. Worked out once per recording and robot and kept on the recording (a replay reports it before its first
    tick, ``twin check`` before a long run; a warm service replays one recording many times)."""
    key = repr(robot)
    if key not in rec.fit_checks:
        said: list[str] = []
        fit = JointFit(robot, SimpleNamespace(rec=rec), said.extend, each=True)
        fit.logs = False  # (the run's own JointFit logs what this finds, once: it logged twice)
        for _, kind, msg in rec.items:
            if kind == "joint_state":
                fit.take(msg)
        fit.finish()
        rec.fit_checks[key] = said
    return list(rec.fit_checks[key])


def unheard_actions(triggers: Iterable[Any], rec: Any) -> list[tuple[str, bool]]:
    """A line per trigger that waits for an action recording ``rec`` never has (it would never fire), and whether
    it is a warning (``twin check`` exits 3, a replay is degraded): one of the recording's actions is close to it
    (a misspelling), or the recording has no action at all while triggers wait for some (its action topic is
    another: the String topics it did not read are named). Otherwise a note, which ``twin check`` prints and a run's
    summary keeps: a scene may have triggers for tasks this one is not, and a name close to one another trigger
    waits for under its own (``move_to_b`` beside ``move_to_a``) may be one of them."""
    ops = sorted({str(m.get("operation")) for _, kind, m in rec.items if kind == "action"})
    triggers = [t for t in triggers if t.on.get("action") is not None]
    if not ops:
        if not triggers:
            return []
        others = list(getattr(rec, "other_action_topics", None) or [])
        read = list((getattr(rec, "topics", None) or {}).get("/action") or ["/action"])
        return [(f"{rec.path}: it has no action at all on {', '.join(read)}, and triggers "
                 f"{', '.join(t.name for t in triggers)} wait for actions: they will never fire"
                 + (f" (the bag's String topics it did not read: {', '.join(others)}; "
                    f"--remap /action:={others[0]} reads one)" if others else ""), True)]
    awaited = {str(t.on["action"]) for t in triggers}
    out = []
    for trig in triggers:
        want = str(trig.on["action"])
        if want in ops:
            continue
        # a typo (relase: 0.92 alike), not a related action (open_gripper for close_gripper, movel for movej, grasp
        # for ungrasp: 0.8-0.83), nor one another trigger waits for under its own name (then said as a note)
        close = difflib.get_close_matches(want, [op for op in ops if op not in awaited], n=1, cutoff=0.85)
        near = close or difflib.get_close_matches(want, sorted(awaited & set(ops)), n=1, cutoff=0.85)
        out.append((f"{rec.path}: trigger {trig.name} waits for action {want!r}, which the bag never has"
                    + (f" (did you mean {close[0]!r}?)" if close else
                       f" (did you mean {near[0]!r}? another trigger waits for that one too)" if near else
                       f" (its actions: {', '.join(ops)})")
                    + ": it will never fire", bool(close)))
    return out


class JointFit:
    """The scene's robot between a source and the models: every joint state renamed by the robot's joint
    map, the source's joints checked against the robot once (a replay before the first tick, a live source
    over its first :data:`LIVE_FIT_S` seconds of joint states, or at its end if that came first). ``report``
    takes the warnings (the run's degraded reasons). Joint positions are checked (limits, jumps) on each joint
    state of a live source, or with ``each``; a replay's once, before its first tick (:func:`telemetry_warnings`)."""

    def __init__(self, robot: Robot | None, source: Any, report: Any, each: bool = False,
                 triggers: Iterable[Any] = (), note: Any = None) -> None:
        self.robot = robot
        self.triggers = list(triggers)  # (a replay's misspelt actions: :func:`unheard_actions`)
        self.note = note  # takes the notes (a replay's triggers that wait for an action it never has)
        self.logs = True  # whether a warning is logged as it is found, besides going to ``report``
        self.rec = getattr(source, "rec", None)
        self.report = report
        self.pending = robot is not None and source is not None and self.rec is None
        self._heard: dict[str, None] = {}  # a live source's joint names so far, in the order they came
        self._first: float | None = None  # the stamp of its first joint state
        self._early: list[str] | None = None  # the robot's joints missing after LIVE_FIT_S (None: not yet looked)
        checks = robot is not None and (each or self.rec is None)
        self._bounds = joint_bounds(robot) if robot is not None and checks else {}
        # joint -> (the position furthest out, its stamp, how many joint states had it out of range)
        self._outside: dict[str, tuple[float, float, int]] = {}
        self._t0: float | None = 0.0 if self.rec is not None else None  # (live: the first joint state's stamp)
        self._limit = jump_limits(robot) if robot is not None and checks else {}  # arm joint -> its largest move
        self._wraps = frozenset(j for j, v in (read_urdf(robot.urdf_file).joints.items() if robot is not None else ())
                                if v["type"] == "continuous")  # (reported within one turn: -pi to pi wraps)
        self._last_q: dict[str, float] = {}  # arm joint -> its last position
        self._last_stamp: float | None = None
        self._spacings: collections.deque[float] = collections.deque(maxlen=GAP_RECENT)  # (across a gap: no jump)
        self._speed = speed_limits(robot) if robot is not None and checks else {}  # arm joint -> URDF velocity
        self._anchor: dict[str, tuple[float, float]] = {}  # arm joint -> (stamp, position) its speed is measured from
        self._fast: tuple[float, str, float, float] | None = None  # (share of its limit, joint, speed, stamp): fastest
        self.too_fast = 0  # stretches of SPEED_WINDOW_S with an arm joint past SPEED_FACTOR times its limit
        self._last_jump: float | None = None  # the stamp of the last joint state with a jump
        self._jump: tuple[float, str, float, float] | None = None  # (share of its limit, joint, move, stamp): largest
        self.jumped = 0  # joint states that came with an arm joint moved past its limit

    def before_run(self) -> None:
        """A replay's joints against the robot (RunAborted when none of them is the robot's), its joint positions
        (:func:`telemetry_warnings`), and a trigger waiting for a misspelt action (:func:`unheard_actions`)."""
        if self.rec is not None:
            unheard = unheard_actions(self.triggers, self.rec)
            self._report([line for line, warn in unheard if warn])
            if self.note is not None:
                self.note([line for line, warn in unheard if not warn])
        if self.robot is not None and self.rec is not None:
            try:
                self._report(check_fit(self.robot, self.rec.joints_in_order, self.rec.path, self.rec)
                             + telemetry_warnings(self.robot, self.rec))
            except TwinError as e:
                raise RunAborted(str(e)) from None

    def _report(self, warnings: list[str]) -> None:
        for w in warnings if self.logs else ():
            log.warning("%s", w)
        self.report(warnings)

    def take(self, msg: dict[str, Any]) -> dict[str, Any]:
        """One joint state, renamed (and, the first live one, checked: reported, never fatal)."""
        if self.robot is None:
            return msg
        if self.pending:
            self._heard.update(dict.fromkeys(msg["name"]))
            self._first = msg["stamp"] if self._first is None else self._first
            if self._early is None and msg["stamp"] - self._first >= LIVE_FIT_S:
                self._early_names()
        out = rename(self.robot, msg)
        bounds, limits, last_q, jumped = self._bounds, self._limit, self._last_q, False
        if not (bounds or limits):  # (a replay: checked once, before its first tick)
            return out
        gap = self._after_gap(msg["stamp"])
        for name, q in zip(out["name"], out["position"], strict=False):
            b = bounds.get(name)
            if b is not None and not b[0] <= q <= b[1]:
                self._out_of_range(name, q, msg["stamp"])
            limit = limits.get(name)
            if limit is not None:
                before = last_q.get(name)
                move = abs(q - before) if before is not None else 0.0
                if name in self._wraps:
                    move = min(move % (2 * math.pi), 2 * math.pi - move % (2 * math.pi))
                if move > limit and not gap:
                    jumped = True
                    if self._jump is None or move / limit > self._jump[0]:
                        self._jump = (move / limit, name, move, msg["stamp"])
                last_q[name] = q
        self.jumped += jumped
        if jumped:
            self._last_jump = msg["stamp"]
        if self._speed:
            self._speeds(out["name"], out["position"], msg["stamp"], gap)
        return out

    def _speeds(self, names: list[str], positions: list[float], stamp: float, gap: bool) -> None:
        """Each arm joint's speed since the joint state :data:`SPEED_WINDOW_S` or more before (after a gap, or the
        first time, it starts from here), against :data:`SPEED_FACTOR` times its URDF limit."""
        limits, anchors, fast = self._speed, self._anchor, False
        for name, q in zip(names, positions, strict=False):
            limit = limits.get(name)
            if limit is None:
                continue
            a = anchors.get(name)
            if a is None or gap:
                anchors[name] = (stamp, q)
                continue
            span = stamp - a[0]
            if span < SPEED_WINDOW_S:
                continue
            if self._last_jump is not None and self._last_jump > a[0]:  # (a leap in it: said as the arm's jump)
                anchors[name] = (stamp, q)
                continue
            move = abs(q - a[1])
            if name in self._wraps:
                move = min(move % (2 * math.pi), 2 * math.pi - move % (2 * math.pi))
            speed = move / span
            if speed > SPEED_FACTOR * limit:
                fast = True
                if self._fast is None or speed / limit > self._fast[0]:
                    self._fast = (speed / limit, name, speed, stamp)
            anchors[name] = (stamp, q)
        self.too_fast += fast

    def _after_gap(self, stamp: float) -> bool:
        """Whether this joint state comes after a gap in the stream, as the source's own check finds one (the
        robot stopped publishing for :func:`~.live.gap_threshold`: said as a gap, so a move across it is no jump)."""
        last, self._last_stamp = self._last_stamp, stamp
        if last is None:
            return False
        spacing, spacings = stamp - last, self._spacings
        gap = spacing > GAP_S and len(spacings) >= 3 and spacing > gap_threshold(spacings)
        spacings.append(spacing)
        return gap

    def _out_of_range(self, name: str, q: float, stamp: float) -> None:
        lo, hi = self._bounds[name][2:]
        worst, at, n = self._outside.get(name, (q, stamp, 0))
        if n == 0:
            log.warning("joint %s at %g, outside its limits %g to %g (by more than a quarter of its range)",
                        name, q, lo, hi)
        far = max(lo - q, q - hi) >= max(lo - worst, worst - hi)
        self._outside[name] = (q, stamp, n + 1) if far else (worst, at, n + 1)

    def finish(self) -> None:
        """The run has ended (the conductor's summary): check a live source's joints if :meth:`take` has not yet
        (a run shorter than :data:`LIVE_FIT_S`), and report the arm's jumps (:data:`JUMP_M`), speeds past its URDF
        limits (:data:`SPEED_FACTOR`) and joint positions out of range (:data:`LIMIT_SLACK`), each once."""
        self._check_names()
        where = self.rec.path if self.rec is not None else "the live telemetry"
        t0 = self._t0 if self._t0 is not None else (self._first or 0.0)
        if self._jump is not None:
            share, name, move, at = self._jump
            n, self._jump = self.jumped, None
            self._report([f"{where}: the arm jumps between two joint states {n} time{'s' * (n > 1)}: {name} by up to "
                          f"{move:.3g} at t={at - t0:.2f} s, {share:.1f} times its limit {self._limit[name]:.3g} "
                          f"(a move that could leap the gripper's tip more than {JUMP_M * 100:g} cm): the twin holds "
                          "the last joints until the next, so its hand leaps and what the real one touched on the way "
                          "is not simulated. Joint states too sparse for the arm's speed, or two robots on one "
                          "stream?"])
        if self._fast is not None:
            share, name, speed, at = self._fast
            n, self._fast = self.too_fast, None
            unit = "m/s" if self.robot is not None and read_urdf(self.robot.urdf_file).joints[name]["type"] == \
                "prismatic" else "rad/s"
            self._report([f"{where}: the arm moves faster than the robot can, in {n} stretch{'es' * (n > 1)} of "
                          f"{SPEED_WINDOW_S * 1000:g} ms: {name} at up to {speed:.3g} {unit} at t={at - t0:.2f} s, "
                          f"{share:.1f} times its URDF velocity limit {self._speed[name]:.4g} {unit}: do its "
                          "timestamps run fast (played back faster than recorded, "
                          "or stamped on another clock)? The twin replays the motion at that speed, so what the "
                          "robot's objects did may not follow"])
        if self._outside:
            joints = "; ".join(
                f"{name} at {q:.4g} (t={at - t0:.2f} s; its limits {self._bounds[name][2]:.4g} to "
                f"{self._bounds[name][3]:.4g}) in {n} joint state{'s' * (n > 1)}"
                for name, (q, at, n) in sorted(self._outside.items())[:4])
            more = f" and {len(self._outside) - 4} more joints" if len(self._outside) > 4 else ""
            self._outside = {}
            self._report([f"{where}: joint positions far outside the robot's limits: {joints}{more}. Degrees for "
                          "radians, millimetres for metres, or another robot's joints? The twin's robot went where "
                          "it was told, so what it touched there is not what the robot touched"])

    def _early_names(self) -> None:
        """A live source's joint names against the robot after its first :data:`LIVE_FIT_S` s: none of them the
        robot's is said at once (the wrong robot, or no joint map); joints still missing are logged, and judged at
        the run's end on every name heard (a gripper's driver that started late is no missing joint)."""
        assert self.robot is not None
        self._early = []
        try:
            warnings = check_fit(self.robot, self._heard, "the live telemetry")
        except TwinError as e:
            self.pending = False
            self._report([str(e)])
            return
        for w in warnings:
            log.warning("so far: %s", w)
        self._early = self.robot.fit(list(self._heard))[1]

    def _check_names(self) -> None:
        """A live source's joint names against the robot, once, on every name heard: joints that came only after
        the first :data:`LIVE_FIT_S` s are a note."""
        if self.pending and self.robot is not None and self._heard:
            self.pending = False
            try:
                warnings = check_fit(self.robot, self._heard, "the live telemetry")
            except TwinError as e:
                warnings = [str(e)]
            self._report(warnings)
            late = [j for j in self._early or () if j not in self.robot.fit(list(self._heard))[1]]
            if late and not warnings and self.note is not None:
                self.note([f"the live telemetry: the robot's joints {_few(late)} came only after its first "
                           f"{LIVE_FIT_S:g} s of joint states (a driver that started late?): they stood where they "
                           "started until then"])
