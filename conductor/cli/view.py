"""``twin view RUNLOG``: turn a run log into a Rerun recording (and optionally show it)."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path

from protocol.errors import TwinError, ViewerError

from ..record import EXIT_CODES
from .run import finite, positive

HELP = """\
Turn a run log (the MCAP that 'twin run' writes as run.mcap) into a Rerun recording (.rrd) with the
same views as the live stream: the scene coloured by the model that owns each object, the
responsibility lanes, handovers and events in the text log, real-time factor and step rates.

  twin view runs/ball_drop-20250101-120000/run.mcap            # writes run.rrd beside it
  rerun runs/ball_drop-20250101-120000/run.rrd                 # open it in the Rerun viewer
  twin view run.mcap --serve                                   # or serve the web viewer (Ctrl-C stops)

The scene gives the objects' shapes and the robot: --scene if given, else the scene text the run log carries
(placed as the run perceived it), else, for a log older than that, scenes/<name>.yaml when its entities match;
without one, objects are drawn as labelled markers.

Exit 0; 1: the viewer could not be reached, or the recording (--out) or the layout cannot be written; 2: not a
run log (a robot recording, no such file); 4: the run log is cut short (its run was killed or is still going
on): shown up to its last whole message.
"""


def _mcap_kind(path: Path) -> str | None:
    """None for a run log (profile ``twin``, as conductor/runlog.py writes it), else what the MCAP file is."""
    from mcap.reader import make_reader
    from mcap.records import Channel, Header
    from mcap.stream_reader import StreamReader

    profile, topics, cdr = "", set(), False
    try:
        with open(path, "rb") as f:
            for rec in StreamReader(f, skip_magic=False).records:  # the header, then the first channels suffice
                if isinstance(rec, Header):
                    profile = rec.profile
                    if profile == "twin":
                        return None
                elif isinstance(rec, Channel):
                    topics.add(rec.topic)
                    cdr = cdr or rec.message_encoding == "cdr"
                    break
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is not None:
            topics = {ch.topic for ch in summary.channels.values()}
            cdr = cdr or any(ch.message_encoding == "cdr" for ch in summary.channels.values())
    except Exception:  # a damaged file: what was read so far tells enough
        pass
    if profile == "ros2" or cdr:
        shown = ", ".join(sorted(topics)[:4]) + (", ..." if len(topics) > 4 else "")
        return (f"a robot recording (rosbag2 layout{', ' + shown if shown else ''}), not a run log: run it with "
                f"'twin run SCENE --recording {path}'")
    return f"an MCAP file that is not a run log (profile {profile!r}; a run log is the run.mcap 'twin run' writes)"


def not_a_run_log(path: Path) -> str | None:
    """Why ``path`` is not a run log, in one line (None if it is one): a robot recording, a .db3, not MCAP..."""
    run_it = f"run it with 'twin run SCENE --recording {path}'"
    if not path.exists():
        return "no such run log"
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return f"a robot recording (rosbag2 directory), not a run log: {run_it}"
        return "a directory, not a run log (a run log is the run.mcap 'twin run' writes)"
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as e:
        return f"cannot be read: {e.strerror}"
    if head == b"SQLite format 3\x00":
        return f"an SQLite rosbag2 file (.db3), not a run log: {run_it}"
    if not head.startswith(b"\x89MCAP0\r\n"):
        return "not an MCAP file (a run log is the run.mcap 'twin run' writes)"
    return _mcap_kind(path)


def _not_a_recording(out: Path) -> str | None:
    """Why ``out`` must not be overwritten (None: it does not exist, is a Rerun recording, which it replaces, an empty
    file, or no regular file at all: a pipe, /dev/null, /dev/stdout, written to as they are, never read here)."""
    try:
        if not out.is_file() or out.stat().st_size == 0:
            return None
        with open(out, "rb") as f:
            head = f.read(4)
    except OSError:  # (a file that cannot be read: the recording's own open says why)
        return None
    return None if head.startswith(b"RRF") else "exists and is not a Rerun recording"


def run_status(run_log: Path) -> str | None:
    """How the run of ``run_log`` ended, in a line, when it did not end complete (its summary in the log's
    metadata); None for a complete run or a log without a summary (cut short: said apart)."""
    from ..runlog import read_metadata

    try:
        s = json.loads(read_metadata(run_log).get("twin.summary", {}).get("json", "{}"))
    except ValueError:
        return None
    status = s.get("status") if isinstance(s, dict) else None
    if not isinstance(status, str) or status == "complete":
        return None
    reasons = [str(r) for r in s.get("status_reasons") or []]
    more = f" (and {len(reasons) - 2} more)" if len(reasons) > 2 else ""
    return f"the run ended {status.upper()}: {'; '.join(reasons[:2]) or 'no reason given'}{more}"


def cmd_view(args) -> int:
    run_log = Path(args.run_log)
    why = not_a_run_log(run_log)
    if why is not None:  # before anything is written: a recording viewed by mistake leaves no .rrd behind
        print(f"twin view: {run_log}: {why}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else run_log.with_suffix(".rrd")
    if out.resolve() == run_log.resolve() or (args.foxglove_layout and Path(args.foxglove_layout).resolve() ==
                                               run_log.resolve()):
        print(f"twin view: {run_log} is also the output named: give another file, the run log is kept",
              file=sys.stderr)
        return 2
    if args.foxglove_layout:
        drawn = [flag for flag, given in (("--out", args.out), ("--serve", args.serve is not None),
                                          ("--spawn", args.spawn), ("--connect", args.connect is not None),
                                          ("--until", args.until is not None), ("--pose-hz", args.pose_hz != 60.0))
                 if given]
        if drawn:  # a layout is all --foxglove-layout makes: the others would be ignored without a word
            print(f"twin view: --foxglove-layout writes a layout only: {', '.join(drawn)} cannot go with it (run "
                  "twin view twice)", file=sys.stderr)
            return 2
        return _write_layout(run_log, Path(args.foxglove_layout), args.scene)
    kept = _not_a_recording(out)
    if kept:  # another run's log, a summary, a scene... named by a slip of --out: never overwritten
        print(f"twin view: --out {out} {kept}: it is kept; give a new file or an .rrd to replace", file=sys.stderr)
        return 2
    # heavy (rerun, ~0.8 s): only when the command runs
    from ..runlog import cut_short
    from ..viewer import ViewerError, close_stream, log_run, scene_for_run_log

    scene, note = scene_for_run_log(run_log, args.scene)
    print(f"viewing {run_log}: {note}", flush=True)
    mode = "save"
    if args.serve is not None:
        mode = "serve" if args.serve == "" else f"serve={args.serve}"
    elif args.spawn:
        mode = "spawn"
    elif args.connect is not None:
        mode = "connect" if args.connect == "" else f"connect={args.connect}"
    t0 = time.perf_counter()
    problems: list[str] = []
    try:
        stream, logger = log_run(run_log, out, scene=scene, mode=mode, pose_hz=args.pose_hz, until=args.until,
                                 problems=problems)
    except ViewerError as e:
        print(f"twin view: {e}", file=sys.stderr)
        return 1
    c = logger.counts
    handovers = f"{c['handovers']} handover{'' if c['handovers'] == 1 else 's'}"
    print(f"{c.get('records', c['messages'])} messages read, {handovers}, {c['poses']} poses shown "
          f"in {time.perf_counter() - t0:.1f} s" + (f" ({c['bad']} not shown)" if c["bad"] else ""), flush=True)
    if mode != "save":
        print(stream.hint(), flush=True)
        if mode.startswith("serve"):
            print("serving until Ctrl-C", flush=True)
            stop = threading.Event()
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: stop.set())
            stop.wait()
        close_stream(stream)
    else:
        print(f"Rerun recording: {out}   (open it with: rerun {out})", flush=True)
    ended = run_status(run_log)
    if ended:  # what is shown is the run as it went: said, so nobody takes a failed run's pictures at face value
        print(ended, flush=True)
    if cut_short(run_log):  # said last, where it is seen; and in the exit code
        print(f"twin view: {run_log} is cut short (no end: its run was killed or is still going on, or the file is a "
              "partial copy): shown up to its last whole message", file=sys.stderr)
        return EXIT_CODES["truncated"]
    if problems:  # a whole file that could not be read to its end
        print(f"twin view: {run_log} is {problems[0]}: shown up to there; the rest of the run is not",
              file=sys.stderr)
        return EXIT_CODES["truncated"]
    return 0


def _write_layout(run_log: Path, out: Path, scene_file: str | None) -> int:
    """``--foxglove-layout``: a Foxglove/Lichtblick layout for this run (its scene's lanes, its robot's joints)."""
    from ..provenance import scene_of_log
    from ..runlog import read_run_log
    from ..runlog.foxglove import layout
    from ..scene import load_scene, parse_scene

    try:
        if scene_file:
            scene = load_scene(scene_file)
        else:
            text, file, perceived = scene_of_log(run_log)
            scene = parse_scene(text, file)
            scene.apply_perception(perceived)
    except TwinError as e:
        print(f"twin view: {e}", file=sys.stderr)
        return 2
    names = next((list(m["name"]) for k, _, m in read_run_log(run_log)
                  if k.endswith("/telemetry/joint_states") and isinstance(m, dict)), [])
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(layout(scene, names), indent=2) + "\n", encoding="utf-8")
    except OSError as e:
        print(f"twin view: cannot write the layout {out}: {e.strerror or e}", file=sys.stderr)
        return 1
    print(f"Foxglove layout: {out}   (in Foxglove or Lichtblick: open {run_log}, then Layouts > Import)")
    return 0


def _web_port(text: str) -> str:
    if text:
        from ..viewer.stream import web_port_of  # (rerun: only when a port is given, and serving needs it anyway)

        try:
            web_port_of(text)
        except ViewerError as e:
            raise argparse.ArgumentTypeError(str(e).removeprefix(f"serve={text}: ")) from None
    return text


def register(subparsers) -> None:
    v = subparsers.add_parser("view", help="turn a run log into a Rerun recording (.rrd) or show it",
                              description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    v.add_argument("run_log", metavar="RUNLOG", help="run log (MCAP) written by 'twin run' or 'twin conductor'")
    v.add_argument("--out", metavar="FILE.rrd", help="where to write the recording (default: RUNLOG with .rrd)")
    v.add_argument("--scene", metavar="SCENE.yaml", help="scene file the run used (shapes, robot)")
    v.add_argument("--pose-hz", type=positive, default=60.0,
                   help="poses, joints and plots per simulated second shown (default 60; handovers always)")
    v.add_argument("--until", type=lambda t: finite(t, strict=False), metavar="SECONDS",
                   help="stop at this simulated time (the viewer opens on that moment)")
    v.add_argument("--foxglove-layout", metavar="FILE.json",
                   help="write a Foxglove/Lichtblick layout for this run instead (3D scene coloured by owner, "
                        "ownership lanes, joint plots, event log) and exit")
    g = v.add_mutually_exclusive_group()
    g.add_argument("--serve", nargs="?", const="", metavar="WEBPORT", type=_web_port,
                   help="also serve the Rerun web viewer on this port (default: a free one) until Ctrl-C; Rerun's "
                        "web server listens on every interface of this machine, the recording's own stream on "
                        "127.0.0.1 only")
    g.add_argument("--spawn", action="store_true", help="also start a local Rerun viewer and send it the run")
    g.add_argument("--connect", nargs="?", const="", metavar="URL",
                   help="also send the run to a Rerun viewer at URL (default rerun+http://127.0.0.1:9876/proxy)")
    v.set_defaults(func=cmd_view)
