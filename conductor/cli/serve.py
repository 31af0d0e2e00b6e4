"""``twin serve`` (the conductor as a long-lived service with warm agents), ``twin submit`` (its client) and
``twin trigger`` (a scene's service trigger fired from outside, during a run)."""
from __future__ import annotations

import json
import os
import re
import signal
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import yaml
import zenoh

from protocol import codec
from protocol.config import (
    DEFAULT_ENDPOINT,
    MAX_MESSAGE_SIZE,
    ZenohOptions,
    add_zenoh_args,
    check_endpoint,
    options_from_args,
)
from protocol.errors import InputError, ProtocolError, SceneError, TwinError
from protocol.keys import Keys

from ..launch import ClosedBus, output_dir, write_summary
from ..record import exit_code
from ..sampling import print_distribution, print_outcome
from ..scene import check_launchable, load_scene
from ..scene.perception import load_perception
from ..service import MAX_SCENE_CHARS, Job, Service
from ..sources.recording import parse_joint_order, parse_remap
from .run import (
    DefaultsHelp,
    _print_event,
    add_recording_options,
    count,
    positive,
    print_summary,
    ros2_domain,
    ros2_namespace,
    seed_arg,
)


def cmd_serve(args) -> int:
    run_root = output_dir(Path(args.run_dir))
    _held = _own(run_root)  # as long as this process lives
    bus = None
    if args.connect:  # join a router that is already there (the agents connect to it too)
        opts = options_from_args(args)
        opts.mode = "client" if args.mode == "router" else args.mode
        endpoint = opts.connect[0]
    else:
        listen = check_endpoint(args.listen[0] if args.listen else DEFAULT_ENDPOINT)
        opts = ZenohOptions(mode="router", listen=[listen])
        endpoint = listen
        if not args.open_bus:
            bus = ClosedBus(run_root)
            bus.serves(endpoint, args.ensemble)
            opts.auth_dictionary = str(bus.dictionary)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = opts.open_patiently(stop.is_set, waiting=lambda why: print(
        f"twin serve: {why}; trying again every second (Ctrl-C gives up)", flush=True))
    if session is None:  # stopped while waiting: asked for, as a stop while serving is (exit 0), and nothing ran
        print("twin serve: stopped before a router answered (nothing was served)", flush=True)
        if bus is not None:
            bus.close()
        return 0
    try:
        with Service(session, endpoint, args.ensemble, run_root, parallel=args.parallel, max_pools=args.max_pools,
                     agent_env=bus.agent_env() if bus is not None else None,
                     register_timeout=args.register_timeout, network_mode=opts.mode) as svc:
            svc.serve()
            print(f"twin serve: ensemble {args.ensemble!r} on {endpoint}"
                  + (" (the bus is open)" if bus is None and not args.connect else "")
                  + f"; runs go to {run_root}; Ctrl-C stops\n"
                  f"  clients: twin submit SCENE --recording R{client_flags(args.ensemble, endpoint, bus)}",
                  flush=True)
            stop.wait()
            print("twin serve: stopping (running runs end as truncated)", flush=True)
    finally:
        session.close()
        if bus is not None:
            bus.close()
    return 0


def client_flags(ensemble: str, endpoint: str, bus: ClosedBus | None) -> str:
    """The options a client (``twin submit``, ``status``, ``stop``, ``trigger``) needs to reach this service: the
    endpoint when it is not the default, the ensemble when it is not ``default``, the access file of a closed bus
    (said in full: a client given only the access file asked the default endpoint and found no router)."""
    flags = [] if endpoint == DEFAULT_ENDPOINT else [f"--connect {endpoint}"]
    flags += [] if ensemble == "default" else [f"--ensemble {ensemble}"]
    flags += [] if bus is None else [f"--credentials {bus.access}"]
    return "".join(" " + f for f in flags)


def _own(run_root: Path) -> Any:
    """Take ``run_root`` for this service (an exclusive lock on ``.serve.lock`` in it, released when the process
    ends, however it ends): a second service there would write its own access file over the first's and number
    its runs over them. Raises :class:`TwinError` when another live service holds it."""
    import fcntl

    f = open(run_root / ".serve.lock", "a+")  # noqa: SIM115 - kept open: the lock lasts as long as the file
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        raise TwinError(f"{run_root}: another twin serve uses this run directory (give this one --run-dir "
                        "of its own)") from None
    return f


def job_from_args(args) -> Job:
    """The job ``twin submit``'s command line describes (paths made absolute when they exist here)."""
    scene_path = Path(args.scene)
    if scene_path.is_file() and scene_path.stat().st_size > MAX_SCENE_CHARS:  # (the service would refuse it)
        raise InputError(f"{scene_path}: {scene_path.stat().st_size / 2**20:.1f} MiB, more than the "
                         f"{MAX_SCENE_CHARS / 2**20:g} MiB a scene sent to the service may be")
    check_launchable(load_scene(scene_path))  # a bad scene is said here, with file and line, before anything is sent
    text = scene_path.read_text(encoding="utf-8")
    parse_remap(args.remap)
    job = Job(scene_text=text, scene_file=str(scene_path.resolve()), max_ticks=args.max_ticks, rtf=args.rtf,
              deadline=args.deadline, remap=args.remap, joint_order=parse_joint_order(args.joint_order),
              idle_timeout=args.idle_timeout)
    if args.recording:
        job.recording = os.path.abspath(args.recording) if os.path.exists(args.recording) else args.recording
    job.live = args.live_ensemble
    job.ros2_domain, job.ros2_namespace = args.ros2_domain, args.ros2_namespace
    job.samples, job.seed = args.samples, args.seed
    if args.perception:
        job.perception = load_perception(args.perception)
    return job


class Silent(TwinError):
    """No service answered (the client may ask again); a refusal is :class:`Refused`."""


BAD_REQUEST = tuple(e.__name__ for e in (ValueError, SceneError, InputError, ProtocolError))
"""The kinds of a refusal that say the request was bad (exit 2), not that the service could not take it."""


def run_id(text: str) -> str:
    """A run id as the service numbers its runs (``3``; ``03`` is 3); ValueError for anything else (a sample of a
    sampled run is not a run of its own)."""
    if not re.fullmatch(r"[0-9]+", text.strip()):
        raise ValueError(f"{text!r} is no run id: a run id is the number twin submit printed (3, 12...)")
    return str(int(text))


class TimedOut(Silent):
    """A service (or a run's conductor) took the query but did not answer in time."""


class Refused(TwinError):
    """The service answered with an error: ``kind`` is its type (``ValueError``, ``SceneError``: the request was
    bad; others: the service could not take it)."""

    def __init__(self, message: str, kind: str = "") -> None:
        super().__init__(message)
        self.kind = kind

    @property
    def bad_request(self) -> bool:
        return self.kind in BAD_REQUEST


def _ask(session: Any, key: str, args: dict[str, Any], expect: str, timeout: float, late: str = "",
         selector: str = "") -> Any:
    """One query to the service (on ``key``, with ``selector``'s parameters); its decoded answer. TwinError with the
    service's reason, or when none answered (``late``: what became of a request answered too late, said then)."""
    t0 = time.monotonic()
    payload = codec.encode("control", args=args)
    if len(payload) > MAX_MESSAGE_SIZE:  # (Zenoh drops it unsent: the service would seem busy)
        raise Refused(f"the request is {len(payload) / 2**20:.1f} MiB, more than the {MAX_MESSAGE_SIZE / 2**20:g} MiB "
                      "a message may be: is the scene or the perception that large?", "ValueError")
    for reply in session.get(key + selector, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return codec.decode(key, reply.ok.payload, expect)
        if reply.err.payload.to_bytes() == codec.ZENOH_TIMEOUT:  # Zenoh's own error reply: something took the query
            raise TimedOut(f"no answer on {key} within {timeout:g} s: something there took the query but did not "
                           f"answer in time (busy or held up){late}")
        err = codec.decode(key, reply.err.payload, "error")
        raise Refused(f"the service refused: {err.message}", str(err.get("kind") or ""))
    waited = time.monotonic() - t0  # (Zenoh ends a query at once when nothing on the network takes that key)
    when = (f"within {timeout:g} s" if waited > 0.9 * timeout else
            f"(nothing there takes that key: the query ended after {waited:.1f} s)")
    raise Silent(f"nothing answered on {key} {when} (no twin serve or twin run of that ensemble there, or one that "
                 "did not let this session in)")


def cmd_submit(args) -> int:
    if not (args.recording or args.live_ensemble or args.ros2_domain is not None or args.max_ticks):
        print("twin submit: nothing to run on: give --recording FILE, --live-ensemble ENSEMBLE or --ros2-domain N",
              file=sys.stderr)
        return 2
    if args.samples is not None and not args.recording:
        print("twin submit --samples: give --recording (samples vary a replay)", file=sys.stderr)
        return 2
    job = job_from_args(args)
    session, keys = _client(args, "twin submit")
    if session is None:
        return 1
    try:
        try:
            late = "; a twin serve queues no start it did not answer in time: submit again, or give a longer --timeout"
            answer = _ask(session, keys.conductor("start"), job.as_args(), "value_reply", args.timeout, late,
                          f"?timeout={args.timeout:g}").value
        except Refused as e:  # a bad request (exit 2, as a bad command line here), or a service that cannot take it
            print(f"twin submit: {e}", file=sys.stderr)
            return 2 if e.bad_request else 1
        run = answer["run"]
        print(f"run {run} of {Path(args.scene).name} {_placed(answer)}", flush=True)
        summary = follow(session, keys, str(run), args.timeout)
    finally:
        session.close()
    return report(summary, args.summary)


def report(summary: dict[str, Any], summary_file: str | None = None) -> int:
    """Print a run's summary from the service as ``twin run`` prints its own; its exit code."""
    if "predicates" in summary:  # a sampled run: its distribution
        print_distribution(summary, summary.get("scene", "?"), str(summary.get("recording")))
        print_outcome(summary)
    else:
        print_summary(summary)
    service = summary.get("service") or {}
    if service.get("restarted_agents"):
        print(f"service: new processes in this run: {', '.join(service['restarted_agents'])} (exited, stopped, not "
              "answering in the run before, or their model file changed)")
    if service.get("replaced_after"):
        print(f"service: {', '.join(service['replaced_after'])} did not answer in this run: started again for the "
              "next one")
    if summary.get("trimmed"):
        print(f"note: {summary['trimmed']}")
    if summary_file:
        print(f"summary: {write_summary(summary_file, summary)}")
    return exit_code(summary)  # (2: a scene or an input file the service could not use, as twin run says it)


def _placed(answer: dict[str, Any]) -> str:
    """Where the service put a submitted run: started at once, or queued behind the runs before it."""
    ahead, parallel = answer.get("ahead"), answer.get("parallel")
    if not isinstance(ahead, list) or not isinstance(parallel, int):  # a service that does not say
        return "submitted to the service"
    if len(ahead) < parallel:
        return "started on the service"
    runs = ", ".join(map(str, ahead))
    return f"queued on the service behind run{'s' if len(ahead) > 1 else ''} {runs} ({parallel} at a time)"


def follow(session: Any, keys: Keys, run: str, timeout: float, poll: float = 0.2, stop_on_ctrl_c: bool = True,
           shown: int = 0, interrupted: threading.Event | None = None) -> dict[str, Any]:
    """Print the run's events as they come (after the first ``shown``) and return its summary. Ctrl-C (or
    ``interrupted``, set by a caller's own SIGINT handler) asks the service to stop the run (it still ends with a
    summary, ``truncated``), or without ``stop_on_ctrl_c`` is KeyboardInterrupt here, between two queries (the run
    goes on). A service that stops answering for ``timeout`` seconds is a TwinError."""
    stopping = interrupted or threading.Event()
    old = signal.signal(signal.SIGINT, lambda *_: stopping.set()) if interrupted is None and \
        threading.current_thread() is threading.main_thread() else None
    asked_stop, last_answer = False, time.monotonic()
    try:
        while True:
            if stopping.is_set() and not stop_on_ctrl_c:
                raise KeyboardInterrupt  # (here, not inside a Zenoh call)
            if stopping.is_set() and not asked_stop:
                asked_stop = True
                try:
                    _ask(session, keys.conductor("stop"), {"run": run}, "ack", timeout)
                    print(f"\nasked the service to stop run {run}", flush=True)
                except TwinError as e:  # it finished meanwhile: its summary is next
                    print(f"\n{str(e).removeprefix('the service refused: ')}", flush=True)
            try:
                view = _ask(session, keys.conductor("status"), {"run": run, "since": shown}, "status", timeout).fields
                last_answer = time.monotonic()
            except Silent as e:  # (a service gone answers at once that nothing is there: asked again each poll)
                if time.monotonic() - last_answer > timeout:
                    raise Silent(f"the service stopped answering about run {run} ({timeout:g} s without an answer "
                                 "after it took the run): it was stopped or died, or the network between went down; "
                                 f"what the run wrote is in its folder on the service's machine ({e})") from None
                time.sleep(poll)
                continue
            new = view.get("events", [])
            if view.get("events_from") != shown:  # (a service before events_from sends them all)
                new = new[shown:]
            for ev in new:
                _print_event(ev.get("kind", ""), ev)
            shown += len(new)
            if view.get("state") == "finished":
                return dict(view["summary"])
            time.sleep(poll)
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)


def _arg(text: str) -> tuple[str, Any]:
    """``--arg NAME=VALUE``, the value read as YAML (ValueError in one line when it is not a value a trigger can be
    given: unreadable YAML, a date)."""
    name, eq, value = text.partition("=")
    if not eq or not name.isidentifier():
        raise ValueError(f"--arg {text!r}: write NAME=VALUE (VALUE read as YAML: 3, 0.5, true, ball)")
    try:
        read = yaml.safe_load(value)
        codec.pack(read)  # (what goes on the wire: a date, a set, is no value there)
    except (yaml.YAMLError, TypeError, ValueError, OverflowError) as e:
        problem = str(e).splitlines()[0]
        raise ValueError(f"--arg {text!r}: the value is not a number, word, list or map the trigger can be given "
                         f"({type(e).__name__}: {problem}; quote it to pass it as text)") from None
    if isinstance(read, (int, float)) and not isinstance(read, bool) and ":" in value:
        raise ValueError(f"--arg {text!r}: YAML 1.1 reads {value.strip()} as the base-60 number {read} (1:30 is 90): "
                         f"write the number itself, or quote it to pass it as text")
    return name, read


def cmd_trigger(args) -> int:
    """Call a scene's service trigger on a running run; print what it did (exit 0), or why it did not fire or what
    of it failed (exit 1)."""
    pairs = [_arg(a) for a in args.arg or []]
    twice = sorted(n for n, k in Counter(n for n, _ in pairs).items() if k > 1)
    if twice:  # (the last one silently won)
        raise ValueError(f"--arg {', '.join(twice)} given more than once: give each argument once")
    call = dict(pairs)
    # the selector says how long this waits (a run that takes the call later drops it unfired) and, for a twin
    # serve, which run: the arguments go to the trigger as they are
    which = f"?timeout={args.timeout:g}"
    if args.run is not None:
        which += f";run={run_id(args.run)}"
    session, keys = _client(args, "twin trigger")
    if session is None:
        return 1
    try:
        answer = _ask(session, keys.conductor(f"trigger/{args.name}") + which, call, "value_reply",
                      args.timeout)
    except Silent as e:
        print(f"twin trigger: {e}" + ("; the call is not fired (a run drops a call taken after its caller's "
                                      "timeout)" if isinstance(e, TimedOut) else ""), file=sys.stderr)
        return 1
    except TwinError as e:
        why = str(e).removeprefix("the service refused: ")
        print(f"twin trigger: {why if why.startswith(args.name + ':') else f'{args.name}: {why}'}", file=sys.stderr)
        return 1
    finally:
        session.close()
    print(json.dumps(answer.value, indent=2, default=str))
    failed = _problems(answer.value)
    if failed:  # it fired, and an effect failed (the run is degraded by it): a script must not read success
        print(f"twin trigger: {args.name} fired, but not everything it did worked: {'; '.join(failed)[:500]}",
              file=sys.stderr)
        return 1
    return 0


def _problems(answer: Any) -> list[str]:
    """The ``problem`` and ``error`` entries anywhere in a trigger call's answer."""
    out: list[str] = []
    stack = [answer]
    while stack:
        v = stack.pop()
        if isinstance(v, dict):
            out += [str(v[k]) for k in ("problem", "error") if v.get(k)]
            stack.extend(v.values())
        elif isinstance(v, list):
            stack.extend(reversed(v))
    return out


def cmd_status(args) -> int:
    """``twin status``: the status of an ensemble's conductor (a twin run's, or a twin serve's), as JSON."""
    if args.run is not None:
        return run_status(args)
    if args.wait:
        raise ValueError("--wait waits for one run of a twin serve: give --run ID")
    session, keys = _client(args, "twin status")  # (a missing router is an answer too)
    if session is None:
        return 1
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


def run_status(args) -> int:
    """``twin status --run ID [--wait]``: one run on a twin serve: its state and events, its live status while it
    runs, its summary once over (as JSON); with ``--wait``, its events as they come and its summary as ``twin
    submit`` prints it, with the run's exit code (Ctrl-C leaves the run going)."""
    run = run_id(args.run)
    session, keys = _client(args, "twin status")
    if session is None:
        return 1
    leaving = threading.Event()  # Ctrl-C while waiting: leave between two queries, never inside one
    old = signal.signal(signal.SIGINT, lambda *_: leaving.set()) if args.wait else None
    try:
        view = _ask(session, keys.conductor("status"), {"run": run}, "status", args.timeout).fields
        if "state" not in view:  # (a twin run's conductor answers with its own status, whatever it is asked)
            print(f"twin status --run: the conductor of ensemble {keys.ensemble!r} is a twin run (one run), not a "
                  "twin serve: leave out --run", file=sys.stderr)
            return 2
        if not args.wait:
            print(json.dumps(view, indent=2, default=str))
            return 0
        print(f"run {run} of {view.get('scene', '?')}: {view['state']}", flush=True)
        for ev in view.get("events", []):
            _print_event(ev.get("kind", ""), ev)
        try:
            summary = view["summary"] if view["state"] == "finished" else \
                follow(session, keys, run, args.timeout, stop_on_ctrl_c=False, shown=len(view.get("events", [])),
                       interrupted=leaving)
        except KeyboardInterrupt:
            print(f"\nleft run {run} going (twin stop {run} ends it)", file=sys.stderr)
            return 130
    except Refused as e:
        print(f"twin status: {str(e).removeprefix('the service refused: ')}", file=sys.stderr)
        return 2 if e.bad_request else 1
    except Silent as e:
        print(f"twin status: {e}", file=sys.stderr)
        return 1
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)
        session.close()
    return report(summary)


def cmd_stop(args) -> int:
    """``twin stop [RUN...]``: end runs of a twin serve (each ends truncated; a queued one never starts), or the run
    of a twin run / twin conductor when no RUN is given."""
    runs = list(dict.fromkeys(run_id(r) for r in args.runs))  # (each asked once)
    session, keys = _client(args, "twin stop")
    if session is None:
        return 1
    code = 0
    try:
        # a twin run's conductor stops its one run whatever it is asked, and a service runs many: which is it?
        view = _ask(session, keys.conductor("status"), {}, "status", args.timeout).fields
        if runs and not view.get("service"):
            print(f"twin stop: the conductor of ensemble {keys.ensemble!r} is a twin run (one run), not a twin serve: "
                  "give no run id to stop it", file=sys.stderr)
            return 2
        if not runs and view.get("service"):
            going = "; ".join(f"{st}: {', '.join(view.get(st) or [])}" for st in ("running", "queued")
                              if view.get(st)) or "none is running or queued"
            print(f"twin stop: ensemble {keys.ensemble!r} is a twin serve: name the runs to stop ({going})",
                  file=sys.stderr)
            return 2
        targets: list[str | None] = [*runs] if runs else [None]
        for run in targets:
            try:
                ack = _ask(session, keys.conductor("stop"), {} if run is None else {"run": run}, "ack", args.timeout)
                said = ack.get("message") or "stopping"
                print(f"run {run}: {said}" if run is not None else f"the run of ensemble {keys.ensemble!r}: {said}",
                      flush=True)
            except Refused as e:
                print(f"twin stop: {str(e).removeprefix('the service refused: ').removeprefix('stop: ')}",
                      file=sys.stderr)
                code = max(code, 2 if e.bad_request else 1)  # (no such run: 2, as twin status --run says; over: 1)
    except Silent as e:
        print(f"twin stop: {e}", file=sys.stderr)
        return 1
    finally:
        session.close()
    return code


def _client(args, who: str) -> tuple[Any, Keys]:
    """A session for a command-line client (None, said on stderr, when no router answered) and its keys."""
    opts = options_from_args(args)
    opts.connect_timeout_ms = int(args.timeout * 1000)
    try:
        return opts.open(), Keys(opts.ensemble)
    except zenoh.ZError:
        print(f"{who}: {opts.unanswered(args.timeout)}", file=sys.stderr)
        return None, Keys(opts.ensemble)


def register(sub) -> None:
    """Add serve, status, submit, stop and trigger to the ``twin`` subcommands."""
    sv = sub.add_parser(
        "serve", help="run the conductor as a service: runs are started over Zenoh, agents stay warm",
        description="A long-lived conductor. Clients (twin submit) start runs on twin/<ensemble>/conductor/start "
                    "with the scene's text and a source; runs queue; the agents of each set of models are started "
                    "once and initialised again for every run (an agent that died is started again). Embeds a "
                    "Zenoh router unless --connect is given.", formatter_class=DefaultsHelp)
    add_zenoh_args(sv, default_mode="router", listens=DEFAULT_ENDPOINT)
    sv.add_argument("--run-dir", default="runs/serve",
                    help="where each run's log and summary go (<dir>/<run id>/; default runs/serve); run ids go on "
                         "after those already there; one service per run directory")
    sv.add_argument("--parallel", type=count, default=1, help="runs at once, each on its own warm agents (default 1)")
    sv.add_argument("--max-pools", type=count, default=4,
                    help="sets of warm agents kept (the least recently used is stopped beyond; default 4)")
    sv.add_argument("--open-bus", action="store_true",
                    help="let any process join the embedded router (default: agents and holders of "
                         "<run dir>/access.json)")
    sv.add_argument("--register-timeout", type=positive, default=60.0, help="seconds to wait for a run's agents")
    sv.set_defaults(func=cmd_serve)

    st = sub.add_parser("status", help="ask a running conductor for its status",
                        description="Print, as JSON, the status of the conductor of an ensemble: of a run, its "
                                    "tick, agents and ownership; of a twin serve, its queued and running runs, the "
                                    "status of each finished one, and its pools of warm agents (their pids, and "
                                    "those that exited, started again at their next run); with --run, one run of a "
                                    "twin serve (exit 2 for a run it does not know).",
                                    formatter_class=DefaultsHelp)
    st.add_argument("--timeout", type=positive, default=3.0,
                    help="seconds to wait for the answer (with --wait: how long the service may stay silent)")
    st.add_argument("--run", metavar="ID", default=None,
                    help="of a twin serve: one run (its state and events; its live status, then its summary), also "
                         "one the service ran long ago (read back from its folder)")
    st.add_argument("--wait", action="store_true",
                    help="with --run: print its events as they come and its summary as twin submit does, and exit "
                         "with the run's code: 0 complete, 1 failed, 2 bad input (or a run it does not know), 3 "
                         "degraded, 4 truncated, 5 interrupted (Ctrl-C leaves the run going: 130)")
    add_zenoh_args(st)
    st.set_defaults(func=cmd_status)

    sb = sub.add_parser(
        "submit", help="start a run on a twin serve and print its summary like twin run",
        description="Send a scene (its text) and a source to a running twin serve, follow the run's handovers, "
                    "print the summary; the exit code is the run's (0 complete, 3 degraded, 4 truncated, ...).",
                    formatter_class=DefaultsHelp)
    sb.add_argument("scene", help="scene YAML file (its text is sent)")
    sb.add_argument("--recording", help="a recording on the service's machine (made absolute if it exists here)")
    add_recording_options(sb)
    sb.add_argument("--live-ensemble", metavar="ENSEMBLE", default=None,
                    help="attach live to the telemetry a robot publishes on twin/<ENSEMBLE>/telemetry/**")
    sb.add_argument("--ros2-domain", type=ros2_domain, default=None, metavar="N", help="attach live to a ROS 2 robot")
    sb.add_argument("--ros2-namespace", type=ros2_namespace, default="",
                    help="ROS 2 namespace of its topics (with --ros2-domain)")
    sb.add_argument("--perception", metavar="FILE", help="perceived geometry (a recording or a JSON/YAML file), "
                                                         "read here and sent")
    sb.add_argument("--idle-timeout", type=positive, default=3.0,
                    help="live: end the run after this many seconds without telemetry (default 3)")
    sb.add_argument("--rtf", type=positive, default=None,
                    help="pace a replay at this real-time factor (default: as fast as possible)")
    sb.add_argument("--max-ticks", type=count, default=None, help="stop after this many ticks")
    sb.add_argument("--deadline", type=positive, default=None, metavar="SECONDS",
                    help="wall seconds the run may take before it is stopped as truncated (default for a replay: "
                         "600 + 20 x the recording's length)")
    sb.add_argument("--samples", type=count, default=None, metavar="K",
                    help="K variations of the replay (as twin run --samples), run side by side on the service's "
                         "pools (serve --parallel); prints the distribution")
    sb.add_argument("--seed", type=seed_arg, default=0,
                    help="with --samples: sample i is drawn with seed + i (so seeds 5 and 6 share all "
                         "draws but one: for independent repeats, space the seeds by K or more)")
    sb.add_argument("--summary", metavar="FILE.json", help="write the run summary as JSON")
    sb.add_argument("--timeout", type=positive, default=10.0,
                    help="seconds the service may stay silent before the client gives up (default 10; a start "
                         "the service could not answer within them is not queued)")
    add_zenoh_args(sb)
    sb.set_defaults(func=cmd_submit)

    tr = sub.add_parser(
        "trigger", help="fire a scene's service trigger (on: {service: NAME}) in a running run",
        description="Call twin/<ensemble>/conductor/trigger/NAME: the run's conductor fires the scene's triggers on "
                    "{service: NAME} between two ticks, with the --arg values bound to the trigger's args, and "
                    "answers with what they did (exit 0), or with why not (precondition false, missing argument: "
                    "exit 1). Against a twin serve, --run names the run (default: the one running).",
                    formatter_class=DefaultsHelp)
    tr.add_argument("name", help="the service trigger's name")
    tr.add_argument("--arg", action="append", metavar="NAME=VALUE", help="an argument of the call (repeatable)")
    tr.add_argument("--run", default=None, help="with twin serve: the run id (default: the only running run)")
    tr.add_argument("--timeout", type=positive, default=10.0, help="seconds to wait for the answer (default 10)")
    add_zenoh_args(tr)
    tr.set_defaults(func=cmd_trigger)

    sp = sub.add_parser(
        "stop", help="stop runs of a twin serve (or the run of a twin run)",
        description="Ask twin/<ensemble>/conductor/stop to end runs: on a twin serve, each RUN (a running one ends "
                    "as truncated with its summary; a queued one never starts); with no RUN, the run of a twin run "
                    "or twin conductor. Exit 1 if any was not stopped because it had already finished, 2 for an id "
                    "that is no run of the service or a command line that does not fit the conductor (run ids for a "
                    "twin run, none for a twin serve).",
        epilog="twin status --run ID shows one run, twin status --run ID --wait waits for its summary.",
        formatter_class=DefaultsHelp)
    sp.add_argument("runs", nargs="*", metavar="RUN", help="run ids, as twin submit printed them")
    sp.add_argument("--timeout", type=positive, default=10.0, help="seconds to wait for each answer")
    add_zenoh_args(sp)
    sp.set_defaults(func=cmd_stop)

