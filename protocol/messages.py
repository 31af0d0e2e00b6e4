"""Message types of the twin and their schemas.

A message is a msgpack map with ``v`` (protocol version) and ``type``. :data:`SCHEMAS` lists, per
type, its fields and their types; a field name ending in ``?`` may be absent, a type ending in ``?``
may be ``None``. :class:`Message` is the decoded, validated form: a dict with attribute access
(``msg.tick``), so hot paths stay cheap and model code stays readable.

Value conventions shared by every model:
- ``pose``: ``[x, y, z, qx, qy, qz, qw]`` in metres, world frame (quaternion xyzw);
- handover values may carry ``extra`` (e.g. ``{"velocity": [vx, vy, vz, wx, wy, wz]}``);
- telemetry joint state: ``{"stamp", "name", "position", "velocity", "effort"}`` (lists of equal length);
- telemetry action: ``{"stamp", "operation", "phase": "start"|"end", "params": {...}}``.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .errors import ProtocolError

PROTOCOL_VERSION = 1

STEP_STATUSES = ("ok", "warning", "discard", "error", "fatal")
STEP_MODES = ("service", "clock", "free")
ROLES = ("simulation", "observer")

SCHEMAS: dict[str, dict[str, str]] = {
    # agent -> conductor/register
    "register": {
        "name": "str", "kind": "str", "role": "str", "step_mode": "str", "rate": "num?",
        "params": "map", "attributes": "list", "outputs": "list", "events": "list",
        "evaluators": "list", "services": "list", "pid?": "int", "host?": "str", "telemetry?": "bool", "reads?": "list",
        "clock_ack?": "bool",  # a clock-driven model that answers each clock tick on done/<id>
        "batch?": "bool",  # a service model that steps the batches of ticks in tick.more
    },
    "register_reply": {"id": "str", "accepted": "bool", "reason?": "str"},
    # conductor -> model/<id>/params (request is "query"; reply:)
    "query": {"args?": "any"},
    "params_reply": {"params": "map"},
    # conductor -> model/<id>/init
    "init": {
        "params": "map", "scene": "map", "owned": "list", "rate": "num", "base_rate": "num",
        "step_mode": "str", "models": "map",
    },
    "ack": {"ok": "bool", "message?": "str", "value?": "any"},
    "start": {"tick": "int", "t": "num"},
    "stop": {"reason?": "str"},
    # conductor -> model/<id>/step
    "step": {
        "tick": "int", "t": "num", "dt": "num", "telemetry": "map", "inputs": "map",
        "ownership": "int",
    },
    "step_reply": {
        "tick": "int", "status": "str", "state": "map", "outputs": "map", "events": "list",
        "message?": "str", "step_s?": "num",
        "more?": "list",  # the replies to this model's later ticks of a batched tick message, in order
    },
    # conductor -> step (broadcast): shared joints + one section {dt, actions, inputs} per model due
    # (models without telemetry or inputs are listed in "due" and share the "shared" section);
    # a batch carries the following ticks, each of the same shape, in "more"
    "tick": {"tick": "int", "t": "num", "joints": "map?", "models": "map", "due?": "list", "shared?": "map",
             "more?": "list"},
    "clock": {"tick": "int", "t": "num", "dt": "num", "telemetry?": "map", "inputs?": "map"},
    "state": {"model": "str", "tick": "int", "t": "num", "values": "map"},
    "out": {"model": "str", "name": "str", "tick": "int", "t": "num", "value": "any"},
    "event": {"model": "str", "name": "str", "tick": "int", "t": "num", "data": "map"},
    "ownership": {
        "version": "int", "tick": "int", "t": "num", "owners": "map", "change": "map?",
    },
    # handover
    "release": {"entity": "str", "attribute": "str", "tick": "int", "t": "num"},
    "release_reply": {"entity": "str", "attribute": "str", "value": "any", "extra": "map"},
    "acquire": {
        "entity": "str", "attribute": "str", "value": "any", "extra": "map", "tick": "int", "t": "num",
    },
    # evaluators and services
    "eval": {"args": "list", "tick": "int", "t": "num"},
    "call": {"args": "list", "kwargs": "map", "tick": "int", "t": "num"},
    "value_reply": {"value": "any"},
    "error": {"kind": "str", "message": "str", "traceback?": "str"},
    # telemetry
    "joint_state": {
        "stamp": "num", "name": "list", "position": "list", "velocity": "list", "effort": "list",
    },
    "action": {"stamp": "num", "operation": "str", "phase": "str", "params": "map"},
    # conductor status / control
    "status": {"fields": "map"},
    "control": {"args?": "map"},
}

_TYPES: dict[str, Any] = {
    "str": str,
    "int": int,
    "num": (int, float),
    "bool": bool,
    "map": dict,
    "list": (list, tuple, np.ndarray),
    "any": object,
}


def _compile(schema: dict[str, str]) -> tuple:
    out = []
    for fname, tname in schema.items():
        optional = fname.endswith("?")
        nullable = tname.endswith("?")
        base = tname[:-1] if nullable else tname
        out.append((fname[:-1] if optional else fname, optional, nullable or base == "any", base,
                    _TYPES[base], base in ("int", "num")))
    return tuple(out)


_COMPILED: dict[str, tuple] = {}


def check_fields(key: str, mtype: str, schema: dict[str, str], obj: dict) -> None:
    """Raise ProtocolError if ``obj`` does not carry the fields of ``schema`` with the right types."""
    compiled = _COMPILED.get(mtype)
    if compiled is None or SCHEMAS.get(mtype) is not schema:
        compiled = _compile(schema)
        if SCHEMAS.get(mtype) is schema:
            _COMPILED[mtype] = compiled
    for name, optional, nullable, base, py, numeric in compiled:
        if name not in obj:
            if optional:
                continue
            raise ProtocolError(key, f"{mtype} message lacks field {name!r}")
        val = obj[name]
        if val is None:
            if nullable:
                continue
            raise ProtocolError(key, f"{mtype}.{name} must not be null")
        if not isinstance(val, py) or (numeric and isinstance(val, bool)):
            got = "bool" if isinstance(val, bool) else type(val).__name__
            raise ProtocolError(key, f"{mtype}.{name} must be {base}, got {got}")
    if mtype == "step_reply" and obj["status"] != "ok" and obj["status"] not in STEP_STATUSES:
        raise ProtocolError(key, f"step_reply.status must be one of {STEP_STATUSES}, got {obj['status']!r}")
    more = obj.get("more") if mtype in ("tick", "step_reply") else None
    if more is not None:
        _check_more(key, mtype, schema, obj, more)
    if mtype == "register":
        if obj["step_mode"] not in STEP_MODES:
            raise ProtocolError(key, f"register.step_mode must be one of {STEP_MODES}")
        if obj["role"] not in ROLES:
            raise ProtocolError(key, f"register.role must be one of {ROLES}")
    if mtype == "joint_state":
        n = len(obj["name"])
        for f in ("position", "velocity", "effort"):
            if len(obj[f]) not in (0, n):
                raise ProtocolError(key, f"joint_state.{f} has {len(obj[f])} values for {n} names")
    if mtype == "action" and obj["phase"] not in ("start", "end"):
        raise ProtocolError(key, f"action.phase must be 'start' or 'end', got {obj['phase']!r}")


def _check_more(key: str, mtype: str, schema: dict[str, str], obj: dict, more) -> None:
    """The later ticks of a batch (``tick.more``, ``step_reply.more``): each one a message of the same type,
    in increasing tick order, none with a batch of its own."""
    if more.__class__ is not list:
        raise ProtocolError(key, f"{mtype}.more must be a list of {mtype} messages")
    last = obj["tick"]
    for i, item in enumerate(more):
        where = f"{mtype}.more[{i}]"
        if item.__class__ is not dict:
            raise ProtocolError(key, f"{where} must be a map")
        if "more" in item:
            raise ProtocolError(key, f"{where} must not carry a batch of its own")
        if mtype == "step_reply" and (item.get("v") != PROTOCOL_VERSION or item.get("type") != mtype):
            raise ProtocolError(key, f"{where} must be a step_reply of protocol version {PROTOCOL_VERSION}")
        try:
            check_fields(key, mtype, schema, item)
        except ProtocolError as e:
            raise ProtocolError(key, f"in {where}: {e.problem}") from None
        if item["tick"] <= last:
            raise ProtocolError(key, f"{where}.tick {item['tick']} does not follow tick {last}")
        last = item["tick"]


class Message(dict):
    """A decoded, validated message: a dict whose fields also read as attributes."""

    __slots__ = ()

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def mtype(self) -> str:
        return self["type"]
