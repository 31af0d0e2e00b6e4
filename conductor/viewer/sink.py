"""The live viewer: a sink fed from the ensemble's traffic on a worker thread, so the tick loop never waits on it."""
from __future__ import annotations

import collections
import logging
import threading
import time
from pathlib import Path

import zenoh

from protocol import codec

from ..runlog import results_of
from .logger import TwinLogger
from .stream import Stream, close_stream, open_stream, parse_mode

log = logging.getLogger("twin.viewer")


# --------------------------------------------------------------------------- the live sink
class ViewerSink:
    """Live Rerun stream of an ensemble, fed from its own Zenoh traffic.

    Subscriptions hand samples to ring channels (Rust side: no Python, no GIL, never blocks the
    session; if the worker falls far behind the oldest high-rate samples are dropped, as a viewer
    may); a worker thread drains them every ``period`` seconds and logs through :class:`TwinLogger`.

    In the conductor's own process, feed it from the run log (``tap=conductor.run_log``, as ``twin run`` does): the
    step broadcast and a replay's telemetry go from the conductor's session to other sessions only.

    Example (a session of its own, or with ``tap``)::

        sink = ViewerSink(session, keys, scene, mode="save", path="runs/x/run.rrd").start()
        conductor.run()
        print(sink.close())   # how to open the result
    """

    HIGH = ("state/*", "out/*/*", "clock", "done/*", "telemetry/**")
    LOW = ("ownership", "event/*/*")

    def __init__(self, session, keys, scene=None, mode: str = "save", path: str | Path | None = None,
                 url: str | None = None, *, pose_hz: float = 30.0, period: float = 0.2,
                 web_port: int | None = None, grpc_port: int | None = None, capacity: int = 1 << 16,
                 slice: int = 32, pause: float = 0.0002, tap=None):
        self.session = session
        # tap: a RunLog whose subscription already receives every message of the ensemble; the
        # sink then takes its copy there (a deque append per message) instead of subscribing again
        self.tap = tap
        self._tapped: collections.deque = collections.deque()  # (kept within ``capacity`` by :meth:`_tap`)
        self.dropped = 0  # high-rate samples the tap left out, the worker being ``capacity`` messages behind
        self.keys = keys
        self.scene = scene
        self.mode = mode
        self.path = path
        self.url = url
        self.pose_hz = pose_hz
        self.period = period
        self.web_port = web_port
        self.grpc_port = grpc_port
        self.capacity = capacity
        self.slice = max(1, slice)
        self.pause = pause
        self.stream: Stream | None = None
        self.logger: TwinLogger | None = None
        self._subs: list = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False
        self.worker_cpu_s = 0.0  # CPU time of the worker thread so far (for the benchmark)

    def start(self) -> ViewerSink:
        name = self.scene.name if self.scene is not None else self.keys.ensemble
        self.stream = open_stream(self.mode, self.path, self.url, scene=self.scene, name=name,
                                  web_port=self.web_port, grpc_port=self.grpc_port)
        self.logger = TwinLogger(self.stream.rec, self.scene, pose_hz=self.pose_hz)
        self.logger.begin()
        try:  # encode and write the static scene (robot meshes: megabytes) now, not during the run
            self.stream.rec.flush(timeout_sec=10.0)
        except Exception as e:
            log.debug("viewer: flush of the static scene: %s", e)
        if self.tap is not None:
            self.tap.taps.append(self._tap)
        else:
            prefix = self.keys.prefix + "/"
            low = [self.session.declare_subscriber(prefix + k, zenoh.handlers.RingChannel(1 << 14))
                   for k in self.LOW]
            high = [self.session.declare_subscriber(prefix + k, zenoh.handlers.RingChannel(self.capacity))
                    for k in self.HIGH]
            self._subs = low + high
        self._thread = threading.Thread(target=self._run, name="rerun-sink", daemon=True)
        self._thread.start()
        if self.stream.mode == "serve":
            print(f"Rerun web viewer (live): {self.stream.url}", flush=True)
        return self

    def _tap(self, item: tuple[str, bytes, int]) -> None:
        """The run log's copy of a message, queued for the worker; when it is ``capacity`` messages behind, a
        high-rate sample (a pose, an output, a joint state) is left out and counted, never what :meth:`_kept` keeps
        (the lanes and the log: a full queue had dropped its oldest, whatever they were)."""
        if len(self._tapped) >= self.capacity and not self._kept(item[0], item[1]):
            self.dropped += 1
            return
        self._tapped.append(item)

    @staticmethod
    def _kept(key: str, payload: bytes) -> bool:
        """Whether a message is one a sink behind never leaves out: an ownership change, an event, a robot action,
        a step answer carrying an event (a service-stepped model's events come in its answers: its ``events``
        lists, empty ones being ``\x90`` in msgpack, are all empty or not)."""
        if "/ownership" in key or "/event/" in key or "/action" in key:
            return True
        return "/done/" in key and payload.count(b"\xa6events") != payload.count(b"\xa6events\x90")

    def _started(self) -> TwinLogger:
        assert self.logger is not None, "ViewerSink.start() first"
        return self.logger

    def _drain(self, limit: int = 20000) -> int:
        offer = self._started().offer
        n = 0
        now = time.time_ns()
        q = self._tapped
        dt = 1.0 / self.scene.rate if self.scene is not None else None
        while q and n < limit:
            key, payload, _ = q.popleft()
            n += 1
            offer(key, payload, now)
            if "/done/" in key:  # the run log's subscription: a service model's results come in its answers
                self._results(key, payload, dt, now)
            if not n % self.slice:
                time.sleep(self.pause)
        for sub in self._subs:
            while n < limit:
                s = sub.try_recv()
                if s is None:
                    break
                n += 1
                offer(str(s.key_expr), s.payload.to_bytes(), now)
                if not n % self.slice:
                    # hand the GIL to the conductor's threads between short slices of work
                    time.sleep(self.pause)
        return n

    def _results(self, key: str, payload: bytes, dt: float | None, now: int) -> None:
        try:
            answer = codec.unpack(payload)
        except Exception:
            return  # counted as bad by the logger's offer
        for k, m in results_of(key, answer, dt):
            self._started().offer_decoded(k, m, now)

    def _run(self) -> None:
        last_flush = time.monotonic()
        while not self._stop.is_set():
            try:
                self._drain()
                if time.monotonic() - last_flush > 0.2:
                    self._started().flush()
                    last_flush = time.monotonic()
            except Exception as e:
                log.warning("viewer: %s: %s", type(e).__name__, e)
            self.worker_cpu_s = time.thread_time()
            self._stop.wait(self.period)

    def close(self, settle: float = 0.1) -> str:
        """Stop the worker, log what is still queued, close the stream; returns how to open it."""
        if self._closed or self.stream is None:
            return self.stream.hint() if self.stream else ""
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
        deadline = time.monotonic() + 2.0
        time.sleep(settle)
        while time.monotonic() < deadline and self._drain() > 0:
            time.sleep(settle)
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass
        self._subs = []
        if self.tap is not None:
            try:
                self.tap.taps.remove(self._tap)
            except ValueError:
                pass
        if self._tapped or self.dropped:  # (the recording holds less than the run log: said)
            log.warning("viewer: %d messages not drawn (%d left out while it was behind, %d not drawn within the "
                        "2 s its close waits); the run log has them all", self.dropped + len(self._tapped),
                        self.dropped, len(self._tapped))
        try:
            self._started().finish()
        except Exception as e:
            log.warning("viewer: %s", e)
        close_stream(self.stream)
        return self.stream.hint()


def start_sink(session, keys, scene, mode: str, run_dir: str | Path, **kw) -> ViewerSink | None:
    """The sink ``twin run --rerun MODE`` starts before the run (None for mode ``none``).

    Every mode also saves ``<run_dir>/run.rrd``. A viewer that cannot be opened is a warning: the run
    goes on without it. (The sink stays in the conductor's process: a sink process of its own measured
    dearer, 25 % against 16 % of the real-time factor, since the router then forwards every message
    to it over TCP.)
    """
    name, _ = parse_mode(mode)
    if name == "none":
        return None
    try:
        return ViewerSink(session, keys, scene, mode=mode, path=Path(run_dir) / "run.rrd", **kw).start()
    except Exception as e:
        log.warning("Rerun stream not started (%s); the run goes on without it", e)
        print(f"warning: Rerun stream not started: {e}", flush=True)
        return None
