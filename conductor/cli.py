"""The ``twin`` command line. ``twin COMMAND --help`` explains each command."""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading

from protocol.config import ZenohOptions, add_zenoh_args, options_from_args
from protocol.errors import SceneError, TwinError
from protocol.keys import Keys

log = logging.getLogger("twin")

DESCRIPTION = """\
twin: a multi-agent heterogeneous digital twin for robots on Eclipse Zenoh.

Each model of the robot and its world runs as its own agent process; the conductor steps them,
moves the responsibility for each object's attributes between them as the robot acts, and logs
everything. Start with:  twin run scenes/ball_drop.yaml --recording recordings/ball_drop_00.mcap
"""


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING - 10 * verbose
    logging.basicConfig(level=max(logging.DEBUG, level), format="%(asctime)s %(name)s %(levelname)s: %(message)s",
                        datefmt="%H:%M:%S")


def _load_scene(path: str):
    from .scene import load_scene

    return load_scene(path)


def _live_factory(args):
    """A function (session, keys) -> live source for ``--live`` / ``--ros2-domain``, or None."""
    domain = getattr(args, "ros2_domain", None)
    if domain is not None:
        from .ros2 import Ros2Source

        return lambda session, keys: Ros2Source(session, keys, domain=domain, namespace=args.ros2_namespace,
                                                idle_timeout=args.idle_timeout)
    if getattr(args, "live", False):
        from .sources import LiveSource

        return lambda session, keys: LiveSource(session, keys, idle_timeout=args.idle_timeout)
    return None


def _source(args, session=None, keys=None):
    from .sources import ReplaySource, load_recording

    factory = _live_factory(args)
    if factory is not None:
        return factory(session, keys), {}
    if getattr(args, "recording", None):
        rec = load_recording(args.recording)
        meta = {"twin.recording": {"path": args.recording}}
        return ReplaySource(rec), meta


def _perceive(scene, source, perception: str | None = None) -> None:
    """Put the scene's entities where the robot perceived them: from ``--perception FILE`` if given,
    else from the replayed recording's ``twin.scene`` metadata."""
    if perception:
        scene.apply_perception(load_perception(perception))
        return
    rec = getattr(source, "rec", None)
    if rec is not None and "twin.scene" in rec.metadata:
        scene.apply_perception(_perception_from_metadata(rec.metadata["twin.scene"], rec.path))


def _perception_from_metadata(meta: dict, path: str) -> dict:
    from .scene import check_perception

    try:
        doc = json.loads(meta.get("json", "{}"))
    except (ValueError, RecursionError) as e:
        raise TwinError(f"{path}: metadata 'twin.scene' is not valid JSON ({e})") from None
    return check_perception(doc, f"{path}: metadata 'twin.scene'")


def load_perception(path: str) -> dict:
    """What the robot perceived before the run (``{"entities": {name: {"pose": [...], ...}}}``): from a
    recording's ``twin.scene`` metadata (.mcap) or from a JSON / YAML file of that shape."""
    import yaml

    from .scene import check_perception

    if path.lower().endswith(".mcap"):
        from .sources import load_recording

        meta = load_recording(path).metadata.get("twin.scene")
        if not meta:
            raise TwinError(f"{path}: the recording carries no perceived scene (metadata 'twin.scene')")
        return _perception_from_metadata(meta, path)
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except (OSError, yaml.YAMLError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise TwinError(f"{path}: cannot read the perception file: {e}") from None
    return check_perception(doc, path)


def _print_event(kind: str, data: dict) -> None:
    if kind == "handover":
        print(f"  t={data['t']:8.3f}s  handover  {data['entity']}.{data['attribute']}: {data['from']} -> {data['to']}"
              f"  ({data['trigger']})", flush=True)
    elif kind == "agent_lost":
        print(f"  t=        agent lost: {data['model']} (its responsibilities fall back to the main model)", flush=True)
    elif kind == "rejoin":
        print(f"  agent rejoined: {data['model']}", flush=True)


def _print_progress(p: dict) -> None:
    if not sys.stderr.isatty():
        return
    dur = p.get("duration")
    total = f" / {dur:.1f} s" if dur and dur != float("inf") else ""
    rtf = f"  (real-time factor {p['rtf']:.2f})" if p.get("rtf") else ""
    print(f"\r  t = {p['t']:.1f} s{total}{rtf}   ", end="", file=sys.stderr, flush=True)


def print_summary(s: dict) -> None:
    print(f"\nrun of {s['scene']}: {s['ticks']} ticks, {s['sim_s']:.2f} s simulated in {s['wall_s']:.2f} s "
          f"(real-time factor {s['rtf']})")
    print(f"handovers: {len(s['handovers'])}; malformed messages: {s['malformed_messages']}")
    for k, v in s["semantic_state"].items():
        print(f"  {k} = {v}")
    if s.get("lag"):
        print(f"lag: {s['lag']}")
    for w in s.get("input_warnings", []):
        print(f"input: {w}")
    if s["errors"]:
        print("problems:")
        for e in s["errors"][:10]:
            print(f"  - {e}")
    print(f"run log: {s['run_log']}")
    if s.get("rerun"):
        print(s["rerun"])


# ------------------------------------------------------------------ commands
def cmd_router(args) -> int:
    opts = options_from_args(args)
    opts.mode = "router"
    session = opts.open()
    print(f"zenoh router listening on {', '.join(opts.listen or ['tcp/127.0.0.1:7447'])} (Ctrl-C stops)", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    session.close()
    return 0


def cmd_agent(args) -> int:
    from agents.base import run_agent
    from agents.registry import resolve_kind

    opts = options_from_args(args)
    try:
        cls = resolve_kind(args.kind)
    except ValueError as e:
        print(f"twin agent: {e}", file=sys.stderr)
        return 2
    return run_agent(cls(), args.name or cls.kind, opts, register_timeout=args.register_timeout)


def cmd_conductor(args) -> int:
    from .core import Conductor

    scene = _load_scene(args.scene)
    opts = options_from_args(args)
    session = opts.open()
    keys = Keys(opts.ensemble)
    try:
        source, meta = _source(args, session, keys)
        _perceive(scene, source, args.perception)
        c = Conductor(scene, session, keys, source, run_log=args.run_log, rtf=args.rtf, max_ticks=args.max_ticks,
                      on_event=_print_event, metadata=meta, register_timeout=args.register_timeout,
                      progress=_print_progress, network_mode=opts.mode)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: c.stop_requested.set())
        s = c.run()
        c.close()
    finally:
        session.close()
    print_summary(s)
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(s, f, indent=2, default=str)
    return 0 if not s["errors"] else 1


def cmd_run(args) -> int:
    from .launch import run_embedded

    scene = _load_scene(args.scene)
    source, meta = (None, {})
    factory = _live_factory(args)  # a live source needs the router's session: run_embedded builds it
    if factory is None and args.recording:
        source, meta = _source(args)
    _perceive(scene, source, args.perception)
    print(f"running {scene.name} ({', '.join(f'{n}:{m.kind}' for n, m in scene.models.items())})", flush=True)
    held = []

    def hold(summary: dict) -> None:
        """--rerun serve: show the summary, keep the web viewer up until Ctrl-C."""
        print_summary(summary)
        held.append(True)
        print("\nthe Rerun web viewer goes on serving this run (address above); Ctrl-C ends", flush=True)
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        stop.wait()

    summary = run_embedded(scene, source, ensemble=args.ensemble, run_dir=args.run_dir, rtf=args.rtf,
                           max_ticks=args.max_ticks, on_event=_print_event, metadata=meta,
                           live=factory, idle_timeout=args.idle_timeout, rerun=args.rerun,
                           progress=_print_progress, hold=None if args.no_hold else hold,
                           router_options=ZenohOptions(mode="router", listen=[args.listen]) if args.listen else None)
    if not held:
        print_summary(summary)
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=2, default=str)
        print(f"summary: {args.summary}")
    return 0 if not summary["errors"] else 1


def cmd_status(args) -> int:
    from protocol import codec

    opts = options_from_args(args)
    session = opts.open()
    keys = Keys(opts.ensemble)
    try:
        for reply in session.get(keys.conductor("status"), timeout=args.timeout):
            if reply.ok is not None:
                msg = codec.decode(keys.conductor("status"), reply.ok.payload, "status")
                print(json.dumps(msg.fields, indent=2, default=str))
                return 0
        print(f"no conductor answered on {keys.conductor('status')}", file=sys.stderr)
        return 1
    finally:
        session.close()


PLUGINS = ("conductor.bench_cli", "conductor.record_cli", "conductor.evaluate_cli", "conductor.view_cli",
           "conductor.robot_cli", "conductor.deploy_cli")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="twin", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    r = sub.add_parser("router", help="run a Zenoh router for agents on several machines",
                       description="Run a Zenoh router that agents and the conductor connect to.")
    add_zenoh_args(r, default_mode="router")
    r.set_defaults(func=cmd_router)

    a = sub.add_parser("agent", help="run one model as an agent process",
                       description="Run one model as an agent: it registers with the conductor and serves "
                                   "twin/<ensemble>/model/<name>/... until SIGINT/SIGTERM.")
    a.add_argument("kind", help="built-in kind (physics, grasp_monitor, in_hand, spu, fluid, trivial) or module:Class")
    a.add_argument("--name", help="model name in the scene (default: the kind)")
    a.add_argument("--register-timeout", type=float, default=0.0,
                   help="give up if no conductor answers within this many seconds (default: retry forever)")
    add_zenoh_args(a)
    a.set_defaults(func=cmd_agent)

    def run_opts(x):
        x.add_argument("scene", help="scene YAML file")
        x.add_argument("--recording", help="robot recording to replay (MCAP, rosbag2 layout)")
        x.add_argument("--live", action="store_true", help="attach to live telemetry on twin/<ensemble>/telemetry/**")
        x.add_argument("--ros2-domain", type=int, default=None, metavar="N",
                       help="attach live to a ROS 2 robot on rmw_zenoh: its /joint_states and /action in domain N")
        x.add_argument("--ros2-namespace", default="", help="ROS 2 namespace of those topics (with --ros2-domain)")
        x.add_argument("--perception", metavar="FILE",
                       help="where the robot perceived the scene's objects: a recording (.mcap, its 'twin.scene' "
                            "metadata) or a JSON/YAML file {entities: {name: {pose: [...]}}} (default: the replayed "
                            "recording's own)")
        x.add_argument("--idle-timeout", type=float, default=3.0, help="live: end the run after this many seconds without telemetry")
        x.add_argument("--rtf", type=float, default=None, help="pace a replay at this real-time factor (default: as fast as possible)")
        x.add_argument("--max-ticks", type=int, default=None, help="stop after this many ticks")
        x.add_argument("--summary", metavar="FILE.json", help="write the run summary as JSON")
        x.add_argument("--register-timeout", type=float, default=60.0, help="seconds to wait for the scene's agents")

    c = sub.add_parser("conductor", help="run the conductor for a scene (agents started separately)",
                       description="Run the conductor: wait for the scene's agents, initialise them, run the clock, "
                                   "move responsibilities, write the run log.")
    run_opts(c)
    c.add_argument("--run-log", default="run.mcap", help="MCAP file for the run log (default run.mcap)")
    add_zenoh_args(c)
    c.set_defaults(func=cmd_conductor)

    rn = sub.add_parser("run", help="run a scene end to end on an embedded router (the default way)",
                        description="Open a Zenoh router in this process, start the conductor and every agent the "
                                    "scene names as subprocesses on loopback, replay the recording, print the summary.")
    run_opts(rn)
    rn.add_argument("--ensemble", default=os.environ.get("TWIN_ENSEMBLE", "default"), help="ensemble name")
    rn.add_argument("--run-dir", help="folder for the run log, agent logs and summary (default runs/<scene>-<time>)")
    rn.add_argument("--listen", metavar="ENDPOINT", default=os.environ.get("TWIN_LISTEN"),
                    help="endpoint of the embedded router (default: a free tcp/127.0.0.1 port)")
    rn.add_argument("--rerun", default="none", metavar="MODE",
                    help="Rerun stream: none, save, spawn, serve or connect=URL (default none); every mode also "
                         "writes run.rrd; with serve the web viewer stays up after the run until Ctrl-C")
    rn.add_argument("--no-hold", action="store_true",
                    help="with --rerun serve: exit at the end of the run instead of serving until Ctrl-C")
    rn.set_defaults(func=cmd_run)

    st = sub.add_parser("status", help="ask a running conductor for its status",
                        description="Print the status of the conductor of an ensemble: tick, agents, ownership.")
    st.add_argument("--timeout", type=float, default=3.0)
    add_zenoh_args(st)
    st.set_defaults(func=cmd_status)

    # further commands live in their own modules, each with register(subparsers)
    import importlib

    for modname in PLUGINS:
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as e:
            if e.name != modname:
                raise
            continue
        mod.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    _setup_logging(args.verbose)
    if not getattr(args, "func", None):
        p.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except SceneError as e:
        print(f"scene error: {e}", file=sys.stderr)
        return 2
    except TwinError as e:
        print(f"twin: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
