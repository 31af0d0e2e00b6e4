"""The run log: every message the ensemble published, written to MCAP as the run goes.

Samples are queued by a Zenoh callback and written by a thread, in small chunks that are flushed to
disk as soon as they close, so a crash loses at most the last chunk. :func:`read_run_log` reads a
complete or a truncated file.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from mcap.writer import CompressionType, Writer

from protocol import codec

log = logging.getLogger("twin.runlog")

CHUNK_SIZE = 32 * 1024


class RunLog:
    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")
        self._w = Writer(self._f, chunk_size=CHUNK_SIZE, compression=CompressionType.NONE)
        self._w.start(profile="twin", library="twin-runlog")
        self._schema = self._w.register_schema(name="twin.msgpack", encoding="", data=b"")
        self._channels: dict[str, int] = {}
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._seq = 0
        self.count = 0
        self._metadata = metadata or {}
        self._closed = False
        self.taps: list = []  # callables given each (key, payload, t_ns) too (the live Rerun sink)
        self._thread = threading.Thread(target=self._run, name="runlog", daemon=True)
        self._thread.start()
        self._last_flush = time.monotonic()

    def record(self, key: str, payload: bytes, t_ns: int | None = None) -> None:
        """Queue one message (called from Zenoh callbacks: cheap, never blocks)."""
        self._q.put((key, payload, t_ns or time.time_ns()))

    def on_sample(self, sample) -> None:
        try:
            item = (str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())
            self._q.put(item)
            for tap in self.taps:
                tap(item)
        except Exception:  # never let logging break the transport callback
            log.exception("run log could not queue a sample")

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                break
            self._write(*item)
            # drain what is there without blocking, then flush
            try:
                while True:
                    item = self._q.get_nowait()
                    if item is None:
                        self._finish()
                        return
                    self._write(*item)
            except queue.Empty:
                pass
            now = time.monotonic()
            if now - self._last_flush > 0.2:
                self._f.flush()
                self._last_flush = now
        self._finish()

    def _write(self, key: str, payload: bytes, t_ns: int) -> None:
        ch = self._channels.get(key)
        if ch is None:
            ch = self._channels[key] = self._w.register_channel(topic=key, message_encoding="msgpack",
                                                                schema_id=self._schema)
        self._w.add_message(ch, log_time=t_ns, publish_time=t_ns, data=payload, sequence=self._seq)
        self._seq += 1
        self.count += 1

    def _finish(self) -> None:
        for name, data in self._metadata.items():
            self._w.add_metadata(name, data)
        self._w.finish()
        self._f.close()

    def close(self, metadata: dict[str, dict[str, str]] | None = None) -> None:
        if self._closed:
            return
        self._closed = True
        if metadata:
            self._metadata = metadata
        self._q.put(None)
        self._thread.join(timeout=30)


def read_run_log(path: str | Path, decode: bool = True) -> Iterator[tuple[str, int, object]]:
    """Yield (key, log_time_ns, message) from a run log; stops quietly at a truncated tail."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    channels: dict[int, str] = {}
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False)
        try:
            for rec in reader.records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    key = channels.get(rec.channel_id, "?")
                    if decode:
                        try:
                            msg = codec.unpack(rec.data)
                        except Exception:
                            msg = None
                    else:
                        msg = rec.data
                    yield key, rec.log_time, msg
        except Exception as e:  # truncated or damaged tail
            log.info("run log %s ends early: %s", path, e)


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    except Exception:
        return {}
