"""The twin as a node of the ROS 2 graph (``twin run --ros2-domain N``): what it concludes, published back on
rmw_zenoh so that ``ros2 topic list`` shows it and RViz can draw its entities beside the robot.

Node ``/digital_twin`` (graph liveliness tokens as rmw_zenoh declares them, :func:`protocol.ros2.liveliness_key`)
publishes, in CDR with rmw_zenoh's attachment (:mod:`protocol.ros2`):

- ``/twin/ownership`` (``std_msgs/msg/String``, JSON ``{"version", "owners": {entity: {attribute: model}}}``) on
  every change of the responsibility map;
- ``/twin/handovers`` (``std_msgs/msg/String``, JSON of the conductor's handover event) on each handover;
- ``/twin/semantic_state`` (``std_msgs/msg/String``, JSON ``{label: value}``) at the end of the run;
- ``/tf`` (``tf2_msgs/msg/TFMessage``): each entity's pose in frame ``world``, as its owner reports it, at most
  ``pose_hz`` times per simulated second.

It takes what the run log takes (:attr:`conductor.runlog.RunLog.taps`: in Zenoh's thread, a look at the key and a
deque append of the messages it publishes from), and does the work on a thread of its own. Each message goes out
under its REP-2016 type hash (Jazzy and later) and under :data:`NO_TYPE_HASH` (Humble).
"""
from __future__ import annotations

import collections
import json
import logging
import os
import threading
import time
from typing import Any

from protocol import codec
from protocol.ros2 import STRING, encode_attachment, encode_string, liveliness_key, topic_key

from .runlog import results_of

log = logging.getLogger("twin.ros2")

TF = "tf2_msgs/msg/TFMessage"
TOPICS = (("/twin/ownership", STRING), ("/twin/handovers", STRING), ("/twin/semantic_state", STRING), ("/tf", TF))
NODE = "digital_twin"
NO_TYPE_HASH = "TypeHashNotSupported"
"""The type hash in the data keys of ROS 2 Humble's rmw_zenoh (0.1.x), which has none: the twin publishes each
message under it too, so a Humble node hears it (Jazzy and later key by the REP-2016 hash)."""


_EVENTS = ("/event/_conductor/handover", "/event/_conductor/run_end")
"""The conductor's events it publishes from."""


def _kind(key: str) -> str:
    """The third chunk of a twin key (``twin/<ensemble>/done/...``: ``done``), or ''."""
    return key.split("/", 3)[2] if key.count("/") >= 2 else ""


def join_graph(session: Any, domain: int, namespace: str, conductor: Any, source: Any = None) -> Ros2Out | None:
    """The twin of ``conductor`` as a node of ROS 2 domain ``domain`` (``twin run`` and ``twin conductor`` with
    ``--ros2-domain``), publishing from what its run log takes; None, said, when it keeps no run log."""
    if conductor.run_log is None:
        log.warning("no run log: the twin publishes nothing on the ROS 2 graph")
        return None
    return Ros2Out(session, domain, conductor.clock.dt, namespace=namespace).attach(conductor.run_log, source)


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


class Ros2Out:
    """Publishes the run of one ensemble on ROS 2 domain ``domain`` (see the module docstring)."""

    def __init__(self, session: Any, domain: int, dt: float, namespace: str = "", pose_hz: float = 20.0) -> None:
        self.session, self.domain, self.dt = session, int(domain), dt
        self.every = max(1, round(1.0 / (pose_hz * dt))) if pose_hz > 0 else 1
        self.ts = _typestore()
        sid = str(session.info.zid())
        self._tokens = [session.liveliness().declare_token(liveliness_key(domain, sid, 0, 0, "NN", NODE, namespace))]
        self._pubs: dict[str, list[Any]] = {}
        for eid, (topic, ros_type) in enumerate(TOPICS, start=10):
            h = self.ts.hash_rihs01(ros_type)
            # (Humble's rmw_zenoh keys its data with no type hash: a Humble node hears only the second)
            self._pubs[topic] = [[session.declare_publisher(topic_key(domain, topic, ros_type, hashed, namespace))
                                  for hashed in (h, NO_TYPE_HASH)], os.urandom(16), 0]
            self._tokens.append(session.liveliness().declare_token(liveliness_key(
                domain, sid, 0, eid, "MP", NODE, namespace, topic=topic, ros_type=ros_type, type_hash=h)))
        self._q: collections.deque[tuple[str, bytes, int]] = collections.deque(maxlen=1 << 16)
        self._stop = threading.Event()
        self._poses: dict[str, list[float]] = {}
        self._last_tf_tick = -(10 ** 9)
        self.sent: collections.Counter[str] = collections.Counter()
        self.lost = 0  # messages to publish from that found the queue full (the oldest went)
        self._source: Any = None
        self._thread = threading.Thread(target=self._run, name="ros2-out", daemon=True)
        self._thread.start()

    def attach(self, run_log: Any, source: Any = None) -> Ros2Out:
        """Take what ``run_log`` takes; ``/tf`` is stamped on its clock (a replay's recording), or on a live
        ``source``'s robot clock once its first message came (its stamps were the run's seconds, 5.0 at tick 500: a
        tf2 lookup between the robot's frames and the twin's found no common time)."""
        run_log.taps.append(self._tap)
        self._run_log = run_log
        self._source = source if getattr(source, "live", False) else None
        return self

    def _stamp_ns(self, tick: int) -> int | None:
        """The time of ``tick`` in nanoseconds, on the robot's clock (see :meth:`attach`): a live source's, as the
        robot stamps (a sim-time node's clock that came after stamps of 0, a clock stepped forward), else the run
        log's; None while a live robot's time 0 is not known (stamped otherwise, /tf would step back to it)."""
        if self._source is not None:
            robot = self._source.robot_time(tick * self.dt)
            return None if robot is None else round(float(robot) * 1e9)
        run_log = getattr(self, "_run_log", None)
        return (int(run_log.origin_ns) if run_log is not None else 0) + round(tick * self.dt * 1e9)

    def _tap(self, item: tuple[str, bytes, int]) -> None:
        """Keep (key, payload, wall ns) if :meth:`_take` publishes from it (in Zenoh's thread: no more than a look at
        the key); one that finds the queue full is counted, said at :meth:`close`."""
        key = item[0]
        if _kind(key) in ("done", "ownership") or key.endswith(_EVENTS):
            if len(self._q) == self._q.maxlen:
                self.lost += 1
            self._q.append(item)

    # ------------------------------------------------------------------------------ publishing
    def _put(self, topic: str, payload: bytes) -> None:
        entry = self._pubs[topic]
        entry[2] += 1
        attachment = encode_attachment(entry[2], time.time_ns(), entry[1])
        for pub in entry[0]:
            pub.put(payload, attachment=attachment)
        self.sent[topic] += 1

    def _string(self, topic: str, doc: Any) -> None:
        self._put(topic, encode_string(json.dumps(doc, default=str)))

    def _tf(self, tick: int) -> None:
        t = self.ts.types
        ns = self._stamp_ns(tick)
        if ns is None:
            return
        stamp = t["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        transforms = [t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](stamp=stamp, frame_id="world"), child_frame_id=name,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                rotation=t["geometry_msgs/msg/Quaternion"](x=float(p[3]), y=float(p[4]), z=float(p[5]),
                                                           w=float(p[6]))))
            for name, p in sorted(self._poses.items())]
        self._put("/tf", bytes(self.ts.serialize_cdr(t[TF](transforms=transforms), TF)))

    def _take(self, key: str, payload: bytes) -> None:
        kind = _kind(key)
        if kind == "done":
            tick = None
            for _, m in results_of(key, codec.unpack(payload), self.dt):
                for ent, attrs in (m.get("values") or {}).items() if m["type"] == "state" else ():
                    pose = attrs.get("pose") if isinstance(attrs, dict) else None
                    if isinstance(pose, (list, tuple)) and len(pose) == 7:
                        self._poses[ent] = [float(v) for v in pose]
                        tick = m["tick"]
            if tick is not None and tick - self._last_tf_tick >= self.every:
                self._last_tf_tick = tick
                self._tf(tick)
        elif kind == "ownership":
            msg = codec.unpack(payload)
            self._string("/twin/ownership", {"version": msg.get("version"), "owners": msg.get("owners")})
        elif key.endswith("/event/_conductor/handover"):
            self._string("/twin/handovers", codec.unpack(payload).get("data"))
        elif key.endswith("/event/_conductor/run_end"):
            self._string("/twin/semantic_state", codec.unpack(payload).get("data", {}).get("semantic_state"))

    def _run(self) -> None:
        while not self._stop.is_set() or self._q:
            try:
                key, payload, _ = self._q.popleft()
            except IndexError:
                self._stop.wait(0.02)
                continue
            try:
                self._take(key, payload)
            except Exception as e:  # one bad message never stops the others
                log.warning("ros2 out: %s on %s: %s", type(e).__name__, key, e)

    def close(self) -> None:
        run_log = getattr(self, "_run_log", None)
        if run_log is not None and self._tap in run_log.taps:
            run_log.taps.remove(self._tap)
        self._stop.set()
        self._thread.join(timeout=10)
        if self.lost:
            log.warning("ros2 out: %d of the run's messages were not published on ROS 2 (its queue of %d was full)",
                        self.lost, self._q.maxlen)
        for pubs, _, _ in self._pubs.values():
            for pub in pubs:
                pub.undeclare()
        for token in self._tokens:
            token.undeclare()
