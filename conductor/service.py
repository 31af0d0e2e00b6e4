"""The conductor as a service (``twin serve``): one long-lived process that takes runs over Zenoh, queues them, and
keeps the agents it started warm between them.

A client (``twin submit``) asks ``twin/<E>/conductor/start`` with the scene's text, the source (a recording on the
server, a live ensemble, a ROS 2 domain) and optionally the perceived geometry; the answer is a run id. Each run is
done by an ordinary :class:`~conductor.core.Conductor` on a *pool* ensemble ``<E>-w<N>``: the agents of one set of
models (name, kind, step mode), started once and initialised again for every run (their runtime closes the model
and builds it afresh). An agent that died is started again before the next run on its pool. ``conductor/status``
answers for the service (queue, runs, pools), or with ``{run: ID}`` for one run (its live status, then its summary);
``conductor/stop`` with ``{run: ID}`` ends a queued or running run (``truncated``).

::

    with Service(session, endpoint, "default", Path("runs/serve")) as svc:
        summary = svc.run(Job(scene_text=..., scene_file="scenes/ball_drop.yaml", recording="rec.mcap"))
"""
from __future__ import annotations

import contextlib
import functools
import importlib.machinery
import importlib.util
import itertools
import json
import logging
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from protocol import codec
from protocol.config import MAX_MESSAGE_SIZE
from protocol.errors import ProtocolError, SceneError, TwinError
from protocol.keys import LISTENER, Keys
from protocol.ros2 import NAMESPACE_RULE, namespace_problem

from .core import Conductor, RunOptions
from .launch import AgentProcs, agent_command, is_stopped, write_summary
from .link import call_deadline
from .provenance import run_metadata, scene_of_log
from .record import unrun
from .runlog import read_run_log
from .sampling import check_seed, distribution, sample_dir, unvaried, variations, worst_status
from .scene import Scene, check_launchable, parse_scene
from .scene.perception import check_perception, perceive, perception_from_metadata
from .sources.fit import check_fit
from .sources.live import LiveSource
from .sources.recording import Recording, load_recording
from .sources.replay import ReplaySource
from .sources.ros2 import MAX_ROS2_DOMAIN, Ros2Source

log = logging.getLogger("twin.service")

ASKING_S = 3.0
"""A client that follows a run asks for its status every 0.2 s: one silent this long has gone (a closing service
does not wait for it)."""

JOB_KEYS = ("scene", "scene_file", "recording", "perception", "live", "ros2_domain", "ros2_namespace",
            "remap", "joint_order", "max_ticks", "rtf", "deadline", "idle_timeout", "samples", "seed")


KEPT_RECORDINGS = 64
KEPT_MESSAGES = 500_000
"""A service keeps the recordings its runs read, for the next runs of them: at most this many, and this many
messages in all (about 1 GiB, at 2.2 kB a message read; the 79 shipped recordings hold 182 000). A long-lived
service working through large bags kept 64 of them whatever their size."""
MAX_SAMPLES = 10_000
"""The most samples one ``conductor/start`` may ask for (each is a whole run)."""


MAX_SCENE_CHARS = 2**20
"""The longest scene text a start may carry (the shipped scenes are under 20 kB; parsing one of megabytes takes
seconds, with the interpreter held)."""


def _whole(least: int, most: int | None = None) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        ok = v.__class__ is int and v >= least and (most is None or v <= most)
        return None if ok else f"a whole number from {least}" + (f" to {most}" if most is not None else "")
    return check


def _above_0(v: Any) -> str | None:
    ok = v.__class__ in (int, float) and math.isfinite(v) and v > 0
    return None if ok else "a finite number above 0"


def _words(v: Any) -> str | None:
    return None if isinstance(v, list) and all(isinstance(w, str) and w for w in v) else "a list of strings"


def _text(v: Any) -> str | None:
    return None if isinstance(v, str) else "a string"


_JOB_TYPES: dict[str, Callable[[Any], str | None]] = {
    "recording": _text, "live": _text, "ros2_domain": _whole(0, MAX_ROS2_DOMAIN),
    "ros2_namespace": lambda v: None if isinstance(v, str) and namespace_problem(v) is None else
    f"a ROS 2 namespace ({NAMESPACE_RULE})",
    "remap": _words, "joint_order": _words, "max_ticks": _whole(1), "rtf": _above_0, "deadline": _above_0,
    "idle_timeout": _above_0, "samples": _whole(1, MAX_SAMPLES),
    "perception": lambda v: None if isinstance(v, dict) else "a map"}
"""What each ``conductor/start`` argument must be (as the command line's types say; the seed is checked apart)."""


def _trim_recordings(kept: dict[str, tuple[float, Recording]]) -> None:
    """Let the least recently used recordings go beyond :data:`KEPT_RECORDINGS` and :data:`KEPT_MESSAGES` (the
    first are the least recently used; the last one is kept)."""
    while len(kept) > 1 and (len(kept) > KEPT_RECORDINGS
                             or sum(len(r.items) for _, r in kept.values()) > KEPT_MESSAGES):
        kept.pop(next(iter(kept)))


@dataclass
class Job:
    """One run asked of the service: the scene (its text, and the file name it is reported and resolved under),
    the source (``recording``: a path on the server; ``live``: an ensemble whose telemetry to attach to;
    ``ros2_domain``), and the perception (a ``{entities: ...}`` map; default: the recording's own)."""

    scene_text: str
    scene_file: str = "<scene>"
    recording: str | None = None
    perception: dict[str, Any] | None = None
    live: str | None = None
    ros2_domain: int | None = None
    ros2_namespace: str = ""
    remap: list[str] | None = None
    joint_order: list[str] | None = None
    max_ticks: int | None = None
    rtf: float | None = None
    deadline: float | None = None
    idle_timeout: float = 3.0
    samples: int | None = None  # K variations of a replay (conductor.sampling), run side by side on the pools
    seed: int = 0

    @classmethod
    def from_args(cls, args: dict[str, Any]) -> Job:
        """A job from a ``conductor/start`` request's arguments; ValueError naming the key that is wrong."""
        unknown = sorted(set(args) - set(JOB_KEYS))
        if unknown:
            raise ValueError(f"unknown start arguments: {', '.join(unknown)} (known: {', '.join(JOB_KEYS)})")
        if not isinstance(args.get("scene"), str) or not args["scene"].strip():
            raise ValueError("start: 'scene' must be the scene's YAML text")
        if len(args["scene"]) > MAX_SCENE_CHARS:  # (its parse held every other start, for 30 s at 2.4 MiB)
            raise ValueError(f"start: the scene is {len(args['scene']) / 2**20:.1f} MiB of text; a scene may be at "
                             f"most {MAX_SCENE_CHARS / 2**20:g} MiB (they are a few kB)")
        kinds = [k for k in ("recording", "live", "ros2_domain") if args.get(k) is not None]
        if len(kinds) > 1:
            raise ValueError(f"start: give one source, not {' and '.join(kinds)}")
        if not kinds and not args.get("max_ticks"):
            raise ValueError("start: nothing to run on: give 'recording', 'live' or 'ros2_domain' (or 'max_ticks')")
        if args.get("rtf") is not None and kinds and kinds[0] != "recording":
            raise ValueError("start: 'rtf' paces a replay: a live run goes at the robot's pace")
        said = [k for k in ("remap", "joint_order") if args.get(k)]
        if said and kinds != ["recording"]:
            raise ValueError(f"start: {' and '.join(repr(k) for k in said)} say how to read a bag: give 'recording'")
        job = cls(scene_text=args["scene"], scene_file=str(args.get("scene_file") or "<scene>"))
        for k in JOB_KEYS[2:]:
            if args.get(k) is not None:
                problem = _JOB_TYPES.get(k, lambda v: None)(args[k])
                if problem:  # (a samples of -2 ran none and said nothing; a max_ticks of 'x' failed at tick 0)
                    raise ValueError(f"start: '{k}' must be {problem}, not {args[k]!r:.60}")
                setattr(job, k, args[k])
        if job.perception is not None:
            check_perception(job.perception, "start: perception")
        try:
            check_seed(job.seed)
        except ValueError as e:
            raise ValueError(f"start: {e}") from None
        return job

    def as_args(self) -> dict[str, Any]:
        """The ``conductor/start`` arguments of this job (what :meth:`from_args` reads)."""
        out: dict[str, Any] = {"scene": self.scene_text, "scene_file": self.scene_file}
        for k in JOB_KEYS[2:]:
            v = getattr(self, k)
            if v is not None and not (k == "ros2_namespace" and v == "") and not (k == "idle_timeout" and v == 3.0) \
                    and not (k == "seed" and v == 0):
                out[k] = v
        return out


@dataclass
class RunEntry:
    """A run the service knows: queued, running or finished (then with its summary)."""

    id: str
    job: Job
    state: str = "queued"  # queued, running, finished
    scene: str = "?"
    events: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] | None = None
    conductor: Conductor | None = None
    stop_reason: str | None = None
    done: threading.Event = field(default_factory=threading.Event)
    samples: list[RunEntry] = field(default_factory=list)  # a sampled run's own runs, one per variation
    followed: bool = False  # a client asked for its status (it waits for the summary)
    asked: float = 0.0  # when it last asked (time.monotonic())
    fetched: bool = False  # a client has been given its summary
    begun: bool = False  # a worker has begun it, or a stop before that has (taken under the service's lock)
    outcome: str | None = None  # its status, once finished (kept when the summary itself is let go)

    def view(self, since: int = 0) -> dict[str, Any]:
        """What a client sees of the run; its events from the ``since``-th on (a client that follows a run asks
        for those it has not had: a sampled run of thousands has an event per sample)."""
        out: dict[str, Any] = {"run": self.id, "state": self.state, "scene": self.scene,
                               "events": self.events[since:], "events_from": since}
        c = self.conductor
        if self.state == "running" and c is not None:
            out["live"] = c.status()
        if self.summary is not None:
            out["summary"] = self.summary
        return out


class Pool:
    """The warm agents of one set of models on their own ensemble, started once and reused run after run."""

    def __init__(self, ensemble: str, models: dict[str, str], endpoint: str, logdir: Path,
                 env: dict[str, str] | None = None) -> None:
        self.ensemble, self.models, self.endpoint, self.env = ensemble, models, endpoint, env
        self.procs = AgentProcs(logdir)
        self.busy = False
        self.runs = 0
        self.restarts = 0
        self.last_used = time.monotonic()
        self._files: dict[str, tuple[Path | None, float | None]] = {}  # agent -> its model file, and its mtime then
        self._replaced: list[str] = []  # agents started again after the last run (said by the next)
        for name in models:
            self._spawn(name)

    def _spawn(self, name: str) -> None:
        path = kind_file(self.models[name], self.env)
        self._files[name] = (path, _mtime(path))
        self.procs.spawn(name, agent_command(self.models[name], name, self.endpoint, self.ensemble), env=self.env)

    def revive(self) -> list[str]:
        """Start again every agent whose process has exited or is stopped, and every one whose model file (a
        ``module:Class`` kind's module, an ``fmu:`` unit) changed since it started: a warm agent keeps the code it
        imported, and a researcher editing their model would get the old model's answers without a word. Their
        names."""
        dead = [n for n, p in self.procs.procs.items() if p.poll() is not None]
        for name in dead:
            log.warning("pool %s: agent %s exited (code %s): starting it again", self.ensemble, name,
                        self.procs.procs[name].returncode)
            self._spawn(name)
        changed = [n for n, (path, then) in self._files.items() if n not in dead and _mtime(path) != then]
        for name in changed:
            log.warning("pool %s: the model file of agent %s (%s) changed since it started: starting it again",
                        self.ensemble, name, self._files[name][0])
            self.procs.end(name)
            self._spawn(name)
        # a stopped one (SIGSTOP, Ctrl-Z) would answer nothing: the run waited out the register timeout for it
        # (one a debugger holds is someone's work: left alone)
        stopped = [n for n, p in self.procs.procs.items()
                   if n not in dead and n not in changed and p.poll() is None and is_stopped(p.pid, traced=False)]
        for name in stopped:
            log.warning("pool %s: agent %s (pid %d) is stopped: starting it again", self.ensemble, name,
                        self.procs.procs[name].pid)
            self.procs.end(name, timeout=2.0)
            self._spawn(name)
        self.restarts += len(dead) + len(changed) + len(stopped)
        replaced, self._replaced = self._replaced, []  # (started again after the run before: new to this one)
        return replaced + dead + changed + stopped

    def replace(self, names: set[str], session: Any = None) -> list[str]:
        """End and start again each agent in ``names`` whose process still runs: a run found it not answering
        (stopped, stuck in its model, or past the step timeout), and a warm agent in that state would fail every
        run after it on this pool. With ``session``, each is first asked for its health once more, for
        :data:`PROBE_S`, and one that answers is kept (it was slow, not stuck: a loaded machine, a stall that
        passed). Their names."""
        out = []
        running = {n for n in names if (p := self.procs.procs.get(n)) is not None and p.poll() is None}
        for name in sorted(running - (self.answering(session, running) if session is not None else set())):
            p = self.procs.procs[name]
            log.warning("pool %s: agent %s (pid %d) did not answer in the last run: starting it again",
                        self.ensemble, name, p.pid)
            self.procs.end(name, timeout=2.0)
            self._spawn(name)
            out.append(name)
        self.restarts += len(out)
        self._replaced += out
        return out

    def answering(self, session: Any, names: set[str]) -> set[str]:
        """Those of ``names`` whose own process (by its pid) answers a health query within :data:`PROBE_S`, all
        asked at once; one that nothing serves yet (its link lapsed while it was stopped, and it is connecting
        again) is asked again every 0.2 s until then: asked once, it was found gone and started again."""
        keys, out, pending = Keys(self.ensemble), set(), set(names)
        deadline = time.monotonic() + PROBE_S
        while pending and (left := deadline - time.monotonic()) > 0:
            asked = {}
            for name in pending:
                with contextlib.suppress(Exception):  # (a session closing under it: none answers)
                    asked[name] = session.get(keys.model(name, "health"), payload=codec.encode("query"), timeout=left)
            unserved = set()
            for name, replies in asked.items():
                replied = False
                for reply in replies:  # (drained: ended by the first answer or Zenoh's timeout)
                    replied = True
                    with contextlib.suppress(ProtocolError, AttributeError):
                        value = codec.decode(keys.model(name, "health"), reply.ok.payload, "value_reply").value
                        if isinstance(value, dict) and value.get("pid") == self.procs.procs[name].pid:
                            out.add(name)
                if not replied:  # (ended at once without a word: nothing serves its key now)
                    unserved.add(name)
            pending = unserved
            if pending:
                time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
        if out:
            log.warning("pool %s: %s did not answer in the last run but answer now: kept", self.ensemble,
                        ", ".join(sorted(out)))
        return out

    def view(self) -> dict[str, Any]:
        return {"models": self.models, "busy": self.busy, "runs": self.runs, "restarts": self.restarts,
                "pids": {n: p.pid for n, p in self.procs.procs.items()},
                "exited": {n: p.returncode for n, p in self.procs.procs.items() if p.poll() is not None},
                "stopped": sorted(n for n, p in self.procs.procs.items() if p.poll() is None and is_stopped(p.pid))}

    def close(self) -> None:
        self.procs.stop()


PROBE_S = 5.0
"""How long an agent that a run found not answering is given to answer a health query after it, before the pool
starts it again (:meth:`Pool.replace`): more than a step's usual answer by far, so a stuck agent is not kept, and
a healthy one that missed the run's 2 s closing ``stop`` on a loaded machine is not started again for nothing."""

KEEP_FINISHED = 200
"""Finished runs the service holds in memory (summary, events); an older one is let go of, and its summary read
back from its folder when a client asks for it (a service that ran for days held every run it had done, each
sample's too, and grew without bound: 1 GB after 35 runs, one of them 100,000 samples)."""

REPLY_LIMIT = MAX_MESSAGE_SIZE // 2
"""Bytes of the largest status reply the service sends (a session carries messages up to
:data:`~protocol.config.MAX_MESSAGE_SIZE`; a larger reply was dropped without a word, and the client said that
nothing answered)."""


def kind_file(kind: str, env: dict[str, str] | None = None) -> Path | None:
    """The file a model kind is loaded from, found as an agent would find it (its working directory, then
    ``PYTHONPATH``, then this interpreter's path), without importing anything: a ``package.module:Class`` kind's
    module or an ``fmu:PATH`` unit; None for a built-in kind (the project's own code) or one not found."""
    if kind.startswith("fmu:"):
        return Path(kind[4:])
    if ":" not in kind:
        return None
    parts = kind.split(":", 1)[0].split(".")
    for entry in _agent_path(env):
        base = Path(entry or ".", *parts)
        for candidate in (base.with_suffix(".py"), base / "__init__.py"):
            if candidate.is_file():
                return candidate
    return None


def _agent_path(env: dict[str, str] | None) -> list[str]:
    """Where an agent started with ``env`` looks for a model's module: its working directory, its
    ``PYTHONPATH``, then this interpreter's path."""
    extra = ((env or {}).get("PYTHONPATH") or os.environ.get("PYTHONPATH") or "").split(os.pathsep)
    return [os.getcwd(), *extra, *sys.path]


def unfound_kinds(scene: Scene, env: dict[str, str] | None = None) -> list[Any]:
    """The models of ``scene`` whose code this machine's agents would not find: a ``module:Class`` kind whose
    module (its top package) is on neither the agents' path nor this interpreter's (an ``fmu:PATH`` that is no file
    here is found when the scene is read). ``twin submit`` checks the scene on the client, which may have them
    where the service has not; the agent would exit at once and the run fail (exit 1) where it is the scene's
    problem (exit 2)."""
    out = []
    for name, spec in scene.models.items():
        if spec.kind.startswith("fmu:") or ":" not in spec.kind:
            continue
        if not _top_findable(spec.kind.split(":", 1)[0].split(".")[0], env):
            out.append(scene.problem(("models", name, "kind"), f"module {spec.kind.split(':', 1)[0]!r} is not on "
                                     f"the service's machine (its agents look in {os.getcwd()} and on PYTHONPATH)"))
    return out


def _top_findable(top: str, env: dict[str, str] | None) -> bool:
    """Whether an agent could find the top package or module ``top``: a folder or a file of it (source,
    compiled, an extension) in its working directory or on its ``PYTHONPATH``, or by this interpreter's own
    finders (an editable install's, a namespace package). Nothing is imported."""
    suffixes = tuple(importlib.machinery.all_suffixes())
    for entry in _agent_path(env):
        base = Path(entry or ".")
        if (base / top).is_dir() or any((base / (top + suffix)).is_file() for suffix in suffixes):
            return True
    try:
        return importlib.util.find_spec(top) is not None  # (a top package imports nothing to be found)
    except (ImportError, ValueError):
        return False


def _close(source: Any) -> None:
    """Let a run's source go (a live or ROS 2 source stops hearing the robot); a replay has nothing to let go."""
    close = getattr(source, "close", None)
    if close is not None:
        close()


def _mtime(path: Path | None) -> float | None:
    try:
        return path.stat().st_mtime if path is not None else None
    except OSError:
        return None


QUEUED = "queued"
"""The file in a run's folder while the run waits for its turn (the folder is made when the run is queued)."""


def queued_folder(run_root: Path, run: str) -> str:
    """Make run ``run``'s folder as it is queued (``run`` back), marked :data:`QUEUED`: its id is taken on disk (a
    service started again after this one died gave it to another run), and that one says it never started
    (:func:`close_cut_runs`)."""
    try:
        (run_root / run).mkdir(parents=True, exist_ok=True)
        (run_root / run / QUEUED).touch()
    except OSError as e:
        raise TwinError(f"cannot make the run's folder in {run_root}: {e}") from None
    return run


def first_free_id(run_root: Path) -> int:
    """The first run id after every run folder already in ``run_root`` (1 in an empty one): a service started
    again on the same run directory never writes over the runs of the one before."""
    ids = [int(p.name) for p in run_root.iterdir() if p.name.isdigit()] if run_root.is_dir() else []
    return max(ids, default=0) + 1


def read_cut_log(log_file: Path) -> dict[str, Any]:
    """What the run log of a run cut short holds of it: its scene's name, the ticks it reached (``ticks``, up to
    the last tick a message of the log names; ``sim_s``, that tick's time) and its ``handovers`` up to the cut, as
    a summary gives them; {} when the log holds nothing of the run (or cannot be read)."""
    try:
        text, file, _ = scene_of_log(log_file)
        data = yaml.safe_load(text)
        name = data.get("name") if isinstance(data, dict) else None
        last, t, handovers = -1, 0.0, []
        for _, _, m in read_run_log(log_file):
            if not isinstance(m, dict):
                continue
            for rep in [m, *(m.get("more") or [])] if m.get("type") == "tick" else [m]:
                tick = rep.get("tick") if isinstance(rep, dict) else None
                if isinstance(tick, int) and tick > last and isinstance(rep.get("t"), (int, float)):
                    last, t = tick, float(rep["t"])
            if m.get("type") == "event" and m.get("model") == "_conductor" and m.get("name") == "handover":
                handovers.append(m.get("data"))
    except (TwinError, OSError, ValueError, yaml.YAMLError) as e:
        log.warning("%s: cannot read what the run did before it was cut: %s", log_file, e)
        return {}
    if last < 0:
        return {}
    return {"scene": str(name) if isinstance(name, (str, int, float)) else Path(file).stem, "ticks": last + 1,
            "sim_s": round(t, 6), "handovers": handovers}


def close_cut_runs(run_root: Path) -> list[str]:
    """Give each run folder in ``run_root`` that has no summary (its service died before the run ended: a
    service writes every run's summary, whatever ends it) an ``interrupted`` one that says so, so that a service
    started again on the folder answers for the run instead of knowing nothing of it. The runs' ids."""
    cut = []
    for folder in sorted(run_root.iterdir() if run_root.is_dir() else [], key=lambda p: p.name):
        if not (folder.name.isdigit() and folder.is_dir()) or (folder / "summary.json").exists() \
                or not os.access(folder, os.W_OK):  # (one it cannot write to stays unknown, as before)
            continue
        log_file = folder / "run.mcap"
        reason = (f"run {folder.name} was cut short: the service that ran it stopped before it ended (found "
                  "without a summary by the service started after it); what it wrote before is in "
                  f"{folder}" + (" (its run log may be cut)" if log_file.exists() else ""))
        if (folder / QUEUED).exists():
            reason = (f"run {folder.name} never started: the service that queued it stopped before its turn (found "
                      "queued by the service started after it)")
            (folder / QUEUED).unlink(missing_ok=True)
        got = read_cut_log(log_file) if log_file.exists() else {}
        if got:
            reason += (f"; its run log reaches tick {got['ticks'] - 1} (t={got['sim_s']:g} s) with "
                       f"{len(got['handovers'])} handover{'s' * (len(got['handovers']) != 1)}: what the run "
                       "concluded after that is unknown")
        write_summary(folder / "summary.json", {**unrun(reason, status="interrupted"), **got, "cut_short": True,
                                                "run_log": str(log_file) if log_file.exists() else None})
        cut.append(folder.name)
    return cut


def pool_key(scene: Scene) -> tuple[tuple[str, str, str], ...]:
    """What makes two scenes' agents interchangeable: each model's name, kind and step mode."""
    return tuple(sorted((n, m.kind, m.step) for n, m in scene.models.items()))


class Service:
    """Runs jobs one after another (or ``parallel`` at once, on separate pools) on warm agents.

    ``session`` is open on the router at ``endpoint`` (where the agents connect); ``ensemble`` is the service's
    own (clients ask ``twin/<ensemble>/conductor/...``); run logs and summaries go to ``run_root/<run id>/``;
    ``max_pools`` idle pools are kept (the least recently used one is stopped beyond that); ``agent_env`` is
    given to every agent (e.g. the closed bus's credentials)."""

    def __init__(self, session: Any, endpoint: str, ensemble: str, run_root: Path, *, parallel: int = 1,
                 max_pools: int = 4, agent_env: dict[str, str] | None = None, register_timeout: float = 60.0,
                 network_mode: str | None = None) -> None:
        self.session, self.endpoint, self.keys = session, endpoint, Keys(ensemble)
        self.network_mode = network_mode  # its session's Zenoh mode: a client's runs wait out a router's restart
        self.run_root = Path(run_root)
        self.run_root.mkdir(parents=True, exist_ok=True)
        self.parallel, self.max_pools, self.agent_env = max(1, parallel), max(1, max_pools), agent_env
        self.register_timeout = register_timeout
        self.pools: dict[tuple[tuple[str, str, str], ...], list[Pool]] = {}
        self.runs: dict[str, RunEntry] = {}
        self._queue: queue.SimpleQueue[RunEntry | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.first_run = first_free_id(self.run_root)  # (runs before it, of an earlier service here: read back)
        if cut := close_cut_runs(self.run_root):
            log.warning("runs cut short by the service before this one (no summary; now interrupted): %s",
                        ", ".join(cut))
        self._ids = itertools.count(self.first_run)
        self._pool_ids = itertools.count(0)
        self._recordings: dict[str, tuple[float, Recording]] = {}
        self._finished = 0  # runs finished (those let go of too)
        self._decl: list[Any] = []
        self._workers: list[threading.Thread] = []
        self._closed = threading.Event()
        # runs going on at once, a sampled run's samples each counted (a sampled run itself holds none: its samples
        # wait for theirs): a sampled run beside another took `parallel` more ensembles on a machine sized for it
        self._slots = threading.BoundedSemaphore(self.parallel)

    # ------------------------------------------------------------------------------ life cycle
    def __enter__(self) -> Service:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def serve(self) -> Service:
        """Answer ``conductor/start``, ``status`` and ``stop`` on the service's ensemble; start the workers."""
        s, k = self.session, self.keys
        others = [r for r in s.liveliness().get(k.alive("_conductor"), timeout=2.0) if r.ok is not None]
        if others:
            raise TwinError(f"ensemble {k.ensemble!r} already has a conductor on this network (use --ensemble)")
        for op in ("start", "status", "stop"):  # (each bound to its operation: a query's key may be a wildcard)
            self._decl.append(s.declare_queryable(k.conductor(op), functools.partial(self._on_query, op)))
        self._decl.append(s.declare_queryable(k.conductor("trigger/*"), _TriggerRelay(self)))
        self._decl.append(s.liveliness().declare_token(k.alive("_conductor")))
        for i in range(self.parallel):
            t = threading.Thread(target=self._work, name=f"twin-serve-{i}", daemon=True)
            t.start()
            self._workers.append(t)
        return self

    def close(self, grace: float = 5.0) -> None:
        """Stop taking runs, end the running ones (truncated) and the queued ones (never started), stop every
        agent; then, for up to ``grace`` seconds, go on answering ``status`` until each client that follows a run
        has been given its summary (a client must not be left asking a service that is gone), but not for one that
        has stopped asking (:data:`ASKING_S`)."""
        self._closed.set()
        self.stop_all("the service closing")
        for _ in self._workers:
            self._queue.put(None)
        for t in self._workers:
            t.join(timeout=30)
        for pools in self.pools.values():
            for p in pools:
                p.close()
        self.pools = {}
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline:
            with self._lock:
                now = time.monotonic()
                waiting = [e for e in self.runs.values() if e.followed and not e.fetched and now - e.asked < ASKING_S]
            if not waiting:
                break
            time.sleep(0.05)
        with self._lock:
            gone = [e.id for e in self.runs.values() if e.followed and not e.fetched]
        if gone:
            log.warning("the client%s of run%s %s did not take the summary (gone, or still asking after %.0f s): "
                        "it is in the run's folder", "s" * (len(gone) > 1), "s" * (len(gone) > 1), ", ".join(gone),
                        grace)
        for d in self._decl:
            with contextlib.suppress(Exception):
                d.undeclare()
        self._decl = []

    def stop_all(self, reason: str) -> None:
        """End every run going on (``truncated``, saying ``reason``); those queued do not start."""
        with self._lock:
            entries = list(self.runs.values())
        for e in entries:
            if e.state != "finished":
                self._stop_run(e, reason)

    # ------------------------------------------------------------------------------ runs
    def submit(self, job: Job) -> RunEntry:
        """Queue ``job``; its entry (``entry.done`` is set when its summary is there)."""
        return self._submit(job)[0]

    def _submit(self, job: Job, scene: str = "?") -> tuple[RunEntry, list[str]]:
        """Queue ``job`` (of scene ``scene``): its entry, and the runs before it not finished (queued, running)."""
        if self._closed.is_set():
            raise TwinError("the service is closing")
        with self._lock:
            ahead = [e.id for e in self.runs.values() if e.state != "finished"]
            entry = RunEntry(id=queued_folder(self.run_root, str(next(self._ids))), job=job, scene=scene)
            self.runs[entry.id] = entry
        self._queue.put(entry)
        return entry, ahead

    def run(self, job: Job, run_dir: str | Path | None = None,
            stopped: Callable[[], str | None] | None = None) -> dict[str, Any]:
        """Run ``job`` now in this thread (no queue) and return its summary (``twin evaluate``'s warm path); its
        log goes to ``run_dir`` (default ``<run root>/<run id>``). ``stopped``: the reason its caller stops (set
        before it calls :meth:`stop_all`), or None; a run it names one for does not start."""
        with self._lock:
            reason = stopped() if stopped is not None else None
            if reason is None:
                entry = RunEntry(id=str(next(self._ids)), job=job, followed=True)  # (held until it is returned)
                self.runs[entry.id] = entry
        if reason is not None:  # (looked at under stop_all's lock: a run it did not see would have run to its end)
            summary = unrun(f"not run: stopped by {reason}", "truncated")
            if run_dir is not None:  # (its folder says so too: what an earlier run left there is not its own)
                from .parcels import land

                land(summary, Path(run_dir))
            return summary
        self._execute(entry, Path(run_dir) if run_dir is not None else None)
        assert entry.summary is not None
        entry.fetched = True
        return entry.summary

    def _work(self) -> None:
        while not self._closed.is_set():
            entry = self._queue.get()
            if entry is None:
                return
            if entry.state == "finished":  # stopped while queued
                continue
            try:
                with contextlib.nullcontext() if entry.job.samples else self._slots:  # (its samples take theirs)
                    self._execute(entry)
            except Exception as e:  # a bug here must not end the service, nor leave the client waiting
                log.exception("run %s", entry.id)
                self._finish(entry, unrun(f"the service failed: {type(e).__name__}: {e}", scene=entry.scene),
                             self.run_root / entry.id)

    def _sampled(self, entry: RunEntry, run_dir: Path) -> None:
        """A job with ``samples``: its K variations, each an ordinary run on a pool (``parallel`` at once), and the
        distribution of their answers as the entry's summary."""
        job = entry.job
        try:
            scene, source, _ = self._prepare(job)
            if not isinstance(source, ReplaySource):
                raise ValueError("samples vary a replay: give a recording")
            base = job.perception if job.perception is not None else (
                perception_from_metadata(source.rec.metadata["twin.scene"], source.rec.path)
                if "twin.scene" in source.rec.metadata else {"entities": {}})
        except (TwinError, ValueError, OSError) as e:
            self._finish(entry, {**unrun(str(e), scene=entry.scene), "bad_input": True}, run_dir)
            return
        entry.scene, entry.state, t0 = scene.name, "running", time.perf_counter()
        jobs = [replace(job, samples=None, perception=v) for v in variations(scene, base, int(job.samples or 0),
                                                                             job.seed)]

        def one(i: int, sample: Job) -> dict[str, Any]:
            child = RunEntry(id=f"{entry.id}.{i}", job=sample, scene=scene.name)
            with self._lock:
                entry.samples.append(child)
                stopped = entry.stop_reason
            if stopped is not None:  # stopped before this sample began: it is not run
                return unrun(f"not run: the sampled run was stopped by {stopped}", "truncated", scene.name)
            with self._slots:
                self._execute(child, sample_dir(run_dir, i))
            assert child.summary is not None
            with self._lock:  # (a client following the run prints each as it ends)
                entry.events.append({"kind": "sample", "sample": i, "status": child.summary.get("status"),
                                     "semantic_state": child.summary.get("semantic_state", {})})
            return child.summary

        with ThreadPoolExecutor(self.parallel) as pool:
            summaries = list(pool.map(lambda ij: one(*ij), enumerate(jobs)))
        with self._lock:
            entry.samples = []  # (each sample's summary is in its folder; the distribution holds what they say)
        d = distribution(summaries)
        d.update(scene=scene.name, recording=job.recording, seed=job.seed, status=worst_status(summaries),
                 variations=[j.perception for j in jobs], where=f"twin serve, {self.parallel} at a time",
                 note=unvaried([j.perception or {} for j in jobs]), wall_s=round(time.perf_counter() - t0, 2),
                 runs=[str(sample_dir(run_dir, i)) for i in range(len(jobs))])
        self._finish(entry, d, run_dir)

    def _execute(self, entry: RunEntry, run_dir: Path | None = None) -> None:
        with self._lock:
            stopped_first, entry.begun = entry.begun, True
        if stopped_first:  # stopped while it waited: its stop finishes it, and it never runs
            entry.done.wait()
            return
        (self.run_root / entry.id / QUEUED).unlink(missing_ok=True)
        run_dir = run_dir or self.run_root / entry.id
        if entry.job.samples:
            run_dir.mkdir(parents=True, exist_ok=True)
            self._sampled(entry, run_dir)
            return
        run_dir.mkdir(parents=True, exist_ok=True)
        try:
            scene, source, meta = self._prepare(entry.job)
        except (TwinError, ValueError, OSError) as e:  # a bad scene or source: a failed run that says why
            self._finish(entry, {**unrun(str(e), scene=entry.scene), "bad_input": True}, run_dir)
            return
        entry.scene = scene.name
        if entry.stop_reason is not None:  # stopped while it was being prepared: not started for nothing
            _close(source)
            self._finish(entry, unrun(f"stopped before it started, by {entry.stop_reason}", "truncated", scene.name),
                         run_dir)
            return
        pool = self._take_pool(scene, run_dir)
        try:
            summary, c = self._on_pool(entry, pool, scene, source, meta, run_dir)
            if self._start_lost(entry, c, source):
                first = c.record.failure
                log.warning("run %s failed before its first tick (%s): running it again once, on pool %s's agents "
                            "started again", entry.id, first, pool.ensemble)
                _close(source)
                try:  # (read once already: only a file changed meanwhile fails here, and the first summary stands)
                    scene, source, meta = self._prepare(entry.job)
                except (TwinError, ValueError, OSError) as e:
                    log.warning("run %s could not be prepared again: %s", entry.id, e)
                else:
                    summary, c = self._on_pool(entry, pool, scene, source, meta, run_dir)
                    summary["service"]["first_attempt"] = f"failed before its first tick, run again: {first}"
            pool.runs += 1  # (a run taken again counted once)
        finally:
            _close(source)  # (a live source's subscription: this session outlives the run)
            self._give_back(pool)
        self._finish(entry, summary, run_dir)

    def _on_pool(self, entry: RunEntry, pool: Pool, scene: Scene, source: Any, meta: dict[str, Any],
                 run_dir: Path) -> tuple[dict[str, Any], Conductor]:
        """One run of ``entry`` on ``pool`` (its dead agents started again first; those it found not answering
        replaced after): its summary, and the conductor that ran it."""
        if isinstance(source, LiveSource):  # (a ROS 2 attach too) the robot is heard elsewhere than the agents
            source.relay_to(self.session, Keys(pool.ensemble))
        restarted = pool.revive()
        opts = RunOptions(run_log=str(run_dir / "run.mcap"), rtf=entry.job.rtf, max_ticks=entry.job.max_ticks,
                          metadata=meta, register_timeout=self.register_timeout, network_mode=self.network_mode,
                          deadline=entry.job.deadline if entry.job.deadline is not None else
                          (600.0 + 20.0 * source.rec.duration if isinstance(source, ReplaySource) else None))
        c = Conductor(scene, self.session, Keys(pool.ensemble), source, opts,
                      on_event=lambda kind, data: entry.events.append({"kind": kind, **data}))
        c.agent_check = pool.procs.check_started
        entry.conductor = c
        entry.state = "running"
        if entry.stop_reason is not None:
            c.stop(entry.stop_reason)
        robot = self._answer_for_robot(entry.job.live, c)
        try:
            summary = c.run()
        finally:
            for declared in robot:
                with contextlib.suppress(Exception):  # (a session closing under it)
                    declared.undeclare()
            c.close()
        unanswering = c.registry.never_registered | c.link.silent | {
            str(ev.get("model")) for ev in entry.events if ev.get("kind") == "agent_lost"}
        summary["service"] = {"run": entry.id, "pool": pool.ensemble, "warm_runs": pool.runs,
                              "restarted": len(restarted), "restarted_agents": restarted,
                              "replaced_after": pool.replace(unanswering, self.session)}
        return summary, c

    @staticmethod
    def _start_lost(entry: RunEntry, c: Conductor, source: Any) -> bool:
        """Whether a replay failed before its first tick because a warm agent did not answer (lost, or past its
        timeout, while the run initialised it): nothing of the recording was read yet, and the pool has started
        the agent again (:meth:`Pool.replace`), so the run is worth one more try. (A live source's robot moves
        on meanwhile, and a stop is a stop.)"""
        return (c.record.failure is not None and c.clock.tick == 0 and bool(c.link.silent)
                and entry.stop_reason is None and isinstance(source, ReplaySource))

    def _answer_for_robot(self, live: str | None, c: Conductor) -> list[Any]:
        """A live run listens to the robot's ensemble, ``live``, and its conductor answers on its pool's: a robot
        waiting for its twin (``twin robot play --wait-twin``) asks ``live``'s conductor/status and found none, and
        watching ``live``'s conductor token it could not see the run end early. While the run lasts, the service
        answers there with the run's status and holds a :data:`~protocol.keys.LISTENER` token there (not the
        conductor's, which would refuse a twin of the robot's own): what it declared, to undeclare at the end."""
        if live is None or live == self.keys.ensemble:  # (the service's own status answers there: running runs)
            return []
        key = Keys(live).conductor("status")

        def on_status(query: Any) -> None:
            with query:
                try:
                    query.reply(key, codec.encode("status", {"fields": {**c.status(), "service": self.keys.ensemble}}))
                except Exception as e:  # never leave a query unanswered
                    query.reply_err(codec.encode_error(e))

        # (the token first: a robot that found the run by its status finds the token there too)
        return [self.session.liveliness().declare_token(Keys(live).alive(LISTENER)),
                self.session.declare_queryable(key, on_status)]

    def _finish(self, entry: RunEntry, summary: dict[str, Any], run_dir: Path | None = None) -> None:
        """The run is over: its summary, also in ``run_dir/summary.json`` when given (every run the service
        numbered leaves its folder with a summary, even one that never started)."""
        try:
            if run_dir is not None:
                run_dir.mkdir(parents=True, exist_ok=True)
                write_summary(run_dir / "summary.json", summary)
                (run_dir / QUEUED).unlink(missing_ok=True)  # (one stopped while it waited)
        except (OSError, TwinError) as e:  # (its client still gets it: a worker waiting for it must not wait on)
            log.error("run %s: its summary could not be written: %s", entry.id, e)
        finally:
            entry.summary = json.loads(json.dumps(summary, default=str))  # as it crosses the wire
            entry.outcome = str(summary.get("status"))
            entry.state = "finished"
            entry.conductor = None
            entry.done.set()
            if "." not in entry.id:  # (a sample is let go of with its sampled run)
                self._let_go()

    def _let_go(self) -> None:
        """Count the run that finished; let go of the oldest finished runs beyond :data:`KEEP_FINISHED` (not one
        whose client still asks for it and has yet to take its summary)."""
        with self._lock:
            self._finished += 1
            now = time.monotonic()
            finished = [e for e in self.runs.values() if e.state == "finished"]
            over = len(finished) - KEEP_FINISHED
            for e in finished:
                if over <= 0:
                    break
                if e.fetched or not e.followed or now - e.asked > ASKING_S:  # (a client that stopped asking has gone)
                    del self.runs[e.id]
                    over -= 1

    def _stop_run(self, entry: RunEntry, reason: str) -> None:
        with self._lock:
            entry.stop_reason = reason
            samples = list(entry.samples)
            unbegun, entry.begun = not entry.begun, True  # (a worker that takes it now finds it stopped)
        for child in samples:  # a sampled run: each of its running samples ends truncated, the rest do not start
            if child.state != "finished":
                self._stop_run(child, reason)
        c = entry.conductor
        if c is not None:
            c.stop(reason)
        elif unbegun:  # (one already begun sees its stop_reason: before its conductor starts, or by it)
            self._finish(entry, unrun(f"stopped before it started, by {reason}", "truncated", entry.scene),
                         self.run_root / entry.id if "." not in entry.id else None)  # (a sample: its parent's)

    # ------------------------------------------------------------------------------ a job's parts
    def recording(self, path: str, remap: list[str] | None = None, joint_order: list[str] | None = None) -> Recording:
        """The recording at ``path`` (loaded once per file version and reading options, then kept: the most recently
        used, at most :data:`KEPT_RECORDINGS` of them and :data:`KEPT_MESSAGES` messages in all)."""
        key = json.dumps([os.path.abspath(path), remap, joint_order])
        mtime = os.stat(path).st_mtime
        with self._lock:
            hit = self._recordings.pop(key, None)
            if hit is not None and hit[0] == mtime:
                self._recordings[key] = hit  # (the most recently used last)
                return hit[1]
        rec = load_recording(path, remap=remap, joint_order=joint_order)
        with self._lock:
            self._recordings[key] = (mtime, rec)
            _trim_recordings(self._recordings)
        return rec

    def keep(self, path: str, rec: Recording) -> None:
        """Keep ``rec``, read from ``path`` with the default options, for the runs of ``path`` (as
        :meth:`recording` keeps what it reads)."""
        with self._lock:
            self._recordings[json.dumps([os.path.abspath(path), None, None])] = (os.stat(path).st_mtime, rec)
            _trim_recordings(self._recordings)

    def _prepare(self, job: Job) -> tuple[Scene, Any, dict[str, Any]]:
        scene = check_launchable(parse_scene(job.scene_text, job.scene_file))  # no agent that would exit at once
        if problems := unfound_kinds(scene, self.agent_env):  # (checked on the client: it may have them, we not)
            raise SceneError.of(problems)
        meta: dict[str, Any] = {}
        source: Any = None
        if job.recording is not None:
            rec = self.recording(job.recording, job.remap, job.joint_order)
            source = ReplaySource(rec)
            meta = {"twin.recording": {"path": job.recording, "storage": rec.storage, "topics": json.dumps(rec.topics)}}
            if scene.declared_robot is not None:
                check_fit(scene.declared_robot, rec.joints_in_order, job.recording, rec)
        elif job.live is not None:
            source = LiveSource(self.session, Keys(job.live), idle_timeout=job.idle_timeout)
        elif job.ros2_domain is not None:
            source = Ros2Source(self.session, self.keys, domain=int(job.ros2_domain), namespace=job.ros2_namespace,
                                idle_timeout=job.idle_timeout)
        if job.perception is not None:
            scene.apply_perception(job.perception)
        else:
            perceive(scene, source)
        meta.update(run_metadata(scene, job.scene_text, source.rec if isinstance(source, ReplaySource) else None))
        return scene, source, meta

    def _take_pool(self, scene: Scene, run_dir: Path) -> Pool:
        """An idle pool for ``scene``'s models (started now if there is none; the least recently used idle pool
        stopped when more than ``max_pools`` would be kept)."""
        key = pool_key(scene)
        with self._lock:
            for p in self.pools.get(key, []):
                if not p.busy:
                    p.busy = True
                    return p
            idle = [(p.last_used, k, p) for k, ps in self.pools.items() for p in ps if not p.busy]
            total = sum(len(ps) for ps in self.pools.values())
            if total >= self.max_pools and idle:
                _, k, old = min(idle, key=lambda x: x[0])
                self.pools[k].remove(old)
                old.busy = True  # closed below, outside the lock
            else:
                old = None
            name = f"{self.keys.ensemble}-w{next(self._pool_ids)}"
            pool = Pool(name, {n: m.kind for n, m in scene.models.items()}, self.endpoint,
                        self.run_root / "agents" / name, self.agent_env)
            pool.busy = True
            self.pools.setdefault(key, []).append(pool)
        if old is not None:
            old.close()
        return pool

    def _give_back(self, pool: Pool) -> None:
        """``pool`` idle again; the least recently used idle pools stopped while more than ``max_pools`` are kept
        (more run side by side when ``parallel`` is larger: they were all kept idle after)."""
        with self._lock:
            pool.busy = False
            pool.last_used = time.monotonic()
            idle = sorted(((p.last_used, k, p) for k, ps in self.pools.items() for p in ps if not p.busy),
                          key=lambda x: x[0])
            extra = max(0, sum(len(ps) for ps in self.pools.values()) - self.max_pools)
            gone = [p for _, _, p in idle[:extra]]
            for _, k, p in idle[:extra]:
                self.pools[k].remove(p)
                p.busy = True  # (closed below, outside the lock)
        for p in gone:
            p.close()

    # ------------------------------------------------------------------------------ the queryables
    def status(self, run: str | None = None, since: int = 0) -> dict[str, Any]:
        """The service's status, or run ``run``'s (its events from the ``since``-th on)."""
        with self._lock:
            if run is not None:
                entry = self.runs.get(run)
                if entry is None:
                    return self._read_back(run)
                entry.followed, entry.asked = True, time.monotonic()
                entry.fetched = entry.state == "finished"
                return entry.view(since)
            return {"service": True, "ensemble": self.keys.ensemble, "parallel": self.parallel,
                    "queued": [e.id for e in self.runs.values() if e.state == "queued"],
                    "running": [e.id for e in self.runs.values() if e.state == "running"],
                    "finished": self._finished, "first_run": self.first_run,
                    "statuses": {e.id: e.outcome for e in self.runs.values() if e.state == "finished"},
                    "pools": {p.ensemble: p.view() for ps in self.pools.values() for p in ps}}

    def _read_back(self, run: str) -> dict[str, Any]:
        """The view of a finished run the service let go of (or that an earlier service on this run folder did),
        from its folder's summary."""
        where = self.run_root / run / "summary.json"
        if not run.isdigit() or not where.is_file():
            raise ValueError(f"no run {run!r} on this service")
        try:
            summary = json.loads(where.read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"run {run} is over, and its summary ({where}) cannot be read: {e}") from None
        handovers = [{"kind": "handover", **h} for h in summary.get("handovers") or [] if isinstance(h, dict)]
        return {"run": run, "state": "finished", "scene": summary.get("scene", "?"), "events": handovers,
                "summary": summary, "read_from": str(where)}

    def _status_reply(self, run: str | None, since: int = 0) -> bytes:
        """The status of ``run`` (or of the service) as a reply: a sampled run's summary too large for one Zenoh
        message (thousands of samples: the variations and run folders of each) goes without those two lists, and
        says where the whole is, rather than never arriving."""
        fields = self.status(run, since)
        payload = codec.encode("status", {"fields": fields})
        summary = fields.get("summary")
        if len(payload) <= REPLY_LIMIT or not isinstance(summary, dict):
            return payload
        where = self.run_root / str(run) / "summary.json"
        cut = {k: v for k, v in summary.items() if k not in ("variations", "runs")}
        cut["trimmed"] = (f"the variations and run folders of each sample are left out of this answer "
                          f"({len(payload) >> 20} MiB, more than one Zenoh reply carries): the whole summary is in "
                          f"{where} on the service's machine")
        payload = codec.encode("status", {"fields": {**fields, "summary": cut}})
        if len(payload) > REPLY_LIMIT:
            raise TwinError(f"run {run}: its summary is too large to send ({len(payload) >> 20} MiB even without "
                            f"its variations): it is in {where} on the service's machine")
        return payload

    def _no_run_to_stop(self, run: Any) -> TwinError | ValueError:
        """Why ``run`` cannot be stopped: a run that is over (TwinError: nothing was stopped, exit 1), or no such run
        (ValueError: a bad request, exit 2)."""
        with self._lock:
            going = {st: [e.id for e in self.runs.values() if e.state == st] for st in ("running", "queued")}
        now = "; ".join(f"{st}: {', '.join(ids)}" for st, ids in going.items() if ids) or "no run is running or queued"
        if run is None:
            return ValueError(f"stop: name the run to stop (twin stop ID; {now})")
        if str(run).isdigit() and (self.run_root / str(run) / "summary.json").is_file():
            return TwinError(f"stop: run {run} has already finished (its summary is in {self.run_root / str(run)})")
        return ValueError(f"stop: no run {run!r} on this service ({now})")

    def _on_query(self, op: str, query: Any) -> None:
        if op == "start":  # (prepared in a thread of its own: Zenoh runs a queryable's callbacks one at a time, and a
            # start waited behind another's preparation, past the time its client waited, then was queued all the same)
            threading.Thread(target=self._answer, args=(op, query, time.monotonic()), name="twin-serve-start",
                             daemon=True).start()
        else:
            self._answer(op, query, time.monotonic())

    def _answer(self, op: str, query: Any, t0: float) -> None:
        key, asked = self.keys.conductor(op), str(query.key_expr)
        wait = query.parameters.get("timeout")
        with query:
            try:
                if asked != key:  # (conductor/* reaches start, status and stop: it had stopped the run it read)
                    raise ValueError(f"{asked}: ask {key} by its own name (a wildcard reaches start, status and stop "
                                     "alike)")
                args: dict[str, Any] = {}
                if query.payload is not None and len(query.payload.to_bytes()) > 0:
                    msg = codec.decode(key, query.payload, ("control", "query"))
                    args = dict(msg.get("args") or {})
                if op == "start":
                    deadline = call_deadline(wait)  # (ValueError for a bad one)
                    job = Job.from_args(args)
                    scene = parse_scene(job.scene_text, job.scene_file)  # a bad scene is refused now, in the reply
                    if job.recording is not None and not os.path.exists(job.recording):
                        raise ValueError(f"{job.recording}: no such recording on the service's machine")
                    _in_time(wait, t0, deadline)
                    entry, ahead = self._submit(job, scene.name)
                    query.reply(key, codec.encode("value_reply", value={"run": entry.id, "ahead": ahead,
                                                                        "parallel": self.parallel}))
                elif op == "status":
                    run, since = args.get("run"), args.get("since", 0)
                    if type(since) is not int or since < 0:
                        raise ValueError(f"status: since {since!r}: the number of the run's events already had (0 "
                                         "or more)")
                    query.reply(key, self._status_reply(None if run is None else str(run), since))
                else:
                    entry_ = self.runs.get(str(args.get("run")))
                    if entry_ is None:
                        raise self._no_run_to_stop(args.get("run"))
                    if entry_.state == "finished":  # nothing was stopped: said, not acknowledged (exit 1)
                        raise TwinError(f"stop: run {entry_.id} has already finished ({entry_.outcome})")
                    said = (f"already stopping (by {entry_.stop_reason})" if entry_.stop_reason is not None else
                            "stopped while it was being prepared: it will not start"
                            if entry_.state == "queued" and entry_.begun else
                            "taken off the queue: it will not start" if entry_.state == "queued" else
                            "stopping: it ends truncated")
                    self._stop_run(entry_, "a conductor/stop request")
                    query.reply(key, codec.encode("ack", ok=True, message=said))
            except (ProtocolError, ValueError, TwinError) as e:
                query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e)))
            except Exception as e:  # never leave a client without an answer
                log.exception("%s", key)
                query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e)))


class _TriggerRelay:
    """The service's ``conductor/trigger/*`` queryable (:meth:`__call__`)."""

    def __init__(self, service: Service) -> None:
        self.service = service

    def __call__(self, query: Any) -> None:
        """``conductor/trigger/<name>`` on the service: passed on to the run's own conductor (the run the selector
        names, ``trigger/<name>?run=ID``, or the one running run), with its arguments as they are, its answer passed
        back; in a thread of its own (it waits)."""
        threading.Thread(target=self._relay, args=(query,), name="twin-serve-trigger", daemon=True).start()

    def _relay(self, query: Any) -> None:
        key = str(query.key_expr)
        with query:
            try:
                args: dict[str, Any] = {}
                if query.payload is not None and len(query.payload.to_bytes()) > 0:
                    args = dict(codec.decode(key, query.payload, ("control", "query")).get("args") or {})
                name = key.rsplit("/", 1)[-1]
                if "*" in name or "$" in name or key != self.service.keys.conductor(f"trigger/{name}"):  # (a wildcard:
                    # trigger/* was sent on as a trigger named '*', twin/*/conductor/trigger/X fired X everywhere)
                    raise ValueError(f"{key}: name one trigger of this service (conductor/trigger/NAME), not a pattern")
                run = query.parameters.get("run")  # (not among the arguments: a trigger may take one named run)
                wait = query.parameters.get("timeout")
                t0, deadline = time.monotonic(), call_deadline(wait)  # (ValueError for a bad one)
                svc = self.service
                target = _conductor_to_trigger(svc.runs, svc._lock, run).keys.conductor(f"trigger/{name}")
                timeout = 10.0
                if deadline is not None:  # the run's conductor drops the call unfired when its time (less) is up;
                    left = max(deadline - time.monotonic(), 0.001)  # this waits a little longer, less than the caller
                    target += f"?timeout={left:.3f}"
                    timeout = left + min(0.25, float(wait) / 8)
                for reply in svc.session.get(target, payload=codec.encode("control", args=args), timeout=timeout):
                    if reply.ok is not None:
                        query.reply(key, reply.ok.payload.to_bytes())
                    elif reply.err.payload.to_bytes() == codec.ZENOH_TIMEOUT:
                        raise ValueError(f"the run did not take the call within {time.monotonic() - t0:.1f} s (its "
                                         "tick loop is held up: a model that does not answer?): not fired")
                    else:
                        query.reply_err(reply.err.payload.to_bytes())
                    return
                raise ValueError(f"the run's conductor did not answer on {target} (has the run just ended?)")
            except (ProtocolError, ValueError) as e:
                query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e)))
            except Exception as e:  # never leave a caller without an answer
                log.exception("%s", key)
                query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e)))


def _in_time(wait: str | None, t0: float, deadline: float | None) -> None:
    """A start prepared (its scene parsed) past the time its client waits (``?timeout=``: ``deadline``) is not
    queued: the client has given up, and a run it believes refused would run all the same."""
    if deadline is not None and time.monotonic() > deadline:
        took = time.monotonic() - t0
        log.warning("a start took %.1f s to prepare, past the %s s its client waits: not queued", took, wait)
        raise TwinError(f"the start took {took:.1f} s to prepare, past the {wait} s its client waits: not queued")

def _conductor_to_trigger(runs: dict[str, RunEntry], lock: threading.Lock, run: str | None) -> Conductor:
    """The conductor of the running run among ``runs`` a service call goes to: run ``run``, or the one running;
    ValueError saying why none."""
    with lock:  # (a run may end meanwhile: its conductor read with its state)
        running = [e for e in runs.values() if e.state == "running" and e.conductor is not None]
        sampled = [e.id for e in runs.values() if e.state == "running" and e.job.samples]
        entry = runs.get(run) if run is not None else None
        chosen = running[0] if run is None and len(running) == 1 else entry
        c = chosen.conductor if chosen is not None else None
        state = entry.state if entry is not None else ""
    if run is None:
        if len(running) == 1 and c is not None:
            return c
        if not running and sampled:  # (it said "no run is running" while status listed the sampled run)
            raise ValueError(f"only sampled runs are running ({', '.join(sampled)}): their samples are not "
                             "triggered one by one")
        raise ValueError("no run is running" if not running else
                         f"{len(running)} runs are running ({', '.join(e.id for e in running)}): name one "
                         "(twin trigger --run ID, which asks for trigger/NAME?run=ID)")
    if entry is None:
        raise ValueError(f"no run {run!r} on this service")
    if entry.job.samples:
        raise ValueError(f"run {run} is a sampled run: its samples are not triggered one by one")
    if state != "running" or c is None:
        raise ValueError(f"run {run} is {state}" + (f" ({entry.outcome})" if state == "finished" else "") +
                         ": a service trigger fires while a run ticks")
    return c
