"""The embedded default: an in-process Zenoh router, the conductor, and every agent as a subprocess."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from protocol.config import ZenohOptions
from protocol.errors import InputError, Problem, RunAborted, TwinError
from protocol.keys import Keys

from .core import Conductor, RunOptions
from .scene import Scene, check_launchable
from .sources.live import LiveSource

log = logging.getLogger("twin.launch")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def agent_command(kind: str, name: str, endpoint: str, ensemble: str, extra: list[str] | None = None) -> list[str]:
    return [sys.executable, "-m", "agents", kind, "--name", name, "--connect", endpoint,
            "--ensemble", ensemble, *(extra or [])]


def _agent_env(extra: dict | None = None) -> dict[str, str]:
    """An agent process's environment: ours, ``extra``, and this checkout first on the import path."""
    e = dict(os.environ)
    e.update(extra or {})
    root = str(Path(__file__).resolve().parent.parent)
    e["PYTHONPATH"] = root + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    return e


def describe_agents(scene: Scene, timeout: float = 120.0, skip: Iterable[str] = ()
                    ) -> tuple[dict[str, dict[str, Any]], list[Problem]]:
    """What each model's agent would declare when it registers, asked of ``python -m agents KIND --describe``
    (one process per kind, all at once, no bus): ``({model: descriptor}, problems)``, a problem at the model's
    ``kind`` for an agent that cannot say (its kind does not import, its unit does not load...). The models in
    ``skip`` are not asked (a kind already known to be wrong)."""
    models = {name: spec for name, spec in scene.models.items() if name not in set(skip)}
    kinds = sorted({spec.kind for spec in models.values()})
    procs = {k: subprocess.Popen([sys.executable, "-m", "agents", k, "--describe"], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, env=_agent_env(), text=True) for k in kinds}
    said: dict[str, dict[str, Any] | str] = {}
    deadline = time.monotonic() + timeout
    for k, p in procs.items():
        try:
            out, err = p.communicate(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()
            said[k] = f"its agent did not describe itself within {timeout:.0f} s"
            continue
        said[k] = _descriptor(out) or "its agent cannot start: " + (
            ((err or out).strip().splitlines() or [f"exit code {p.returncode}"])[-1])
    descs: dict[str, dict[str, Any]] = {}
    problems: list[Problem] = []
    for name, spec in models.items():
        d = said[spec.kind]
        if isinstance(d, str):
            problems.append(scene.problem(("models", name, "kind"), d))
        else:
            descs[name] = {**d, "name": name}
    return descs, problems


def _descriptor(out: str) -> dict[str, Any] | None:
    """The descriptor ``--describe`` printed: its last line of output (a model's module may print before it)."""
    lines = out.strip().splitlines()
    try:
        d = json.loads(lines[-1]) if lines else None
    except ValueError:
        return None
    return d if isinstance(d, dict) and "kind" in d else None


def is_stopped(pid: int, traced: bool = True) -> bool:
    """Whether process ``pid`` is stopped (its state in /proc is T, or t: stopped by a debugger, unless not
    ``traced``)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2:][:1] in (("T", "t") if traced else ("T",))


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def _die_with_parent() -> None:
    """Agents started by `twin run` get SIGTERM if the launcher dies (even by SIGKILL): no orphans. (Linux sends
    it when the *thread* that started the child ends: :data:`_LAUNCHER` starts them all.)"""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


_LAUNCHER = ThreadPoolExecutor(1, thread_name_prefix="twin-launcher")
"""The thread every agent process is started from: it lasts as long as this process. Started from a thread
that ends sooner (a run's worker, a sampled run's), warm agents would get SIGTERM when it ended."""


class AgentProcs:
    """Agent subprocesses with their logs; killed on exit whatever happens."""

    def __init__(self, logdir: Path):
        self.logdir = logdir
        self.procs: dict[str, subprocess.Popen] = {}

    def spawn(self, name: str, cmd: list[str], env: dict | None = None) -> subprocess.Popen:
        self.logdir.mkdir(parents=True, exist_ok=True)
        with open(self.logdir / f"agent-{name}.log", "ab") as f:  # (the child writes to its own copy: a warm
            # service kept one open here for every agent it ever restarted)
            p = _LAUNCHER.submit(subprocess.Popen, cmd, stdout=f, stderr=subprocess.STDOUT, env=_agent_env(env),
                                 start_new_session=True, preexec_fn=_die_with_parent).result()
        self.procs[name] = p
        return p

    def check_started(self, missing: set, final: bool = False) -> None:
        """Raise RunAborted, with the end of its log, if an agent we wait for has already exited; ``final`` (the
        wait for registrations is over): for the first agent still missing, whatever it is doing."""
        for name in sorted(missing):
            p = self.procs.get(name)
            if p is not None and (final or p.poll() is not None):
                if p.poll() is None:  # started here, still running, never heard from
                    others = sorted(missing - {name})
                    why = ("its process is stopped (SIGSTOP, or a debugger: SIGCONT lets it go on)" if is_stopped(p.pid)
                           else "a slow start needs a longer --register-timeout")
                    raise RunAborted(f"agent {name} (pid {p.pid}, started by this twin) did not register in time "
                                     + (f"(nor did {', '.join(others)}) " if others else "")
                                     + f"({why}); {self._log_end(name)}")
                ended = (f"was killed by {_signal_name(-p.returncode)}" if p.returncode < 0
                         else f"exited with code {p.returncode}")
                raise RunAborted(f"agent {name} {ended}; {self._log_end(name)}")

    def _log_end(self, name: str) -> str:
        """The last lines of agent ``name``'s log, saying where it is."""
        log_path = self.logdir / f"agent-{name}.log"
        try:
            tail = log_path.read_text(errors="replace").strip().splitlines()[-6:]
        except OSError:
            tail = []
        return (f"its log ({log_path}) ends:\n    " + "\n    ".join(tail)) if tail else f"its log ({log_path}) is empty"

    def end(self, name: str, timeout: float = 5.0) -> None:
        """Stop agent ``name``'s process (SIGTERM, then SIGKILL after ``timeout`` s), to start it again; a stopped
        one (SIGSTOP) is let go on to take its SIGTERM."""
        p = self.procs.get(name)
        if p is None or p.poll() is not None:
            return
        p.send_signal(signal.SIGTERM)
        p.send_signal(signal.SIGCONT)
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()

    def stop(self, timeout: float = 5.0) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + timeout
        for p in self.procs.values():
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def write_summary(path: str | Path, summary: dict) -> Path:
    """Write a run summary atomically (a reader sees the whole summary or the one before, never half), its folder
    made if need be, and return where it went: if ``path`` cannot be written (a full disk), the summary goes to
    the temporary directory instead, and that is said on stderr, so the answer of a run is never lost."""
    path = Path(path)
    first = Path(os.path.realpath(path))  # through a symbolic link, not over it
    for target in (first, Path(tempfile.gettempdir()) / f"twin-summary-{os.getpid()}-{path.name}"):
        if target.exists() and not target.is_file():  # a pipe, a device (/dev/stdout...): written to, never replaced
            try:
                _write_in_place(target, json.dumps(summary, indent=2, default=str) + "\n")
            except OSError as e:
                log.error("cannot write the summary to %s: %s", target, e)
                continue
            return target
        tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
        try:
            target.parent.mkdir(parents=True, exist_ok=True)  # (--summary into a folder not yet made, as --json)
            with open(tmp, "w") as f:
                json.dump(summary, f, indent=2, default=str)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, target)
        except OSError as e:
            log.error("cannot write the summary to %s: %s", target, e)
            with contextlib.suppress(OSError):
                tmp.unlink()
            continue
        if target != first:
            print(f"twin: the summary could not be written to {path}; it is in {target}", file=sys.stderr)
        return target
    raise TwinError(f"the summary could not be written to {path} nor to the temporary directory")


def _write_in_place(target: Path, text: str) -> None:
    """Write ``text`` to a file that is not a regular one: a named pipe with no reader is an error, not a wait."""
    import fcntl

    fd = os.open(target, os.O_WRONLY | os.O_NONBLOCK)
    try:
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)  # a reader is there: wait
        with os.fdopen(fd, "w", closefd=False) as f:
            f.write(text)
    finally:
        os.close(fd)


class Stopper:
    """Ends the runs going on in this process and lets no more begin: the Ctrl-C of a command that runs many
    (``twin evaluate``, ``--samples``). A run is :meth:`watching` while its conductor runs; :meth:`stop` is
    thread-safe (it takes a lock: call it from a thread, not from a signal handler)."""

    def __init__(self) -> None:
        self.reason: str | None = None
        self._lock = threading.Lock()
        self._live: set[Conductor] = set()

    def stop(self, reason: str) -> None:
        with self._lock:
            self.reason = self.reason or reason
            live = list(self._live)
        for c in live:
            c.stop(reason)

    @contextlib.contextmanager
    def watching(self, conductor: Conductor) -> Iterator[None]:
        """While the block runs, :meth:`stop` ends ``conductor``'s run (at once when it was stopped before)."""
        with self._lock:
            self._live.add(conductor)
            reason = self.reason
        if reason is not None:
            conductor.stop(reason)
        try:
            yield
        finally:
            with self._lock:
                self._live.discard(conductor)


ECHO_S = 1.0
"""Seconds after a first stop signal in which another is the same stop delivered twice, and ignored: a signal sent
to a process group reaches the command and a wrapper that passes it on too (``timeout``, some shells' job control)."""


@contextlib.contextmanager
def ctrl_c_stops(stop: Callable[[str], None]) -> Iterator[None]:
    """While the block runs, the first Ctrl-C (or SIGTERM) calls ``stop("Ctrl-C")`` in a thread of its own (the
    runs going on end ``truncated``, no more begin, what completed is still reported); a second Ctrl-C
    interrupts at once, unless it comes within :data:`ECHO_S` of the first. Outside the main thread nothing
    changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    seen: list[float] = []

    def first(signum: int, frame: Any) -> None:
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        at = time.monotonic()
        seen.append(at)

        def second(signum: int, frame: Any) -> None:  # acts at once, unless it is the first one again
            if time.monotonic() - at < ECHO_S:
                return
            for sig in old:
                signal.signal(sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL)
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            os.kill(os.getpid(), signum)  # (its default action now: the process ends)

        for sig in old:
            signal.signal(sig, second)
        with contextlib.suppress(OSError):  # not print: the signal may have come in the middle of one
            os.write(2, f"{name}: ending the runs going on (truncated); no more start\n".encode())
        threading.Thread(target=stop, args=(name,), name="twin-stop", daemon=True).start()

    for sig in old:
        signal.signal(sig, first)
    try:
        yield
    finally:
        left = ECHO_S - (time.monotonic() - seen[0]) if seen else 0.0
        if left > 0:  # the stop's echo may still be on its way: taken (and ignored) here, not by the handler after
            time.sleep(left)
        for sig, handler in old.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def _signals_stop(conductor: Conductor) -> Iterator[None]:
    """While the run goes, SIGINT and SIGTERM end it at the next tick as ``interrupted`` (its summary is still
    written); outside the main thread signals cannot be caught, and nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in old:
        signal.signal(sig, lambda n, _: conductor.stop(signal=signal.Signals(n).name))
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def open_router(port: int | None = None, options: ZenohOptions | None = None):
    opts = options or ZenohOptions(mode="router")
    if not opts.listen:
        opts.listen = [f"tcp/127.0.0.1:{port or free_port()}"]
    opts.mode = "router"
    return opts.open(), opts.listen[0]


class ClosedBus:
    """User/password authentication with secrets made for one run: the embedded router admits only processes
    that hold them. The agents it starts get theirs in their environment; anyone else (a robot player, ``twin
    status``) reads ``access.json`` in the run folder (readable by its owner only)."""

    def __init__(self, run_dir: Path) -> None:
        self.agent = ("agent", secrets.token_urlsafe(24))
        self.guest = ("guest", secrets.token_urlsafe(24))
        self.dictionary = run_dir / ".zenoh-users"
        self.access = run_dir / "access.json"
        for path, text in ((self.dictionary, "".join(f"{u}:{p}\n" for u, p in (self.agent, self.guest))),
                           (self.access, json.dumps({"user": self.guest[0], "password": self.guest[1]}) + "\n")):
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(text)

    def serves(self, endpoint: str, ensemble: str) -> None:
        """Add where its router listens and the ensemble to the access file, once it is known: a client given only
        ``--credentials`` (``twin status``, ``twin stop``, ``twin robot play``) then finds a router that listens on
        a free port of its own, as ``twin run``'s does."""
        new = self.access.with_name(self.access.name + ".new")
        fd = os.open(new, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps({"user": self.guest[0], "password": self.guest[1], "connect": endpoint,
                                "ensemble": ensemble}) + "\n")
        os.replace(new, self.access)  # (a client reading it meanwhile reads the one before, whole)

    def agent_env(self) -> dict[str, str]:
        return {"TWIN_USER": self.agent[0], "TWIN_PASSWORD": self.agent[1]}

    def close(self) -> None:
        for path in (self.dictionary, self.access):
            with contextlib.suppress(OSError):
                path.unlink()


def _folder_name(name: str) -> str:
    """A scene's name as one folder name under ``runs/`` (a name such as ``../x`` must not lead out of it)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).lstrip(".") or "run"


_LOCKS: dict[Path, int] = {}
"""The run folders this process's runs are using: an open, locked ``.lock`` file in each."""


def _lock(run_dir: Path) -> None:
    """Take ``run_dir`` for one run (TwinError if another run, here or in another process, has it): two runs in
    one folder would write over each other's log, both reported complete."""
    import fcntl

    try:
        fd = os.open(run_dir / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise TwinError(f"--run-dir {run_dir}: cannot be written ({e.strerror or e})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise TwinError(f"--run-dir {run_dir}: another run is using it (pid {holder}): give each run its own "
                        "folder") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _LOCKS[run_dir.resolve()] = fd


def _unlock(run_dir: Path) -> None:
    fd = _LOCKS.pop(run_dir.resolve(), None)
    if fd is not None:
        os.close(fd)  # (the lock goes with it)


def output_dir(path: Path, option: str = "--run-dir") -> Path:
    """``path``, made if need be, where this process can write: :class:`TwinError` saying why otherwise (a file, a
    folder that cannot be made, a read-only one), rather than a traceback from whatever first writes there."""
    if path.exists() and not path.is_dir():
        raise TwinError(f"{option} {path}: a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError as e:
        made = path.is_dir()
        raise TwinError(f"{option} {path}: {'cannot be written' if made else 'cannot be made'} "
                        f"({e.strerror or e})") from None
    return path


REPLACED = ("run.mcap", "summary.json", "run.rrd")
"""What a run replaces in its run directory (and its ``agent-*.log``)."""


def _fresh_run_dir(run_dir: Path, reads: str | Path | None = None) -> Path:
    """``run_dir``, made if need be. An earlier run's log there is replaced (said in the log), and the Rerun recording
    made of it and its agents' logs are removed with it: left beside the new log they would be taken for this run's.
    A run never replaces the recording it ``reads`` (the earlier run's log given to ``--from-log``, the only copy
    of a live robot's telemetry): :class:`InputError` then, before anything is touched."""
    if reads is not None and run_dir.is_dir():
        src = Path(reads).resolve()
        if src.parent == run_dir.resolve() and (src.name in REPLACED or src.match("agent-*.log")):
            raise InputError(f"--run-dir {run_dir}: this run would replace {src.name} there, the recording it reads: "
                             "give the run another --run-dir")
    output_dir(run_dir)
    _lock(run_dir)
    if (run_dir / "run.mcap").exists():
        log.warning("%s holds an earlier run: its run.mcap, summary.json and agent logs are replaced", run_dir)
        for stale in [run_dir / "run.rrd", *run_dir.glob("agent-*.log")]:  # else taken for this run's
            stale.unlink(missing_ok=True)
    return run_dir


JOIN_S = 10.0
"""Seconds ``twin run --connect`` tries to join the router it names before it says why not."""


def _join(connect: str) -> Any:
    """A client session of the router at ``connect`` (``twin run --connect``), tried a second at a time for
    :data:`JOIN_S` (an open waiting for ever in native code was deaf to Ctrl-C); TwinError saying why not."""
    joining = ZenohOptions(mode="client", connect=[connect])
    joined = joining.open_patiently(lambda: False, give_up_s=JOIN_S)
    if joined is None:
        raise TwinError(joining.unanswered(JOIN_S))
    return joined


def run_embedded(scene: Scene, source=None, *, ensemble: str = "default", run_dir: str | Path | None = None,
                 rtf: float | None = None, max_ticks: int | None = None, on_event=None, metadata=None,
                 router_options: ZenohOptions | None = None, agent_extra: list[str] | None = None,
                 register_timeout: float = 60.0, live=False, idle_timeout: float = 3.0,
                 rerun: str = "none", progress=None, hold=None, open_bus: bool = False,
                 deadline: float | None = None, connect: str | None = None,
                 ros2_out: tuple[int, str] | None = None, stopper: Stopper | None = None) -> dict:
    """Run ``scene`` with an in-process Zenoh router, the conductor in this process and every agent as a
    subprocess; returns the summary (also written to ``<run_dir>/summary.json``). Unless ``open_bus``, the
    router admits only the processes of this run (:class:`ClosedBus`). With ``connect``, join the router already
    there (e.g. ``rmw_zenohd``) instead: the agents connect to it too. ``ros2_out`` (domain, namespace): the run
    is published back on the ROS 2 graph (:mod:`conductor.ros2_out`). With a ``stopper``, it (not this
    process's signals) ends the run early."""
    check_launchable(scene)  # before anything starts: an agent of an unknown kind would exit at once
    keys = Keys(ensemble)  # (a bad ensemble name: ValueError before the folder, the router or secrets are made)
    default = Path("runs") / f"{_folder_name(scene.name)}-{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = _fresh_run_dir(Path(run_dir or default), getattr(getattr(source, "rec", None), "path", None))
    bus = None
    router_options = router_options or ZenohOptions(mode="router")
    try:  # whatever fails before the run's processes exist frees what was taken: the bus's secrets, the folder
        bus = None if open_bus or connect else ClosedBus(run_dir)
        if bus is not None:
            router_options.auth_dictionary = str(bus.dictionary)
        session, endpoint = (_join(connect), connect) if connect else open_router(options=router_options)
        if bus is not None:
            bus.serves(endpoint, ensemble)
    except BaseException:
        if bus is not None:
            bus.close()
        _unlock(run_dir)
        raise
    procs = AgentProcs(run_dir)
    conductor = None
    try:
        if callable(live):  # a factory (session, keys) -> source, e.g. a ROS 2 attach
            source = live(session, keys)
        elif live:
            source = LiveSource(session, keys, idle_timeout=idle_timeout)
        opts = RunOptions(run_log=str(run_dir / "run.mcap"), rtf=rtf, max_ticks=max_ticks, metadata=metadata or {},
                          register_timeout=register_timeout, deadline=deadline)
        conductor = Conductor(scene, session, keys, source, opts, on_event=on_event, progress=progress)
        for name, spec in scene.models.items():
            procs.spawn(name, agent_command(spec.kind, name, endpoint, ensemble, agent_extra),
                        env=bus.agent_env() if bus is not None else None)
        if bus is not None and live:
            print(f"the bus is closed: a robot joins with --credentials {bus.access} (or --open-bus)", flush=True)
        conductor.agent_check = procs.check_started
        graph = None
        if ros2_out is not None:
            from .ros2_out import join_graph

            graph = join_graph(session, ros2_out[0], ros2_out[1], conductor, source)
        sink = None
        if rerun and rerun != "none":
            from .viewer import start_sink  # heavy (rerun, ~0.8 s): only when a stream is asked for

            sink = start_sink(session, keys, scene, rerun, run_dir, tap=conductor.run_log)
        try:
            with stopper.watching(conductor) if stopper is not None else _signals_stop(conductor):
                summary = conductor.run()
            if sink is not None and hold is not None and getattr(sink.stream, "mode", None) == "serve":
                hold(summary)  # the web viewer goes on serving the finished run (until Ctrl-C)
        finally:
            if graph is not None:
                graph.close()
            hint = sink.close() if sink is not None else None
        if hint:  # how to look at it (a person), and where it went (a program)
            summary.update({"rerun": hint, "rerun_stream": sink.stream.facts()})  # type: ignore[union-attr]
        write_summary(run_dir / "summary.json", summary)
        return summary
    finally:
        if conductor is not None:
            conductor.close()
        procs.stop()
        session.close()
        if bus is not None:
            bus.close()
        _unlock(run_dir)
