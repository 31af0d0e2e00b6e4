"""Live telemetry from the network: a robot (or ``twin robot play``) publishing on ``telemetry/**``."""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from protocol import codec
from protocol.errors import ProtocolError, RunAborted
from protocol.geometry import finite_numbers
from protocol.joints import fill_unknown, unknown_fields

log = logging.getLogger("twin.source")

GAP_S = 0.5
"""Joint states further apart than this on the robot's clock, and than :data:`GAP_PERIODS` of their own usual
spacing, are a gap: the robot stopped publishing (a restart, a stall), and the twin held its last joints
meanwhile. (A network stall delays messages; it does not space their stamps.)"""
GAP_PERIODS = 5
"""A robot that publishes its joint states twice a second spaces them 0.5 s apart by design: a gap is this many of
its usual spacings (the median of the last :data:`GAP_RECENT`) as well as :data:`GAP_S`, several messages missing
in a row, not one stamp's jitter at a slow rate."""
GAP_RECENT = 64
"""Joint states whose spacings make a live stream's usual one (its median)."""
SLOW_JOINTS_S = 0.1
"""Joint states usually further apart than this (fewer than ten a second) are said in a note: the twin holds the
robot's last joints between two of them, so its robot moves in steps of up to this long (an arm at 2 rad/s, a
fifth of a radian), and what touched what in between rests on that."""

BEHIND_S = 0.5
"""A message stamped this much before the one of its kind before it is left out: a robot started again from its
beginning, or a clock stepped back (a little out of order, from two publishers, is taken)."""
AHEAD_S = 1.0
"""A message stamped this much further after the one of its kind before it than the time between their arrivals
is left out: its clock jumped forward, and taken it would hold back every message after it."""
STEP_CONFIRM = 5
"""Joint states in a row stamped far ahead (:data:`AHEAD_S`) and in step with one another: the robot's clock
stepped forward (an NTP step) and stays there. They and every message after are taken that much earlier, by when
they came (left out, every one to the end of the run was). Fewer, or out of step with one another, are left out
as stamped far ahead: one bad stamp, or two robots on one stream."""
OTHER_CLOCK_S = 60.0
"""A robot whose first stamp is this far from this host's clock stamps by another (sim time, a clock never set): the
twin's lag is counted from how far apart the two were at its first message."""
RATE_SPAN_S = 2.0
"""Seconds of joint states over which the robot's clock rate is judged against this host's (:data:`RATE_SLACK`)."""
RATE_SLACK = 0.2
"""A robot's clock going more than this share faster or slower than this host's is said (a sim-time robot); less is
the network's jitter over :data:`RATE_SPAN_S` and a clock's drift."""
PENDING_MAX = 1000
"""Messages stamped far ahead held until they make a clock step or not (beyond this, left out at once)."""
AHEAD_WHY = "stamped far ahead of when it came (a clock that jumped forward)"
Held = list[tuple[str, dict[str, Any], float]]  # messages held as maybe a clock step: (kind, message, arrival)
LOG_WAITING = 200_000
"""Messages kept for the run log until it opens (:meth:`LiveSource.log_to`): a robot may publish while the agents
start and register (at 1 kHz, 200 s of joint states); those after this many are counted and said."""


_PLURALS = ("joint states", "action annotations", "actions", "messages")


def counted(n: int, reason: str) -> str:
    """``n`` and a reason that begins with a plural noun ("joint states with ..."): singular for one."""
    if n == 1:
        for noun in _PLURALS:
            if reason.startswith(noun + " ") or reason == noun:
                return f"1 {noun[:-1]}{reason[len(noun):]}"
    return f"{n} {reason}"


def filled_note(n: int, why: str) -> str:
    """The note on ``n`` joint states whose NaN velocities or efforts were filled
    (:func:`protocol.joints.fill_unknown`): they do not make a run degraded, the positions being whole."""
    return f"{counted(n, why)}: each taken from the joint state before, or left out (the positions are whole)"


def slow_joints_note(spacings: Iterable[float]) -> list[str]:
    """A note for joint states that come slower than :data:`SLOW_JOINTS_S` apart (empty otherwise)."""
    usual = sorted(spacings)
    if len(usual) < 3 or usual[len(usual) // 2] <= SLOW_JOINTS_S:
        return []
    every = usual[len(usual) // 2]
    return [f"its joint states come every {every:.2f} s ({1 / every:.3g} a second): the twin holds the robot's last "
            "joints between two of them, so its robot moves in steps"]


def _by_sender(sent: float | None, mapped: float) -> float:
    """A stamp for a message without one: ``sent``, its sender's clock, where it agrees with ``mapped`` (the robot's
    clock as the twin follows it) within :data:`BEHIND_S`; else ``mapped``."""
    return sent if sent is not None and abs(sent - mapped) <= BEHIND_S else mapped


def gap_threshold(spacings: Iterable[float]) -> float:
    """How far apart two joint states must be to be a gap, given the spacings of those before them."""
    usual = sorted(spacings)
    return max(GAP_S, GAP_PERIODS * usual[len(usual) // 2]) if usual else GAP_S


class ActionTally:
    """The robot's actions as they begin and end, for the task cut at either end (a live run's and a replay's): an
    end whose start never came (the stream began in the middle of the task) counts only from a robot that annotates
    its actions' starts, and actions begun that never end only from one that annotates their ends."""

    def __init__(self) -> None:
        self.begun: dict[str, float] = {}  # operation -> stamp of an action begun and not yet ended
        self.starts = self.ends = 0
        self.orphan: tuple[str, float] | None = None  # (operation, stamp): the first action ended, never begun

    def take(self, op: str, phase: Any, stamp: float) -> None:
        if phase == "end":
            self.ends += 1
            if self.begun.pop(op, None) is None and self.orphan is None:
                self.orphan = (op, stamp)
        else:
            self.starts += 1
            self.begun[op] = stamp

    def late_start(self) -> tuple[str, float] | None:
        """(operation, stamp) of the first action that ended without its start, from a robot that says starts."""
        return self.orphan if self.starts else None

    def never_ended(self) -> dict[str, float]:
        """operation -> stamp of the actions begun and never ended, from a robot that says ends."""
        return dict(self.begun) if self.ends else {}


class LiveSource:
    """Telemetry from ``twin/<ensemble>/telemetry/**`` (a robot or ``twin robot play``).

    Samples are queued as they arrive and taken in order, each at its own time: tick *t* takes every message
    whose stamp is at most *t* after the first message's (the stamps are the robot's clock). The conductor
    paces a live run by the wall clock, so it never runs ahead of the robot; when the machine is slower than
    the robot, messages wait in the queue and the twin falls behind, which its lag shows (``lag_stats``),
    but nothing is skipped: every joint state and every action reaches the models at the tick it belongs to.

    What the twin cannot use is left out and counted (:meth:`warnings`, which make the run degraded): messages
    that are not the protocol's or hold values that are not finite numbers, stamps out of step with the stream
    (:data:`BEHIND_S`, :data:`AHEAD_S`); so are gaps in the joint states (:data:`GAP_S`) and an action the robot
    began and never ended before it went quiet. A live run ends when the robot has been quiet for
    ``idle_timeout`` seconds, which :meth:`notes` says: a robot that finished and one that died look the same.

    The run log takes the robot's messages from this source (:meth:`log_to`), every one as it came, those that
    came before the run log opened included: a subscription of its own, declared when the conductor starts
    serving, missed what the robot published while the agents started.
    """

    live = True

    def __init__(self, session: Any, keys: Any, idle_timeout: float = 3.0, wait_first: float = 30.0) -> None:
        self._init_state(idle_timeout, wait_first)
        self._log_waiting: collections.deque[tuple[str, bytes, int]] | None = collections.deque()
        self.where = keys.telemetry("**")
        self._own = keys.telemetry("")  # (the run log may file telemetry under another ensemble: twin serve's)
        self._sub = session.declare_subscriber(self.where, self._on_sample)

    def _init_state(self, idle_timeout: float, wait_first: float) -> None:
        """The queue, counters and pacing state (shared with sources that subscribe elsewhere)."""
        self._lock = threading.Lock()
        self._q: collections.deque[tuple[str, dict[str, Any]]] = collections.deque()
        self.malformed = 0
        self.lags: list[float] = []
        self.backlog_max = 0  # the most messages that ever waited for their tick
        self.idle_timeout = idle_timeout
        self.wait_first = wait_first
        self._last_arrival: float | None = None
        self._t0: float | None = None  # the first message's stamp: the run's time 0
        self.on_t0: Callable[[float], None] | None = None  # told it once it is known (the run log's origin)
        self.duration = float("inf")
        self.where = "the robot's topics"
        self.left_out: collections.Counter[str] = collections.Counter()  # why -> how many messages
        self.partial: collections.Counter[str] = collections.Counter()  # joint states with NaN efforts... filled
        self.gaps: list[tuple[float, float]] = []  # (stamp where the joint states stopped, for how long)
        self.frozen: list[tuple[float, float]] = []  # (stamp the joint states repeated, for how long they came so)
        # (first, last arrival) of the last joint state's stamp as it repeats, and whether the robot acted meanwhile
        self._repeat: tuple[float, float, bool] | None = None
        self._spacings: collections.deque[float] = collections.deque(maxlen=GAP_RECENT)  # of the last joint states
        self._last: dict[str, tuple[float, float]] = {}  # kind -> (stamp, arrival) of the last message taken
        self._first: float | None = None  # the first stamp taken
        self.first_arrival: float | None = None  # when it came (monotonic): a live run's pace counts from there
        self._clock_gap = 0.0  # this host's clock less the robot's, when the robot's is another (OTHER_CLOCK_S)
        self._latest = -math.inf  # the latest stamp queued, and how far one queued after it came before it
        self._disorder = 0.0
        self._offset = 0.0  # seconds taken off every stamp since the robot's clock stepped forward
        self.steps: list[tuple[float, float]] = []  # (stamp where, seconds) the robot's clock stepped forward
        self._unclocked = 0  # joint states without a stamp before the robot's first stamped one
        self._clocked = False  # a joint state stamped by the robot's own clock has come
        self.clock_joined: tuple[float, int] | None = None  # (where, after how many unstamped) its clock came in
        self._pending: Held = []  # stamped far ahead, held as maybe a clock step
        self._early: Held = []  # without a stamp (actions), come before any joint state: stamped by the first
        self.queued: collections.Counter[str] = collections.Counter()  # kind -> messages taken for their ticks
        self._actions = ActionTally()
        self._before: dict[str, Any] | None = None  # the last joint state heard (its efforts fill a NaN one's)
        self.ended_quiet = False
        # what this source's own subscription hears, kept for the run log until it opens (None: it logs nothing)
        self._log_waiting = None
        self._log: Callable[[str, bytes, int], None] | None = None
        self._log_lock = threading.Lock()
        self.log_missed = 0  # messages that came before the run log opened and did not fit in LOG_WAITING
        self._relay: tuple[Any, Any, dict[str, Any]] | None = None  # (session, keys, publishers): relay_to

    def relay_to(self, session: Any, keys: Any) -> None:
        """Put each message the run takes on ``keys``' telemetry too, at its tick: the run's agents are on another
        ensemble than the robot (twin serve's pools), and a clock-driven or free-running model that wants
        telemetry hears it there, not in its step messages."""
        self._relay = (session, keys, {})

    def log_to(self, take: Callable[[str, bytes, int], None] | None, telemetry: str | None = None) -> bool:
        """Hand every message this source hears to ``take(key, payload, wall ns when it came)`` from now on, those
        that came before first, in order, each under ``telemetry`` (the run log's ``twin/<ensemble>/telemetry/``)
        if given; ``take`` None: there is no run log, keep nothing for one. False when this source does not hear
        the robot on a subscription of its own (a ROS 2 attach republishes what it takes: the run log's
        subscription hears that)."""
        with self._log_lock:
            waiting, self._log_waiting = self._log_waiting, None
            if waiting is None or take is None:
                return False
            own, moved = self._own, (telemetry if telemetry not in (None, self._own) else None)

            def handed(key: str, payload: bytes, t_ns: int) -> None:
                take(moved + key[len(own):] if moved is not None and key.startswith(own) else key, payload, t_ns)

            for item in waiting:
                handed(*item)
            self._log = handed
            return True

    def close(self) -> None:
        """Stop hearing the robot (a warm service's runs come and go on one session: the subscription of a
        finished run went on filling its queue, and its run log's, as long as the robot published)."""
        with self._log_lock:
            self._log, self._log_waiting = None, None
        sub, self._sub = self._sub, None
        relay, self._relay = self._relay, None
        for decl in [sub, *(relay[2].values() if relay is not None else ())]:
            if decl is not None:
                try:
                    decl.undeclare()
                except Exception:  # (a session closed already)
                    pass

    def _to_log(self, key: str, payload: bytes) -> None:
        with self._log_lock:
            if self._log is not None:
                self._log(key, payload, time.time_ns())
            elif self._log_waiting is not None:
                if len(self._log_waiting) < LOG_WAITING:
                    self._log_waiting.append((key, payload, time.time_ns()))
                else:
                    self.log_missed += 1

    def _on_sample(self, sample) -> None:
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        self._to_log(key, payload)  # every message, those the twin cannot use too: the log shows what came
        try:
            msg = codec.decode(key, payload, ("joint_state", "action"))
        except ProtocolError as e:
            filled = self._filled(key, payload)
            if filled is None:
                self._leave_out("malformed (not the protocol's, or values that are not finite numbers)", e)
                return
            self._admit("joint_state", filled)
            return
        if msg.mtype == "joint_state":
            self._before = msg
        self._admit(msg.mtype, dict(msg))

    def _filled(self, key: str, payload: bytes) -> dict[str, Any] | None:
        """A joint state whose only fault is NaN (or infinite) velocities or efforts, those filled from the joint state
        before, as a ROS 2 robot's and a replay's are (:func:`~protocol.joints.fill_unknown`): the positions still
        say where the robot is (every such message was left out, the twin's robot frozen). None for anything else."""
        try:
            obj = codec.unpack(payload)
        except Exception:
            return None
        if not isinstance(obj, dict) or obj.get("type") != "joint_state":
            return None
        fields = [f for f in ("velocity", "effort") if isinstance(obj.get(f), list) and not finite_numbers(obj[f])]
        try:
            codec.check_fields(key, "joint_state", {**obj, **{f: [] for f in fields}})
        except ProtocolError:
            return None
        if not fields or not all(isinstance(v, (int, float)) for f in fields for v in obj[f]):
            return None
        return self._fill(dict(obj))

    def _fill(self, msg: dict[str, Any]) -> dict[str, Any]:
        """``msg`` (a joint state of whole positions) with its NaN velocities or efforts filled from the joint state
        before (:func:`~protocol.joints.fill_unknown`), counted in :attr:`partial`; it is the next one's before."""
        bad = unknown_fields(msg)
        if bad:
            fill_unknown(msg, self._before)
            with self._lock:
                self.partial[f"joint states with NaN or infinite {' and '.join(bad)}"] += 1
        self._before = msg
        return msg

    @property
    def t0(self) -> float | None:
        """The stamp of the run's time 0 (its first message's; None before one is taken), on the run's clock: the
        robot's, less what :meth:`robot_time` adds back."""
        return self._t0

    def robot_time(self, t: float) -> float | None:
        """The robot's own clock at the run's time ``t``, as it stamps its messages (None before time 0 is known):
        a clock that stepped forward, or a sim-time node's clock that began after stamps of 0, is taken that much
        earlier on the run's clock (``_offset``), which this adds back."""
        return None if self._t0 is None else self._t0 + t + self._offset

    def _leave_out(self, why: str, detail: object) -> None:
        with self._lock:
            self.malformed += 1
            self.left_out[why] += 1
        log.warning("telemetry left out, %s: %s", why, detail)

    def _admit(self, kind: str, msg: dict[str, Any], now: float | None = None) -> bool:
        """Queue one checked message for its tick, unless its stamp is out of step with the stream (then it is
        left out and counted, or held as maybe the start of a clock step: :data:`STEP_CONFIRM`); note a gap before
        it and the actions begun. Whether it was queued. Every message counts as the robot speaking (one left out
        too: a robot whose clock stepped back was taken for quiet and its run ended)."""
        now = time.monotonic() if now is None else now
        left: list[tuple[str, str]] = []  # (why, what) left out
        with self._lock:
            self._last_arrival = now
            unstamped = msg.get("stamp") is None
            if unstamped and kind != "joint_state" and self._last.get("joint_state") is None \
                    and len(self._early) < PENDING_MAX:
                self._early.append((kind, msg, now))  # (stamped by the first joint state, on the robot's clock)
                return True
            if unstamped:
                msg = {k: v for k, v in msg.items() if k != "sent"} | {"stamp": self._robot_time(msg.get("sent"), now)}
            if kind == "joint_state" and not self._clocked:
                self._join_clock(unstamped, float(msg["stamp"]), now)
            if kind == "joint_state" and msg.get("name") and not msg.get("position"):
                left.append(("joint states without positions (velocities or efforts alone: the twin moves its "
                             "robot by the positions)", f"joint_state stamped {msg['stamp']}"))
                taken = False
            else:
                for k, m, came in self._stamp_early(float(msg["stamp"]), now):
                    self._take_in(k, m, came, left)
                taken = self._take_in(kind, msg, now, left)
        for why, what in left:
            self._leave_out(why, what)
        return taken

    def _stamp_early(self, stamp: float, now: float) -> Held:
        """The messages without a stamp that came before the first joint state (an action annotation), stamped on
        its clock (``stamp``, come at ``now``) by how long before it they came, or by their sender's clock where that
        agrees within :data:`BEHIND_S`: stamped by the sender's wall clock as they came, a robot on sim time set the
        run's time 0 on the wall clock, every joint state was taken at once and its action's end left out as behind
        its start."""
        early, self._early = self._early, []
        out: Held = []
        for kind, msg, came in early:
            out.append((kind, {k: v for k, v in msg.items() if k != "sent"}
                        | {"stamp": _by_sender(msg.get("sent"), stamp - (now - came))}, came))
        return out

    def _robot_time(self, sent: float | None, now: float) -> float:
        """A stamp for a message without one of its own (a ROS 2 action annotation, a JointState whose header
        says 0), on the robot's clock: the last joint state's stamp and the time since it came. ``sent``, the
        sender's clock when it sent the message (ROS 2's source timestamp, its wall clock), when it agrees with
        that within :data:`BEHIND_S`; before any joint state, ``sent`` or this host's clock. (A robot on sim time
        stamps its joint states by the simulation: its actions stamped by the wall clock were left out.)"""
        last = self._last.get("joint_state")
        if last is None:
            return sent if sent is not None else time.time()
        return _by_sender(sent, last[0] + self._offset + (now - last[1]))

    def _join_clock(self, unstamped: bool, stamp: float, now: float) -> None:
        """Count the joint states without a stamp of their own before the robot's first stamped one; when that one
        comes, on another clock than they were given (a ROS 2 node on sim time stamps 0 until its first ``/clock``),
        take its clock to go on from them: its stamps were left out, each far behind the ones before it."""
        if unstamped:
            self._unclocked += 1
            return
        last = self._last.get("joint_state")
        self._clocked = True
        if last is None or not self._unclocked:
            return
        going_on = last[0] + (now - last[1])  # where the run's time has got to since the last one came
        if abs(stamp - self._offset - going_on) > BEHIND_S:
            self._offset = stamp - going_on
            self.clock_joined = (going_on, self._unclocked)
            log.warning("the robot's first %d joint states had no stamp; its stamps from %.3f on are on another clock: "
                        "they are taken to go on from the unstamped ones", self._unclocked, stamp)

    def _take_in(self, kind: str, raw: dict[str, Any], now: float, left: list[tuple[str, str]]) -> bool:
        """:meth:`_admit` under the lock, and again for the held messages of a clock step once it is one."""
        msg = {**raw, "stamp": float(raw["stamp"]) - self._offset} if self._offset else raw
        stamp = float(msg["stamp"])
        out: Held = []  # held messages that turned out no clock step
        taken, why = self._admit_locked(kind, msg, stamp, now, out)
        if why is not None and why.startswith("stamped far ahead"):
            why, again = self._hold(kind, raw, stamp, now, out)
            for k, m, t in again:
                taken = self._take_in(k, m, t, left) or taken
        left += [(AHEAD_WHY, f"{k} stamped {float(m['stamp']) - self._offset:.3f}") for k, m, _ in out]
        if why is not None:
            left.append((why, f"{kind} stamped {stamp:.3f}"))
        return taken

    def _hold(self, kind: str, raw: dict[str, Any], stamp: float, now: float,
              out: Held) -> tuple[str | None, Held]:
        """Hold a message stamped far ahead (its reason back if it is left out at once), and the held messages to
        take again when it is the :data:`STEP_CONFIRM`-th joint state of a clock step (the offset then set)."""
        same = [(m, t) for k, m, t in self._pending if k == kind]
        if same:  # in step with the one held before it, or what was held is no clock step
            was, arrived = float(same[-1][0]["stamp"]) - self._offset, same[-1][1]
            if stamp < was - BEHIND_S or stamp - was > (now - arrived) + AHEAD_S:
                out += self._pending
                self._pending = []
        if len(self._pending) >= PENDING_MAX:
            return AHEAD_WHY, []
        self._pending.append((kind, raw, now))
        joints = [(m, t) for k, m, t in self._pending if k == "joint_state"]
        last = self._last.get("joint_state")
        if len(joints) < STEP_CONFIRM or last is None:
            return None, []
        first, arrived = float(joints[0][0]["stamp"]) - self._offset, joints[0][1]
        jump = (first - last[0]) - (arrived - last[1])
        self._offset += jump
        self.steps.append((last[0], jump))
        again, self._pending = self._pending, []
        log.warning("the robot's clock stepped forward %.3f s: its stamps are taken that much earlier", jump)
        return None, again

    def _admit_locked(self, kind: str, msg: dict[str, Any], stamp: float, now: float,
                      out: Held) -> tuple[bool, str | None]:
        """:meth:`_admit` under the lock: whether ``msg`` was queued, else why not. A joint state taken ends what
        was held as maybe a clock step (into ``out``: left out)."""
        last = self._last.get(kind)
        if last is not None and stamp < last[0] - BEHIND_S:
            return False, "stamped before the message before it (a robot started again, or its clock stepped back)"
        ahead = last or self._last.get("joint_state")  # (a first action on another clock held the queue back)
        if ahead is not None and stamp - ahead[0] > (now - ahead[1]) + AHEAD_S:
            return False, AHEAD_WHY
        if kind == "joint_state" and self._pending:
            out += self._pending
            self._pending = []
        if kind == "joint_state" and last is not None and stamp == last[0]:
            # the last joint state again (a frozen driver republishing it): its stamp's arrival stays that of its
            # first coming, or the stamps after the driver thaws would look far ahead of it
            first, _, acting = self._repeat or (last[1], now, bool(self._actions.begun))
            self._repeat = first, now, acting
            self._q.append((kind, msg))
            self.queued[kind] += 1
            self._last_arrival = now
            return True, None
        if kind == "joint_state" and last is not None:
            spacing = stamp - last[0]
            frozen = self._thawed(last[0])
            # (until three spacings are known the robot's rate is not: its first few are no gap)
            if not frozen and spacing > GAP_S and len(self._spacings) >= 3 and spacing > gap_threshold(self._spacings):
                self.gaps.append((last[0], spacing))
            self._spacings.append(spacing)
        elif kind == "action":
            self._actions.take(str(msg.get("operation")), msg.get("phase"), stamp)
            if self._repeat is not None:
                self._repeat = (*self._repeat[:2], True)
        self._last[kind] = (stamp, now)
        self._latest = max(self._latest, stamp)
        self._disorder = max(self._disorder, self._latest - stamp)
        if self._first is None:
            self._first, self.first_arrival = stamp, now
            apart = time.time() - stamp  # (a robot on sim time, or a clock of its own: lag counts from its first)
            self._clock_gap = apart if abs(apart) > OTHER_CLOCK_S else 0.0
        self._q.append((kind, msg))
        self.queued[kind] += 1
        self._last_arrival = now
        return True, None

    def _thawed(self, stamp: float) -> bool:
        """The joint states' stamp moved on from ``stamp``: whether it had repeated for more than :data:`GAP_S` (a
        frozen driver: the stop in the stamps is that, not a gap; noted if the robot acted meanwhile, as for a
        recording: an idle gripper's driver may republish its state)."""
        span, self._repeat = self._repeat, None
        if span is None or span[1] - span[0] <= GAP_S:
            return False
        if span[2]:
            self.frozen.append((stamp, span[1] - span[0]))
        return True

    def _frozen_warning(self, t0: float) -> list[str]:
        with self._lock:
            frozen, span, last = list(self.frozen), self._repeat, self._last.get("joint_state")
        if span is not None and span[2] and span[1] - span[0] > GAP_S and last is not None:  # (frozen to the end)
            frozen.append((last[0], span[1] - span[0]))
        if not frozen:
            return []
        at, longest = max(frozen, key=lambda f: f[1])
        n = len(frozen)
        return [f"the robot's joint states repeated one stamp {n} time{'s' * (n > 1)} for more than {GAP_S:g} s (the "
                f"longest {longest:.2f} s from t={at - t0:.2f} s) while they went on coming and the robot acted: a "
                "driver republishing its last message? The twin's robot stood still there"]

    def warnings(self) -> list[str]:
        """What the twin could not use of the robot's telemetry (each makes the run degraded)."""
        t0 = self._t0 if self._t0 is not None else self._first or 0.0
        with self._lock:
            held, self._pending = self._pending, []
            early, self._early = self._early, []
        for k, m, _ in held:  # (held as maybe a clock step, and the robot went quiet before it was one)
            self._leave_out(AHEAD_WHY, f"{k} stamped {float(m['stamp']) - self._offset:.3f}")
        for k, m, _ in early:
            self._leave_out("actions that came before any joint state, and none came (nothing to stamp them by)",
                            f"{k} {m.get('operation')} {m.get('phase')}")
        out = [f"{n} telemetry message{'s' * (n > 1)} left out: {why}" for why, n in sorted(self.left_out.items())]
        if self.steps:
            at, jump = self.steps[0]
            n = len(self.steps)
            out.append(f"the robot's clock stepped forward {n} time{'s' * (n > 1)} (first by {jump:.2f} s after "
                       f"t={at - t0:.2f} s): the twin took its stamps after each step that much earlier, by when they "
                       "came, so its times there are as good as the network's delays")
        if self.clock_joined is not None:
            at, n = self.clock_joined
            out.append(f"the robot's first {n} joint state{'s' * (n > 1)} had no stamp of their own (a header that "
                       f"says 0: a ROS 2 node on sim time before its first /clock?) and were stamped as they came; "
                       f"its own stamps from t={at - t0:.2f} s on are on another clock, taken to go on from there, "
                       "so its times before then are as good as the network's delays")
        if self.log_missed:
            out.append(f"{self.log_missed} telemetry messages that came before the run began are not in its run log "
                       f"(more than {LOG_WAITING} waited for it to open)")
        out += self._frozen_warning(t0)
        if self.gaps:
            at, longest = max(self.gaps, key=lambda g: g[1])
            gap, n = gap_threshold(self._spacings), len(self.gaps)
            out.append(f"the robot's joint states stopped {n} time{'s' * (n > 1)} for more than {gap:g} s (the "
                       f"longest {longest:.2f} s from t={at - t0:.2f} s): the twin held "
                       "the last joints meanwhile")
        out += self._stopped_warning(t0)
        out += self._rate_warning()
        late = self._actions.late_start()
        if late is not None:
            op, at = late
            out.append(f"the robot's telemetry began in the middle of its task (the twin joined late?): its action "
                       f"{op} ended at t={at - t0:.2f} s, but its start never came; what the robot did before the "
                       "twin's first message is not in the answer")
        open_ = self._actions.never_ended()
        if self.ended_quiet and open_:
            ops = ", ".join(f"{op} (begun at t={s - t0:.2f} s)" for op, s in sorted(open_.items()))
            out.append(f"the robot went quiet during its action {ops}, which never ended: it may have stopped "
                       "before its task was done")
        return out

    def _stopped_warning(self, t0: float) -> list[str]:
        """The joint states stopped for good while the robot's actions went on (a driver that died, the arm's topic
        lost): the twin held the arm still through them, which no gap between two joint states says."""
        with self._lock:
            joints, action, spacings = self._last.get("joint_state"), self._last.get("action"), list(self._spacings)
            repeating = self._repeat is not None  # (still coming, one stamp again and again: said as frozen)
        if joints is None or action is None or repeating or action[0] - joints[0] <= gap_threshold(spacings):
            return []
        return [f"the robot's joint states stopped at t={joints[0] - t0:.2f} s while its actions went on to "
                f"t={action[0] - t0:.2f} s: the twin held the last joints meanwhile, its arm still"]

    def _rate_warning(self) -> list[str]:
        """The robot's clock runs at another rate than the wall clock the twin is paced by (a simulator slower or
        faster than real time, stamping by its sim time): the twin's arm then moves at that rate against its own
        physics, and no single message says so."""
        with self._lock:
            first, came, last, frozen = self._first, self.first_arrival, self._last.get("joint_state"), \
                bool(self.frozen) or self._repeat is not None
        if first is None or came is None or last is None or frozen:
            return []
        wall = last[1] - came
        if wall < RATE_SPAN_S:
            return []
        rate = (last[0] - first) / wall
        if abs(rate - 1.0) <= RATE_SLACK:
            return []
        return [f"the robot's clock went {rate:.2f} s a second of this host's clock over {wall:.1f} s (a simulator "
                "on its sim time, slower or faster than real time?): the live twin follows the wall clock, so its "
                f"arm moved {rate:.2f} times as fast as the robot's stamps say, against physics at full speed"]

    def notes(self) -> list[str]:
        """What is not a defect but bears on the answer: how a live run ended, joint states that come slowly."""
        slow = [f"the robot's {line[4:]}" for line in slow_joints_note(self._spacings)]
        slow += [filled_note(n, why) for why, n in sorted(self.partial.items())]
        if not self.ended_quiet:
            return slow
        return slow + [f"the run ended when the robot had been quiet for {self.idle_timeout:g} s (--idle-timeout): the "
                "twin cannot tell a robot that finished its task from one that stopped; see the robot's own log"]

    def wait_for_data(self, stop: threading.Event) -> bool:
        """Wait for the robot's first message; False on a stop. RunAborted when none came within ``wait_first``
        seconds: a run without its robot would tick on empty, forever (its idle time counts from a first message)."""
        deadline = time.monotonic() + self.wait_first
        while time.monotonic() < deadline and not stop.is_set():
            # (an action held for the first joint state is not yet one: the run's time 0 is not known before it)
            if self._last_arrival is not None and not (self._early and self._last.get("joint_state") is None):
                return True
            stop.wait(0.01)
        if stop.is_set():
            return False
        if self._early:
            raise RunAborted(f"live: {len(self._early)} action annotations came, but no joint state within "
                             f"{self.wait_first:g} s on {self.where}: is the robot publishing its joint states there?")
        raise RunAborted(f"live: no telemetry came on {self.where} within {self.wait_first:g} s: is the robot "
                         "publishing, on this ensemble (or ROS 2 domain), with credentials the router admits?")

    def due(self, t: float) -> list[tuple[str, dict[str, Any]]]:
        """The messages of tick time ``t``, in arrival order: those stamped at most ``t`` after the first. One not
        yet due holds back none behind it (two publishers a little out of step, as :data:`BEHIND_S` takes: the arm's
        joint states waited behind the gripper's, and came in bursts, the twin's arm leaping); the queue is looked
        through as far as a message stamped as much after ``t`` as one queued has come before one queued earlier (at
        most :data:`BEHIND_S`: none later can be further before it)."""
        out: list[tuple[str, dict[str, Any]]] = []
        now = time.time()
        with self._lock:
            q = self._q
            self.backlog_max = max(self.backlog_max, len(q))
            if q and self._t0 is None:
                self._t0 = float(q[0][1]["stamp"])
                if self.on_t0 is not None:
                    self.on_t0(self._t0)
            t0 = self._t0 if self._t0 is not None else 0.0
            waiting: list[tuple[str, dict[str, Any]]] = []
            reach = t + min(BEHIND_S, self._disorder) + 1e-9  # (in order so far: the first not yet due ends it)
            while q:
                kind, msg = q[0]
                stamp = float(msg["stamp"])
                if stamp - t0 > reach:
                    break
                q.popleft()
                if stamp - t0 > t + 1e-9:
                    waiting.append((kind, msg))
                    continue
                out.append((kind, msg))
                if kind == "joint_state":  # (the stamps are the robot's wall clock, or another: from its first)
                    self.lags.append(max(0.0, now - stamp - self._clock_gap))
            q.extendleft(reversed(waiting))
        if self._relay is not None:
            self._pass_on(out)
        return out

    def _pass_on(self, taken: list[tuple[str, dict[str, Any]]]) -> None:
        """Relay what ``due`` took (from the conductor's thread, never from a Zenoh callback)."""
        assert self._relay is not None
        session, keys, pubs = self._relay
        for kind, msg in taken:
            key = keys.telemetry("joint_states" if kind == "joint_state" else "action")
            pub = pubs.get(key)
            if pub is None:  # (a clock-driven model steps on it: under congestion it waits, never dropped)
                import zenoh

                pub = pubs[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            try:
                pub.put(codec.encode(kind, msg))
            except ProtocolError as e:
                log.warning("not passed on: %s", e)

    def exhausted(self, t: float) -> bool:
        """The robot has been quiet for ``idle_timeout`` seconds and every message it sent was taken."""
        if (self._last_arrival is not None and time.monotonic() - self._last_arrival > self.idle_timeout
                and not self._q):
            self.ended_quiet = True
        return self.ended_quiet

    def lag_stats(self) -> dict:
        if not self.lags:
            return {"samples": 0}
        a = np.asarray(self.lags)
        return {"samples": int(a.size), "p50_ms": float(np.percentile(a, 50) * 1e3),
                "p99_ms": float(np.percentile(a, 99) * 1e3), "max_ms": float(a.max() * 1e3),
                "backlog_max": self.backlog_max, "malformed": self.malformed}
