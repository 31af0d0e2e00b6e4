"""The run log: every message the ensemble published, written to MCAP as the run goes.

Samples are queued by a Zenoh callback and written by a thread, in small chunks that are flushed to
disk as soon as they close, so a crash loses at most the last chunk. :func:`read_run_log` reads a
complete or a truncated file.
"""
from __future__ import annotations

import logging
import queue
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from protocol import codec
from protocol.errors import TwinError

log = logging.getLogger("twin.runlog")

CHUNK_SIZE = 32 * 1024
MAX_MESSAGE = 1 << 20
"""Bytes the run log keeps of one message: a larger one is counted (:attr:`RunLog.dropped`), not written."""
MIN_FREE = 64 << 20
"""Bytes that must be free where the run log goes before a run starts (a ball_drop run writes about 4 MB)."""


class RunLog:
    """Every message of the ensemble, written to an MCAP file by a thread of its own as the run goes.

    ``on_error(reason)`` is called once if writing fails (a full disk, a removed directory): the run must
    stop then, since what it concludes could no longer be checked against its log. Creating a run log where
    less than :data:`MIN_FREE` bytes are free raises :class:`TwinError` at once."""

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None,
                 on_error: Callable[[str], None] | None = None, dt: float | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.path.parent).free
        if free < MIN_FREE:
            raise TwinError(f"run log {self.path}: only {free >> 20} MiB free there, a run needs "
                            f"{MIN_FREE >> 20} MiB (--run-dir chooses another place)")
        self._f = open(self.path, "wb")
        self._w = Writer(self._f, chunk_size=CHUNK_SIZE, compression=CompressionType.NONE)
        self._w.start(profile="twin", library="twin-runlog")
        self._schema = self._w.register_schema(name="twin.msgpack", encoding="", data=b"")
        self._channels: dict[str, int] = {}
        # on a step answer's channel: it carries the model's results, and the tick period that times them
        self._carries = {RESULTS: "state,out,event", **({DT: repr(float(dt))} if dt else {})}
        self._q: queue.SimpleQueue[tuple[str, bytes, int] | None] = queue.SimpleQueue()
        self._seq = 0
        self.count = 0
        self.dropped: dict[str, int] = {}  # key -> messages over MAX_MESSAGE left out
        self.error: str | None = None
        self._on_error = on_error
        self._metadata = dict(metadata or {})
        self._closed = False
        self.taps: list[Callable[[tuple[str, bytes, int]], None]] = []  # also given each message (the viewer)
        self._thread = threading.Thread(target=self._run, name="runlog", daemon=True)
        self._thread.start()
        self._last_flush = time.monotonic()

    def record(self, key: str, payload: bytes, t_ns: int | None = None) -> None:
        """Queue one message (called from Zenoh callbacks: cheap, never blocks)."""
        self._q.put((key, payload, t_ns or time.time_ns()))

    def on_sample(self, sample: Any) -> None:
        try:
            item = (str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())
            self._q.put(item)
            for tap in self.taps:
                tap(item)
        except Exception:  # never let logging break the transport callback
            log.exception("run log could not queue a sample")

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as e:  # the disk is full, the folder is gone, ...: the run must know at once
            self.error = f"run log {self.path}: writing failed ({type(e).__name__}: {e})"
            log.error("%s", self.error)
            if self._on_error is not None:
                self._on_error(self.error)
            while self._q.get() is not None:  # keep taking messages (nothing blocks) until closed
                pass
            try:
                self._f.close()
            except OSError:
                pass

    def _loop(self) -> None:
        while True:
            item = self._q.get()
            while item is not None:  # what is there, without blocking, then flush
                self._write(*item)
                try:
                    item = self._q.get_nowait()
                except queue.Empty:
                    break
            if item is None:
                self._finish()
                return
            now = time.monotonic()
            if now - self._last_flush > 0.2:
                self._f.flush()
                self._last_flush = now

    def _write(self, key: str, payload: bytes, t_ns: int) -> None:
        if len(payload) > MAX_MESSAGE:
            self.dropped[key] = self.dropped.get(key, 0) + 1
            return
        ch = self._channels.get(key)
        if ch is None:  # a step answer's channel says that it carries the model's results (see read_run_log)
            ch = self._channels[key] = self._w.register_channel(
                topic=key, message_encoding="msgpack", schema_id=self._schema,
                metadata=self._carries if "/done/" in key else {})
        self._w.add_message(ch, log_time=t_ns, publish_time=t_ns, data=payload, sequence=self._seq)
        self._seq += 1
        self.count += 1

    def _finish(self) -> None:
        for name, data in self._metadata.items():
            self._w.add_metadata(name, data)
        self._w.finish()
        self._f.close()

    def close(self, metadata: dict[str, dict[str, str]] | None = None) -> None:
        """Add ``metadata`` to what the log was given at the start, write the end of the file, wait for it."""
        if self._closed:
            return
        self._closed = True
        self._metadata.update(metadata or {})
        self._q.put(None)
        self._thread.join(timeout=30)


DT = "twin.dt"
"""Metadata of a ``done/<id>`` channel: the conductor's tick period (s), which times the results it carries."""
RESULTS = "twin.results"
"""Metadata of a ``done/<id>`` channel whose step answers carry the model's state, outputs and events: a service
model publishes those on ``state``/``out``/``event`` only while someone subscribes, so the log keeps them once,
in the answers, and :func:`read_run_log` gives them back as the messages they stand for."""


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


def read_run_log(path: str | Path, decode: bool = True) -> Iterator[tuple[str, int, object]]:
    """Yield (key, log_time_ns, message) from a run log; stops quietly at a truncated tail. After each step answer
    that carries a model's results come the ``state``/``out``/``event`` messages it stands for (see
    :data:`RESULTS`)."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    channels: dict[int, str] = {}
    carries: dict[int, float | None] = {}  # channel -> the tick period of its results
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False)
        try:
            for rec in reader.records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                    if rec.metadata.get(RESULTS):
                        carries[rec.id] = float(rec.metadata[DT]) if DT in rec.metadata else None
                elif isinstance(rec, Message):
                    key = channels.get(rec.channel_id, "?")
                    msg = None
                    if decode or rec.channel_id in carries:
                        try:
                            msg = codec.unpack(rec.data)
                        except Exception:
                            msg = None
                    yield key, rec.log_time, (msg if decode else rec.data)
                    if rec.channel_id in carries:
                        for k, m in results_of(key, msg, carries[rec.channel_id]):
                            yield k, rec.log_time, (m if decode else codec.encode_unchecked(str(m["type"]), dict(m)))
        except Exception as e:  # truncated or damaged tail
            log.info("run log %s ends early: %s", path, e)


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    except Exception:
        return {}
