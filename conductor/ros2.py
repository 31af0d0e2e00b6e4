"""Attach the twin to a ROS 2 robot that talks over ``rmw_zenoh`` (no ROS 2 installation needed).

A ROS 2 node using ``rmw_zenoh_cpp`` publishes each message with a Zenoh ``put`` (rmw_zenoh
``docs/design.md``, sections "Topic and Service name mapping to Zenoh key expressions" and "Publishers"):

* key expression ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, the topic's name
  without its leading ``/`` (namespaces stay as key chunks: ``0/robot1/joint_states/...``), the DDS type
  name (``sensor_msgs::msg::dds_::JointState_``) and the REP-2016 type hash (``RIHS01_<sha256>``);
* payload: the message in CDR, with its 4-byte encapsulation header;
* attachment (33 bytes): sequence number (int64 LE), source timestamp (int64 ns since the epoch, LE),
  GID length (one byte, 16) and the publisher's GID (16 bytes).

Graph discovery uses liveliness tokens ``@ros2_lv/<domain>/<session>/<node>/<entity>/<kind>/<enclave>/
<namespace>/<node name>[/<topic>/<type>/<hash>/<qos>]`` where namespaces and topic names are *mangled*
(every ``/`` becomes ``%``, an empty one is ``%``). The twin does not need them to subscribe, but
:class:`Ros2Publisher` declares them so a ROS 2 graph sees ``twin robot play --ros2-domain N``.

:class:`Ros2Source` subscribes to ``/joint_states`` (``sensor_msgs/msg/JointState``) and ``/action``
(``std_msgs/msg/String`` holding the twin's JSON action annotation) of one domain, any type hash (the hash
differs between ROS 2 distributions), decodes the CDR with ``mcap_ros2`` and feeds the conductor exactly as
:class:`~conductor.sources.LiveSource` does (wall-clock pacing, lag, coalescing rule). It also republishes
what it takes on ``twin/<ensemble>/telemetry/...`` so clock-driven and free-running models and the run log
see the robot as they would see ``twin robot play``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import struct
import time

from protocol import codec
from protocol.errors import ProtocolError

from .rosbag import JOINT_STATE_DEF, STRING_DEF
from .sources import LiveSource

log = logging.getLogger("twin.ros2")

JOINT_STATE = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"
#: REP-2016 type hashes (ROS 2 Jazzy and later); subscribers accept any hash
TYPE_HASHES = {
    JOINT_STATE: "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    STRING: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
}
LIVELINESS_PREFIX = "@ros2_lv"
DEFAULT_QOS = "::,10:,:,:,,"  # reliable, volatile, keep-last 10 (rmw_zenoh's compact form)
CDR_LE = b"\x00\x01\x00\x00"
ATTACHMENT = struct.Struct("<qqB16s")  # 33 bytes


# ----------------------------------------------------------------- naming
def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """rmw_zenoh's mangling for liveliness tokens: every ``/`` becomes ``%`` (empty -> ``%``)."""
    return name.replace("/", "%") if name else "%"


def fully_qualified(topic: str, namespace: str = "") -> str:
    """``/joint_states`` in namespace ``/robot1`` -> ``/robot1/joint_states`` (absolute topics stay)."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if topic.startswith("/"):
        return topic if not ns or topic.startswith(ns + "/") else ns + topic
    return f"{ns}/{topic}"


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str = "*", namespace: str = "") -> str:
    """The data key expression of a topic (``type_hash='*'`` matches every distribution's hash)."""
    fq = fully_qualified(topic, namespace).lstrip("/")
    return f"{int(domain)}/{fq}/{dds_type_name(ros_type)}/{type_hash}"


def liveliness_key(domain: int, session_id: str, node_id: int, entity_id: int, kind: str, node: str,
                   namespace: str = "", enclave: str = "", topic: str | None = None, ros_type: str | None = None,
                   type_hash: str | None = None, qos: str = DEFAULT_QOS) -> str:
    """A graph-cache liveliness token: ``NN`` (node) or ``MP``/``MS``/``SS``/``SC`` with the topic part."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    key = f"{LIVELINESS_PREFIX}/{int(domain)}/{session_id}/{node_id}/{entity_id}/{kind}/{mangle(enclave)}/{mangle(ns)}/{node}"
    if topic is not None:
        key += f"/{mangle(fully_qualified(topic, namespace))}/{dds_type_name(ros_type)}/{type_hash}/{qos}"
    return key


# ------------------------------------------------------------- attachment
def encode_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    if len(gid) != 16:
        raise ValueError("a publisher GID has 16 bytes")
    return ATTACHMENT.pack(int(seq), int(stamp_ns), 16, bytes(gid))


def decode_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp in ns, GID); raises ValueError on anything else."""
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"rmw_zenoh attachment has {ATTACHMENT.size} bytes, got {len(data)}")
    seq, stamp, n, gid = ATTACHMENT.unpack(data)
    if n != 16:
        raise ValueError(f"GID length must be 16, got {n}")
    return seq, stamp, gid


# -------------------------------------------------------------------- CDR
class _CdrOut:
    """Little-endian CDR writer; alignment counts from the end of the encapsulation header."""

    def __init__(self):
        self.buf = bytearray()

    def _align(self, n: int) -> None:
        self.buf += b"\x00" * (-len(self.buf) % n)

    def u32(self, v: int, fmt: str = "<I") -> None:
        self._align(4)
        self.buf += struct.pack(fmt, v)

    def string(self, s: str) -> None:
        raw = s.encode() + b"\x00"
        self.u32(len(raw))
        self.buf += raw

    def f64_seq(self, values) -> None:
        values = [float(x) for x in values]
        self.u32(len(values))
        if values:
            self._align(8)
            self.buf += struct.pack(f"<{len(values)}d", *values)

    def bytes(self) -> bytes:
        return CDR_LE + bytes(self.buf)


def encode_joint_state(stamp: float, names, position, velocity, effort, frame_id: str = "") -> bytes:
    """``sensor_msgs/msg/JointState`` in CDR (stamp in seconds since the epoch)."""
    sec = math.floor(stamp)
    nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)
    w = _CdrOut()
    w.u32(int(sec), "<i")
    w.u32(nanosec)
    w.string(frame_id)
    w.u32(len(names))
    for n in names:
        w.string(str(n))
    w.f64_seq(position)
    w.f64_seq(velocity)
    w.f64_seq(effort)
    return w.bytes()


def encode_string(text: str) -> bytes:
    """``std_msgs/msg/String`` in CDR."""
    w = _CdrOut()
    w.string(text)
    return w.bytes()


_DECODERS: dict[str, object] = {}


def decoder(ros_type: str):
    """A CDR decoder for ``ros_type`` built by ``mcap_ros2`` from the message definition."""
    dec = _DECODERS.get(ros_type)
    if dec is None:
        from mcap.records import Schema
        from mcap_ros2.decoder import DecoderFactory

        text = {JOINT_STATE: JOINT_STATE_DEF, STRING: STRING_DEF}[ros_type]
        dec = DecoderFactory().decoder_for("cdr", Schema(id=1, name=ros_type, encoding="ros2msg", data=text.encode()))
        _DECODERS[ros_type] = dec
    return dec


def decode_joint_state(payload: bytes, source_ns: int | None = None) -> dict:
    """CDR JointState -> the twin's ``joint_state`` fields (stamp: header stamp, else the source time)."""
    m = decoder(JOINT_STATE)(payload)
    stamp = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
    if stamp <= 0:
        stamp = source_ns * 1e-9 if source_ns else time.time()
    msg = {"stamp": stamp, "name": [str(n) for n in m.name], "position": [float(x) for x in m.position],
           "velocity": [float(x) for x in m.velocity], "effort": [float(x) for x in m.effort]}
    return msg


def decode_action(payload: bytes, source_ns: int | None = None) -> dict:
    """CDR String holding ``{"operation", "phase", "params"}`` JSON -> the twin's ``action`` fields."""
    m = decoder(STRING)(payload)
    a = json.loads(m.data)
    if not isinstance(a, dict) or "operation" not in a:
        raise ValueError("the /action string must be a JSON object with 'operation'")
    return {"stamp": source_ns * 1e-9 if source_ns else time.time(), "operation": str(a["operation"]),
            "phase": str(a.get("phase", "start")), "params": dict(a.get("params") or {})}


# ----------------------------------------------------------------- source
class Ros2Source(LiveSource):
    """Live telemetry from a ROS 2 robot on rmw_zenoh (domain ``domain``, optional ``namespace``).

    Same contract as :class:`~conductor.sources.LiveSource`: every tick takes what arrived, lag is
    measured against the message's stamp (the JointState header, else the attachment's source time),
    and joint states more than ``max_backlog`` seconds behind are coalesced to the newest.
    """

    def __init__(self, session, keys, domain: int = 0, namespace: str = "", joint_topic: str = "/joint_states",
                 action_topic: str = "/action", idle_timeout: float = 3.0, max_backlog: float = 0.25,
                 wait_first: float = 30.0, republish: bool = True):
        # the LiveSource state, without its subscription on twin/<e>/telemetry/**
        self._init_state(idle_timeout, max_backlog, wait_first)
        self.session = session
        self.keys = keys
        self.domain = int(domain)
        self.received = {"joint_state": 0, "action": 0}
        self.last_seq: dict[bytes, int] = {}
        self.dropped = 0  # gaps in a publisher's sequence numbers
        self.joint_key = topic_key(domain, joint_topic, JOINT_STATE, "*", namespace)
        self.action_key = topic_key(domain, action_topic, STRING, "*", namespace)
        self._republish = republish
        self._pubs: dict[str, object] = {}
        self._subs = [session.declare_subscriber(self.joint_key, self._on_joint),
                      session.declare_subscriber(self.action_key, self._on_action)]
        self._sub = None
        log.info("ROS 2 attach: %s and %s", self.joint_key, self.action_key)

    def _source_ns(self, sample) -> int | None:
        att = sample.attachment
        if att is None:
            return None
        seq, stamp, gid = decode_attachment(att.to_bytes())
        last = self.last_seq.get(gid)
        if last is not None and seq > last + 1:
            self.dropped += seq - last - 1
        self.last_seq[gid] = seq
        return stamp

    def _take(self, sample, kind: str, decode) -> None:
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes(), self._source_ns(sample))
            codec.encode(kind, msg)  # the same validation as any twin telemetry
        except Exception as e:  # malformed CDR, attachment or JSON: count, log, go on
            self.malformed += 1
            log.warning("malformed ROS 2 message #%d on %s: %s", self.malformed, key, e)
            return
        with self._lock:
            self._q.append((time.time(), kind, msg))
            self._last_arrival = time.monotonic()
            self.received[kind] += 1

    def _on_joint(self, sample) -> None:
        self._take(sample, "joint_state", decode_joint_state)

    def _on_action(self, sample) -> None:
        self._take(sample, "action", decode_action)

    def due(self, t: float) -> list[tuple[str, dict]]:
        out = super().due(t)
        if self._republish:
            for kind, msg in out:  # from the conductor's thread, never from a Zenoh callback
                key = self.keys.telemetry("joint_states" if kind == "joint_state" else "action")
                pub = self._pubs.get(key)
                if pub is None:
                    pub = self._pubs[key] = self.session.declare_publisher(key)
                try:
                    pub.put(codec.encode(kind, msg))
                except ProtocolError as e:
                    log.warning("not republished: %s", e)
        return out

    def lag_stats(self) -> dict:
        s = super().lag_stats()
        s.update(ros2_domain=self.domain, received=dict(self.received), malformed=self.malformed,
                 sequence_gaps=self.dropped)
        return s

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass
        self._subs = []


# -------------------------------------------------------------- publisher
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
            self._tokens.append(session.liveliness().declare_token(
                liveliness_key(domain, sid, 0, eid, "MP", node, namespace, topic=topic, ros_type=ros_type, type_hash=h)))

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
