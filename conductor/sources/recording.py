"""Robot recordings: reading a ROS 2 bag into the telemetry the twin replays.

A recording is a single MCAP file, a rosbag2 directory (MCAP or SQLite storage) or a bare ``.db3``
file (see :mod:`.bags`) with two logical topics: ``/joint_states`` (``sensor_msgs/msg/JointState``)
and ``/action`` (``std_msgs/msg/String`` holding JSON ``{operation, phase, params}``). Either may be
remapped to the bag's own topics (``/joint_states:=/arm/joint_states``); joint states spread over
several topics are merged by joint name. Both sources hand the conductor, for each tick, the
telemetry messages due by then, as protocol dicts (``joint_state`` / ``action``) with ``stamp`` in
seconds since the start of the recording.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from protocol.errors import InputError
from protocol.geometry import finite_number, finite_numbers
from protocol.joints import LatestJoints, fill_unknown
from protocol.ros2 import parse_action

from .bags import Bag, open_bag
from .live import GAP_S, ActionTally, counted, filled_note, gap_threshold, slow_joints_note

log = logging.getLogger("twin.source")


@dataclass
class Recording:
    path: str
    items: list[tuple[float, str, dict]]  # (stamp, "joint_state"|"action", message)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    # messages left out because they were malformed: reason -> count, and the first few in full
    skipped: dict[str, int] = field(default_factory=dict)
    skipped_examples: list[str] = field(default_factory=list)
    # where the messages came from: logical topic -> the bag's topics read for it, and the file form
    topics: dict[str, list[str]] = field(default_factory=dict)
    storage: str = "mcap"
    joint_names: list[str] = field(default_factory=list)  # every joint name in the joint states used
    undecodable: dict[str, str] = field(default_factory=dict)  # topics not needed that cannot be decoded
    origin_ns: int | None = None  # the log time (ns) that stamps count from: the first message's
    cut_short: str = ""  # why the input ends before its source did (a run log whose run did not finish, a file cut)
    damaged: list[str] = field(default_factory=list)  # parts of the file that could not be read, their messages lost
    read_notes: list[str] = field(default_factory=list)  # reading options that did nothing (see notes())
    # what its joint positions say against a robot (sources.fit.telemetry_warnings), by the robot: worked out once
    fit_checks: dict[str, list[str]] = field(default_factory=dict, repr=False, compare=False)
    # (stamp, seconds) where its joint states kept one header stamp while their log times went on (a frozen driver:
    # said when the robot's actions go on meanwhile; an idle gripper's driver may republish its state)
    frozen: list[tuple[float, float]] = field(default_factory=list)
    other_joint_topics: list[str] = field(default_factory=list)  # JointState topics of the bag not read
    other_action_topics: list[str] = field(default_factory=list)  # String topics of the bag not read

    @property
    def duration(self) -> float:
        return self.items[-1][0] if self.items else 0.0

    @cached_property
    def joints_in_order(self) -> list[str]:
        """Every joint name its joint states carry, in the order they first come (worked out once: a warm
        service runs one recording many times, each run checking its joints against the scene's robot)."""
        from .fit import recorded_joints

        return recorded_joints(self.items)

    def ground_truth(self) -> dict:
        gt = self.metadata.get("twin.ground_truth", {})
        out = {}
        for k, v in gt.items():
            out[k] = {"true": True, "false": False}.get(v, v)
        return out

    def warnings(self) -> list[str]:
        """One line per kind of malformed message left out, and per hole in the telemetry (empty for a clean
        recording)."""
        return ([f"{self.path}: {counted(n, reason)}, left out" for reason, n in sorted(self.skipped.items())]
                + ([f"{self.path}: {self.cut_short}"] if self.cut_short else [])
                + [f"{self.path}: {line}" for line in self.damaged]
                + [f"{self.path}: {hole}" for hole in self.holes + self.unfinished])

    @cached_property
    def holes(self) -> list[str]:
        """Where the joint states stop for more than :func:`~.live.gap_threshold` of their spacings (0.5 s, or five
        times their usual spacing at a slower rate: a recorder that dropped messages; the twin holds the robot's
        last joints meanwhile, as it does live), and actions far outside the joint states' time (on another clock:
        the twin would act on them while the robot stands)."""
        joints = self.joint_stamps
        if not joints:
            return []
        out = []
        gap = gap_threshold(self.joint_spacings)
        gaps = [(a, b - a) for a, b in zip(joints, joints[1:], strict=False) if b - a > gap]
        if gaps:
            at, longest = max(gaps, key=lambda g: g[1])
            out.append(f"its joint states stop {len(gaps)} time{'s' * (len(gaps) > 1)} for more than {gap:g} s "
                       f"(the longest {longest:.2f} s from t={at:.2f} s): the twin holds the robot's last joints "
                       "meanwhile (did the recorder drop messages?)")
        first, last = joints[0], joints[-1]
        outside = [t for t, k, _ in self.items if k == "action" and not first - gap <= t <= last + gap]
        if outside:
            out.append(f"{len(outside)} of its actions (the first at t={outside[0]:.2f} s) come more than {gap:g} s "
                       f"outside its joint states (t={first:.2f} to {last:.2f} s): are the actions on another "
                       "clock?")
        acts = [t for t, k, _ in self.items if k == "action"]
        frozen = [(at, d) for at, d in self.frozen if any(at < t < at + d for t in acts)]  # (while the robot acts)
        if frozen:
            at, longest = max(frozen, key=lambda f: f[1])
            n = len(frozen)
            out.append(f"its joint states repeat one header stamp {n} time{'s' * (n > 1)} for more than {GAP_S:g} s "
                       f"(the longest {longest:.2f} s from t={at:.2f} s) while they go on being recorded and the "
                       "robot's actions go on: a driver republishing its last message? The twin's robot stands still "
                       "there")
        return out

    def notes(self) -> list[str]:
        """One line per kind of well-formed message left out, and per option that did nothing (a --joint-order for
        joint states that name their joints): they do not make a run degraded."""
        return ([f"{self.path}: {line}" for line in self.read_notes]
                + ([f"{self.path}: {NO_EFFORTS}"] if not self.efforts else [])
                + [f"{self.path}: {line}" for line in slow_joints_note(self.joint_spacings)])

    @cached_property
    def unfinished(self) -> list[str]:
        """The task cut at either end, as a live run says it (:meth:`~.live.LiveSource.warnings`): an action whose
        end comes but whose start does not (the recording began in the middle of the task; from a robot that
        annotates its actions' starts), and actions begun that never end (it stopped before the task was done; from
        a robot that annotates their ends). What the robot did outside the recording is not in the answer."""
        tally = ActionTally()
        for t, kind, m in self.items:
            if kind == "action":
                tally.take(str(m.get("operation")), m.get("phase"), t)
        out = []
        orphan, begun = tally.late_start(), tally.never_ended()
        if orphan is not None:
            out.append(f"it begins in the middle of the robot's task: its action {orphan[0]} ends at t={orphan[1]:.2f} "
                       "s, but its start is not in the recording; what the robot did before it is not in the answer")
        if begun:
            ops = ", ".join(f"{op} (begun at t={t:.2f} s)" for op, t in sorted(begun.items(), key=lambda b: b[1]))
            out.append(f"it ends in the middle of the robot's task: its action {ops} never ends in the recording; "
                       "what the robot did after it is not in the answer")
        return out

    @cached_property
    def joint_stamps(self) -> list[float]:
        """When each joint state comes, in order."""
        return [t for t, k, _ in self.items if k == "joint_state"]

    @cached_property
    def joint_spacings(self) -> list[float]:
        """The time from each joint state to the next, in order."""
        joints = self.joint_stamps
        return [b - a for a, b in zip(joints, joints[1:], strict=False)]

    @cached_property
    def efforts(self) -> bool:
        """Whether any of its joint states carries a non-zero effort (a real robot's often carry none)."""
        return any(k == "joint_state" and any(m["effort"]) for _, k, m in self.items)



def ended_short(metadata: dict[str, dict[str, str]]) -> str:
    """Why the telemetry of a run log (its ``twin.summary`` metadata) is not the whole of what its run was to
    replay: the run stopped early, or its own input was cut short or had messages left out ('' otherwise, and
    for a file that is not a run log)."""
    if "twin.summary" not in metadata:
        return ""
    try:
        summary = json.loads(metadata["twin.summary"].get("json", "{}"))
    except ValueError:
        return "the log of a run whose summary cannot be read: how much of its input it holds is unknown"
    status = summary.get("status") if isinstance(summary, dict) else None
    if status in ("truncated", "interrupted", "failed"):
        why = (summary.get("status_reasons") or [""])[0]
        return (f"the log of a run that ended {status}{f' ({why})' if why else ''}: its telemetry is only what that "
                "run was given before it stopped")
    inputs = summary.get("input_warnings") if isinstance(summary, dict) else None
    if inputs:
        return f"the log of a run whose own input was not whole ({inputs[0]}): its telemetry is that run's"
    return ""


JOINT_STATE = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"
JOINTS, ACTIONS = "/joint_states", "/action"  # the two logical topics
LOGICAL = {JOINTS: JOINT_STATE, ACTIONS: STRING}
NOT_MEASURED = ("command", "desired", "target", "goal", "reference", "setpoint")
"""Words in a JointState topic's name that say it is not what the robot measured (``/commanded_joint_states``):
left out of the topics found automatically (``--remap`` still reads one)."""
MAX_SPAN = 86_400.0  # a recording longer than a day is a mix of clocks, not a robot run
NO_EFFORTS = ("its joint states carry no efforts (none, or all zero): a model that tells a grasp by the fingers' force "
              "decides without it (the grasp monitor: from finger positions and the hand commands, which can miss a "
              "ball that slips out of a closed hand)")
NO_NAMES = "joint states without joint names (pass --joint-order NAME,NAME,... to name them)"
READABLE = {"mcap": "MCAP recording", "rosbag2-mcap": "rosbag2 recording (MCAP storage)",
            "rosbag2-sqlite3": "rosbag2 recording (SQLite storage)", "sqlite3": "SQLite rosbag2 file"}


def parse_remap(remap: list[str] | None) -> list[tuple[str, str]]:
    """``["/joint_states:=/arm/joint_states", ...]`` as (logical topic, bag topic) pairs; ValueError on bad syntax."""
    pairs = []
    for text in remap or []:
        frm, sep, to = text.partition(":=")
        frm, to = frm.strip(), to.strip()
        if not sep or frm not in LOGICAL or not to.startswith("/") or len(to) < 2 or ":=" in to:
            raise ValueError(f"bad --remap {text!r}: write FROM:=TO with FROM {JOINTS} or {ACTIONS} and TO a topic "
                             f"of the recording, e.g. {JOINTS}:=/arm/joint_states")
        pairs.append((frm, to))
    return pairs


def parse_joint_order(text: str | None) -> list[str] | None:
    """``--joint-order j1,j2,finger`` as a list; ValueError on an empty or repeated name."""
    if text is None:
        return None
    names = [n.strip() for n in text.split(",")]
    if not all(names) or len(set(names)) != len(names):
        raise ValueError(f"bad --joint-order {text!r}: give the joint names once each, separated by commas, "
                         "e.g. --joint-order j1,j2,finger")
    return names


def _names(ros, npos: int, joint_order: list[str] | None) -> tuple[list[str] | None, str]:
    names = list(ros.name)
    if names:
        if not all(isinstance(n, str) and n for n in names):
            return None, "joint states with joint names that are not text"
        if len(set(names)) != len(names):  # which value would be the joint's?
            return None, "joint states that name a joint twice"
        return names, ""
    if not joint_order:
        return None, NO_NAMES
    if len(joint_order) != npos:
        return None, (f"joint states without joint names whose position count differs from the {len(joint_order)} "
                      "names of --joint-order")
    return list(joint_order), ""


def _joint_state(ros, t: int, joint_order: list[str] | None = None) -> tuple[dict | None, str]:
    """The protocol message of a decoded JointState, or None and why it cannot be used."""
    pos, vel, eff = list(ros.position), list(ros.velocity), list(ros.effort)
    names, why = _names(ros, len(pos), joint_order)
    if names is None:
        return None, why
    if len(pos) != len(names) or (vel and len(vel) != len(names)) or (eff and len(eff) != len(names)):
        return None, "joint states whose name/position/velocity/effort lengths differ"
    if not finite_numbers((*pos, *vel, *eff)):
        if not finite_numbers(tuple(pos)):
            return None, "joint states with NaN, infinite or non-numeric values"
        # (a gripper driver's NaN effort: the positions still say where the robot is; _read fills the field from the
        # topic's joint state before, or leaves it out)
        bad = [f for f, vs in (("velocities", vel), ("efforts", eff)) if not finite_numbers(tuple(vs))]
        return ({"stamp": t, "name": names, "position": [float(v) for v in pos],
                 "velocity": [float(v) if finite_number(v) else math.nan for v in vel],
                 "effort": [float(v) if finite_number(v) else math.nan for v in eff]},
                f"joint states with NaN or infinite {' and '.join(bad)}")
    return {"stamp": t, "name": names, "position": [float(v) for v in pos],
            "velocity": [float(v) for v in vel], "effort": [float(v) for v in eff]}, ""




def _action(ros, t: int) -> tuple[dict | None, str]:
    try:
        return {"stamp": t, **parse_action(ros.data)}, ""
    except ValueError as e:
        return None, str(e)


# ------------------------------------------------------------------ which topics
def _auto_topics(bag: Bag, logical: str) -> list[str]:
    """``/joint_states`` and ``/action`` if present, else the one topic of that type whose name ends so (a
    namespaced robot such as ``/panda/joint_states``); several joint-state topics so named are merged."""
    typ = LOGICAL[logical]
    if bag.types is None:  # no summary section (a truncated file): the standard names
        return [logical]
    found = sorted(t for t, ty in bag.types.items() if ty == typ)
    if logical in found or not found:
        return [logical]
    if logical == JOINTS:  # (a commanded, desired or target state is not what the robot did: never merged in)
        tail = [t for t in found if t.rsplit("/", 1)[-1].endswith("joint_states")
                and not any(w in t.rsplit("/", 1)[-1].lower() for w in NOT_MEASURED)]
    else:
        tail = [t for t in found if t.endswith(logical)]
    if len(tail) == 1:
        log.info("%s: reading %s as %s", bag.path, tail[0], logical)
    elif len(tail) > 1 and logical == JOINTS:
        log.info("%s: merging %s by joint name as %s", bag.path, ", ".join(tail), logical)
    elif len(tail) > 1:
        raise InputError(f"{bag.path}: several {typ} topics ({', '.join(tail)}) and none is {logical}: "
                        f"cannot tell which one is the robot's (choose with --remap {logical}:=TOPIC)")
    return tail or [logical]


def _check_remapped(bag: Bag, logical: str, topics: list[str]) -> None:
    if bag.types is None:
        return
    typ = LOGICAL[logical]
    for t in topics:
        if t not in bag.types:
            raise InputError(f"{bag.path}: --remap {logical}:={t}: the recording has no topic {t} "
                            f"(its topics: {', '.join(sorted(bag.types)) or 'none'})")
        if bag.types[t] and bag.types[t] != typ:
            raise InputError(f"{bag.path}: --remap {logical}:={t}: {t} holds {bag.types[t]}, not {typ}")


def _choose_topics(bag: Bag, remap: list[tuple[str, str]]) -> dict[str, list[str]]:
    """Logical topic -> the bag's topics read for it; a needed topic that cannot be decoded is an error."""
    chosen: dict[str, list[str]] = {JOINTS: [], ACTIONS: []}
    for frm, to in remap:
        if to not in chosen[frm]:
            chosen[frm].append(to)
    for logical, topics in chosen.items():
        if topics:
            _check_remapped(bag, logical, topics)
        else:
            chosen[logical] = _auto_topics(bag, logical)
    needed = {t for ts in chosen.values() for t in ts}
    for t in sorted(needed & set(bag.undecodable)):
        raise InputError(f"{bag.path}: topic {t} cannot be decoded ({bag.undecodable[t]})")
    unneeded = {t: why for t, why in bag.undecodable.items() if t not in needed}
    other = sorted(t for t in unneeded if t in bag.foreign)  # not ROS 2 messages (a twin run log's own channels)
    if other:
        log.info("%s: %d topic(s) in encodings other than CDR, not needed, skipped: %s", bag.path, len(other),
                 ", ".join(other))
    broken = {t: why for t, why in unneeded.items() if t not in bag.foreign}
    if broken:
        log.warning("%s: %d topic(s) that cannot be decoded and are not needed, skipped: %s", bag.path, len(broken),
                    "; ".join(f"{t} ({why})" for t, why in sorted(broken.items())))
    return chosen


# ------------------------------------------------------------------ reading and merging
@dataclass
class _Read:
    items: list[tuple[int, str, dict, str]] = field(default_factory=list)  # (log time ns, kind, message, topic)
    skipped: dict[str, int] = field(default_factory=dict)
    examples: list[str] = field(default_factory=list)
    nameless: int = 0  # joint states named by --joint-order
    # per joint-state topic: (header stamp ns, log time it first came, log time it last came) of its latest
    stuck: dict[str, tuple[int, int, int]] = field(default_factory=dict)
    frozen: list[tuple[int, float]] = field(default_factory=list)  # (log time ns, seconds) a header stamp stayed
    partial: dict[str, int] = field(default_factory=dict)  # joint states with NaN velocities/efforts (why -> count)
    last: dict[str, dict] = field(default_factory=dict)  # joint-state topic -> its latest joint state

    def header(self, topic: str, ros: Any, t: int) -> None:
        """A joint state's header stamp: one that stays while the log times go on for :data:`~.live.GAP_S` is a
        frozen driver (the same message republished), which the log times alone make look like a robot standing."""
        stamp = getattr(getattr(ros, "header", None), "stamp", None)
        ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) if stamp is not None else 0
        was = self.stuck.get(topic)
        if was is not None and ns == was[0] and ns:
            self.stuck[topic] = (ns, was[1], t)
            return
        self.end_stuck(topic)
        self.stuck[topic] = (ns, t, t)

    def end_stuck(self, topic: str) -> None:
        was = self.stuck.pop(topic, None)
        if was is not None and (was[2] - was[1]) * 1e-9 > GAP_S:
            self.frozen.append((was[1], (was[2] - was[1]) * 1e-9))

    def skip(self, why: str, topic: str, seq: int, t: int) -> None:
        self.skipped[why] = self.skipped.get(why, 0) + 1
        if len(self.examples) < 5:
            self.examples.append(f"{topic} message #{seq} (log time {t * 1e-9:.3f} s): {why}")


def _read(bag: Bag, chosen: dict[str, list[str]], joint_order: list[str] | None) -> _Read:
    out = _Read()
    joints = set(chosen[JOINTS])
    topic = ""
    try:
        for topic, t, seq, ros in bag.messages(sorted({*chosen[JOINTS], *chosen[ACTIONS]})):
            # t: integer ns until re-based (floats of epoch times lose ~0.2 us)
            kind = "joint_state" if topic in joints else "action"
            if ros is None:
                msg, why = None, ("joint states" if kind == "joint_state" else "action annotations") + \
                    " that cannot be decoded"
            elif kind == "joint_state":
                msg, why = _joint_state(ros, t, joint_order)
                out.nameless += msg is not None and not len(ros.name)
                if msg is not None:
                    out.header(topic, ros, t)
            else:
                msg, why = _action(ros, t)
            if msg is None:
                out.skip(why, topic, seq, t)
            else:
                if why:  # (NaN velocities or efforts: filled from the topic's joint state before, or left out)
                    out.partial[why] = out.partial.get(why, 0) + 1
                    fill_unknown(msg, out.last.get(topic))
                if kind == "joint_state":
                    out.last[topic] = msg
                out.items.append((t, kind, msg, topic))
    except InputError:
        raise
    except Exception as e:
        held, wanted = (bag.types or {}).get(topic), JOINT_STATE if topic in joints else STRING
        if held and held != wanted:  # (one of another type whose messages lack what the twin reads)
            raise InputError(f"{bag.path}: {topic} holds {held}, not {wanted}, and its messages cannot be read as "
                             f"such ({type(e).__name__}: {e}): give the robot's with --remap "
                             f"{JOINTS if topic in joints else ACTIONS}:=TOPIC") from None
        raise InputError(f"{bag.path}: not a readable {READABLE.get(bag.storage, 'recording')} "
                        f"({type(e).__name__}: {e})") from None
    for topic in list(out.stuck):
        out.end_stuck(topic)
    return out


class _JointMerger:
    """Joint states of several topics (an arm's and a gripper's) as one: the latest values of every joint, merged
    by name as every reader of joint states merges them (:class:`~protocol.joints.LatestJoints`), emitted for
    each incoming message in the ``joint_order`` given. Before a topic is first heard from, its joints are taken
    to be as its first message says (:meth:`seed`): the recording is read whole, so an arm's motion before its
    gripper's driver first speaks is not lost (a live run takes the arm alone meanwhile). ``strict``: topics chosen
    automatically must not share a joint name (two robots' joint states are not one robot's)."""

    def __init__(self, path: str, strict: bool, joint_order: list[str] | None):
        self.path, self.strict = path, strict
        self.rank = {n: i for i, n in enumerate(joint_order or [])}
        self.joints = LatestJoints()
        self.topic_of: dict[str, str] = {}  # each joint's topic, as first heard

    def seed(self, topic: str, m: dict) -> None:
        """A topic's first message: what its joints are until it speaks (call for each topic, in time order)."""
        self._check(topic, m)
        self.joints.take({**m, "stamp": None})

    def _check(self, topic: str, m: dict) -> None:
        for n in m["name"]:
            first = self.topic_of.setdefault(n, topic)
            if self.strict and first != topic:
                raise InputError(f"{self.path}: joint {n!r} is on both {first} and {topic}: two robots? choose "
                                 f"the topics with --remap {JOINTS}:=TOPIC (once per topic to merge)")

    def add(self, topic: str, m: dict) -> dict:
        self._check(topic, m)
        merged = self.joints.take(m)
        if not self.rank:
            return merged
        at = sorted(range(len(merged["name"])), key=lambda i: self.rank.get(merged["name"][i], len(self.rank)))
        return {**merged, **{f: [merged[f][i] for i in at] for f in ("name", "position", "velocity", "effort")
                             if merged[f]}}


def _merge(path: str, items: list[tuple[int, str, dict, str]], strict: bool, joint_order: list[str] | None,
           notes: list[str]) -> list[tuple[int, str, dict]]:
    """The time-ordered ``items`` with the joint states of several topics merged (see :class:`_JointMerger`);
    a topic first heard after others' joint states is a line of ``notes``."""
    first: dict[str, tuple[int, dict]] = {}
    for t, k, m, topic in items:
        if k == "joint_state" and topic not in first:
            first[topic] = (t, m)
    if len(first) < 2:
        return [(t, k, m) for t, k, m, _ in items]
    merger = _JointMerger(path, strict, joint_order)
    for topic, (_, m) in first.items():  # (in time order)
        merger.seed(topic, m)
    t_first = min(t for t, _ in first.values())
    for topic, (t, _) in first.items():
        before = sum(1 for u, k, _, other in items if k == "joint_state" and other != topic and u < t)
        if before:
            notes.append(f"{topic} first spoke {(t - t_first) * 1e-9:.2f} s after the first joint state: its joints "
                         f"in the {counted(before, 'joint states')} before are taken as its first message gives them")
    return [(t, k, merger.add(topic, m) if k == "joint_state" else m) for t, k, m, topic in items]


def _check_log_times(path: str, items: list[tuple[int, str, dict, str]]) -> None:
    """InputError if the joint states (``items`` in time order) all have one log time: replayed by them, the whole
    motion went in one tick, and the run said complete."""
    joint_times = [it[0] for it in items if it[1] == "joint_state"]
    if len(joint_times) > 1 and joint_times[0] == joint_times[-1]:
        raise InputError(f"{path}: its {len(joint_times)} joint states all have one log time "
                         f"({joint_times[0] * 1e-9:.3f} s), so they say nothing of when the robot moved (recorded "
                         "with use_sim_time and no /clock, or converted without log times?): the twin replays a "
                         "recording by its log times")


def _efforts_left_out(items: list[tuple[int, str, dict, str]], merged: list[tuple[int, str, dict]]) -> list[str]:
    """A note when the joint states, merged, carry no efforts although some joints came with theirs: a joint state
    carries an effort for every joint or for none, so a gripper's efforts went when the arm's driver gave none."""
    if any(k == "joint_state" and m["effort"] for _, k, m in merged):
        return []
    given: dict[str, set[str]] = {}  # topic -> joints it gave efforts for
    bare: dict[str, set[str]] = {}  # topic -> joints it gave none for
    for _, k, m, topic in items:
        if k == "joint_state":
            (given if m.get("effort") else bare).setdefault(topic, set()).update(m["name"])
    had = set().union(*given.values()) if given else set()
    lacking = set().union(*bare.values()) - had if bare else set()
    if not had or not lacking:
        return []
    from .fit import _few

    def few(names: set[str]) -> str:
        return _few(sorted(names), 4)

    return [f"the efforts of {few(had)} (on {', '.join(sorted(given))}) are not replayed: {few(lacking)} (on "
            f"{', '.join(sorted(bare))}) come without efforts, and one joint state carries an effort for every joint "
            "or for none"]


def _nothing_usable(bag: Bag, chosen: dict[str, list[str]], got: _Read) -> InputError:
    why = ""
    if got.skipped:
        why = f" ({sum(got.skipped.values())} left out: " + "; ".join(
            f"{n} {reason}" for reason, n in sorted(got.skipped.items())) + ")"
    others = sorted(t for t, ty in (bag.types or {}).items() if ty == JOINT_STATE and t not in chosen[JOINTS])
    hint = f"; its JointState topics: {', '.join(others)} (choose with --remap {JOINTS}:=TOPIC)" if others else ""
    # a file cut before its first whole chunk of them (not "its messages up to the cut are replayed": none is)
    cut = "; the recording is cut short (no end: its recorder was killed, or the copy stopped) before any of " \
        "them was whole" if bag.cut else ""
    if bag.damaged:
        n = len(bag.damaged)
        cut += f"; {n} chunk{'s' * (n > 1)} of its messages cannot be read ({bag.damaged[0][2]})"
    return InputError(f"{bag.path}: no usable {' or '.join(chosen[JOINTS] + chosen[ACTIONS])} messages{why}{hint}{cut}")


def _span(a_ns: int, b_ns: int) -> str:
    """A damaged chunk's log times, from the first message read."""
    if b_ns < 0:
        return f"the {-a_ns * 1e-9:.2f} s before the first message read"
    return f"t={a_ns * 1e-9:.2f} to {b_ns * 1e-9:.2f} s"


def load_recording(path: str | Path, remap: list[str] | None = None,
                   joint_order: list[str] | None = None) -> Recording:
    """Read a robot recording (an MCAP file, a rosbag2 directory or a ``.db3``); raises InputError with the
    file name on problems, ValueError on a bad ``remap``.

    ``remap`` holds ROS-style ``FROM:=TO`` strings choosing the bag's topics for ``/joint_states`` and
    ``/action`` (the same FROM several times: joint states merged by name); ``joint_order`` names the joints
    of joint states whose ``name`` list is empty. Every message is placed at its log time (when the recorder
    got it), so joint states and action annotations share one clock, and replayed in time order. Malformed
    messages (lengths that differ, a NaN position, an action without an operation...) are left out, counted by
    reason in :attr:`Recording.skipped` and logged (a NaN velocity or effort is taken from the joint state before,
    and a note says how many); an MCAP file's CRCs are checked: a chunk of it that cannot be read (a CRC that
    fails, data that does not decompress) is left out and said in :meth:`Recording.warnings` (the run is degraded),
    never read as different data."""
    pairs = parse_remap(remap)
    with open_bag(path) as bag:
        chosen = _choose_topics(bag, pairs)
        got = _read(bag, chosen, joint_order)
    if not got.items:
        raise _nothing_usable(bag, chosen, got)
    for line in got.examples:
        log.warning("%s: left out %s", bag.path, line)
    items = got.items
    backwards = sum(1 for a, b in zip(items, items[1:]) if b[0] < a[0])
    if backwards:
        log.warning("%s: %d messages were recorded out of time order; replayed in time order", bag.path, backwards)
    read_notes = [filled_note(n, why) for why, n in sorted(got.partial.items())]
    if joint_order and not got.nameless and len(chosen[JOINTS]) < 2:
        read_notes.append("--joint-order is not used: every joint state names its joints")
    items.sort(key=lambda x: x[0])
    t0 = items[0][0]
    span = (items[-1][0] - t0) * 1e-9
    _check_log_times(bag.path, items)
    if span > MAX_SPAN:
        raise InputError(f"{bag.path}: the messages span {span:.0f} s (first at log time {t0 * 1e-9:.3f} s, last at "
                        f"{items[-1][0] * 1e-9:.3f} s): more than a day, so its log times mix clocks")
    merged = _merge(bag.path, items, not any(frm == JOINTS for frm, _ in pairs), joint_order, read_notes)
    read_notes += _efforts_left_out(items, merged)
    damaged = [f"a chunk of its messages ({_span(a - t0, b - t0)}) cannot be read ({why}): its messages are left out"
               for a, b, why in bag.damaged]
    out: list[tuple[float, str, dict]] = []
    for t, k, m in merged:
        m["stamp"] = (t - t0) * 1e-9
        out.append((m["stamp"], k, m))
    names = sorted({n for _, k, m in out if k == "joint_state" for n in m["name"]})
    return Recording(bag.path, out, bag.metadata, got.skipped, got.examples, topics=chosen, storage=bag.storage,
                     joint_names=names, undecodable=dict(bag.undecodable), origin_ns=int(t0),
                     cut_short=bag.cut or ended_short(bag.metadata), damaged=damaged, read_notes=read_notes,
                     frozen=[((t - t0) * 1e-9, d) for t, d in got.frozen],
                     other_joint_topics=sorted(t for t, ty in (bag.types or {}).items()
                                               if ty == JOINT_STATE and t not in chosen[JOINTS]),
                     other_action_topics=sorted(t for t, ty in (bag.types or {}).items()
                                                if ty == STRING and t not in chosen[ACTIONS]))
