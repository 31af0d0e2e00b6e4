"""Live telemetry from the network: a robot (or ``twin robot play``) publishing on ``telemetry/**``."""
from __future__ import annotations

import logging
import threading
import time

import numpy as np

from protocol import codec
from protocol.errors import ProtocolError

log = logging.getLogger("twin.source")


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
        self._last_arrival: float | None = None
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
        for _arrival, kind, msg in q:
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
        a = np.asarray(self.lags)
        return {"samples": int(a.size), "p50_ms": float(np.percentile(a, 50) * 1e3),
                "p99_ms": float(np.percentile(a, 99) * 1e3), "max_ms": float(a.max() * 1e3),
                "coalesced": self.coalesced}
