"""The robot player (``twin robot play``): put a recording on the network as the robot would, so a twin can attach live.

Each message goes out at its recorded time (divided by ``--speed``, paced by the monotonic clock) with ``stamp``
set to this machine's wall clock at that time, as a robot stamps a measurement when it takes it (a send held up
shows as lag, not as motion squeezed into a burst), on ``twin/<ensemble>/telemetry/joint_states`` and
``.../telemetry/action`` (the twin's codec), or with ``--ros2-domain N`` on rmw_zenoh's keys in CDR, as a
ROS 2 robot would publish them. A twin started with ``--live`` (or ``--ros2-domain N``) measures its lag
against those stamps.
"""
from __future__ import annotations

import json
import os
import threading
import time

from protocol import codec
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.ros2 import (
    JOINT_STATE,
    STRING,
    TYPE_HASHES,
    encode_attachment,
    encode_joint_state,
    encode_string,
    liveliness_key,
    topic_key,
)


def wait_for_twin(session, keys: Keys, timeout: float, stop: threading.Event) -> bool:
    """Wait until the ensemble's conductor has initialised its agents (or is already running)."""
    deadline = time.monotonic() + timeout
    key = keys.conductor("status")
    while time.monotonic() < deadline and not stop.is_set():
        for reply in session.get(key, timeout=1.0):
            if reply.ok is None:
                continue
            try:
                st = codec.decode(key, reply.ok.payload, "status").fields
            except ProtocolError:
                continue
            agents = st.get("agents") or {}
            if st.get("running") or (agents and all(a.get("ready") for a in agents.values())):
                return True
        stop.wait(0.1)
    return False


class Player:
    """Publishes a :class:`~conductor.sources.recording.Recording` paced by the wall clock."""

    def __init__(self, session, keys: Keys, rec, speed: float = 1.0, ros2_domain: int | None = None,
                 ros2_namespace: str = ""):
        if speed <= 0:
            raise ValueError("--speed must be positive")
        self.rec = rec
        self.speed = speed
        self.sent = {"joint_state": 0, "action": 0}
        self.late_max = 0.0
        stamps = sorted({float(t) for t, kind, _ in rec.items if kind == "joint_state"})
        # the median joint-state spacing (s, recorded), of the robot's samples: an arm's and a gripper's messages
        # of one sample (stamps a microsecond apart) are not two
        gaps = sorted(g for g in (b - a for a, b in zip(stamps, stamps[1:], strict=False)) if g > 1e-4)
        self.spacing = gaps[len(gaps) // 2] if gaps else 0.1
        self._ros2 = None
        self._pubs = {}
        if ros2_domain is not None:
            self._ros2 = Ros2Publisher(session, ros2_domain, ros2_namespace)
        else:
            self._pubs = {"joint_state": session.declare_publisher(keys.telemetry("joint_states")),
                          "action": session.declare_publisher(keys.telemetry("action"))}
        # whether anything subscribes to the joint states as they go (Zenoh's matching status: a subscription on
        # another session too, through the router): a twin listening elsewhere, or a router lost, is then said
        self.reached = self.before = self.unheard = 0  # joint states sent as one did; before any did; after none did
        joints = self._ros2.joint_publisher if self._ros2 is not None else self._pubs["joint_state"]
        self._matched = bool(joints.matching_status.matching)
        self._matching = joints.declare_matching_listener(self._on_matching)

    def _on_matching(self, status) -> None:
        self._matched = bool(status.matching)

    def play_once(self, stop: threading.Event, then_pause: bool = False) -> bool:
        """One pass of the recording; False if ``stop`` ended it before its last message was sent. ``then_pause``:
        the pass lasts one message spacing more than the recording (a next pass does not send its first message
        with this one's last, and a recording of one instant is not sent as fast as the machine can)."""
        wall = time.time()  # (read first: a stamp is then never after the moment its message is sent)
        start = time.monotonic()
        for stamp, kind, msg in self.rec.items:
            due = stamp / self.speed
            delay = start + due - time.monotonic()
            if delay > 0 and stop.wait(delay):
                return False
            self.late_max = max(self.late_max, time.monotonic() - start - due)
            out = dict(msg, stamp=wall + due)  # the robot's clock when it measured (its schedule), not when sent
            if self._ros2 is not None:
                (self._ros2.joint_state if kind == "joint_state" else self._ros2.action)(out)
            else:
                self._pubs[kind].put(codec.encode(kind, out))
            self.sent[kind] += 1
            if kind == "joint_state":
                if self._matched:
                    self.reached += 1
                elif self.reached:
                    self.unheard += 1
                else:
                    self.before += 1
        if then_pause:
            stop.wait(max(0.0, start + (self.rec.duration + self.spacing) / self.speed - time.monotonic()))
        return True

    def unheard_lines(self, where: str) -> list[str]:
        """What the joint states sent found no subscriber for: none ever (a twin listening elsewhere), or some after
        one had (the router or the twin went away)."""
        if self.sent["joint_state"] and not self.reached:
            return [f"none of its {self.sent['joint_state']} joint states reached a subscriber: nothing listened on "
                    f"{where} (a twin of another ensemble, ROS 2 domain or namespace, or on the twin's keys where "
                    "this played ROS 2's, or the other way round?)"]
        if self.unheard:
            return [f"{self.unheard} of its {self.sent['joint_state']} joint states were sent while nothing "
                    "subscribed, after others had reached a subscriber (the router, or the twin, went away)"]
        return []

    def close(self) -> None:
        try:
            self._matching.undeclare()
        except Exception:  # (a session closed already)
            pass
        if self._ros2 is not None:
            self._ros2.close()
        for p in self._pubs.values():
            p.undeclare()


class Ros2Publisher:
    """Publishes joint states and actions as a ROS 2 node on rmw_zenoh would (``twin robot play --ros2-domain``)."""

    def __init__(self, session, domain: int = 0, namespace: str = "", node: str = "twin_robot_play"):
        self.session = session
        self.domain = int(domain)
        sid = str(session.info.zid())
        self._tokens = [session.liveliness().declare_token(
            liveliness_key(domain, sid, 0, 0, "NN", node, namespace))]
        self._pubs = {}
        for eid, (topic, ros_type) in enumerate((("/joint_states", JOINT_STATE), ("/action", STRING)), start=10):
            h = TYPE_HASHES[ros_type]
            key = topic_key(domain, topic, ros_type, h, namespace)
            self._pubs[ros_type] = [session.declare_publisher(key), os.urandom(16), 0]
            token = liveliness_key(domain, sid, 0, eid, "MP", node, namespace, topic=topic, ros_type=ros_type,
                                   type_hash=h)
            self._tokens.append(session.liveliness().declare_token(token))

    @property
    def joint_publisher(self):
        """The Zenoh publisher of ``/joint_states``."""
        return self._pubs[JOINT_STATE][0]

    def _put(self, ros_type: str, payload: bytes) -> None:
        entry = self._pubs[ros_type]
        pub, gid, seq = entry
        entry[2] = seq + 1
        pub.put(payload, attachment=encode_attachment(seq + 1, time.time_ns(), gid))

    def joint_state(self, msg: dict) -> None:
        self._put(JOINT_STATE, encode_joint_state(msg["stamp"], msg["name"], msg["position"], msg["velocity"],
                                                  msg["effort"]))

    def action(self, msg: dict) -> None:
        self._put(STRING, encode_string(json.dumps({"operation": msg["operation"], "phase": msg["phase"],
                                                    "params": msg.get("params", {})})))

    def close(self) -> None:
        for p, _, _ in self._pubs.values():
            p.undeclare()
        for t in self._tokens:
            t.undeclare()
