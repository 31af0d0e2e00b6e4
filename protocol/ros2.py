"""ROS 2 on Zenoh (``rmw_zenoh``) as the twin speaks it: key expressions, attachments, liveliness
tokens and the CDR of the two message types a robot sends (no ROS 2 installation needed).

A ROS 2 node using ``rmw_zenoh_cpp`` publishes each message with a Zenoh ``put`` (rmw_zenoh
``docs/design.md``, sections "Topic and Service name mapping to Zenoh key expressions" and "Publishers"):

* key expression ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, the topic's name
  without its leading ``/`` (namespaces stay as key chunks: ``0/robot1/joint_states/...``), the DDS type
  name (``sensor_msgs::msg::dds_::JointState_``) and the REP-2016 type hash (``RIHS01_<sha256>``);
* payload: the message in CDR, with its 4-byte encapsulation header;
* attachment (33 bytes): sequence number (int64 LE), source timestamp (int64 ns since the epoch, LE),
  GID length (one byte, 16) and the publisher's GID (16 bytes); rmw_zenoh's first releases (Jazzy 0.2.0-0.2.3,
  Humble 0.1.0-0.1.1) wrote each of the three after its name, which is read too.

Graph discovery uses liveliness tokens ``@ros2_lv/<domain>/<session>/<node>/<entity>/<kind>/<enclave>/
<namespace>/<node name>[/<topic>/<type>/<hash>/<qos>]`` where namespaces and topic names are *mangled*
(every ``/`` becomes ``%``, an empty one is ``%``). The twin does not need them to subscribe, but
:class:`recordings.player.Ros2Publisher` declares them so a ROS 2 graph sees ``twin robot play --ros2-domain N``.

:class:`conductor.sources.ros2.Ros2Source` subscribes to ``/joint_states`` (``sensor_msgs/msg/JointState``)
and ``/action`` (``std_msgs/msg/String`` holding the twin's JSON action annotation) of one domain, any type
hash (the hash differs between ROS 2 distributions), decodes the CDR with ``mcap_ros2`` and feeds the conductor
exactly as :class:`~conductor.sources.live.LiveSource` does (wall-clock pacing, lag, coalescing rule). It also
republishes what it takes on ``twin/<ensemble>/telemetry/...`` so clock-driven and free-running models and the
run log see the robot as they would see ``twin robot play``.
"""
from __future__ import annotations

import json
import math
import re
import struct
import time
from collections.abc import Callable, Collection, Iterable
from functools import lru_cache
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, cast, overload

import numpy as np
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

if TYPE_CHECKING:
    from .messages import Action, JointState

__all__ = ["JOINT_STATE", "STRING", "JOINT_STATE_DEF", "STRING_DEF", "TYPE_HASHES", "LIVELINESS_PREFIX", "DEFAULT_QOS",
           "CDR_LE", "ATTACHMENT", "dds_type_name", "mangle", "NAMESPACE_RULE", "namespace_problem", "fully_qualified",
           "topic_key", "liveliness_key", "encode_attachment", "decode_attachment", "encode_joint_state",
           "encode_string", "Decoder", "decoder", "read_joint_state", "joint_state_message", "same_joint_state",
           "decode_joint_state", "decode_action", "parse_action"]

JOINT_STATE = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"
#: the ROS 2 message definitions of the two types the twin reads and writes (rosbag2 schemas, CDR decoders)
JOINT_STATE_DEF = """std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
STRING_DEF = "string data\n"
#: REP-2016 type hashes (ROS 2 Jazzy and later); subscribers accept any hash
TYPE_HASHES = {
    JOINT_STATE: "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    STRING: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
}
LIVELINESS_PREFIX = "@ros2_lv"
DEFAULT_QOS = "::,10:,:,:,,"  # reliable, volatile, keep-last 10 (rmw_zenoh's compact form)
CDR_LE = b"\x00\x01\x00\x00"
"""The encapsulation header of little-endian plain CDR."""
ATTACHMENT = struct.Struct("<qqB16s")  # 33 bytes
"""rmw_zenoh's attachment: sequence number, source timestamp (ns), GID length, GID."""


# ----------------------------------------------------------------- naming
def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (ValueError unless the type
    has the three parts ``package/kind/Name``)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """rmw_zenoh's mangling for liveliness tokens: every ``/`` becomes ``%`` (empty -> ``%``)."""
    return name.replace("/", "%") if name else "%"


_NAMESPACE = re.compile(r"/?([A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*)?/?")


NAMESPACE_RULE = "e.g. /robot1 or /lab/arm_2: names of letters, digits and underscores, not beginning with a digit"
"""What a ROS 2 namespace is, in words (:func:`namespace_problem`)."""


def namespace_problem(namespace: str) -> str | None:
    """What is wrong with ``namespace`` as a ROS 2 namespace (names of letters, digits and underscores, not
    beginning with a digit, between slashes), or None: anything else makes a key expression Zenoh refuses (``a//b``,
    ``a*b``) once a run has begun, or one no ROS 2 node could have (``robot 1``)."""
    if _NAMESPACE.fullmatch(namespace):
        return None
    return f"not a ROS 2 namespace: {namespace!r} ({NAMESPACE_RULE})"


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


@overload
def liveliness_key(domain: int, session_id: str, node_id: int, entity_id: int, kind: str, node: str,
                   namespace: str = "", enclave: str = "", topic: None = None, ros_type: None = None,
                   type_hash: None = None, qos: str = DEFAULT_QOS) -> str: ...
@overload
def liveliness_key(domain: int, session_id: str, node_id: int, entity_id: int, kind: str, node: str,
                   namespace: str = "", enclave: str = "", *, topic: str, ros_type: str,
                   type_hash: str, qos: str = DEFAULT_QOS) -> str: ...
def liveliness_key(domain: int, session_id: str, node_id: int, entity_id: int, kind: str, node: str,
                   namespace: str = "", enclave: str = "", topic: str | None = None, ros_type: str | None = None,
                   type_hash: str | None = None, qos: str = DEFAULT_QOS) -> str:
    """A graph-cache liveliness token: ``NN`` (node) or ``MP``/``MS``/``SS``/``SC`` with the topic part
    (``topic``, ``ros_type`` and ``type_hash`` go together)."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    key = (f"{LIVELINESS_PREFIX}/{int(domain)}/{session_id}/{node_id}/{entity_id}/{kind}/{mangle(enclave)}/"
           f"{mangle(ns)}/{node}")
    if topic is not None:
        # the overloads give ros_type with topic; a None here fails in dds_type_name, as it always has
        key += f"/{mangle(fully_qualified(topic, namespace))}/{dds_type_name(cast(str, ros_type))}/{type_hash}/{qos}"
    return key


# ------------------------------------------------------------- attachment
def encode_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of a publication (sequence number, source timestamp in ns since the epoch,
    the publisher's GID); ValueError unless ``gid`` has 16 bytes."""
    if len(gid) != 16:
        raise ValueError("a publisher GID has 16 bytes")
    return ATTACHMENT.pack(int(seq), int(stamp_ns), 16, bytes(gid))


def decode_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp in ns, GID) of the 33-byte attachment, or of the keyed one of rmw_zenoh's
    first releases (Jazzy 0.2.0-0.2.3, Humble 0.1.0-0.1.1: each value after its name, :func:`_keyed_attachment`);
    raises ValueError on anything else."""
    if len(data) != ATTACHMENT.size:
        return _keyed_attachment(data)
    seq, stamp, n, gid = ATTACHMENT.unpack(data)
    if n != 16:
        raise ValueError(f"GID length must be 16, got {n}")
    return seq, stamp, gid


_KEYED = ("sequence_number", "source_timestamp", "source_gid")


def _keyed_attachment(data: bytes) -> tuple[int, int, bytes]:
    """The keyed attachment, as Zenoh's serializer writes it: ``sequence_number`` (a string: its length as a
    varint, its bytes), an int64 LE; ``source_timestamp``, an int64 LE; ``source_gid``, its bytes' count as a
    varint, its bytes."""
    at, values = 0, {}

    def varint() -> int:
        nonlocal at
        n = shift = 0
        while at < len(data) and shift < 35:
            b = data[at]
            at += 1
            n |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return n
        raise ValueError("rmw_zenoh attachment: a length cut short")

    def chunk(n: int) -> bytes:
        nonlocal at
        if at + n > len(data):
            raise ValueError("rmw_zenoh attachment: cut short")
        at += n
        return data[at - n:at]

    for name in _KEYED:
        key = chunk(varint())
        if key != name.encode():
            raise ValueError(f"rmw_zenoh attachment of {len(data)} bytes: neither the 33-byte one nor the keyed one "
                             f"(found {key[:24]!r} where {name!r} goes)")
        values[name] = chunk(varint()) if name == "source_gid" else struct.unpack("<q", chunk(8))[0]
    if at != len(data) or not 0 < len(values["source_gid"]) <= 24:
        raise ValueError(f"rmw_zenoh keyed attachment of {len(data)} bytes: not its layout")
    return int(values["sequence_number"]), int(values["source_timestamp"]), bytes(values["source_gid"])


# -------------------------------------------------------------------- CDR
class _CdrOut:
    """Little-endian CDR writer; alignment counts from the end of the encapsulation header."""

    def __init__(self) -> None:
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

    def f64_seq(self, values: Iterable[float]) -> None:
        seq = values if isinstance(values, (list, tuple, np.ndarray)) else list(values)
        arr = np.ascontiguousarray(seq, dtype="<f8").reshape(-1)
        self.u32(arr.size)
        if arr.size:
            self._align(8)
            self.buf += arr.tobytes()

    def bytes(self) -> bytes:
        return CDR_LE + bytes(self.buf)


def encode_joint_state(stamp: float, names: Collection[str], position: Iterable[float], velocity: Iterable[float],
                       effort: Iterable[float], frame_id: str = "", stamp_ns: int | None = None) -> bytes:
    """``sensor_msgs/msg/JointState`` in CDR (stamp in seconds since the epoch, or exactly ``stamp_ns``
    nanoseconds; rad or m, rad/s or m/s, Nm or N; velocity and effort may be empty)."""
    if stamp_ns is not None:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    else:
        sec = math.floor(stamp)
        nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)
    given = tuple(names)
    try:
        block = _names_block(frame_id, given)
    except AttributeError:  # a name that is not a str
        block = _names_block(frame_id, tuple(str(n) for n in given))
    seqs = [_floats(v) for v in (position, velocity, effort)]
    try:  # (every run log writes one for each joint state it holds: one struct, its layout worked out once)
        tail = _sequences(len(block), *map(len, seqs)).pack(*_counted(seqs))
    except struct.error:  # a value struct does not take as a float (a numeric string, ...): as numpy converts it
        w = _CdrOut()
        w.buf += bytes(8) + block
        for v in seqs:
            w.f64_seq(v)
        tail = bytes(w.buf[8 + len(block):])
    return CDR_LE + _STAMP.pack(int(sec), nanosec) + block + tail


_STAMP = struct.Struct("<iI")


def _floats(values: Iterable[float]) -> list[float] | tuple[float, ...]:
    if isinstance(values, (list, tuple)):
        return values
    if isinstance(values, np.ndarray):
        return cast("list[float]", values.reshape(-1).tolist())
    return list(values)


def _counted(seqs: list[list[float] | tuple[float, ...]]) -> list[float | int]:
    out: list[float | int] = []
    for v in seqs:
        out.append(len(v))
        out.extend(v)
    return out


@lru_cache(maxsize=256)
def _sequences(names_len: int, *lengths: int) -> struct.Struct:
    """The struct of a JointState's float64 sequences (each a count, then its values), after the 8-byte stamp and
    ``names_len`` bytes of frame id and names, with the padding CDR aligns them by (as :class:`_CdrOut`)."""
    at, fmt = 8 + names_len, "<"
    for n in lengths:
        pad = -at % 4
        fmt += f"{pad}xI" if pad else "I"
        at += pad + 4
        if n:
            pad = -at % 8
            fmt += f"{pad}x{n}d" if pad else f"{n}d"
            at += pad + 8 * n
    return struct.Struct(fmt)


@lru_cache(maxsize=64)
def _names_block(frame_id: str, names: tuple[str, ...]) -> bytes:
    """The CDR of a JointState's ``header.frame_id`` and ``name`` after its 8-byte stamp (they repeat from one
    message to the next: encoded once)."""
    w = _CdrOut()
    w.buf += bytes(8)  # the stamp's place, so that the alignment counts as in the message
    w.string(frame_id)
    w.u32(len(names))
    for n in names:
        w.string(n)
    return bytes(w.buf[8:])


def encode_string(text: str) -> bytes:
    """``std_msgs/msg/String`` in CDR."""
    w = _CdrOut()
    w.string(text)
    return w.bytes()


Decoder = Callable[[bytes], SimpleNamespace]
"""A CDR decoder: payload (with its encapsulation header) -> the message, fields as attributes."""

_DECODERS: dict[str, Decoder] = {}


def decoder(ros_type: str) -> Decoder:
    """A CDR decoder for ``ros_type`` (:data:`JOINT_STATE` or :data:`STRING`, KeyError otherwise) built by
    ``mcap_ros2`` from the message definition, once."""
    dec = _DECODERS.get(ros_type)
    if dec is None:
        text = {JOINT_STATE: JOINT_STATE_DEF, STRING: STRING_DEF}[ros_type]
        dec = DecoderFactory().decoder_for("cdr", Schema(id=1, name=ros_type, encoding="ros2msg", data=text.encode()))
        if dec is None:  # mcap_ros2 declines only other encodings than cdr and ros2msg
            raise RuntimeError(f"mcap_ros2 gives no CDR decoder for {ros_type}")
        _DECODERS[ros_type] = dec
    return dec


_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")


def read_joint_state(payload: bytes) -> SimpleNamespace:
    """A little-endian CDR ``sensor_msgs/msg/JointState`` read directly (several times faster than the decoder
    ``mcap_ros2`` builds from the definition, which reads one field at a time): the same attributes
    (``header.stamp.sec``, ``header.frame_id``, ``name``, ``position``, ``velocity``, ``effort``, the sequences
    as lists). Raises ValueError when the payload is not one (cut short, big-endian, lengths that overrun it)."""
    if len(payload) < 16 or payload[1] != 1:
        raise ValueError("not a little-endian CDR JointState")
    buf = bytes(payload[4:])
    n = len(buf)
    u32 = _U32.unpack_from
    try:
        sec, nanosec = _STAMP.unpack_from(buf, 0)
        strings: list[str] = []
        (k,) = u32(buf, 8)  # frame_id's length with its NUL
        off = 12 + k
        if k < 1 or off > n:
            raise ValueError("JointState frame_id overruns the message")
        frame_id = buf[12:off - 1].decode()
        off += -off % 4
        (count,) = u32(buf, off)
        off += 4
        if count > n:
            raise ValueError("JointState name count overruns the message")
        for _ in range(count):
            off += -off % 4
            (k,) = u32(buf, off)
            end = off + 4 + k
            if k < 1 or end > n:
                raise ValueError("JointState string overruns the message")
            strings.append(buf[off + 4:end - 1].decode())
            off = end
        seqs: list[list[float]] = []
        for _ in range(3):
            off += -off % 4
            (count,) = u32(buf, off)
            off += 4
            if count:
                off += -off % 8
                if off + 8 * count > n:
                    raise ValueError("JointState sequence overruns the message")
                seqs.append(list(struct.unpack_from(f"<{count}d", buf, off)))
                off += 8 * count
            else:
                seqs.append([])
    except struct.error:
        raise ValueError("JointState cut short") from None
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec), frame_id=frame_id),
                           name=strings, position=seqs[0], velocity=seqs[1], effort=seqs[2])


def joint_state_message(payload: bytes) -> SimpleNamespace:
    """A CDR JointState: :func:`read_joint_state`, or (big-endian, or what it cannot read) the decoder built from
    the definition, which raises on a malformed payload."""
    try:
        return read_joint_state(payload)
    except ValueError:
        return decoder(JOINT_STATE)(payload)


def same_joint_state(a: SimpleNamespace, b: SimpleNamespace) -> bool:
    """Whether two decoded JointStates hold the same stamp, frame, names and values."""
    try:
        return bool((a.header.stamp.sec, a.header.stamp.nanosec, a.header.frame_id) ==
                    (b.header.stamp.sec, b.header.stamp.nanosec, b.header.frame_id)
                    and [str(x) for x in a.name] == [str(x) for x in b.name]
                    and all([float(x) for x in getattr(a, f)] == [float(x) for x in getattr(b, f)]
                            for f in ("position", "velocity", "effort")))
    except (AttributeError, TypeError, ValueError):
        return False


def decode_joint_state(payload: bytes, source_ns: int | None = None, fallback: bool = True) -> JointState:
    """CDR JointState -> the twin's ``joint_state`` fields (stamp: header stamp, else the source time, else now;
    ``fallback=False``: 0 when the header has none)."""
    m = joint_state_message(payload)
    stamp = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
    if stamp <= 0:
        stamp = (source_ns * 1e-9 if source_ns else time.time()) if fallback else 0.0
    msg: JointState = {"stamp": stamp, "name": [str(n) for n in m.name], "position": [float(x) for x in m.position],
           "velocity": [float(x) for x in m.velocity], "effort": [float(x) for x in m.effort]}
    return msg


def decode_action(payload: bytes, source_ns: int | None = None) -> Action:
    """CDR String holding ``{"operation", "phase", "params"}`` JSON -> the twin's ``action`` fields (stamp: the
    source time, else now). Raises ValueError saying what is wrong (:func:`parse_action`)."""
    a = parse_action(decoder(STRING)(payload).data)
    return {"stamp": source_ns * 1e-9 if source_ns else time.time(), "operation": a["operation"],
            "phase": a["phase"], "params": a["params"]}


def parse_action(text: str) -> dict[str, Any]:
    """An action annotation's JSON ``{"operation", "phase", "params"}`` -> those fields (phase ``start`` when not
    given); ValueError saying what is wrong, in the words a recording counts it by (live and replayed the same)."""
    try:
        a = json.loads(text)
    except (ValueError, RecursionError):
        raise ValueError("action annotations that are not JSON") from None
    if not isinstance(a, dict) or not isinstance(a.get("operation"), str) or not a["operation"]:
        raise ValueError("action annotations without an 'operation' name")
    phase = a.get("phase", "start")
    if phase not in ("start", "end"):
        raise ValueError("action annotations whose phase is not 'start' or 'end'")
    params = a.get("params", {}) or {}
    if not isinstance(params, dict):
        raise ValueError("action annotations whose params are not a map")
    return {"operation": a["operation"], "phase": phase, "params": params}
