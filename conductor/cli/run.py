"""The commands that run the twin: ``twin run`` (embedded), ``twin router``, ``twin conductor``, ``twin agent``
and ``twin status`` (the same pieces on separate machines)."""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import signal
import sys
import threading
from pathlib import Path
from typing import Any, TextIO

import zenoh

from protocol.config import (
    DEFAULT_ENDPOINT,
    ZenohOptions,
    add_zenoh_args,
    check_endpoint,
    options_from_args,
    zenoh_problem,
)
from protocol.errors import TwinError
from protocol.keys import Keys
from protocol.ros2 import namespace_problem

from ..core import Conductor, RunOptions
from ..launch import free_port, run_embedded, write_summary
from ..provenance import recording_of_log, run_metadata, scene_of_log
from ..record import exit_code, unrun
from ..sampling import print_sample
from ..scene import check_launchable, load_scene, parse_scene
from ..scene.perception import load_perception, perceive
from ..sources.fit import check_fit
from ..sources.live import LiveSource
from ..sources.recording import load_recording, parse_joint_order, parse_remap
from ..sources.replay import ReplaySource
from ..sources.ros2 import MAX_ROS2_DOMAIN, Ros2Source

log = logging.getLogger("twin")


def count(text: str) -> int:
    """An argparse type: a whole number of at least 1 (``--samples``, ``--max-ticks``, ``--jobs``)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"at least 1, not {n}")
    return n

def seed_arg(text: str) -> int:
    """An argparse type: ``--seed``, a whole number from 0 to :data:`~conductor.sampling.MAX_SEED`."""
    from ..sampling import check_seed

    try:
        return check_seed(int(text))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e) if text.strip().lstrip("-").isdigit() else
                                         f"not a whole number: {text!r}") from None




def ros2_domain(text: str) -> int:
    """An argparse type: ``--ros2-domain``, a ROS 2 domain id from 0 to :data:`MAX_ROS2_DOMAIN`."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 0 <= n <= MAX_ROS2_DOMAIN:
        raise argparse.ArgumentTypeError(f"a ROS 2 domain id from 0 to {MAX_ROS2_DOMAIN}, not {n}")
    return n


def ros2_namespace(text: str) -> str:
    """An argparse type: ``--ros2-namespace`` (:func:`protocol.ros2.namespace_problem`)."""
    problem = namespace_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def finite(text: str, *, strict: bool = True) -> float:
    """An argparse type: a finite number above 0 (``strict``), or at least 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(x) and (x > 0 if strict else x >= 0)):
        raise argparse.ArgumentTypeError(f"a finite number {'above' if strict else 'of at least'} 0, not {text}")
    return x


class DefaultsHelp(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` that gives an option's default where it has one and its help does not say it already, and
    nothing for a default of None, False or "" (argparse's own says "(default: None)" on every option without)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        d = action.default
        if d is None or d is False or d == "" or d == argparse.SUPPRESS or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def positive(text: str) -> float:
    """An argparse type: a finite number above 0 (seconds, a real-time factor, a rate)."""
    return finite(text)


def _live_factory(args):
    """A function (session, keys) -> live source for ``--live`` / ``--ros2-domain``, or None."""
    domain = getattr(args, "ros2_domain", None)
    if domain is not None:
        return lambda session, keys: Ros2Source(session, keys, domain=domain, namespace=args.ros2_namespace,
                                                idle_timeout=_idle(args))
    if getattr(args, "live", False):
        return lambda session, keys: LiveSource(session, keys, idle_timeout=_idle(args))
    return None


def _load_recording(args):
    """The recording of ``--recording`` as the command line asks to read it (``--remap``, ``--joint-order``)."""
    return load_recording(args.recording, remap=getattr(args, "remap", None),
                          joint_order=parse_joint_order(getattr(args, "joint_order", None)))


def _say_where(note: str | None) -> None:
    """Where the entities start, when it is not where the robot saw them (see :func:`perceive`)."""
    if note:
        print(f"input: {note}", flush=True)


def _source(args, session=None, keys=None):
    factory = _live_factory(args)
    if factory is not None:
        return factory(session, keys), {}
    if getattr(args, "recording", None):
        rec = _load_recording(args)
        for line in rec.notes():  # not defects (the run stays complete), but the replay lacks them
            print(f"input: {line}", flush=True)
        meta = {"twin.recording": {"path": args.recording, "storage": rec.storage, "topics": json.dumps(rec.topics)}}
        return ReplaySource(rec), meta
    return None, {}  # (--max-ticks alone: a run without telemetry)


def check_recording_options(args) -> None:
    """--remap and --joint-order checked before anything starts (ValueError: one line, exit 2)."""
    parse_remap(getattr(args, "remap", None))
    parse_joint_order(getattr(args, "joint_order", None))


def add_recording_options(x) -> None:
    """--remap and --joint-order: how the topics of a robot's own bag become the twin's telemetry."""
    x.add_argument("--remap", action="append", default=None, metavar="FROM:=TO",
                   help="read the recording's topic TO as FROM (/joint_states or /action), e.g. "
                        "/joint_states:=/arm/joint_states; repeat FROM to merge several joint-state topics by joint "
                        "name (default: /joint_states and /action, else the topics whose names end so)")
    x.add_argument("--joint-order", metavar="NAME,NAME,...",
                   help="names of the joints of joint states whose name list is empty, in position order")


def _print_event(kind: str, data: dict) -> None:
    if kind == "handover":
        print(f"  t={data['t']:8.3f}s  handover  {data['entity']}.{data['attribute']}: {data['from']} -> {data['to']}"
              f"  ({data['trigger']})", flush=True)
    elif kind == "agent_lost":
        t = data.get("t")
        when = f"t={t:8.3f}s" if isinstance(t, (int, float)) else "t=" + " " * 9
        what = ("the main model: nothing can take its responsibilities, the run cannot go on" if data.get("main") else
                "its responsibilities fall back to the main model")
        print(f"  {when}  agent lost: {data['model']} ({what})", flush=True)
    elif kind == "rejoin":
        print(f"  agent rejoined: {data['model']}", flush=True)
    elif kind == "sample":
        print_sample(int(data.get("sample", -1)), data)


def _print_progress(p: dict) -> None:
    if not sys.stderr.isatty():
        return
    dur = p.get("duration")
    total = f" / {dur:.1f} s" if dur and dur != float("inf") else ""
    rtf = f"  (real-time factor {p['rtf']:.2f})" if p.get("rtf") else ""
    print(f"\r  t = {p['t']:.1f} s{total}{rtf}   ", end="", file=sys.stderr, flush=True)


STATUS_WORDS = {
    "complete": "COMPLETE: every model answered every step and the whole source ran",
    "degraded": "DEGRADED: the run went to its end, but the answer may be wrong",
    "truncated": "TRUNCATED: the run stopped before the end of its source",
    "interrupted": "INTERRUPTED: the run was stopped by a signal",
    "failed": "FAILED: the run could not run or could not go on",
}


def _rtf(value: Any) -> str:
    """A real-time factor as a person reads it: three significant digits (the summary keeps four decimals)."""
    return f"{value:.3g}" if isinstance(value, (int, float)) and value > 0 else "n/a"


def print_summary(s: dict) -> None:
    """The run's outcome for a person: its status first, in words one cannot miss."""
    scene = s.get("scene") if s.get("scene") not in (None, "?") else None
    took = (" (cut short: its wall time is unknown)" if s.get("cut_short") else
            f" in {s['wall_s']:.2f} s (real-time factor {_rtf(s['rtf'])})")
    print(f"\nrun{f' of {scene}' if scene else ''}: {s['ticks']} ticks, {s['sim_s']:.2f} s simulated{took}")
    print(f"status: {STATUS_WORDS.get(s['status'], s['status'])}")
    reasons = s.get("status_reasons", [])
    for why in reasons[:10]:
        print(f"  - {why}")
    print(f"handovers: {len(s['handovers'])}; malformed messages on the bus: {s['malformed_messages']}")
    if s["semantic_state"] and s["status"] in ("truncated", "interrupted", "failed"):
        print("  when it stopped (not the answer: the run did not go to the end of its source):")
    for k, v in s["semantic_state"].items():
        print(f"  {k} = {v}")
    if s.get("lag"):
        print("lag: " + ", ".join(f"{k} {round(v, 2) if isinstance(v, float) else v}" for k, v in s["lag"].items()))
    for w in s.get("input_warnings", []):
        if f"input: {w}" not in reasons:  # said once (a degraded run gave it as a reason above)
            print(f"input: {w}")
    for w in s.get("step_warnings", []):  # a model said it could not do all of its step (the run went on)
        print(f"warning: {w}")
    for note in s.get("input_notes", []):  # what the answer rests on that is no defect (entities where the scene
        print(f"input: {note}")  # put them, how a live run ended)
    problems = [e for e in s["errors"] if e not in reasons]  # each said once
    if problems:
        print("problems:")
        for e in problems[:10]:
            print(f"  - {e}")
    print(f"run log: {s['run_log'] or 'none (the run did not start)'}")
    if s.get("rerun"):
        print(s["rerun"])


# ------------------------------------------------------------------ commands
ACL_TRACE = "zenoh::net::routing::interceptor::access_control=trace"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def log_denials(stream: TextIO) -> None:
    """Write the router's access-control denials to ``stream`` as they happen, one line each.

    Zenoh traces every access-control decision on ``stdout`` (the allowed ones too: one line per message). This
    switches that trace on (unless ``RUST_LOG`` says otherwise), points file descriptor 1 at a pipe and keeps,
    of what comes through it, everything but the allowed decisions (written to ``stream``). A denial that
    repeats (a flood) is written the first time, then at the 10th, 100th, 1000th... repetition with its count."""
    read_fd, write_fd = os.pipe()
    sys.stdout.flush()
    os.dup2(write_fd, 1)
    os.close(write_fd)
    seen: dict[str, int] = {}

    def pump() -> None:
        caching = ""  # Zenoh works out every permission of a newly declared key at once: not attempts
        with os.fdopen(read_fd, errors="replace") as pipe:
            for raw in pipe:
                line = _ANSI.sub("", raw)
                cached = re.search(r"caching permissions for `([^`]*)`", line)
                if cached is not None:
                    caching = cached.group(1)
                    continue
                if caching and line.rstrip().endswith(f" on {caching}"):
                    continue
                caching = ""
                if " is authorized to " in line:
                    continue
                m = re.search(r"(\S+ is unauthorized to .*|\S+ did not match any configured ACL subject.*)$",
                              line.strip())
                if m is None:
                    stream.write(line)
                    continue
                what = m.group(1)
                n = seen[what] = seen.get(what, 0) + 1
                if n == 1 or math.log10(n).is_integer():
                    stream.write(f"access denied: {what}" + (f" ({n} times)" if n > 1 else "") + "\n")
                stream.flush()

    threading.Thread(target=pump, name="twin-denials", daemon=True).start()
    zenoh.init_log_from_env_or(f"warn,{ACL_TRACE}")


def cmd_router(args) -> int:
    opts = options_from_args(args)
    opts.mode = "router"
    if args.log_denials == "on" or (args.log_denials == "auto" and _access_control(opts)):
        log_denials(os.fdopen(os.dup(1), "w", buffering=1))
    else:
        zenoh.init_log_from_env_or("warn")  # a router shows its warnings (a TLS handshake refused, ...)
    session = opts.open()
    print(f"zenoh router listening on {', '.join(opts.listen or [DEFAULT_ENDPOINT])} (Ctrl-C stops)", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    session.close()
    return 0


def _access_control(opts: ZenohOptions) -> bool:
    """Whether the router's configuration switches access control on."""
    try:
        return json.loads(opts.to_config().get_json("access_control/enabled")) is True
    except Exception:  # the session's own opening reports a bad configuration
        return False


def cmd_agent(args) -> int:
    """``twin agent ...`` is ``python -m agents ...``: this process becomes the agent (an agent never needs the
    conductor's code, and the conductor never imports a model's)."""
    os.execve(sys.executable, [sys.executable, "-m", "agents", *args.agent_args],
              {**os.environ, "TWIN_AGENT_PROG": "twin agent"})
    return 0  # not reached


def cmd_conductor(args) -> int:
    usage = _source_problem(args)
    if usage:  # as twin run says it (the options were ignored, and no source at all ended in a TypeError)
        print(f"twin conductor: {usage}", file=sys.stderr)
        return 2
    check_recording_options(args)
    scene = load_scene(args.scene)
    opts = options_from_args(args)
    keys = Keys(opts.ensemble)
    stopped: list[str] = []  # a signal before the run began: the run is not started
    conductor: list[Conductor] = []

    def on_signal(n, _frame) -> None:
        stopped.append(signal.Signals(n).name)
        if conductor:
            conductor[0].stop(signal=signal.Signals(n).name)

    for sig in (signal.SIGINT, signal.SIGTERM):  # (before the session: a router that never answers is waited for
        signal.signal(sig, on_signal)              # a second at a time, and Ctrl-C ends the wait)
    session = opts.open_patiently(lambda: bool(stopped),
                                  waiting=lambda why: print(f"twin conductor: {why}; waiting (Ctrl-C stops)",
                                                            file=sys.stderr, flush=True))
    if session is None:
        s = unrun(f"stopped ({stopped[0]}) while waiting for the Zenoh router", status="interrupted",
                  scene=scene.name)
    else:
        try:
            source, meta = _source(args, session, keys)
            _say_where(perceive(scene, source, args.perception))
            run = RunOptions(run_log=args.run_log, rtf=args.rtf, max_ticks=args.max_ticks, metadata=meta,
                             register_timeout=args.register_timeout, network_mode=opts.mode,
                             deadline=_deadline(args, source))
            c = Conductor(scene, session, keys, source, run, on_event=_print_event, progress=_print_progress)
            conductor.append(c)
            if stopped:
                c.stop(signal=stopped[0])
            graph = None
            if args.ros2_domain is not None:  # (the twin in the robot's ROS 2 graph, as twin run's)
                from ..ros2_out import join_graph

                graph = join_graph(session, args.ros2_domain, args.ros2_namespace, c, source)
            try:
                s = c.run()
            finally:
                if graph is not None:
                    graph.close()
            c.close()
        finally:
            session.close()
    print_summary(s)
    if args.summary:
        write_summary(args.summary, s)
    return exit_code(s)


RERUN_MODES = ("none", "save", "spawn", "serve", "connect")


def _embedded_endpoint(listen: str | None) -> str | None:
    """The embedded router's endpoint, checked, with a port 0 replaced by a free port (the agents are told
    where to connect before the router opens)."""
    if listen is None:
        return None
    check_endpoint(listen)
    head, _, port = listen.rpartition(":")
    return f"{head}:{free_port()}" if port == "0" else listen


def _deadline(args: argparse.Namespace, source: Any) -> float | None:
    """``--deadline``, else for a replay 600 s plus 20 times the recording's length (none live)."""
    if args.deadline is not None:
        return float(args.deadline)
    rec = getattr(source, "rec", None)
    return None if rec is None else 600.0 + 20.0 * rec.duration


def _idle(args: argparse.Namespace) -> float:
    """``--idle-timeout``, 3 s when not given."""
    return 3.0 if args.idle_timeout is None else float(args.idle_timeout)


def _source_problem(args) -> str | None:
    """What is wrong with the source a run's command line gives (``twin run``'s and ``twin conductor``'s): options
    that would do nothing, no source, two sources, a pace for a live robot (None: nothing)."""
    live = args.live or args.ros2_domain is not None
    from_log = getattr(args, "from_log", None)
    for flag, given, needs in (("--ros2-namespace", bool(args.ros2_namespace) and args.ros2_domain is None,
                                "--ros2-domain N"),
                               ("--idle-timeout", args.idle_timeout is not None and not live,
                                "--live or --ros2-domain N"),
                               ("--remap", bool(args.remap) and not args.recording, "--recording FILE (a bag)"),
                               ("--joint-order", bool(args.joint_order) and not args.recording,
                                "--recording FILE (a bag)")):
        if given:  # an option that would do nothing here: said, not ignored
            return f"{flag} goes only with {needs}"
    if not (args.recording or live or args.max_ticks or from_log):
        return ("nothing to run on: give --recording FILE, --live or --ros2-domain N (or --max-ticks N to run without "
                "telemetry" + (", or --from-log RUN.mcap)" if hasattr(args, "from_log") else ")"))
    sources = [f for f, given in (("--recording", bool(args.recording)), ("--live", bool(args.live)),
                                  ("--ros2-domain", args.ros2_domain is not None), ("--from-log", bool(from_log)))
               if given]
    if len(sources) > 1:  # one run has one source: the others would be ignored without a word
        return f"{' and '.join(sources)} are each a source of the run: give one"
    if args.rtf is not None and live:  # (it paced the live twin ahead of its robot, at that factor)
        return "--rtf paces a replay: a live run goes at the robot's pace"
    return None


def _usage_problem(args) -> str | None:
    """What is wrong with a single run's command line (None: nothing)."""
    if args.no_hold and not args.rerun.strip().lower().startswith("serve"):
        return "--no-hold goes only with --rerun serve"
    alone = [f for f, given in (("--jobs", args.jobs is not None), ("--cold", args.cold),
                                ("--cluster", args.cluster is not None), ("--seed", args.seed != 0)) if given]
    if alone:  # options of samples, given to one run
        return (f"{', '.join(alone)} {'goes' if len(alone) == 1 else 'go'} only with --samples K (they say how samples "
                "are drawn and where they run; one run starts its own processes, here)")
    problem = _source_problem(args)
    if problem:
        return problem
    if args.connect and args.listen:  # (the flag: TWIN_LISTEN, the environment's, is left alone with --connect)
        return ("--listen is where the embedded router listens: with --connect the run embeds none (the robot and "
                "the agents join the router it connects to)")
    if args.connect and args.open_bus:
        return "--open-bus opens the embedded router's bus: with --connect the run embeds none (the router joined " \
               "admits whom its own configuration admits)"
    if not (args.scene or args.from_log):
        return "give the scene file (or --from-log RUN.mcap, which carries its scene)"
    if args.rerun.partition("=")[0].strip().lower() not in RERUN_MODES:
        return f"unknown --rerun mode {args.rerun!r}: use none, save, spawn, serve[=WEBPORT] or connect[=URL]"
    return None


def cmd_run(args) -> int:
    if args.samples is not None:
        from .samples import cmd_samples  # K whole runs, reported as a distribution

        return cmd_samples(args)
    usage = _usage_problem(args)
    if usage:  # said, not silently ignored or guessed
        print(f"twin run: {usage}", file=sys.stderr)
        return 2
    try:
        return _run_one(args)
    except (TwinError, ValueError, zenoh.ZError) as e:  # it could not start (main says why; 2 for bad input: a
        # bad endpoint too; else 1, as for Zenoh's refusals: a port in use): a summary all the same
        if args.summary:
            why = f"zenoh: {zenoh_problem(e)}" if isinstance(e, zenoh.ZError) else str(e)
            print(f"summary: {write_summary(args.summary, unrun(why))}", file=sys.stderr)
        raise


def _run_one(args) -> int:
    """One run of a command line :func:`_usage_problem` found nothing wrong with."""
    check_recording_options(args)
    listen = None if args.connect else _embedded_endpoint(args.listen or os.environ.get("TWIN_LISTEN") or None)
    if args.connect:
        check_endpoint(args.connect)
    source, meta = (None, {})
    factory = _live_factory(args)  # a live source needs the router's session: run_embedded builds it
    if args.from_log:  # the scene, perception and joint states a finished run's log carries
        text, file, perceived = scene_of_log(args.from_log)
        scene = load_scene(args.scene) if args.scene else parse_scene(text, file)
        text = Path(args.scene).read_text(encoding="utf-8") if args.scene else text
        source = ReplaySource(recording_of_log(args.from_log))
        scene.apply_perception(load_perception(args.perception) if args.perception else perceived)
    else:
        scene = load_scene(args.scene)
        text = Path(args.scene).read_text(encoding="utf-8")
        if factory is None and args.recording:
            source, meta = _source(args)
        _say_where(perceive(scene, source, args.perception, live=factory is not None))
    meta = {**meta, **run_metadata(scene, text, source.rec if source is not None else None)}
    if source is not None and scene.declared_robot is not None:  # fail fast, before any agent starts
        check_fit(scene.declared_robot, source.rec.joints_in_order, args.recording or args.from_log,
                  source.rec)
    check_launchable(scene)  # (an unknown kind: said before "running", not after it)
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
                           live=factory, idle_timeout=_idle(args), rerun=args.rerun,
                           progress=_print_progress, hold=None if args.no_hold else hold,
                           register_timeout=args.register_timeout, open_bus=args.open_bus,
                           deadline=_deadline(args, source), connect=args.connect,
                           ros2_out=(args.ros2_domain, args.ros2_namespace) if args.ros2_domain is not None else None,
                           router_options=ZenohOptions(mode="router", listen=[listen]) if listen else None)
    if not held:
        print_summary(summary)
    if args.summary:
        print(f"summary: {write_summary(args.summary, summary)}")
    elif summary.get("run_log"):  # (run_embedded wrote it beside the run log)
        print(f"summary: {Path(summary['run_log']).parent / 'summary.json'}")
    return exit_code(summary)


def register(sub) -> None:
    """Add router, agent, conductor and run to the ``twin`` subcommands."""

    r = sub.add_parser("router", help="run a Zenoh router for agents on several machines",
                       description="Run a Zenoh router that agents and the conductor connect to.",
                       formatter_class=DefaultsHelp)
    add_zenoh_args(r, default_mode="router", listens=DEFAULT_ENDPOINT)
    r.add_argument("--log-denials", choices=["auto", "on", "off"], default="auto",
                   help="write each access-control denial to stderr ('access denied: <who> is unauthorized to Put "
                        "(ingress) on <key>'); auto: when the configuration enables access_control")
    r.set_defaults(func=cmd_router)

    a = sub.add_parser("agent", help="run one model as an agent process (python -m agents)", add_help=False,
                       description="Run one model as an agent: it registers with the conductor and serves "
                                   "twin/<ensemble>/model/<name>/... until SIGINT/SIGTERM. 'twin agent KIND --help' "
                                   "documents KIND's parameters, attributes, outputs, events and evaluators.")
    a.add_argument("agent_args", nargs=argparse.REMAINDER, help="KIND --name NAME [Zenoh flags]; KIND --help")
    a.set_defaults(func=cmd_agent)

    def run_opts(x):
        x.add_argument("scene", nargs="?" if x.prog.endswith(" run") else None,
                       help="scene YAML file" + (" (with --from-log: the log's own by default)"
                                                 if x.prog.endswith(" run") else ""))
        x.add_argument("--recording", help="robot recording to replay: an MCAP file, a rosbag2 directory (MCAP or "
                                           "SQLite storage) or a .db3 file")
        add_recording_options(x)
        x.add_argument("--live", action="store_true", help="attach to live telemetry on twin/<ensemble>/telemetry/**")
        x.add_argument("--ros2-domain", type=ros2_domain, default=None, metavar="N",
                       help="attach live to a ROS 2 robot on rmw_zenoh: its /joint_states and /action in domain N")
        x.add_argument("--ros2-namespace", type=ros2_namespace, default="",
                       help="ROS 2 namespace of those topics (with --ros2-domain)")
        x.add_argument("--perception", metavar="FILE",
                       help="where the robot perceived the scene's objects: a recording (.mcap, its 'twin.scene' "
                            "metadata) or a JSON/YAML file {entities: {name: {pose: [...]}}}, or none: the scene's "
                            "own poses (default: the replayed recording's own)")
        x.add_argument("--idle-timeout", type=positive, default=None,
                       help="live: end the run after this many seconds without telemetry (default 3)")
        x.add_argument("--rtf", type=positive, default=None,
                       help="pace a replay at this real-time factor (default: as fast as possible)")
        x.add_argument("--max-ticks", type=count, default=None, help="stop after this many ticks")
        x.add_argument("--summary", metavar="FILE.json", help="write the run summary as JSON")
        x.add_argument("--register-timeout", type=positive, default=60.0,
                       help="seconds to wait for the scene's agents")
        x.add_argument("--deadline", type=positive, default=None, metavar="SECONDS",
                       help="wall seconds the whole run may take before it is stopped as truncated (default for a "
                            "replay: 600 + 20 x the recording's length; live: none)")

    c = sub.add_parser("conductor", help="run the conductor for a scene (agents started separately)",
                       description="Run the conductor: wait for the scene's agents, initialise them, run the clock, "
                                   "move responsibilities, write the run log.", formatter_class=DefaultsHelp)
    run_opts(c)
    c.add_argument("--run-log", default="run.mcap", help="MCAP file for the run log (default run.mcap)")
    add_zenoh_args(c)
    c.set_defaults(func=cmd_conductor)

    rn = sub.add_parser("run", help="run a scene end to end on an embedded router (the default way)",
                        description="Open a Zenoh router in this process, start the conductor and every agent the "
                                    "scene names as subprocesses on loopback, run them on the source (--recording, "
                                    "a live robot with --live or --ros2-domain, or --from-log a run's log), print the "
                                    "summary.",
                        epilog="The exit code is the run's status: 0 complete; 1 failed (it could not run or go on); "
                               "2 bad input (command line, scene, or an input file that cannot be read or does not "
                               "fit); 3 degraded (it went to its end, but something its answer may depend on went "
                               "wrong: see status_reasons); 4 truncated (stopped before the end of its source); "
                               "5 interrupted (SIGINT/SIGTERM). A live run waits up to 30 s for the robot's first "
                               "message and ends when the robot has been quiet for --idle-timeout seconds.",
                               formatter_class=DefaultsHelp)
    run_opts(rn)
    rn.add_argument("--ensemble", default=os.environ.get("TWIN_ENSEMBLE", "default"),
                    help="ensemble name: the key namespace twin/<ensemble>/ (env TWIN_ENSEMBLE, default 'default')")
    rn.add_argument("--run-dir", help="folder for the run log, agent logs and summary (default runs/<scene>-<time>)")
    rn.add_argument("--listen", metavar="ENDPOINT", default=None,
                    help="endpoint of the embedded router (env TWIN_LISTEN; default: a free tcp/127.0.0.1 port)")
    rn.add_argument("--rerun", default="none", metavar="MODE",
                    help="Rerun stream: none, save, spawn, serve or connect=URL (default none); every mode also "
                         "writes run.rrd; with serve the web viewer stays up after the run until Ctrl-C")
    rn.add_argument("--open-bus", action="store_true",
                    help="let any process on the network join the embedded router (default: only this run's "
                         "agents and holders of <run dir>/access.json, with user/password secrets made per run)")
    rn.add_argument("--connect", metavar="ENDPOINT", default=None,
                    help="join a Zenoh router that is already running (e.g. rmw_zenohd on tcp/localhost:7447) "
                         "instead of embedding one; the agents connect to it too (the bus is then the router's)")
    rn.add_argument("--from-log", metavar="RUN.mcap",
                    help="re-run a finished run from its log alone: the scene text, perception and the joint states "
                         "and actions its replay published (give a scene file to re-run them with another scene)")
    rn.add_argument("--samples", type=count, default=None, metavar="K",
                    help="run K variations of what the twin does not know for sure (perceived positions within "
                         "the perception's position_sigma, the scene's uncertain: ranges) and report each "
                         "predicate's probability with a 95%% interval and the handover times' spread")
    rn.add_argument("--seed", type=seed_arg, default=0,
                    help="with --samples: sample i is drawn with seed + i (so seeds 5 and 6 share all "
                         "draws but one: for independent repeats, space the seeds by K or more)")
    rn.add_argument("--jobs", type=count, default=None, metavar="N",
                    help="with --samples: runs at once here (default 1)")
    rn.add_argument("--cold", action="store_true",
                    help="with --samples: a fresh router and agent processes for every sample (default: each set "
                         "of models is started once, on a service of this run's own, and initialised again for "
                         "each sample)")
    rn.add_argument("--cluster", metavar="ADDRESS",
                    help="with --samples: run them on a Dask distributed cluster (tcp://scheduler:8786)")
    rn.add_argument("--no-hold", action="store_true",
                    help="with --rerun serve: exit at the end of the run instead of serving until Ctrl-C")
    rn.set_defaults(func=cmd_run)

