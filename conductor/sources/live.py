"""Live telemetry from the network: a robot (or ``twin robot play``) publishing on ``telemetry/**``."""
from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

import numpy as np

from protocol import codec
from protocol.errors import ProtocolError, RunAborted

log = logging.getLogger("twin.source")


class LiveSource:
    """Telemetry from ``twin/<ensemble>/telemetry/**`` (a robot or ``twin robot play``).

    Samples are queued as they arrive and taken in order, each at its own time: tick *t* takes every message
    whose stamp is at most *t* after the first message's (the stamps are the robot's clock). The conductor
    paces a live run by the wall clock, so it never runs ahead of the robot; when the machine is slower than
    the robot, messages wait in the queue and the twin falls behind, which its lag shows (``lag_stats``),
    but nothing is skipped: every joint state and every action reaches the models at the tick it belongs to.
    """

    live = True

    def __init__(self, session: Any, keys: Any, idle_timeout: float = 3.0, wait_first: float = 30.0) -> None:
        self._init_state(idle_timeout, wait_first)
        self.where = keys.telemetry("**")
        self._sub = session.declare_subscriber(self.where, self._on_sample)

    def _init_state(self, idle_timeout: float, wait_first: float) -> None:
        """The queue, counters and pacing state (shared with sources that subscribe elsewhere)."""
        self._lock = threading.Lock()
        self._q: collections.deque[tuple[str, dict[str, Any]]] = collections.deque()
        self.malformed = 0
        self.lags: list[float] = []
        self.backlog_max = 0  # the most messages that ever waited for their tick
        self.idle_timeout = idle_timeout
        self.wait_first = wait_first
        self._last_arrival: float | None = None
        self._t0: float | None = None  # the first message's stamp: the run's time 0
        self.duration = float("inf")
        self.where = "the robot's topics"

    def _on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, ("joint_state", "action"))
        except ProtocolError as e:
            self.malformed += 1
            log.warning("malformed telemetry: %s", e)
            return
        with self._lock:
            self._q.append((msg.mtype, dict(msg)))
            self._last_arrival = time.monotonic()

    def wait_for_data(self, stop: threading.Event) -> bool:
        """Wait for the robot's first message; False on a stop. RunAborted when none came within ``wait_first``
        seconds: a run without its robot would tick on empty, forever (its idle time counts from a first message)."""
        deadline = time.monotonic() + self.wait_first
        while time.monotonic() < deadline and not stop.is_set():
            if self._last_arrival is not None:
                return True
            stop.wait(0.01)
        if stop.is_set():
            return False
        raise RunAborted(f"live: no telemetry came on {self.where} within {self.wait_first:g} s: is the robot "
                         "publishing, on this ensemble (or ROS 2 domain), with credentials the router admits?")

    def due(self, t: float) -> list[tuple[str, dict[str, Any]]]:
        """The messages of tick time ``t``, in arrival order: those stamped at most ``t`` after the first."""
        out: list[tuple[str, dict[str, Any]]] = []
        now = time.time()
        with self._lock:
            self.backlog_max = max(self.backlog_max, len(self._q))
            while self._q:
                kind, msg = self._q[0]
                stamp = float(msg["stamp"])
                if self._t0 is None:
                    self._t0 = stamp
                if stamp - self._t0 > t + 1e-9:
                    break
                self._q.popleft()
                out.append((kind, msg))
                if kind == "joint_state":
                    self.lags.append(max(0.0, now - stamp))  # stamps are the robot's wall clock
        return out

    def exhausted(self, t: float) -> bool:
        """The robot has been quiet for ``idle_timeout`` seconds and every message it sent was taken."""
        return (self._last_arrival is not None and time.monotonic() - self._last_arrival > self.idle_timeout
                and not self._q)

    def lag_stats(self) -> dict:
        if not self.lags:
            return {"samples": 0}
        a = np.asarray(self.lags)
        return {"samples": int(a.size), "p50_ms": float(np.percentile(a, 50) * 1e3),
                "p99_ms": float(np.percentile(a, 99) * 1e3), "max_ms": float(a.max() * 1e3),
                "backlog_max": self.backlog_max, "malformed": self.malformed}
