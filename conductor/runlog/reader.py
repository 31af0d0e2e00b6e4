"""Reading a run log back: the twin's own messages, as the ensemble published them, from a format 2 log (JSON,
CDR) or a format 1 log (msgpack); the channels added for viewers are left out."""
from __future__ import annotations

import base64
import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from protocol import codec

from .encoding import RAW, STRING, action_of_cdr, joint_state_of_cdr

log = logging.getLogger("twin.runlog")


DT = "twin.dt"
"""Metadata of a ``done/<id>`` channel: the conductor's tick period (s), which times the results it carries."""
RESULTS = "twin.results"
"""Metadata of a ``done/<id>`` channel whose step answers carry the model's state, outputs and events: a service
model publishes those on ``state``/``out``/``event`` only while someone subscribes, so the log keeps them once,
in the answers, and :func:`read_run_log` gives them back as the messages they stand for."""


FORMAT = 2
"""The run log's format: 1 wrote msgpack (still read), 2 writes JSON/CDR/protobuf with schemas."""
LOG_INFO = "twin.log"
"""File metadata: ``format``, ``clock`` (simulated), ``origin_ns`` (the log time of simulated time 0), ``stamps``."""
KEY = "twin.key"
"""Channel metadata: the Zenoh key the channel's messages were published on (``twin/<ensemble>/...``)."""
ORIGIN = "twin.origin_ns"
"""Channel metadata of a JointState channel: the origin its stamps are taken from (empty: since the epoch)."""
VIEW = "twin.view"
"""Channel metadata of a channel derived for a viewer (:mod:`.foxglove`): not a message of the ensemble."""


def results_of(key: str, answer: Any, dt: float | None = None) -> list[tuple[str, dict[str, Any]]]:
    """The ``state``/``out``/``event`` messages a step answer on ``key`` (``twin/<e>/done/<id>``) stands for, tick
    by tick (the later ticks of a batch in ``more``), each at ``t = tick * dt`` (the conductor's clock)."""
    if not isinstance(answer, dict) or "state" not in answer:
        return []  # a clock-driven model's bare progress answer: it published its results itself
    prefix, _, mid = key.rpartition("/done/")
    out: list[tuple[str, dict[str, Any]]] = []
    for rep in [answer, *(answer.get("more") or [])]:
        if not isinstance(rep, dict):
            continue
        tick = rep.get("tick")
        t = tick * dt if dt is not None and isinstance(tick, int) else None
        env = {"v": answer.get("v", 1), "model": mid, "tick": tick, "t": t}
        if rep.get("state"):
            out.append((f"{prefix}/state/{mid}", {**env, "type": "state", "values": rep["state"]}))
        for name, value in (rep.get("outputs") or {}).items():
            out.append((f"{prefix}/out/{mid}/{name}", {**env, "type": "out", "name": name, "value": value}))
        for ev in rep.get("events") or []:
            if isinstance(ev, dict) and "name" in ev:
                out.append((f"{prefix}/event/{mid}/{ev['name']}",
                            {**env, "type": "event", "name": ev["name"], "data": ev.get("data") or {}}))
    return out


def read_run_log(path: str | Path, decode: bool = True, problems: list[str] | None = None, *,
                 wall: bool = False) -> Iterator[tuple[str, int, object]]:
    """Yield (key, log_time_ns, message) from a run log in file order, up to its end, a cut (a truncated tail) or
    damage (a chunk whose checksum or framing is wrong in a file that is whole); what stopped it short is appended
    to ``problems`` (when given), in a phrase such as "damaged near byte 2111428 of 4200000 (...)".

    ``key`` is the Zenoh key it was published on; ``message`` the decoded dict (None for a payload that was not a
    message of the protocol), or with ``decode=False`` its bytes in the protocol's msgpack form (the original bytes
    for one that was not). After each step answer that carries a model's results come the ``state``/``out``/
    ``event`` messages it stands for (see :data:`RESULTS`). Channels derived for viewers are left out. With
    ``wall`` the time yielded is the message's publish time (the wall clock when it was logged) instead."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, str, int | None]] = {}  # id -> key, encoding, schema, origin
    carries: dict[int, float | None] = {}  # channel -> the tick period of its results
    with open(path, "rb") as f:
        whole = not ends_early(f)
        size = f.tell()
        f.seek(0)
        reader = StreamReader(f, skip_magic=False, validate_crcs=True)
        try:
            for rec in reader.records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    if rec.metadata.get(VIEW):
                        continue
                    since = rec.metadata.get(ORIGIN)
                    channels[rec.id] = (rec.metadata.get(KEY, rec.topic), rec.message_encoding,
                                        schemas.get(rec.schema_id, ""), int(since) if since else None)
                    if rec.metadata.get(RESULTS):
                        carries[rec.id] = float(rec.metadata[DT]) if DT in rec.metadata else None
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    key, encoding, schema, origin = channels[rec.channel_id]
                    msg, raw = _decode(rec.data, encoding, schema, origin, rec.log_time)
                    at = rec.publish_time if wall else rec.log_time
                    yield key, at, (msg if decode else (raw if raw is not None else codec.pack(msg)))
                    if rec.channel_id in carries:
                        for k, m in results_of(key, msg, carries[rec.channel_id]):
                            yield k, at, (m if decode else codec.encode_unchecked(str(m["type"]), dict(m)))
        except Exception as e:  # a truncated tail, or damage
            where = f"near byte {f.tell()} of {size} ({type(e).__name__}: {e})"
            log.info("run log %s stops %s", path, where)  # (the callers say it, in their words)
            if problems is not None:  # (an end was written: what stopped the reading is damage, not a cut)
                problems.append(f"damaged {where}" if whole else f"cut short {where}")


def _decode(data: bytes, encoding: str, schema: str, origin: int | None, log_ns: int) -> tuple[Any, bytes | None]:
    """(message, original bytes if it has no decoded form) of one message of a run log."""
    try:
        if encoding == "json":
            obj = json.loads(data)
            if schema == RAW:
                return None, base64.b64decode(obj.get("data", ""))
            return obj, None
        if encoding == "cdr":
            if schema == STRING:
                return action_of_cdr(data, log_ns, origin), None
            return joint_state_of_cdr(data, origin), None
        return codec.unpack(data), None  # format 1: msgpack
    except Exception:
        return None, bytes(data)


MAGIC = b"\x89MCAP0\r\n"
"""What an MCAP file begins and ends with: one whose last bytes are not these was cut short."""


def ends_early(f: BinaryIO) -> bool:
    """Whether the MCAP file open as ``f`` lacks its end (its last bytes are not the magic a whole file ends with)."""
    f.seek(0, 2)
    size = f.tell()
    if size < 2 * len(MAGIC):
        return True
    f.seek(size - len(MAGIC))
    return f.read(len(MAGIC)) != MAGIC


def cut_short(path: str | Path) -> bool:
    """Whether the run log at ``path`` lacks its end (the process writing it was killed, the disk filled, the file
    is a partial copy, or its run is still going on): :func:`read_run_log` then yields what it holds up to the cut."""
    try:
        with open(path, "rb") as f:
            return ends_early(f)
    except OSError:
        return True


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The file's metadata by name (a later record of a name wins); from a log cut short (no summary at its end),
    what its records up to the cut hold: the run log writes the scene, perception and provenance first."""
    from mcap.reader import make_reader
    from mcap.records import Metadata
    from mcap.stream_reader import StreamReader

    try:
        with open(path, "rb") as f:
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    except Exception:
        pass
    out: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Metadata):
                    out[rec.name] = dict(rec.metadata)
    except Exception:  # the cut itself
        pass
    return out
