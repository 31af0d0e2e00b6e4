"""The run log: every message the ensemble published, and every query and reply that changed the run, written to
MCAP as the run goes, in encodings Foxglove, Lichtblick and ``ros2 bag`` read (:mod:`.encoding`, :mod:`.foxglove`).

Samples are queued by a Zenoh callback and written by a thread, in small chunks that are flushed to disk as soon
as they close, so a crash loses at most the last chunk. The thread wakes every :data:`WAKE_S` and writes what
queued meanwhile, yielding the interpreter every :data:`BATCH` messages: woken once per message, its wake-ups
alone cost the tick loop's process more CPU than the writing, and each took the interpreter from the loop.
Log times are on the simulated clock, aligned with the source: a replayed recording's first message is the
origin (so the run's messages line up with the robot's bag), a live run's is its robot's first stamp
(:meth:`RunLog.take_origin_from`); each message's publish time is the wall time it was seen.
Topics are the key after ``twin/<ensemble>/`` with a leading ``/`` (``/ownership``, ``/state/physics``...), the
full key in each channel's ``twin.key`` metadata; :func:`~.reader.read_run_log` reads a complete or truncated file.
"""
from __future__ import annotations

import collections
import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from protocol import codec
from protocol.errors import TwinError

from .encoding import (
    JOINT_STATE,
    RAW,
    ROS2MSG,
    STRING,
    action_cdr,
    joint_state_cdr,
    raw_json,
    run_schemas,
    schema_bytes,
    schema_name,
    to_json,
)
from .reader import DT, FORMAT, KEY, LOG_INFO, ORIGIN, RESULTS, VIEW

log = logging.getLogger("twin.runlog")

OWNERSHIP_VIEW = "/twin/ownership"
"""Every ``ownership`` message again, and the last one once more at the run's end: a viewer's ownership lanes then
run to the end of the run rather than stop at the last change."""

VIEWED = frozenset({"state", "ownership", "event", "done"})
"""The kinds of message (the key's part after the ensemble) the Foxglove views draw from."""

WAKE_S = 0.02
"""Seconds the writer sleeps between taking what queued (a run's last messages: at :meth:`RunLog.close`)."""
BATCH = 64
"""Messages the writer writes before it lets the tick loop's thread have the interpreter."""
CHUNK_SIZE = 32 * 1024
MAX_MESSAGE = 1 << 20
"""Bytes the run log keeps of one message: a larger one is counted (:attr:`RunLog.dropped`), not written."""
LAST_NS = 2**31 * 10**9
"""A log time from this many nanoseconds on is none the log can hold (2038: a ROS 2 header's seconds are 32 bits);
a message stamped so (a robot's nanoseconds taken for seconds) is kept as raw JSON with why."""
MIN_FREE = 64 << 20
"""Bytes that must be free where the run log goes before a run starts (a ball_drop run writes about 4 MB)."""


class RunLog:
    """Every message of the ensemble, written to an MCAP file by a thread of its own as the run goes.

    ``on_error(reason)`` is called once if writing fails (a full disk, a removed directory): the run must
    stop then, since what it concludes could no longer be checked against its log. Creating a run log where
    less than :data:`MIN_FREE` bytes are free raises :class:`TwinError` at once."""

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None,
                 on_error: Callable[[str], None] | None = None, dt: float | None = None, *, prefix: str = "",
                 origin_ns: int | None = None, entities: dict[str, Any] | None = None,
                 models: list[str] | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.path.parent).free
        if free < MIN_FREE:
            raise TwinError(f"run log {self.path}: only {free >> 20} MiB free there, a run needs "
                            f"{MIN_FREE >> 20} MiB (--run-dir chooses another place)")
        self._f = open(self.path, "wb")
        self._w = Writer(self._f, chunk_size=CHUNK_SIZE, compression=CompressionType.NONE)
        self._w.start(profile="twin", library="twin-runlog")
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self.prefix = prefix.rstrip("/") + "/" if prefix else ""
        self.dt = dt
        # the simulated clock's origin: a replayed recording's start, else now; stamps are then since the epoch
        self.epoch_stamps = origin_ns is None
        self.origin_ns = time.time_ns() if origin_ns is None else int(origin_ns)
        self._now = self.origin_ns  # log time of a message that carries no time of its own: the latest seen
        self._views_args = (entities, list(models or [])) if entities is not None else None
        self._views: Any = None
        self._last_ownership: tuple[str, bytes] | None = None
        self._run_schemas = run_schemas(entities) if entities else {}
        # on a step answer's channel: it carries the model's results, and the tick period that times them
        self._carries = {RESULTS: "state,out,event", **({DT: repr(float(dt))} if dt else {})}
        self._q: collections.deque[tuple[str, bytes, int] | None] = collections.deque()  # appends are atomic
        self._wake = threading.Event()  # set by close: write the rest now
        self._seq = 0
        # a live run's origin, the robot's first stamp (take_origin_from): messages on the simulated clock wait for
        # it (they would be filed at two times for one time 0), the new origin is applied by the writing thread
        self._awaiting = False
        self._origin_next: int | None = None
        self._held: list[tuple[str, bytes, int]] = []
        self.count = 0
        self.dropped: dict[str, int] = {}  # key -> messages over MAX_MESSAGE left out
        self.error: str | None = None
        self._on_error = on_error
        self._metadata = {**(metadata or {}), LOG_INFO: {
            "format": str(FORMAT), "clock": "simulated", "origin_ns": str(self.origin_ns),
            "stamps": "epoch" if self.epoch_stamps else "since origin", "publish_time": "wall clock"}}
        for name, meta in self._metadata.items():  # at once: a log cut short by a crash still says what ran
            self._w.add_metadata(name, meta)
        self._written = {k: dict(v) for k, v in self._metadata.items()}
        self._f.flush()
        self._closed = False
        self._last_take = 0  # wall ns at which the last message of the ensemble came (see settle)
        self.taps: list[Callable[[tuple[str, bytes, int]], None]] = []  # also given each message (the viewer)
        self._thread = threading.Thread(target=self._run, name="runlog", daemon=True)
        self._last_flush = time.monotonic()  # (before the thread starts: it reads it after its first wait)
        self._thread.start()

    def record(self, key: str, payload: bytes, t_ns: int | None = None) -> None:
        """Queue one message (called from Zenoh callbacks: cheap, never blocks)."""
        if self.error is None:
            self._q.append((key, payload, t_ns or time.time_ns()))

    def on_sample(self, sample: Any) -> None:
        """A Zenoh subscriber's callback: :meth:`take` the sample."""
        try:
            self.take(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:  # never let logging break the transport callback
            log.exception("run log could not queue a sample")

    def take(self, key: str, payload: bytes, t_ns: int | None = None) -> None:
        """Queue a message of the ensemble, seen at wall time ``t_ns`` (default now), and hand it to the taps (the
        viewer, the ROS 2 graph)."""
        item = (key, payload, t_ns or time.time_ns())
        self._last_take = item[2]
        if self.error is None:
            self._q.append(item)
        for tap in self.taps:
            tap(item)

    def take_origin_from(self, source: Any) -> None:
        """Take simulated time 0 from a live ``source``: its robot's first stamp (``source.on_t0``), known once the
        robot speaks. The robot's own messages are filed at their stamps, and with the log's opening as time 0 its
        actions and joint states sat after the handovers they caused, by as long as the run took to start. Until
        then, messages on the simulated clock wait (at most until the log is closed, then at the opening's time)."""
        self._awaiting = True
        source.on_t0 = lambda t0: self.set_origin(round(t0 * 1e9))

    def set_origin(self, origin_ns: int) -> None:
        """Make ``origin_ns`` (since the epoch) the log time of simulated time 0 (any thread: the writing thread
        applies it before the next message it writes, within :data:`WAKE_S`, and says it in the file's metadata)."""
        self._origin_next = int(origin_ns)

    def _move_origin(self, origin_ns: int) -> None:
        self.origin_ns = self._now = int(origin_ns)
        self._origin_next, self._awaiting = None, False
        info = self._metadata[LOG_INFO] = {**self._metadata[LOG_INFO], "origin_ns": str(self.origin_ns)}
        self._w.add_metadata(LOG_INFO, info)  # (a log cut short says it too)
        self._written[LOG_INFO] = dict(info)
        held, self._held = self._held, []
        for item in held:
            self._write(*item)

    def settle(self, quiet: float, limit: float) -> None:
        """Wait until no message of the ensemble has come for ``quiet`` seconds (from now on), but at most
        ``limit``: what the agents published last, still on its way, then reaches the log."""
        start = time.time_ns()
        end = start + int(limit * 1e9)
        while True:
            now = time.time_ns()
            wait = min(max(self._last_take, start) + int(quiet * 1e9), end) - now
            if wait <= 0:
                return
            time.sleep(wait * 1e-9)

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as e:  # the disk is full, the folder is gone, ...: the run must know at once
            self.error = f"run log {self.path}: writing failed ({type(e).__name__}: {e})"
            log.error("%s", self.error)
            if self._on_error is not None:
                self._on_error(self.error)
            self._q.clear()  # and nothing more is queued
            try:
                self._f.close()
            except OSError:
                pass

    def _loop(self) -> None:
        q, wake, write = self._q, self._wake, self._write
        while True:
            wake.wait(WAKE_S)
            if self._origin_next is not None:
                self._move_origin(self._origin_next)
            n = 0
            while q:
                item = q.popleft()
                if item is None:
                    self._finish()
                    return
                try:
                    write(*item)
                except OSError:  # (the disk, the folder: the run must know)
                    raise
                except Exception as e:  # one message the log cannot take: counted, the rest written
                    self.dropped[item[0]] = self.dropped.get(item[0], 0) + 1
                    log.warning("run log: a message on %s not written (%s: %s)", item[0], type(e).__name__, e)
                n += 1
                if not n % BATCH:
                    time.sleep(0)  # the tick loop's thread may be waiting for the interpreter
            now = time.monotonic()
            if now - self._last_flush > 0.2:
                self._f.flush()
                self._last_flush = now

    def _write(self, key: str, payload: bytes, wall_ns: int) -> None:
        if self._origin_next is not None:
            self._move_origin(self._origin_next)
        if len(payload) > MAX_MESSAGE:
            self.dropped[key] = self.dropped.get(key, 0) + 1
            return
        rest = key[len(self.prefix):] if self.prefix and key.startswith(self.prefix) else key
        try:
            msg = codec.unpack(payload)
            ok = isinstance(msg, dict) and isinstance(msg.get("type"), str)
            why = None if ok else "not a message of the protocol"
        except Exception as e:
            msg, why = None, f"undecodable: {type(e).__name__}: {e}"
        if self._awaiting and isinstance(msg, dict) and msg.get("type") not in ("joint_state", "action") and (
                "t" in msg or "tick" in msg):
            self._held.append((key, payload, wall_ns))  # (until the origin is known)
            return
        ns = self._time(msg)
        if ns is None:  # (a robot's stamp in nanoseconds for seconds: the writer failed, and the run with it)
            why, ns = f"stamped {msg.get('stamp', msg.get('t'))!r} s, beyond what the log's clock holds", self._now
        if why is not None:
            self._add(key, "/" + rest, RAW, "json", raw_json(payload, why), ns, wall_ns)
        elif msg["type"] == "joint_state" and rest.startswith("telemetry/"):
            topic = "/joint_states" if rest == "telemetry/joint_states" else "/" + rest
            self._add(key, topic, JOINT_STATE, "cdr", joint_state_cdr(msg, ns), ns, wall_ns)
        elif msg["type"] == "action" and rest.startswith("telemetry/"):
            topic = "/action" if rest == "telemetry/action" else "/" + rest
            self._add(key, topic, STRING, "cdr", action_cdr(msg), ns, wall_ns)
        else:
            data = to_json(msg)
            self._add(key, "/" + rest, schema_name(msg), "json", data, ns, wall_ns)
            if msg["type"] == "ownership" and self._views_args is not None:  # for the ownership lanes
                self._add(key, OWNERSHIP_VIEW, "twin.ownership", "json", data, ns, wall_ns, {VIEW: "foxglove"})
                self._last_ownership = (key, data)
        if self._views_args is not None and why is None:
            try:
                self._view(key, rest, msg, ns, wall_ns)
            except OSError:
                raise
            except Exception as e:  # (the message is written: only a view derived from it is missing)
                log.warning("run log: no Foxglove view of a message on %s (%s: %s)", key, type(e).__name__, e)

    def _time(self, msg: Any) -> int | None:
        """The log time of ``msg`` on the simulated clock (see the module docstring); None for a time the log cannot
        hold (before 1970 or from 2038 on: a ROS 2 header's seconds are 32 bits)."""
        if not isinstance(msg, dict):
            return self._now
        if msg.get("type") in ("joint_state", "action"):
            stamp = msg.get("stamp")
            if isinstance(stamp, (int, float)) and math.isfinite(stamp):
                ns = round(stamp * 1e9) + (0 if self.epoch_stamps else self.origin_ns)
                return ns if 0 <= ns < LAST_NS else None
            return self._now
        t = msg.get("t")
        if not (isinstance(t, (int, float)) and math.isfinite(t)):
            tick = msg.get("tick")
            t = tick * self.dt if isinstance(tick, int) and self.dt else None
        if t is None:
            return self._now
        ns = self.origin_ns + round(t * 1e9)
        if not 0 <= ns < LAST_NS:
            return None
        self._now = max(self._now, ns)
        return ns

    def _add(self, key: str, topic: str, schema: str, encoding: str, data: bytes, ns: int, wall_ns: int,
             meta: dict[str, str] | None = None) -> None:
        ch = self._channels.get((topic, schema))
        if ch is None:
            sid = self._schemas.get(schema)
            if sid is None:
                sid = self._schemas[schema] = (
                    self._w.register_schema(name=schema, encoding="ros2msg", data=ROS2MSG[schema]) if encoding == "cdr"
                    else self._w.register_schema(name=schema, encoding="jsonschema",
                                                 data=self._run_schemas.get(schema) or schema_bytes(schema)))
            info = {KEY: key, **(meta or {})}
            if "/done/" in key:  # a step answer's channel says that it carries the model's results (see the reader)
                info.update(self._carries)
            if encoding == "cdr":
                info[ORIGIN] = "" if self.epoch_stamps else str(self.origin_ns)
            ch = self._channels[(topic, schema)] = self._w.register_channel(
                topic=topic, message_encoding=encoding, schema_id=sid, metadata=info)
        self._w.add_message(ch, log_time=max(ns, 0), publish_time=wall_ns, data=data, sequence=self._seq)
        self._seq += 1
        self.count += 1

    def _view(self, key: str, rest: str, msg: dict[str, Any], ns: int, wall_ns: int) -> None:
        """The Foxglove views (:mod:`.foxglove`) of one message, and of the results a step answer carries."""
        if rest.split("/", 1)[0] not in VIEWED:  # the step broadcast, telemetry, queries: nothing to draw
            return
        if self._views is None:
            from .foxglove import Views

            self._views = Views(*self._views_args)  # type: ignore[misc]
        items = [(rest, msg, ns)]
        if rest.startswith("done/") and "state" in msg:  # each tick's state and events an answer carries, at its time
            model = rest[5:]
            for rep in [msg, *(msg.get("more") or [])]:
                if not isinstance(rep, dict):
                    continue
                tick = rep.get("tick")
                t = tick * self.dt if isinstance(tick, int) and self.dt else None
                at = self.origin_ns + round(t * 1e9) if t is not None else ns
                if t is not None and rep.get("state"):
                    items.append(("state/" + model, {"model": model, "t": t, "values": rep["state"]}, at))
                for ev in rep.get("events") or ():
                    if isinstance(ev, dict) and "name" in ev:
                        items.append((f"event/{model}/{ev['name']}", {"model": model, "t": t, "name": ev["name"],
                                                                      "data": ev.get("data") or {}}, at))
        for r, m, at in items:
            for topic, view in self._views.feed(r, m, at):
                ch = self._channels.get((topic, ""))
                if ch is None:
                    schema = view.get_schema()
                    sid = self._w.register_schema(name=schema.name, encoding=schema.encoding, data=schema.data)
                    ch = self._channels[(topic, "")] = self._w.register_channel(
                        topic=topic, message_encoding=schema.encoding, schema_id=sid, metadata={VIEW: "foxglove"})
                self._w.add_message(ch, log_time=max(at, 0), publish_time=wall_ns, data=view.encode(),
                                    sequence=self._seq)
                self._seq += 1

    def _finish(self) -> None:
        if self._origin_next is not None:
            self._move_origin(self._origin_next)
        elif self._held:  # (the robot never spoke: at the opening's time)
            self._awaiting = False
            for item in self._held:
                self._write(*item)
        if self._last_ownership is not None:  # the lanes run to the end of the run, not to the last change
            key, last = self._last_ownership
            self._add(key, OWNERSHIP_VIEW, "twin.ownership", "json", last, self._now, time.time_ns(),
                      {VIEW: "foxglove"})
        for name, meta in self._metadata.items():  # what close() added (the summary)
            if self._written.get(name) != meta:
                self._w.add_metadata(name, meta)
        self._w.finish()
        self._f.close()

    def problem(self) -> str | None:
        """Why the log is not whole (writing failed, or its end not written within the wait of :meth:`close`)."""
        if self.error:
            return self.error
        return f"run log {self.path}: its end was not written within 30 s" if self._thread.is_alive() else None

    def close(self, metadata: dict[str, dict[str, str]] | None = None) -> None:
        """Add ``metadata`` to what the log was given at the start, write the end of the file, wait for it."""
        if self._closed:
            return
        self._closed = True
        self._metadata.update(metadata or {})
        self._q.append(None)
        self._wake.set()
        self._thread.join(timeout=30)


