"""Robot recordings: reading an MCAP file in rosbag2 layout into the telemetry the twin replays.

Recordings are MCAP files in rosbag2 layout: ``/joint_states`` (``sensor_msgs/msg/JointState``)
and ``/action`` (``std_msgs/msg/String`` holding JSON ``{operation, phase, params}``). Both sources
hand the conductor, for each tick, the telemetry messages due by then, as protocol dicts
(``joint_state`` / ``action``) with ``stamp`` in seconds since the start of the recording.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from protocol.errors import TwinError
from protocol.geometry import finite_number

log = logging.getLogger("twin.source")


@dataclass
class Recording:
    path: str
    items: list[tuple[float, str, dict]]  # (stamp, "joint_state"|"action", message)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    # messages left out because they were malformed: reason -> count, and the first few in full
    skipped: dict[str, int] = field(default_factory=dict)
    skipped_examples: list[str] = field(default_factory=list)

    @property
    def duration(self) -> float:
        return self.items[-1][0] if self.items else 0.0

    def ground_truth(self) -> dict:
        gt = self.metadata.get("twin.ground_truth", {})
        out = {}
        for k, v in gt.items():
            out[k] = {"true": True, "false": False}.get(v, v)
        return out

    def warnings(self) -> list[str]:
        """One line per kind of malformed message left out (empty for a clean recording)."""
        return [f"{self.path}: {n} {reason}, left out" for reason, n in sorted(self.skipped.items())]


JOINT_STATE = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"
MAX_SPAN = 86_400.0  # a recording longer than a day is a mix of clocks, not a robot run


def _joint_state(ros, t: float) -> tuple[dict | None, str]:
    """The protocol message of a decoded JointState, or None and why it cannot be used."""
    names, pos, vel, eff = list(ros.name), list(ros.position), list(ros.velocity), list(ros.effort)
    if not names or not all(isinstance(n, str) for n in names):
        return None, "joint states without joint names"
    if len(pos) != len(names) or (vel and len(vel) != len(names)) or (eff and len(eff) != len(names)):
        return None, "joint states whose name/position/velocity/effort lengths differ"
    if not all(finite_number(v) for v in (*pos, *vel, *eff)):
        return None, "joint states with NaN, infinite or non-numeric values"
    return {"stamp": t, "name": names, "position": [float(v) for v in pos],
            "velocity": [float(v) for v in vel], "effort": [float(v) for v in eff]}, ""


def _action(ros, t: float) -> tuple[dict | None, str]:
    try:
        a = json.loads(ros.data)
    except (ValueError, RecursionError):
        return None, "action annotations that are not JSON"
    if not isinstance(a, dict) or not isinstance(a.get("operation"), str) or not a["operation"]:
        return None, "action annotations without an 'operation' name"
    phase = a.get("phase", "start")
    if phase not in ("start", "end"):
        return None, "action annotations whose phase is not 'start' or 'end'"
    params = a.get("params", {}) or {}
    if not isinstance(params, dict):
        return None, "action annotations whose params are not a map"
    return {"stamp": t, "operation": a["operation"], "phase": phase, "params": params}, ""


def _topics(reader, path: str) -> tuple[str, str]:
    """The joint-state and action topics: ``/joint_states`` and ``/action`` if present, else the one
    channel of each type (a namespaced robot such as ``/panda/joint_states``)."""
    try:
        summary = reader.get_summary()
    except Exception:
        summary = None
    if summary is None:  # no summary section (a truncated file): the standard names
        return "/joint_states", "/action"
    by_type: dict[str, set[str]] = {JOINT_STATE: set(), STRING: set()}
    for ch in summary.channels.values():
        sch = summary.schemas.get(ch.schema_id)
        if sch is not None and sch.name in by_type:
            by_type[sch.name].add(ch.topic)
    picked = []
    for want, typ in (("/joint_states", JOINT_STATE), ("/action", STRING)):
        found = by_type[typ]
        if want in found or not found:
            picked.append(want)
            continue
        tail = sorted(t for t in found if t.endswith(want))
        if len(tail) == 1:
            log.info("%s: reading %s as %s", path, tail[0], want)
            picked.append(tail[0])
        elif len(tail) > 1:
            raise TwinError(f"{path}: several {typ} topics ({', '.join(tail)}) and none is {want}: "
                            "cannot tell which one is the robot's")
        else:
            picked.append(want)
    return picked[0], picked[1]


def load_recording(path: str | Path) -> Recording:
    """Read a rosbag2-style MCAP recording; raises TwinError with the file name on problems.

    Every message is placed at its log time (when the recorder got it), so joint states and action
    annotations share one clock. Malformed messages (lengths that differ, NaN, an action without an
    operation...) are left out, counted by reason in :attr:`Recording.skipped` and logged; CRCs are
    checked, so a corrupted file is an error rather than silently different data."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = str(path)
    items: list[tuple[float, str, dict]] = []
    skipped: dict[str, int] = {}
    examples: list[str] = []
    try:
        f = open(path, "rb")
    except OSError as e:
        raise TwinError(f"{path}: cannot open recording: {e.strerror}") from None
    with f:
        try:
            reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])  # seeks as needed
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            joints, actions = _topics(reader, path)
            for _schema, channel, message, ros in reader.iter_decoded_messages(topics=[joints, actions]):
                t = message.log_time  # integer ns until re-based below (floats of epoch times lose ~0.2 us)
                if channel.topic == joints:
                    msg, why = _joint_state(ros, t)
                    kind = "joint_state"
                else:
                    msg, why = _action(ros, t)
                    kind = "action"
                if msg is None:
                    skipped[why] = skipped.get(why, 0) + 1
                    if len(examples) < 5:
                        examples.append(f"{channel.topic} message #{message.sequence} "
                                        f"(log time {t * 1e-9:.3f} s): {why}")
                    continue
                items.append((t, kind, msg))
        except TwinError:
            raise
        except Exception as e:
            raise TwinError(f"{path}: not a readable MCAP recording ({type(e).__name__}: {e})") from None
    if not items:
        raise TwinError(f"{path}: no usable {joints} or {actions} messages"
                        + (f" ({sum(skipped.values())} malformed ones left out)" if skipped else ""))
    for line in examples:
        log.warning("%s: left out %s", path, line)
    backwards = sum(1 for a, b in zip(items, items[1:]) if b[0] < a[0])
    if backwards:
        log.warning("%s: %d messages were recorded out of time order; replayed in time order", path, backwards)
    items.sort(key=lambda x: x[0])
    t0 = items[0][0]
    span = (items[-1][0] - t0) * 1e-9
    if span > MAX_SPAN:
        raise TwinError(f"{path}: the messages span {span:.0f} s (first at log time {t0 * 1e-9:.3f} s, last at "
                        f"{items[-1][0] * 1e-9:.3f} s): more than a day, so its log times mix clocks")
    for _, _, m in items:
        m["stamp"] = (m["stamp"] - t0) * 1e-9
    items = [(m["stamp"], k, m) for _, k, m in items]
    return Recording(path, items, meta, skipped, examples)
