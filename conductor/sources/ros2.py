"""Live telemetry from a ROS 2 robot on ``rmw_zenoh`` (the wire format is :mod:`protocol.ros2`)."""
from __future__ import annotations

import logging
import math

from protocol import codec
from protocol.ros2 import JOINT_STATE, STRING, decode_action, decode_attachment, decode_joint_state, topic_key

from .live import LiveSource

log = logging.getLogger("twin.ros2")

MAX_ROS2_DOMAIN = 232
"""The largest ROS 2 domain id (DDS maps domains 0-232 to UDP ports; rmw_zenoh takes the same ids)."""


class Ros2Source(LiveSource):
    """Live telemetry from a ROS 2 robot on rmw_zenoh (domain ``domain``, optional ``namespace``).

    Same contract as :class:`~conductor.sources.live.LiveSource`: messages are taken in order, each at the tick
    its stamp belongs to, and the lag is measured against that stamp. The stamp is the JointState header's; a
    message without one of its own (an action annotation, a header that says 0) is stamped by the robot's clock
    as it comes (:meth:`~conductor.sources.live.LiveSource._robot_time`: a robot on sim time keeps its actions).
    """

    def __init__(self, session, keys, domain: int = 0, namespace: str = "", joint_topic: str = "/joint_states",
                 action_topic: str = "/action", idle_timeout: float = 3.0, wait_first: float = 30.0,
                 republish: bool = True):
        # the LiveSource state, without its subscription on twin/<e>/telemetry/**
        self._init_state(idle_timeout, wait_first)
        self.session = session
        self.keys = keys
        self.domain = int(domain)
        self.last_seq: dict[bytes, int] = {}
        self.dropped = 0  # gaps in a publisher's sequence numbers
        self.unread_attachments = 0  # publications whose attachment is not rmw_zenoh's as the twin reads it
        self.joint_key = topic_key(domain, joint_topic, JOINT_STATE, "*", namespace)
        self.action_key = topic_key(domain, action_topic, STRING, "*", namespace)
        if republish:  # (on the run's telemetry keys: the run log and the models that want telemetry hear it)
            self.relay_to(session, keys)
        self._subs = [session.declare_subscriber(self.joint_key, self._on_joint),
                      session.declare_subscriber(self.action_key, self._on_action)]
        self._sub = None
        self.where = f"{self.joint_key} and {self.action_key}"
        log.info("ROS 2 attach: %s and %s", self.joint_key, self.action_key)

    def _source_ns(self, sample) -> int | None:
        """The publication's source timestamp from its attachment, its sequence number checked for gaps; None
        without one, or with one the twin cannot read (counted and said: the message itself is still taken, but
        what was lost on the way is not counted)."""
        att = sample.attachment
        if att is None:
            return None
        try:
            seq, stamp, gid = decode_attachment(att.to_bytes())
        except Exception as e:  # (a layout of another rmw_zenoh release: the attachment is only metadata)
            with self._lock:
                self.unread_attachments += 1
                first = self.unread_attachments == 1
            if first:
                log.warning("ROS 2 attachment not read on %s (%s): the messages are taken, their losses uncounted",
                            sample.key_expr, e)
            return None
        with self._lock:
            last = self.last_seq.get(gid)
            if last is not None and seq > last + 1:
                self.dropped += seq - last - 1
            self.last_seq[gid] = seq
        return stamp

    def _take(self, sample, kind: str, decode) -> None:
        key = str(sample.key_expr)
        source_ns = self._source_ns(sample)
        try:
            msg = decode(sample.payload.to_bytes(), source_ns)
            codec.encode(kind, msg)  # the same validation as any twin telemetry
        except Exception as e:  # malformed CDR, attachment or JSON: count, log, go on
            self._leave_out("malformed ROS 2 messages (CDR, attachment, or values that are not finite numbers)",
                            f"{key}: {e}")
            return
        if kind == "action" or msg["stamp"] <= 0:  # no stamp of its own: stamped by the robot's clock as it comes
            msg = {**msg, "stamp": None, "sent": source_ns * 1e-9 if source_ns else None}
        self._admit(kind, msg)

    def _on_joint(self, sample) -> None:
        self._take(sample, "joint_state", self._joint_state)

    def _joint_state(self, payload: bytes, source_ns: int | None) -> dict:
        """A decoded JointState whose NaN velocities or efforts (a gripper driver's) are filled from the joint state
        before, as a replay fills them (:func:`~protocol.joints.fill_unknown`): the positions still say where the
        robot is, and leaving every such message out would freeze the twin's robot. A NaN position is left out."""
        msg: dict = dict(decode_joint_state(payload, source_ns, fallback=False))
        if not all(math.isfinite(v) for v in msg["position"]):  # (left out by the validation after this)
            return msg
        return self._fill(msg)

    def _on_action(self, sample) -> None:
        self._take(sample, "action", decode_action)

    def warnings(self) -> list[str]:
        """The robot's telemetry the twin could not use, and what never came: publications missing from their
        publishers' sequence numbers (lost in transit; a lost action read as a task the twin joined late)."""
        out = super().warnings()
        if self.dropped:
            out.append(f"{self.dropped} of the robot's ROS 2 publication{'s' * (self.dropped > 1)} never came (gaps in "
                       "their publishers' sequence numbers): lost on the way")
        return out

    def notes(self) -> list[str]:
        """The base's notes, and publications whose attachment could not be read (their data was taken)."""
        out = super().notes()
        if self.unread_attachments:
            n = self.unread_attachments
            out.append(f"{n} of the robot's ROS 2 publication{'s' * (n > 1)} carried an attachment the twin could not "
                       "read (another rmw_zenoh release's layout?): taken all the same, but a loss on the way among "
                       "them would not be counted")
        return out

    def lag_stats(self) -> dict:
        s = super().lag_stats()
        s.update(ros2_domain=self.domain, received={k: self.queued[k] for k in ("joint_state", "action")},
                 malformed=self.malformed, sequence_gaps=self.dropped)
        return s

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass
        self._subs = []
        super().close()  # (its relay's publishers)
