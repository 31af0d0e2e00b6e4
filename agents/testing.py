"""A conformance check for models: :func:`check_model` runs one as a real agent process and checks its contract.

Like Gymnasium's ``check_env``, it is public and meant to run over every model: the built-in kinds in the
project's tests, and an author's own model in theirs::

    from agents.testing import check_model

    def test_bouncer_keeps_its_contract():
        check_model("mypackage.models:Bouncer", {"gravity": -9.81},
                    {"entities": {"ball": {"shape": {"type": "sphere", "radius": 0.03},
                                           "pose": [0.5, 0.0, 0.3, 0, 0, 0, 1]}}},
                    owns=[("ball", "pose")])

It opens a Zenoh router in this process on a free loopback port, starts ``python -m agents KIND`` as a
subprocess connected to it, and plays a minimal conductor over the real protocol (:mod:`protocol.keys`,
:mod:`protocol.codec`): it answers the agent's registration and checks the descriptor against the class,
asks for its parameters, initialises it with the given parameters and scene (owning ``owns``), starts it,
steps it ``ticks`` times with the step broadcast, and checks each answer: status ``ok``, a state holding
only owned attributes, only declared outputs and events. Then a ``release`` -> ``acquire`` -> ``release``
round trip on each owned attribute must give the value back, one more step must be fine, the agent must
have counted no malformed message, ``stop`` is acknowledged, and on SIGTERM the process exits with code 0.
All of it runs twice, with fresh processes, and the two runs must answer alike (determinism; floats within
``tolerance``). The first failure raises :class:`ConformanceError` naming the check.
"""
from __future__ import annotations

import ctypes
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from protocol import codec
from protocol.config import ZenohOptions
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import Message, unusable

from .model import Inputs, Model
from .registry import resolve_kind

__all__ = ["ConformanceError", "check_model"]

ROOT = Path(__file__).resolve().parent.parent
"""The checkout this package lives in: first on the agent subprocess's PYTHONPATH."""


class ConformanceError(AssertionError):
    """A model does not keep its contract. ``subject`` is the model checked, ``check`` the check that
    failed (``register``, ``descriptor``, ``params``, ``init``, ``start``, ``step``, ``handover``,
    ``health``, ``stop``, ``exit`` or ``determinism``), ``problem`` what was wrong."""

    def __init__(self, subject: str, check: str, problem: str) -> None:
        self.subject, self.check, self.problem = subject, check, problem
        super().__init__(f"check_model({subject}): {check}: {problem}")


def check_model(kind_or_class: str | type[Model], params: Mapping[str, Any] | None = None,
                scene: Mapping[str, Any] | None = None, *, owns: Iterable[tuple[str, str]] = (),
                ticks: int = 20, rate: float = 100.0,
                telemetry: Callable[[int], Mapping[str, Any] | None] | None = None,
                inputs: Callable[[int], Inputs] | Inputs | None = None, tolerance: float = 0.0,
                name: str | None = None, timeout: float = 30.0) -> list[dict[str, Any]]:
    """Check that a model keeps its contract, running it twice as a real agent process (module docstring).

    ``kind_or_class``: a built-in kind, ``package.module:Class``, or a Model subclass defined at the top
    level of an importable module. ``params``: the scene's arguments for it; ``scene``: the scene as
    models see it at init (at least ``entities``; ``name``, ``main``, ``rate`` and ``robot`` get defaults).
    ``owns``: the ``(entity, attribute)`` pairs it owns from the start (each also gets the round trip).
    ``ticks`` steps at ``rate`` Hz; ``telemetry(tick)`` gives the joint state the step carries (None: no
    telemetry), ``inputs`` the inputs (a mapping, or ``inputs(tick)``). ``tolerance``: how far apart two
    floats may be and still count as equal (in the round trip and between the two runs; 0: exactly).
    ``timeout`` bounds every wait for the agent (start-up and registration included).

    Returns the answers of the first run (``step_reply`` messages without ``step_s``, then the round
    trips' values), for further checks. Raises :class:`ConformanceError` at the first failed check.
    """
    cls = resolve_kind(kind_or_class) if isinstance(kind_or_class, str) else kind_or_class
    kind = kind_or_class if isinstance(kind_or_class, str) else _importable(cls)
    agent = name or cls.kind.partition(":")[0]  # kind fmu:PATH runs as agent fmu
    runner = _Run(cls, kind, agent, dict(params or {}), _scene_info(scene, agent, rate),
                  [(str(e), str(a)) for e, a in owns], ticks, rate, telemetry, inputs, tolerance, timeout)
    first = runner.run()
    second = runner.run()
    problem = _difference(first, second, tolerance)
    if problem:
        raise ConformanceError(runner.subject, "determinism", f"two runs with fresh processes differ: {problem}")
    return first


# ------------------------------------------------------------------------------------------ one run
class _Run:
    """One agent process driven through the whole contract by a minimal conductor."""

    def __init__(self, cls: type[Model], kind: str, name: str, params: dict[str, Any], scene: dict[str, Any],
                 owns: list[tuple[str, str]], ticks: int, rate: float,
                 telemetry: Callable[[int], Mapping[str, Any] | None] | None,
                 inputs: Callable[[int], Inputs] | Inputs | None, tolerance: float, timeout: float) -> None:
        self.cls, self.kind, self.name = cls, kind, name
        self.subject = kind
        self.params, self.scene, self.owns = params, scene, owns
        self.ticks, self.rate = ticks, rate
        self.telemetry, self.inputs = telemetry, inputs
        self.tolerance, self.timeout = tolerance, timeout
        self.log_path: Path | None = None  # the agent's output, while a run goes

    def fail(self, check: str, problem: str) -> ConformanceError:
        """The error of a failed check (with the end of the agent's log, when it has one)."""
        if self.log_path is not None:
            try:
                tail = self.log_path.read_text(errors="replace").strip().splitlines()[-12:]
            except OSError:
                tail = []
            if tail:
                problem += "\n  the agent's log ends:\n    " + "\n    ".join(tail)
        return ConformanceError(self.subject, check, problem)

    def run(self) -> list[dict[str, Any]]:
        """Start a router and the agent, drive it, stop it; always tear both down."""
        port = _free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        keys = Keys(f"conformance-{uuid.uuid4().hex[:12]}")
        session: zenoh.Session = ZenohOptions(mode="router", listen=[endpoint]).open()
        logdir = Path(tempfile.mkdtemp(prefix="twin-check-"))
        self.log_path = logdir / "agent.log"
        proc: subprocess.Popen[bytes] | None = None
        try:
            with open(self.log_path, "wb") as out:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "agents", self.kind, "--name", self.name, "--connect", endpoint,
                     "--ensemble", keys.ensemble], stdout=out, stderr=subprocess.STDOUT, env=self._env(),
                    start_new_session=True, preexec_fn=_die_with_parent)
            wire = _Wire(session, keys, self, proc)
            try:
                record = self._drive(wire)
            finally:
                wire.close()
            self._stop_process(proc)
            return record
        finally:
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
            session.close()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs
            self.log_path = None
            for f in logdir.iterdir():
                f.unlink()
            logdir.rmdir()

    def _env(self) -> dict[str, str]:
        """This checkout and the model's own import root first on the agent's PYTHONPATH."""
        env = dict(os.environ)
        paths = [str(ROOT)]
        module = sys.modules.get(self.cls.__module__)
        file = getattr(module, "__file__", None)
        if file:
            root = Path(file).resolve().parent
            for _ in range(self.cls.__module__.count(".")):
                root = root.parent
            paths.append(str(root))
        if env.get("PYTHONPATH"):
            paths.append(env["PYTHONPATH"])
        env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
        return env

    def _drive(self, wire: _Wire) -> list[dict[str, Any]]:
        """The life cycle, as a conductor runs it, with a check at each step of it."""
        desc = wire.registration()
        self._check_descriptor(desc)
        declared = wire.ask("params", codec.encode("query"), "params_reply").params
        if declared != desc["params"]:
            raise self.fail("params", f"model/<id>/params answers {declared!r}, registration declared "
                                      f"{desc['params']!r}")
        owned = [list(o) for o in self.owns]
        wire.ask("init", codec.encode("init", params=self.params, scene=self.scene, owned=owned, rate=self.rate,
                                      step_mode="service", models={self.name: self.cls.kind}), "ack")
        wire.ask("start", codec.encode("start", tick=0, t=0.0), "ack")
        record = [self._step(wire, tick) for tick in range(self.ticks - 1)]
        record.append(self._rewound(wire, self.ticks - 1) if self.cls.rewinds() else self._step(wire, self.ticks - 1))
        for entity, attribute in self.owns:
            record.append(self._round_trip(wire, entity, attribute))
        record.append(self._step(wire, self.ticks))  # the model goes on after the handovers
        health = wire.ask("health", codec.encode("query"), "value_reply").value
        if health.get("malformed") != 0:
            raise self.fail("health", f"the agent counted {health.get('malformed')} malformed messages "
                                      "in what a well-behaved conductor sent")
        wire.ask("stop", codec.encode("stop", reason="conformance check done"), "ack")
        return record

    def _check_descriptor(self, desc: Message) -> None:
        """The registration declares what the class declares (and supports the step broadcast)."""
        cls = self.cls
        # what the class declares, as it travels (tuples become lists, ...)
        want = codec.unpack(codec.pack({
            "name": self.name, "kind": cls.kind, "role": cls.role, "step_modes": list(cls.step_modes),
            "params": {k: p.describe() for k, p in cls.params.items()}, "attributes": list(cls.attributes),
            "outputs": list(cls.outputs), "events": list(cls.events), "evaluators": sorted(cls.evaluators()),
            "services": sorted(cls.services()), "reads": list(cls.reads), "telemetry": bool(cls.wants_telemetry),
            "batch": True, "clock_ack": True, "rewind": cls.rewinds()}))
        for field, value in want.items():
            if desc.get(field) != value:
                raise self.fail("descriptor", f"register.{field} is {desc.get(field)!r}, the class declares "
                                              f"{value!r}")
        if "service" not in cls.step_modes:
            raise self.fail("descriptor", f"step_modes {cls.step_modes!r} lack 'service': check_model steps "
                                          "a model with the step broadcast")

    def _rewound(self, wire: _Wire, tick: int) -> dict[str, Any]:
        """A model that can go back (snapshot/restore): tick ``tick`` stepped with a checkpoint before it, the model
        sent back to the tick before (``model/<id>/rewind``) and the tick stepped again answers the same."""
        first = self._step(wire, tick, mark=True)
        wire.ask("rewind", codec.encode("rewind", tick=tick - 1), "ack", "rewind")
        again = self._step(wire, tick)
        problem = _difference(first, again, self.tolerance)
        if problem:
            raise self.fail("rewind", f"tick {tick} stepped again after going back to tick {tick - 1} answers "
                                      f"otherwise: {problem}")
        return again

    def _step(self, wire: _Wire, tick: int, mark: bool = False) -> dict[str, Any]:
        """One tick: status ok, a state of owned attributes only, declared outputs and events only."""
        t, dt = tick / self.rate, 1.0 / self.rate
        joints = self.telemetry(tick) if self.telemetry is not None else None
        given = self.inputs(tick) if callable(self.inputs) else (self.inputs or {})
        body = {"tick": tick, "t": t, "joints": dict(joints) if joints is not None else None,
                "models": {self.name: {"dt": dt, "actions": [], "inputs": given}}, **({"mark": [self.name]} if mark
                                                                                       else {})}
        rep = wire.step(codec.encode_unchecked("tick", body), tick)
        if rep["status"] != "ok":
            raise self.fail("step", f"tick {tick}: status {rep['status']}: {rep.get('message', '')}")
        owned = set(self.owns)
        extra = sorted(f"{e}.{a}" for e, attrs in rep["state"].items() for a in attrs if (e, a) not in owned)
        if extra:
            raise self.fail("step", f"tick {tick}: the state holds {', '.join(extra)}, which it does not own")
        bad = [f"{e}.{a} = {v!r} ({why})" for e, attrs in rep["state"].items() for a, v in attrs.items()
               if (why := unusable(a, v))] + [f"output {n} = {v!r} ({why})" for n, v in rep["outputs"].items()
                                             if (why := unusable("", v))]
        if bad:  # a run leaves them out and is degraded (README, Trust)
            raise self.fail("step", f"tick {tick}: values that are no values, which a run leaves out: "
                                    f"{'; '.join(bad[:3])}")
        undeclared = sorted(set(rep["outputs"]) - set(self.cls.outputs))
        if undeclared:
            raise self.fail("step", f"tick {tick}: outputs {undeclared} are not declared in outputs "
                                    f"{self.cls.outputs!r}")
        undeclared = sorted({ev["name"] for ev in rep["events"]} - set(self.cls.events))
        if undeclared:
            raise self.fail("step", f"tick {tick}: events {undeclared} are not declared in events "
                                    f"{self.cls.events!r}")
        rep = dict(rep)
        rep.pop("step_s", None)  # wall time: the only field two runs may not share
        return rep

    def _round_trip(self, wire: _Wire, entity: str, attribute: str) -> dict[str, Any]:
        """release -> acquire -> release: the second release gives back what the first one handed over;
        a last acquire leaves the model owning it again."""
        where = {"entity": entity, "attribute": attribute, "tick": self.ticks, "t": self.ticks / self.rate}
        first = wire.ask("release", codec.encode("release", where), "release_reply", "handover")
        wire.ask("acquire", codec.encode("acquire", where, value=first.value, extra=first.extra), "ack", "handover")
        second = wire.ask("release", codec.encode("release", where), "release_reply", "handover")
        problem = _difference(first.value, second.value, self.tolerance)
        if problem:
            raise self.fail("handover", f"{entity}.{attribute}: released {first.value!r}, acquired it back, and "
                                        f"then released {second.value!r} ({problem})")
        wire.ask("acquire", codec.encode("acquire", where, value=second.value, extra=second.extra), "ack",
                 "handover")
        return {"entity": entity, "attribute": attribute, "value": first.value, "extra": first.extra}

    def _stop_process(self, proc: subprocess.Popen[bytes]) -> None:
        """SIGTERM: the agent exits with code 0 within the timeout."""
        proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(timeout=self.timeout)
        except subprocess.TimeoutExpired:
            raise self.fail("exit", f"the agent did not exit within {self.timeout:g} s of SIGTERM") from None
        if code != 0:
            raise self.fail("exit", f"the agent exited with code {code} on SIGTERM (0 expected)")


class _Wire:
    """The checker's side of the protocol: the register queryable, the done/<id> subscription, queries.
    Every wait is bounded by the run's timeout and watches that the agent process is still alive."""

    def __init__(self, session: zenoh.Session, keys: Keys, run: _Run, proc: subprocess.Popen[bytes]) -> None:
        self.session, self.keys, self.run, self.proc = session, keys, run, proc
        self.name, self.timeout = run.name, run.timeout
        self.registrations: queue.SimpleQueue[zenoh.Query] = queue.SimpleQueue()
        self.done: queue.SimpleQueue[zenoh.Sample] = queue.SimpleQueue()
        self._decl: list[Any] = [
            session.declare_queryable(keys.register, self.registrations.put),
            session.declare_subscriber(keys.done(run.name), self.done.put),
        ]
        self.step_pub = session.declare_publisher(keys.step_all)

    def close(self) -> None:
        for d in self._decl:
            d.undeclare()
        self.step_pub.undeclare()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs

    def _wait(self, source: queue.SimpleQueue[Any], what: str, check: str) -> Any:
        """The next item of ``source`` within the timeout, watching that the agent is still alive."""
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                return source.get(timeout=0.05)
            except queue.Empty:
                pass
            code = self.proc.poll()
            if code is not None:
                raise self.run.fail(check, f"the agent exited with code {code} while we waited for {what}")
            if time.monotonic() > deadline:
                raise self.run.fail(check, f"no {what} within {self.timeout:g} s")

    def registration(self) -> Message:
        """Wait for the agent's ``register`` request, accept it, and return the descriptor."""
        query: zenoh.Query = self._wait(self.registrations, "registration", "register")
        with query:
            try:
                desc = codec.decode(str(query.key_expr), query.payload, "register")
            except ProtocolError as e:
                raise self.run.fail("register", str(e)) from None
            query.reply(query.key_expr, codec.encode("register_reply", id=desc.name, accepted=True))
        if desc.name != self.name:
            raise self.run.fail("register", f"the agent registered as {desc.name!r}, not {self.name!r}")
        return desc

    def ask(self, op: str, payload: bytes, expect: str, check: str | None = None) -> Message:
        """Query ``model/<id>/<op>`` and return the decoded answer; an error answer or none fails ``check``
        (default: the operation)."""
        check = check or op
        key = self.keys.model(self.name, op)
        for reply in self.session.get(key, payload=payload, timeout=self.timeout):
            if reply.ok is not None:
                try:
                    return codec.decode(key, reply.ok.payload, expect)
                except ProtocolError as e:
                    raise self.run.fail(check, str(e)) from None
            if reply.err is not None and reply.err.payload.to_bytes() == codec.ZENOH_TIMEOUT:
                break  # Zenoh's own error reply to a query that timed out: no answer
            try:
                err = codec.decode(key, reply.err.payload if reply.err is not None else b"", "error")
                problem = f"{err.kind}: {err.message}" + (f"\n{err.traceback}" if err.get("traceback") else "")
            except ProtocolError as e:
                problem = f"an undecodable error reply ({e})"
            raise self.run.fail(check, f"{op} answered with an error: {problem}")
        raise self.run.fail(check, f"no answer to {op} within {self.timeout:g} s")

    def step(self, payload: bytes, tick: int) -> dict[str, Any]:
        """Publish one tick of the step broadcast and return this model's answer on done/<id>."""
        self.step_pub.put(payload)
        sample: zenoh.Sample = self._wait(self.done, f"the answer to tick {tick}", "step")
        key = str(sample.key_expr)
        try:
            rep = codec.decode_hot(key, sample.payload, "step_reply")
        except ProtocolError as e:
            raise self.run.fail("step", f"tick {tick}: {e}") from None
        if rep["tick"] != tick or rep.get("more"):
            raise self.run.fail("step", f"tick {tick} was answered for tick {rep['tick']} "
                                        f"({len(rep.get('more') or ())} more)")
        return rep


# ---------------------------------------------------------------------------------------- helpers
try:  # looked up here, not in the child: between fork and exec, a child of a threaded process only calls
    _prctl: Callable[..., int] | None = ctypes.CDLL("libc.so.6", use_errno=True).prctl
except (OSError, AttributeError):
    _prctl = None
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the agent process: SIGTERM when the checking process dies (even by SIGKILL), no orphans."""
    if _prctl is not None:
        _prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _importable(cls: type[Model]) -> str:
    """``module:Class`` for a class the agent process can import (top level of a real module)."""
    if cls.__module__ == "__main__" or "<locals>" in cls.__qualname__ or "." in cls.__qualname__:
        raise ValueError(f"check_model needs a class at the top level of an importable module, got "
                         f"{cls.__module__}.{cls.__qualname__}")
    return f"{cls.__module__}:{cls.__qualname__}"


def _scene_info(scene: Mapping[str, Any] | None, name: str, rate: float) -> dict[str, Any]:
    """The scene as models see it at init, with defaults for what ``scene`` leaves out."""
    info: dict[str, Any] = {"name": "conformance", "entities": {}, "main": name, "rate": rate, "robot": {}}
    info.update(scene or {})
    return info


def _difference(a: Any, b: Any, tolerance: float, path: str = "") -> str:
    """Where ``a`` and ``b`` first differ ('' if nowhere): floats within ``tolerance`` are equal, and
    so are two NaN; arrays and lists compare item by item, maps key by key."""
    here = path or "the value"
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        x, y = np.asarray(a), np.asarray(b)
        if x.shape != y.shape:
            return f"{here}: shape {x.shape} != {y.shape}"
        a, b = x.tolist(), y.tolist()
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        if set(a) != set(b):
            return f"{here}: keys {sorted(map(str, a))} != {sorted(map(str, b))}"
        for k in a:
            d = _difference(a[k], b[k], tolerance, f"{path}.{k}" if path else str(k))
            if d:
                return d
        return ""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return f"{here}: {len(a)} items != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            d = _difference(x, y, tolerance, f"{path}[{i}]")
            if d:
                return d
        return ""
    return "" if _same(a, b, tolerance) else f"{here}: {a!r} != {b!r}"


def _same(a: Any, b: Any, tolerance: float) -> bool:
    """Two plain values are the same: numbers (not bools) within ``tolerance`` when one is a float (two NaN
    too), anything else equal and of the same type."""
    numbers = (isinstance(a, (int, float)) and isinstance(b, (int, float))
               and not isinstance(a, bool) and not isinstance(b, bool))
    if numbers and (isinstance(a, float) or isinstance(b, float)):
        return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tolerance
    return bool(a == b) and type(a) is type(b)
