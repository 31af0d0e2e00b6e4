"""How each message of the run log is written: the encodings Foxglove, Lichtblick and ``ros2 bag`` decode.

- the twin's own messages (``step``, ``done/*``, ``state/*``, ``ownership``, queries and replies, ...) as
  ``json`` with a JSON Schema named ``twin.<type>`` derived from the protocol (:func:`protocol.messages.json_schema`):
  numpy arrays become lists, bytes base64 text, a non-finite number ``null``;
- the robot's joint states as ``sensor_msgs/msg/JointState`` in ``cdr`` (schema ``ros2msg``), ``header.stamp`` on
  the log's clock, and its actions as the ``std_msgs/msg/String`` JSON of a robot's ``/action`` topic, so that
  ``ros2 bag play`` replays them and the log is a recording the twin itself reads (``twin run --recording``);
- a payload that is not a message of the protocol as ``twin.raw`` JSON (its bytes in base64 and why), so that
  nothing the ensemble sent is lost and every channel still decodes with its schema.
"""
from __future__ import annotations

import base64
import json
import math
from functools import cache
from typing import Any

import numpy as np

from protocol.messages import MESSAGES, json_schema
from protocol.ros2 import (
    JOINT_STATE,
    JOINT_STATE_DEF,
    STRING,
    STRING_DEF,
    decode_action,
    encode_joint_state,
    encode_string,
    joint_state_message,
)

try:  # several times faster than json for the step messages; writes NaN and infinities as null too
    import orjson as _orjson

    _ORJSON_OPTS = _orjson.OPT_SERIALIZE_NUMPY | _orjson.OPT_NON_STR_KEYS
except ImportError:  # pragma: no cover - a dependency, but the standard library does the same more slowly
    _orjson = None  # type: ignore[assignment]

RAW = "twin.raw"
RAW_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": RAW, "type": "object",
    "properties": {"reason": {"type": "string", "description": "why it is not a message of the protocol"},
                   "data": {"type": "string", "contentEncoding": "base64", "description": "the payload's bytes"}},
    "required": ["reason", "data"]}
ANY_SCHEMA: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "twin.any",
                              "type": "object", "properties": {"type": {"type": "string"}}, "required": ["type"]}


def _default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(obj)).decode()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def _finite(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no NaN or infinity)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def to_json(msg: Any) -> bytes:
    """``msg`` as compact JSON bytes (see the module docstring for what changes form)."""
    if _orjson is not None:
        try:
            return bytes(_orjson.dumps(msg, default=_default, option=_ORJSON_OPTS))
        except TypeError:  # what orjson declines (an integer too large, a key of another type): the standard way
            pass
    try:
        return json.dumps(msg, default=_default, allow_nan=False, separators=(",", ":")).encode()
    except ValueError:  # a NaN or an infinity somewhere: the slow path
        return json.dumps(_finite(msg), default=_default, allow_nan=False, separators=(",", ":")).encode()


def raw_json(payload: bytes, reason: str) -> bytes:
    return to_json({"reason": reason, "data": base64.b64encode(payload).decode()})


def schema_name(msg: Any) -> str:
    """The JSON schema a decoded message is written with: ``twin.<type>``, ``twin.any`` for an unknown type."""
    mtype = msg.get("type") if isinstance(msg, dict) else None
    return f"twin.{mtype}" if mtype in MESSAGES else "twin.any"


@cache
def schema_bytes(name: str) -> bytes:
    """The JSON Schema of ``name`` (``twin.<type>``, ``twin.any`` or ``twin.raw``), as the log stores it."""
    if name == RAW:
        return json.dumps(RAW_SCHEMA).encode()
    if name == "twin.any":
        return json.dumps(ANY_SCHEMA).encode()
    return json.dumps(json_schema(name.removeprefix("twin."))).encode()


ROS2MSG = {JOINT_STATE: JOINT_STATE_DEF.encode(), STRING: STRING_DEF.encode()}
"""The ``ros2msg`` schema text of each ROS 2 type the log writes, as ``ros2 bag`` writes it in MCAP."""


def joint_state_cdr(msg: dict[str, Any], stamp_ns: int) -> bytes:
    """A twin ``joint_state`` as ``sensor_msgs/msg/JointState`` CDR, stamped exactly ``stamp_ns`` (the log's clock)."""
    def seq(field: str) -> Any:
        v = msg.get(field)
        return v if v is not None else ()

    return encode_joint_state(0.0, seq("name"), seq("position"), seq("velocity"), seq("effort"), stamp_ns=stamp_ns)


def joint_state_of_cdr(data: bytes, origin_ns: int | None) -> dict[str, Any]:
    """The twin ``joint_state`` a JointState CDR message stands for; ``stamp`` is seconds since ``origin_ns`` (a
    replayed recording's start) or since the epoch when ``origin_ns`` is None (a live robot)."""
    m = joint_state_message(data)
    ns = int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec)
    return {"v": 1, "type": "joint_state", "stamp": (ns - (origin_ns or 0)) * 1e-9, "name": [str(n) for n in m.name],
            "position": [float(x) for x in m.position], "velocity": [float(x) for x in m.velocity],
            "effort": [float(x) for x in m.effort]}


def action_cdr(msg: dict[str, Any]) -> bytes:
    """A twin ``action`` as the ``std_msgs/msg/String`` JSON a robot's ``/action`` topic carries (the stamp is the
    message's log time)."""
    return encode_string(to_json({"operation": msg.get("operation"), "phase": msg.get("phase"),
                                  "params": msg.get("params") or {}}).decode())


def action_of_cdr(data: bytes, log_ns: int, origin_ns: int | None) -> dict[str, Any]:
    """The twin ``action`` an ``/action`` String stands for, stamped at its log time (as :func:`joint_state_of_cdr`)."""
    return {"v": 1, "type": "action", **decode_action(data), "stamp": (log_ns - (origin_ns or 0)) * 1e-9}


# the attributes whose values the run's schemas describe: a pose is [x, y, z, qx, qy, qz, qw]. Any other is what
# its owner says it is (a collision's True or {enabled, ignore, by}, a temperature's number): left out of the
# properties (the messages hold it; a schema may not claim a type for it, and a viewer drops a topic whose
# property has none)
VALUE_SCHEMAS: dict[str, dict[str, Any]] = {"pose": {"type": "array", "items": {"type": "number"}}}


def run_schemas(entities: dict[str, Any]) -> dict[str, bytes]:
    """The schemas of one run that name its entities, so a viewer can offer their fields (``/ownership``'s
    ``owners.<entity>.<attribute>`` for the ownership timeline, each entity's ``pose`` to plot): ``twin.ownership``,
    ``twin.state`` and ``twin.step_reply``. ``entities`` is entity -> {attributes: [...]}."""
    def attrs(value: dict[str, Any] | None) -> dict[str, Any]:
        typed = {e: {a: value or VALUE_SCHEMAS[a] for a in (spec.get("attributes") or ["pose"])
                     if value is not None or a in VALUE_SCHEMAS} for e, spec in entities.items()}
        return {"type": "object", "properties": {e: {"type": "object", "properties": props}
                                                 for e, props in typed.items() if props}}

    out: dict[str, bytes] = {}
    for mtype, field, value in (("ownership", "owners", {"type": "string"}), ("state", "values", None),
                                ("step_reply", "state", None)):
        schema = json_schema(mtype)
        described = {"description": schema["properties"][field].get("description", "")}
        schema["properties"][field] = {**attrs(value), **described}
        out[f"twin.{mtype}"] = json.dumps(schema).encode()
    return out
