"""Data sources: replay of a robot recording, and live telemetry from the network.

Recordings are MCAP files in rosbag2 layout: ``/joint_states`` (``sensor_msgs/msg/JointState``)
and ``/action`` (``std_msgs/msg/String`` holding JSON ``{operation, phase, params}``). Both sources
hand the conductor, for each tick, the telemetry messages due by then, as protocol dicts
(``joint_state`` / ``action``) with ``stamp`` in seconds since the start of the recording.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from bisect import bisect_right
from dataclasses import dataclass, field
from pathlib import Path

from protocol import codec
from protocol.errors import ProtocolError, TwinError

log = logging.getLogger("twin.source")


@dataclass
class Recording:
    path: str
    items: list[tuple[float, str, dict]]  # (stamp, "joint_state"|"action", message)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def duration(self) -> float:
        return self.items[-1][0] if self.items else 0.0

    def ground_truth(self) -> dict:
        gt = self.metadata.get("twin.ground_truth", {})
        out = {}
        for k, v in gt.items():
            out[k] = {"true": True, "false": False}.get(v, v)
        return out


def _stamp(header) -> float | None:
    try:
        return header.stamp.sec + header.stamp.nanosec * 1e-9
    except AttributeError:
        return None


def load_recording(path: str | Path) -> Recording:
    """Read a rosbag2-style MCAP recording; raises TwinError with the file name on problems."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = str(path)
    items: list[tuple[float, str, dict]] = []
    try:
        f = open(path, "rb")
    except OSError as e:
        raise TwinError(f"{path}: cannot open recording: {e.strerror}") from None
    with f:
        try:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            f.seek(0)
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            t0 = None
            for schema, channel, message, ros in reader.iter_decoded_messages(topics=["/joint_states", "/action"]):
                t = message.log_time * 1e-9
                if channel.topic == "/joint_states":
                    st = _stamp(ros.header)
                    t = st if st else t
                    msg = {"stamp": t, "name": list(ros.name), "position": list(ros.position),
                           "velocity": list(ros.velocity), "effort": list(ros.effort)}
                    kind = "joint_state"
                else:
                    try:
                        a = json.loads(ros.data)
                        msg = {"stamp": t, "operation": str(a["operation"]), "phase": str(a.get("phase", "start")),
                               "params": dict(a.get("params", {}) or {})}
                    except (ValueError, KeyError, TypeError) as e:
                        log.warning("%s: skipping malformed /action message at %.3f s: %s", path, t, e)
                        continue
                    kind = "action"
                if t0 is None:
                    t0 = t
                items.append((t, kind, msg))
        except TwinError:
            raise
        except Exception as e:
            raise TwinError(f"{path}: not a readable MCAP recording ({type(e).__name__}: {e})") from None
    if not items:
        raise TwinError(f"{path}: no /joint_states or /action messages")
    items.sort(key=lambda x: x[0])
    t0 = items[0][0]
    for _, _, m in items:
        m["stamp"] = m["stamp"] - t0
    items = [(m["stamp"], k, m) for _, k, m in items]
    return Recording(path, items, meta)


class ReplaySource:
    """Feeds a recording tick by tick, as fast as the models allow (or paced by the conductor)."""

    live = False

    def __init__(self, rec: Recording, publish=None):
        self.rec = rec
        self._stamps = [s for s, _, _ in rec.items]
        self._i = 0
        self.publish = publish  # callable(kind, msg) to put telemetry on the network

    @property
    def duration(self) -> float:
        return self.rec.duration

    def due(self, t: float) -> list[tuple[str, dict]]:
        j = bisect_right(self._stamps, t + 1e-9)
        out = [(k, m) for _, k, m in self.rec.items[self._i:j]]
        self._i = j
        return out

    def exhausted(self, t: float) -> bool:
        return self._i >= len(self._stamps) and t >= self.rec.duration

    def lag_stats(self) -> dict:
        return {}


class LiveSource:
    """Telemetry from ``twin/<ensemble>/telemetry/**`` (a robot or ``twin robot play``).

    Samples are queued as they arrive. Each tick takes everything that arrived; if the queue holds more
    than ``max_backlog`` seconds of joint states the conductor cannot keep up, and the rule is: keep
    every action annotation, coalesce joint states to the newest one (counted as ``coalesced``).
    """

    live = True

    def __init__(self, session, keys, idle_timeout: float = 3.0, max_backlog: float = 0.25,
                 wait_first: float = 30.0):
        self._init_state(idle_timeout, max_backlog, wait_first)
        self._sub = session.declare_subscriber(keys.telemetry("**"), self._on_sample)

    def _init_state(self, idle_timeout: float, max_backlog: float, wait_first: float) -> None:
        """The queue, counters and pacing state (shared with sources that subscribe elsewhere)."""
        self._lock = threading.Lock()
        self._q: list[tuple[float, str, dict]] = []
        self.malformed = 0
        self.coalesced = 0
        self.lags: list[float] = []
        self.idle_timeout = idle_timeout
        self.max_backlog = max_backlog
        self.wait_first = wait_first
        self._last_arrival = None
        self._first_stamp = None
        self.duration = float("inf")

    def _on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, ("joint_state", "action"))
        except ProtocolError as e:
            self.malformed += 1
            log.warning("malformed telemetry: %s", e)
            return
        now = time.time()
        with self._lock:
            self._q.append((now, msg.mtype, dict(msg)))
            self._last_arrival = time.monotonic()

    def wait_for_data(self, stop: threading.Event) -> bool:
        deadline = time.monotonic() + self.wait_first
        while time.monotonic() < deadline and not stop.is_set():
            if self._last_arrival is not None:
                return True
            time.sleep(0.01)
        return False

    def due(self, t: float) -> list[tuple[str, dict]]:
        with self._lock:
            q, self._q = self._q, []
        now = time.time()
        out = []
        joints = [x for x in q if x[1] == "joint_state"]
        if len(joints) > 1 and (joints[-1][2]["stamp"] - joints[0][2]["stamp"]) > self.max_backlog:
            keep = joints[-1]
            self.coalesced += len(joints) - 1
            q = [x for x in q if x[1] != "joint_state" or x is keep]
        for arrival, kind, msg in q:
            if kind == "joint_state":
                # stamps are the publisher's wall clock: lag = now - stamp
                self.lags.append(max(0.0, now - float(msg["stamp"])))
            out.append((kind, msg))
        return out

    def exhausted(self, t: float) -> bool:
        return self._last_arrival is not None and time.monotonic() - self._last_arrival > self.idle_timeout

    def lag_stats(self) -> dict:
        if not self.lags:
            return {"samples": 0}
        import numpy as np

        a = np.asarray(self.lags)
        return {"samples": int(a.size), "p50_ms": float(np.percentile(a, 50) * 1e3),
                "p99_ms": float(np.percentile(a, 99) * 1e3), "max_ms": float(a.max() * 1e3),
                "coalesced": self.coalesced}
