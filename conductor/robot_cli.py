"""``twin robot play``: put a recording on the network as the robot would, so a twin can attach live.

Each message goes out at its recorded time (divided by ``--speed``) with ``stamp`` set to this machine's
wall clock at the moment it is sent, on ``twin/<ensemble>/telemetry/joint_states`` and
``.../telemetry/action`` (the twin's codec), or with ``--ros2-domain N`` on rmw_zenoh's keys in CDR, as a
ROS 2 robot would publish them. A twin started with ``--live`` (or ``--ros2-domain N``) measures its lag
against those stamps.
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time

from protocol import codec
from protocol.config import add_zenoh_args, options_from_args
from protocol.errors import ProtocolError
from protocol.keys import Keys


def wait_for_twin(session, keys: Keys, timeout: float, stop: threading.Event) -> bool:
    """Wait until the ensemble's conductor has initialised its agents (or is already running)."""
    deadline = time.monotonic() + timeout
    key = keys.conductor("status")
    while time.monotonic() < deadline and not stop.is_set():
        for reply in session.get(key, timeout=1.0):
            if reply.ok is None:
                continue
            try:
                st = codec.decode(key, reply.ok.payload, "status").fields
            except ProtocolError:
                continue
            agents = st.get("agents") or {}
            if st.get("running") or (agents and all(a.get("ready") for a in agents.values())):
                return True
        stop.wait(0.1)
    return False


class Player:
    """Publishes a :class:`~conductor.sources.Recording` paced by the wall clock."""

    def __init__(self, session, keys: Keys, rec, speed: float = 1.0, ros2_domain: int | None = None,
                 ros2_namespace: str = ""):
        if speed <= 0:
            raise ValueError("--speed must be positive")
        self.rec = rec
        self.speed = speed
        self.sent = {"joint_state": 0, "action": 0}
        self.late_max = 0.0
        self._ros2 = None
        self._pubs = {}
        if ros2_domain is not None:
            from .ros2 import Ros2Publisher

            self._ros2 = Ros2Publisher(session, ros2_domain, ros2_namespace)
        else:
            self._pubs = {"joint_state": session.declare_publisher(keys.telemetry("joint_states")),
                          "action": session.declare_publisher(keys.telemetry("action"))}

    def play_once(self, stop: threading.Event) -> None:
        start = time.time()
        for stamp, kind, msg in self.rec.items:
            target = start + stamp / self.speed
            delay = target - time.time()
            if delay > 0 and stop.wait(delay):
                return
            now = time.time()
            self.late_max = max(self.late_max, now - target)
            out = dict(msg, stamp=now)  # the robot's clock when it sends
            if self._ros2 is not None:
                (self._ros2.joint_state if kind == "joint_state" else self._ros2.action)(out)
            else:
                self._pubs[kind].put(codec.encode(kind, out))
            self.sent[kind] += 1

    def close(self) -> None:
        if self._ros2 is not None:
            self._ros2.close()
        for p in self._pubs.values():
            p.undeclare()


def cmd_play(args) -> int:
    from .sources import load_recording

    rec = load_recording(args.recording)
    opts = options_from_args(args)
    keys = Keys(opts.ensemble)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = opts.open()
    try:
        if args.wait_twin > 0:
            print(f"waiting up to {args.wait_twin:.0f} s for the twin of ensemble {opts.ensemble!r}", flush=True)
            if not wait_for_twin(session, keys, args.wait_twin, stop):
                print(f"twin robot play: no conductor of ensemble {opts.ensemble!r} got ready within "
                      f"{args.wait_twin:.0f} s", file=sys.stderr)
                return 1
        player = Player(session, keys, rec, args.speed, args.ros2_domain, args.ros2_namespace)
        where = (f"ROS 2 domain {args.ros2_domain} (rmw_zenoh keys)" if args.ros2_domain is not None
                 else keys.telemetry("**"))
        print(f"playing {args.recording} ({rec.duration:.2f} s, {len(rec.items)} messages) at x{args.speed:g} "
              f"on {where}" + (" in a loop" if args.loop else ""), flush=True)
        loops = 0
        time.sleep(args.lead_in)  # let subscriptions reach this session's new publishers
        while not stop.is_set():
            player.play_once(stop)
            loops += 1
            if not args.loop or (args.loops and loops >= args.loops):
                break
        player.close()
        print(f"sent {player.sent['joint_state']} joint states and {player.sent['action']} actions in {loops} "
              f"pass(es); latest send {1e3 * player.late_max:.1f} ms behind schedule", flush=True)
        return 0
    finally:
        session.close()


def register(sub) -> None:
    r = sub.add_parser("robot", help="stand in for a robot: publish a recording as live telemetry",
                       description="Commands that behave like a robot on the network.")
    rs = r.add_subparsers(dest="robot_command", metavar="ROBOT")
    p = rs.add_parser("play", help="publish a recording on twin/<ensemble>/telemetry/** at its recorded rate",
                      description="Publish a robot recording (MCAP, rosbag2 layout) as live telemetry at the recorded "
                                  "rate, each message stamped with this machine's wall clock when sent, so "
                                  "'twin conductor SCENE --live' on another machine can attach to it.",
                      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("recording", help="the recording to play (.mcap)")
    p.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")
    p.add_argument("--loops", type=int, default=0, help="with --loop: stop after this many passes (0: never)")
    p.add_argument("--speed", type=float, default=1.0, help="play this many times faster than recorded")
    p.add_argument("--wait-twin", type=float, default=0.0, metavar="SECONDS",
                   help="first wait (up to SECONDS) until the ensemble's conductor has initialised its agents")
    p.add_argument("--lead-in", type=float, default=0.3, metavar="SECONDS",
                   help="pause between declaring the publishers and the first message")
    p.add_argument("--ros2-domain", type=int, default=None, metavar="N",
                   help="publish as a ROS 2 robot on rmw_zenoh would (domain N, CDR) instead of the twin's keys")
    p.add_argument("--ros2-namespace", default="", help="ROS 2 namespace of the topics (with --ros2-domain)")
    add_zenoh_args(p)
    p.set_defaults(func=cmd_play)
    r.set_defaults(func=lambda a: (r.print_help(), 2)[1])
