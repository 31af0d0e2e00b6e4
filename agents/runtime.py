"""The agent runtime: connects one :class:`~agents.model.Model` to an ensemble over Zenoh.

:func:`run_agent` does everything around the model: liveliness token, registration with retry, the
params -> init -> start handshake, the three step modes (the conductor's step broadcast, an external
clock, free running) at the rate the scene chose, one batched ``state/<id>`` message per step,
handover, evaluators and services, error replies instead of crashes, and a clean exit on SIGINT/SIGTERM.

Channels, not callbacks: every Zenoh callback (subscribers, queryables, the registration's replies)
only wraps what it got in a :class:`Request` and puts it in one queue; the agent's main thread takes the
requests in order and runs each through one dispatch table (:attr:`AgentRuntime.dispatch`). So model
code never runs on a Zenoh thread, one hook at a time, with no lock; publishers are declared and queries
answered on the main thread too. Every step, whatever started it, goes through :meth:`AgentRuntime.step`.
"""
from __future__ import annotations

import copy
import logging
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable
from types import FrameType
from typing import Any, NamedTuple

import zenoh
from msgpack import Packer

from protocol import codec
from protocol.config import ZenohOptions
from protocol.errors import ProtocolError
from protocol.joints import LatestJoints
from protocol.keys import Keys, check_name
from protocol.messages import PROTOCOL_VERSION, Message, unusable

from .model import Inputs, Model, StepWarning, Telemetry, arities

__all__ = ["AgentRuntime", "Request", "run_agent", "check_agent_name"]

_NUM = (int, float)
MAX_STEP_DT = 1.0
"""A step spans at most this many seconds, or four of the model's periods if that is longer: a ``dt`` beyond
it is not the conductor's (a forged ``dt: 1e4`` would make a physics model compute millions of substeps)."""
# one packer for the answers on done/<id> (the codec's options; msgpack.packb makes a new one per call)
_pack_answer = Packer(**codec._packer_opts).pack

log = logging.getLogger("twin.agent")


BLOCK = zenoh.CongestionControl.BLOCK
"""How step answers are published: the conductor waits for each, so under congestion one waits for room instead of
being dropped (Zenoh's default for a publication)."""


class Request(NamedTuple):
    """One thing for the main thread to do: ``op`` names its handler in :attr:`AgentRuntime.dispatch`;
    ``item`` is what Zenoh gave the callback (a ``Sample``, a ``Query`` to answer, a ``Reply``), the number
    of the registration request a ``register_end`` closes, or None."""

    op: str
    item: Any = None


class _Answered(NamedTuple):
    """The last tick answered on ``done/<id>``: its number, what its steps published and the answer,
    kept to answer a repeated tick again without stepping twice."""

    tick: int | None
    pubs: list[tuple[str, bytes]]
    done: bytes


_NOTHING_ANSWERED = _Answered(None, [], b"")


class Checkpoint(NamedTuple):
    """What stood before a step message marked for this model (``tick.mark``), to go back to on
    ``model/<id>/rewind``: the message's steps, the last tick stepped before it, the outputs last reported, what
    the model owned, its tick and time, its :meth:`~agents.model.Model.snapshot`; and what the message's ticks
    would publish (``state``/``out``/``event``, per tick), held back until it is known which of them stand
    (:func:`release`): a subscriber never sees the results of a tick that was then undone."""

    steps: list[_Step]
    stepped: int | None
    seen: dict[str, Any]
    owned: set[tuple[str, str]]
    clock: tuple[int, float]
    state: Any
    held: list[tuple[int, list[tuple[str, bytes]]]]

    @classmethod
    def keep(cls, m: Model, steps: list[_Step], stepped: int | None, seen: dict[str, Any]) -> Checkpoint:
        return cls(steps, stepped, dict(seen), set(m.owned), (m.tick, m.t), m.snapshot(), [])

    def rewind(self, m: Model, tick: int, stepped: int | None) -> tuple[int | None, dict[str, Any]]:
        """Set ``m`` back here, then step it again through ``tick`` (answers dropped, nothing published): the last
        tick stepped and the outputs last reported then. ValueError if the message does not cover ``tick``."""
        first = self.steps[0][0]
        if tick < first - 1 or (stepped is not None and tick > stepped):
            raise ValueError(f"{m.id} cannot go back to tick {tick}: its marked step message stepped ticks "
                             f"{first} to {stepped}")
        m.restore(self.state)
        m.owned, (m.tick, m.t) = set(self.owned), self.clock
        seen = dict(self.seen)
        again = [st for st in self.steps if st[0] <= tick]
        step_until(lambda *a: (step_reply(m, *a), []), again, None, seen)
        return (again[-1][0] if again else self.stepped), seen


def release(mark: Checkpoint | None, put: Callable[[str, bytes], None], upto: int | None = None) -> None:
    """Publish what a marked message's ticks held back (:class:`Checkpoint`) that stands: the ticks through
    ``upto`` (its rewind's tick), or all of them once the conductor went on past it (None); each once."""
    if mark is not None:
        for tick, pubs in mark.held:
            if upto is None or tick <= upto:
                for key, data in pubs:
                    put(key, data)
        mark.held.clear()


def check_empty_query(key: str, query: zenoh.Query) -> None:
    """``params`` and ``health`` take no arguments, but what a caller does send must be a ``query``."""
    payload = query.payload
    if payload is not None and len(payload.to_bytes()) > 0:
        codec.decode(key, payload, "query")


ANSWERS_KEPT = 4
"""Step messages whose answers an agent keeps (by their first tick): the conductor may have sent the next message
before it asks again for an answer it lost (:class:`conductor.flow.Pipeline`)."""


def remember(answered: dict[int, _Answered], a: _Answered) -> None:
    """Keep ``a`` under its first tick, and only the last :data:`ANSWERS_KEPT`."""
    answered[a.tick] = a  # type: ignore[index]  # a step message's answer always has its tick
    while len(answered) > ANSWERS_KEPT:
        del answered[next(iter(answered))]

_Step = tuple[int, float, float, list[Any], Inputs, Any]
"""One tick of a step message for this model: (tick, t, dt, actions, inputs, joints)."""


def _batch(reps: list[dict[str, Any]], stopped: bool = False) -> dict[str, Any]:
    """One answer for the ticks of a step message: the first tick's reply, the later ones in ``more``
    (``stopped``: the message's ticks after the last reply were not stepped, as its ``until`` asked)."""
    first = dict(reps[0])
    if len(reps) > 1:
        first["more"] = reps[1:]
    if stopped:
        first["stopped"] = True
    return first


def until_for(mid: str, key: object, msg: dict[str, Any]) -> dict[str, list[str]] | None:
    """Where model ``mid`` stops the step message ``msg`` early (its ``until`` entry), or None: step it all."""
    u = (msg.get("until") or {}).get(mid)
    if u is None:
        return None
    if u.__class__ is not dict or any(not isinstance(u.get(f), list) or not all(isinstance(x, str) for x in u[f])
                                      for f in ("events", "outputs")):
        raise ProtocolError(key, f"tick.until.{mid} must be {{events: [names], outputs: [names]}}")
    return u


def step_until(step: Callable[..., tuple[dict[str, Any], list[tuple[str, bytes]]]], steps: list[_Step],
               until: dict[str, list[str]] | None, seen: dict[str, Any]) -> tuple[list[dict[str, Any]],
                                                                                  list[tuple[str, bytes]]]:
    """Step ``steps`` in order (a failed tick does not end the batch), each reply's outputs noted in ``seen``
    (name -> the value last reported); with ``until``, stop after the first tick that raises one of its events
    or changes one of its outputs from the value last reported. The replies and publications of the ticks
    stepped."""
    reps, pubs = [], []
    for tick, t, dt, actions, inputs, joints in steps:
        rep, published = step(tick, t, dt, {"joints": joints, "actions": actions}, inputs)
        reps.append(rep)
        pubs += published
        stop = False
        for name, value in rep["outputs"].items():
            if until is not None and name in until["outputs"]:
                stop |= name not in seen or codec.differs(seen[name], value)
            seen[name] = value
        if stop or (until is not None and any(ev.get("name") in until["events"] for ev in rep["events"])):
            break
    return reps, pubs


def publications(keys: Keys, mid: str, rep: dict[str, Any], t: float,
                 wanted: Callable[[str], bool]) -> list[tuple[str, bytes]]:
    """What a step reply publishes (``state``, ``out``, ``event``) where ``wanted`` says someone listens."""
    tick, values, pubs = rep["tick"], rep["state"], []
    if values and wanted(key := keys.state(mid)):
        pubs.append((key, codec.encode_unchecked("state", {"model": mid, "tick": tick, "t": t, "values": values})))
    for name, value in rep["outputs"].items():
        if wanted(key := keys.out(mid, name)):
            pubs.append((key, codec.encode_unchecked(
                "out", {"model": mid, "name": name, "tick": tick, "t": t, "value": value})))
    for ev in rep["events"]:
        if wanted(key := keys.event(mid, ev["name"])):
            pubs.append((key, codec.encode_unchecked(
                "event", {"model": mid, "name": ev["name"], "tick": tick, "t": t, "data": ev["data"]})))
    return pubs


def _encodable(rep: dict[str, Any]) -> dict[str, Any]:
    """``rep`` if msgpack can carry it, else the tick's error reply saying why (nothing of it published)."""
    try:
        Packer(**codec._packer_opts).pack(rep)
        return rep
    except Exception as e:
        log.error("step %s: its results cannot be encoded: %s", rep.get("tick"), e)
        return {**rep, "status": "error", "state": {}, "outputs": {}, "events": [],
                "message": f"{type(e).__name__}: {e}"}


def reply_error(query: zenoh.Query, key: str, err: Exception, count_malformed: Callable[[str, Exception], None]
                ) -> None:
    """Answer a query with the error it caused, as data: a malformed request is counted (``count_malformed``) and
    answered with kind ``ProtocolError``; anything else (a model's bug) with its type name, message and traceback.
    Never raises."""
    if isinstance(err, ProtocolError):
        count_malformed(key, err)
        payload = codec.encode("error", kind="ProtocolError", message=str(err))
    else:
        log.error("error answering %s", key, exc_info=err)
        payload = codec.encode("error", kind=type(err).__name__, message=str(err),
                               traceback="".join(traceback.format_exception(err, limit=8)))
    try:
        query.reply_err(payload)
    except Exception:
        log.exception("could not send the error reply on %s", key)


# what every agent of this runtime does (the register descriptor's flags): clock acks, batches of ticks stopped
# early at tick.until, step messages addressed to some models only
_SUPPORTS = {"clock_ack": True, "batch": True, "until": True, "addressed": True}

def step_reply(m: Model, tick: int, t: float, dt: float, telemetry: Telemetry, inputs: Inputs) -> dict[str, Any]:
    """Step a model once and make its step reply: the owned attributes' values read after the step, its
    outputs and events (with what acquire/release/evaluators emitted since the last step: the step adds to
    the same dict and list), the step's time; ``status`` ``warning`` for a :class:`StepWarning`, ``error`` for
    any other exception or a failed read (the model goes on). The agent runtime publishes it; ``bench.limit``
    uses it in-process."""
    outputs, events = m._outputs, m._events
    m.tick, m.t = tick, t
    m.now = t
    status, message = "ok", ""
    t0 = time.perf_counter()
    try:
        m.step(tick, t, dt, telemetry, inputs)
    except StepWarning as w:
        status, message = "warning", str(w)
    except Exception as e:
        log.exception("step %d failed", tick)
        status, message = "error", f"{type(e).__name__}: {e}"
    step_s = time.perf_counter() - t0
    values: dict[str, dict[str, Any]] = {}
    for ent, attr in m.owned:
        try:
            values.setdefault(ent, {})[attr] = m.read(ent, attr)
        except Exception as e:
            status, message = "error", f"read {ent}.{attr}: {e}"
    m._outputs, m._events = {}, []
    rep: dict[str, Any] = {"v": PROTOCOL_VERSION, "type": "step_reply", "tick": tick, "status": status,
                           "state": values, "outputs": outputs, "events": events, "step_s": step_s}
    if status != "ok":
        rep["message"] = message
    return rep


def _queueing(put: Callable[[Request], None], op: str, ordered: bool = False) -> Any:
    """A Zenoh handler that ``put``s what it gets as ``Request(op, item)`` and does nothing else.

    By default zenoh-python runs it on a Python thread of its own for each subscription, fed by Zenoh without the
    GIL. Running it on Zenoh's receiving thread instead measured slower on the step broadcast: that thread pays for
    taking the GIL (and a Python thread state) on every sample. But two subscriptions' threads queue in no set
    order, so the subscriptions a model steps on are ``ordered``: queued on the receiving thread, in the order they
    came on the link (a replay's telemetry before the clock tick it belongs to; a state published before the answer
    that let the conductor send the next tick; a step message addressed to some models before the broadcast that
    the conductor sent after it).
    """
    def callback(item: Any) -> None:
        put(Request(op, item))

    return zenoh.handlers.Callback(callback, indirect=False) if ordered else callback


class Readings:
    """What a clock-driven or free-running model steps on, gathered between its steps from the bus: the latest of
    every joint (a driver may publish arm and gripper apart), the actions since the last step, and the others'
    ``state`` messages. Its inputs are what the others own, as the conductor gives a service-stepped model: an
    attribute the model took is left out (the last owner's last word is not an input), and one it handed on is
    the value it handed on until the new owner speaks (not what an owner before it said)."""

    def __init__(self) -> None:
        self.joints = LatestJoints()
        self.actions: list[Message] = []
        self.inputs: Inputs = {}

    def telemetry(self, msg: Message) -> None:
        if msg.mtype == "joint_state":
            self.joints.take(msg)
        else:
            self.actions.append(msg)

    def state(self, values: dict[str, Any]) -> None:
        for ent, attrs in values.items():
            if isinstance(attrs, dict):
                self.inputs.setdefault(ent, {}).update(attrs)

    def taken(self, entity: str, attribute: str) -> None:
        self.inputs.get(entity, {}).pop(attribute, None)

    def handed_on(self, entity: str, attribute: str, value: Any) -> None:
        self.inputs.setdefault(entity, {})[attribute] = value

    def take(self, owned: set[tuple[str, str]]) -> tuple[Telemetry, Inputs]:
        """The telemetry since the last step and the inputs now (what the model does not own)."""
        tel: Telemetry = {"joints": self.joints.last, "actions": self.actions}
        self.actions = []
        inputs = {e: {k: v for k, v in a.items() if (e, k) not in owned} for e, a in self.inputs.items()}
        return tel, {e: a for e, a in inputs.items() if a}


class AgentRuntime:
    """Connects one :class:`Model` to an ensemble over Zenoh (see the module docstring).

    ``name`` is the agent's name and model id; ``register_timeout`` > 0 gives up registering (exit
    code 3) when no conductor has answered within that many seconds, 0 retries forever.
    """

    CONTROL_OPS = ("health", "params", "init", "start", "stop", "release", "acquire", "rewind", "eval/*", "call/*")
    """The queryables served under ``model/<id>/``."""
    EXIT_GRACE = 5.0
    """Seconds a stop request may take before the process exits regardless."""
    REGISTER_WAIT = 2.0
    """Seconds one registration request waits for the conductor's answer."""
    IDLE_WAIT = 1.0
    """Longest the main loop blocks on an empty queue (a signal or a request ends the wait earlier)."""

    def __init__(self, model: Model, name: str, options: ZenohOptions, register_timeout: float = 0.0) -> None:
        self.model = model
        self.name = name  # (checked by run_agent: a descriptor is asked of an agent of kind fmu:PATH by its kind)
        self.options = options
        self.keys = Keys(options.ensemble)
        self.register_timeout = register_timeout
        self.model_id: str | None = None
        self.step_mode = "service"
        self.rate = 0.0
        self.initialized = False
        self.started = False
        self.malformed = 0
        self._session: zenoh.Session | None = None
        self._queue: queue.SimpleQueue[Request] = queue.SimpleQueue()
        self._exit_code: int | None = None  # set: the main loop ends and run() returns it
        self._signalled = False
        self._queryables: list[zenoh.Queryable[None]] = []
        self._prefix_len = 0
        self._subscribers: list[zenoh.Subscriber[None]] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._done_pub: zenoh.Publisher | None = None
        self._evals = model.evaluators()
        self._services = model.services()
        self._readings = Readings()  # what clock-driven and free-running models step on
        self._last: _Answered = _NOTHING_ANSWERED  # (clock-driven)
        self._answered: dict[int, _Answered] = {}  # the last step messages answered, by first tick (remember)
        self._stepped: int | None = None  # the last tick stepped in this run (a step for it or an older one is refused)
        self._seen: dict[str, Any] = {}  # output -> the value it last reported (step_until)
        self._mark: Checkpoint | None = None  # kept before the last step message marked for it (rewind)
        # registration: one request out at a time; its replies and its end come back as requests
        self._attempt = 0
        self._registering = False
        self._register_again = False
        self._registered_once = False
        self._register_deadline: float | None = None
        self._retry_at: float | None = None
        self._retry_delay = 0.05
        self._conductor_seen = False
        # free running: step _free_tick is due at _free_t0 + _free_tick * _free_period
        self._free_t0: float | None = None
        self._free_tick = 0
        self._free_period = 0.01
        self._reading = False  # subscribed to telemetry and state (clock-driven and free-running models)
        self.dispatch: dict[str, Callable[[Request], None]] = {
            # the step paths
            "step": self._on_step_broadcast,
            "clock": self._on_clock,
            # what clock-driven and free-running models read
            "telemetry": self._on_telemetry,
            "state": self._on_state,
            # control queries on model/<id>/<op>, answered here
            "health": self._answering(self._health),
            "params": self._answering(self._params),
            "init": self._answering(self._init),
            "start": self._answering(self._start),
            "stop": self._answering(self._stop),
            "release": self._answering(self._release),
            "acquire": self._answering(self._acquire),
            "rewind": self._answering(self._rewind),
            "eval": self._answering(self._call),
            "call": self._answering(self._call),
            # registration and life
            "conductor": self._on_conductor_alive,
            "registered": self._on_register_reply,
            "register_end": self._on_register_end,
            "exit": self._on_exit,
        }
        """Request op -> handler: everything the main thread does, it does through this table."""

    # ----------------------------------------------------------- plumbing
    @property
    def session(self) -> zenoh.Session:
        """The Zenoh session (open while :meth:`run` runs)."""
        if self._session is None:
            raise RuntimeError("the agent runtime is not running")
        return self._session

    def descriptor(self) -> dict[str, Any]:
        """The ``register`` message's fields: who this agent is and what its model declares."""
        m = type(self.model)
        return {
            "name": self.name, "kind": m.kind, "role": m.role, "step_modes": list(m.step_modes),
            "params": {k: p.describe() for k, p in m.params.items()},
            "attributes": list(m.attributes), "outputs": list(m.outputs), "events": list(m.events),
            "owner_events": list(m.owner_events), "evaluators": sorted(self._evals),
            "evaluator_args": m.evaluator_names(), "services": sorted(self._services),
            "arity": {"eval": arities(self.model, self._evals), "call": arities(self.model, self._services)},
            "pid": os.getpid(), "host": socket.gethostname(), "telemetry": bool(m.wants_telemetry),
            "reads": list(m.reads), **_SUPPORTS, "rewind": m.rewinds()}

    def _enqueue(self, op: str, ordered: bool = False) -> Any:
        """A Zenoh handler queueing what it gets as ``Request(op, item)`` (:func:`_queueing`)."""
        return _queueing(self._queue.put, op, ordered)

    def _count_malformed(self, key: str, err: Exception) -> None:
        self.malformed += 1
        log.warning("malformed message on %s: %s (total %d)", key, err, self.malformed)

    def _pub(self, key: str, payload: bytes) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(key)
        pub.put(payload)

    # ------------------------------------------------------------ main loop
    def run(self) -> int:
        """Serve until SIGINT/SIGTERM; the exit code (0; 2 refused by the conductor, or Zenoh refused its settings;
        3 no router or conductor answered within ``register_timeout``)."""
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        try:
            session = open_session(self.options, self.register_timeout, lambda: self._signalled)
        except zenoh.ZError as e:  # (a setting Zenoh refuses: one line, not a traceback)
            log.error("Zenoh refused this agent's settings: %s", e)
            return 2
        if session is None:
            return 0 if self._signalled else 3
        self._session = session
        try:
            # serve model/<name>/... before registering: the conductor queries it as soon as it answers
            self._bind(self.name)
            token = self.session.liveliness().declare_token(self.keys.alive(self.name))
            watch = self.session.liveliness().declare_subscriber(
                self.keys.alive("_conductor"), self._enqueue("conductor"), history=True)
            self._start_registering()
            code = self._serve()
            del token, watch
            return code
        finally:
            try:
                self.model.close()
            except Exception:
                log.exception("close failed")
            self._drop_pending()
            self.session.close()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs

    def _serve(self) -> int:
        """The main loop: one request at a time through :attr:`dispatch`, free-running steps and
        registration retries when they are due; until an exit code is set."""
        get, dispatch, empty = self._queue.get, self.dispatch, queue.Empty
        while self._exit_code is None:
            try:
                # the step broadcast's path: no timer, no arithmetic
                req = get(timeout=self.IDLE_WAIT if self._retry_at is None and self._free_t0 is None
                          else self._wait())
            except empty:
                pass
            else:
                try:
                    dispatch[req.op](req)
                except Exception:  # each handler answers its own errors: this is a last resort
                    log.exception("request %s failed", req.op)
            if self._free_t0 is not None and self.started:
                self._free_run()
            if self._retry_at is not None and time.monotonic() >= self._retry_at:
                self._retry_at = None
                self._send_register()
        return self._exit_code

    def _wait(self) -> float:
        """Seconds until the next free-running step or registration retry is due (at most IDLE_WAIT)."""
        due = self._retry_at
        if self._free_t0 is not None and self.started:
            nxt = self._free_t0 + self._free_tick * self._free_period
            due = nxt if due is None else min(due, nxt)
        if due is None:
            return self.IDLE_WAIT
        return min(self.IDLE_WAIT, max(0.0, due - time.monotonic()))

    def _drop_pending(self) -> None:
        """Queries still queued at exit get no answer: drop them so their askers stop waiting now."""
        while True:
            try:
                req = self._queue.get_nowait()
            except queue.Empty:
                return
            if isinstance(req.item, zenoh.Query):
                req.item.drop()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        """Stop cleanly; and if closing hangs (e.g. the router is gone mid-close), exit anyway after
        ``EXIT_GRACE`` seconds: an agent must never outlive its launcher."""
        if not self._signalled:
            self._signalled = True
            # runs on the main thread between two bytecodes, maybe inside a model's step: it only sets the
            # flag the loop checks, and wakes the loop in case it waits (SimpleQueue.put is reentrant)
            if self._exit_code is None:
                self._exit_code = 0
            self._queue.put(Request("exit"))
            t = threading.Timer(self.EXIT_GRACE, lambda: os._exit(0))
            t.daemon = True
            t.start()

    def _on_exit(self, req: Request) -> None:
        """Wakes the loop after a signal (the exit code is set already)."""

    # ------------------------------------------------------- registration
    def _start_registering(self) -> None:
        """Register (again): one request now, sent again with a growing delay until a conductor accepts it,
        or ``register_timeout`` passes."""
        if self._registering:
            self._register_again = True  # the request out may have reached a conductor that is gone
            return
        self._registering, self._register_again = True, False
        self._register_deadline = (time.monotonic() + self.register_timeout if self.register_timeout > 0
                                   else None)
        self._retry_delay = 0.05
        self._send_register()

    def _send_register(self) -> None:
        """One registration request: its replies, then its end (after the last reply, or the timeout),
        come back through the queue, in this order."""
        self._attempt += 1
        attempt = self._attempt
        put = self._queue.put
        handler: zenoh.handlers.Callback[zenoh.Reply] = zenoh.handlers.Callback(
            lambda reply: put(Request("registered", reply)), lambda: put(Request("register_end", attempt)))
        self.session.get(self.keys.register_as(self.name), handler, payload=codec.encode("register", self.descriptor()),
                         timeout=self.REGISTER_WAIT)

    def _on_register_reply(self, req: Request) -> None:
        reply: zenoh.Reply = req.item
        if reply.ok is None:
            return  # an error answer: the request is sent again when this one ends
        try:
            msg = codec.decode(self.keys.register_as(self.name), reply.ok.payload, "register_reply")
        except ProtocolError as e:
            self._count_malformed(self.keys.register_as(self.name), e)
            return
        if not msg.accepted:
            log.error("conductor refused registration of %r: %s", self.name, msg.get("reason", ""))
            self._exit_code = 2
            return
        if self._registering:
            self._registering = False
            self._registered_once = True
            self._bind(msg.id)
            log.info("registered as %s", msg.id)

    def _on_register_end(self, req: Request) -> None:
        """A registration request ended: send it again later if no conductor accepted it (or give up once
        ``register_timeout`` passed), or register again if the conductor reappeared meanwhile."""
        if req.item != self._attempt:
            return
        if not self._registering:
            if self._register_again:
                self._start_registering()
            return
        if self._register_deadline is not None and time.monotonic() > self._register_deadline:
            self._registering = False
            if not self._registered_once:
                log.error("no conductor answered on %s", self.keys.register_as(self.name))
                self._exit_code = 3
            return
        self._retry_at = time.monotonic() + self._retry_delay
        self._retry_delay = min(self._retry_delay * 2, 1.0)

    def _on_conductor_alive(self, req: Request) -> None:
        """The conductor's liveliness token: when it appears again (conductor restart, restored link),
        register again."""
        if req.item.kind == zenoh.SampleKind.PUT:
            if self._conductor_seen:
                log.info("conductor (re)appeared: registering again as %s", self.name)
                self._start_registering()
            self._conductor_seen = True

    def _bind(self, model_id: str) -> None:
        """Serve model/<id>/...: a queryable per control operation."""
        if self.model_id == model_id and self._queryables:
            return
        for q in self._queryables:
            q.undeclare()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs
        self.model_id = model_id
        self.model.id = model_id
        self._prefix_len = len(self.keys.model(model_id, ""))
        self._queryables = [self.session.declare_queryable(self.keys.model(model_id, op),
                                                           self._enqueue(op.split("/", 1)[0]))
                            for op in self.CONTROL_OPS]

    # ----------------------------------------------------- control queries
    def _answering(self, handler: Callable[[str, zenoh.Query], bytes]) -> Callable[[Request], None]:
        """The dispatch entry of a control query: ``handler(key, query)`` makes the reply's payload; any
        exception becomes the error reply (:func:`reply_error`); the query is dropped (finalised) after."""

        def answer(req: Request) -> None:
            query: zenoh.Query = req.item
            key = str(query.key_expr)
            try:
                query.reply(query.key_expr, handler(key, query))
            except Exception as e:
                reply_error(query, key, e, self._count_malformed)
            finally:
                query.drop()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs

        return answer

    def _health(self, key: str, query: zenoh.Query) -> bytes:
        check_empty_query(key, query)
        return codec.encode("value_reply", value={"malformed": self.malformed, "pid": os.getpid(),
                                                  "name": self.name, "started": self.started})

    def _params(self, key: str, query: zenoh.Query) -> bytes:
        check_empty_query(key, query)
        return codec.encode("params_reply", params={k: p.describe() for k, p in type(self.model).params.items()})

    def _init(self, key: str, query: zenoh.Query) -> bytes:
        msg = codec.decode(key, query.payload, "init")
        m = self.model
        check_init(key, msg, type(m))  # (before the model is touched: a bad init closed a running model)
        params = resolve_params(type(self.model), msg.params, float(msg.rate))
        if self.initialized:  # a new run on a warm agent (twin serve), or a rejoin: start from a closed model
            self.initialized = False  # (an init that fails leaves it closed: the next one does not close it again)
            close_quietly(m, "before a new init")  # (what the last run left: this run's starts afresh all the same)
            self._new_run()
            # what the last run raised and set after its last step (a release's unbinding, a close's) is not this
            # run's: published with its tick 0, an event fired its triggers
            m._events.clear()
            m._outputs.clear()
        m.scene, m.models, m.rate = msg.scene, msg.models, float(msg.rate)
        m.owned = {(e, a) for e, a in msg.owned}
        self.step_mode = msg.step_mode
        self.rate = float(msg.rate)
        try:
            m.init(params, msg.scene)
        except Exception:
            close_quietly(m, "after a failed init")  # (what it opened before it failed is let go, not opened twice)
            raise
        self.initialized = True
        self._last, self._answered = _NOTHING_ANSWERED, {}  # a new run (or a rejoin) counts ticks afresh
        self._stepped, self._mark = None, None
        self._seen.clear()
        return codec.encode("ack", ok=True)

    def _new_run(self) -> None:
        """Forget what the last run left: telemetry and inputs gathered for it, its free-running clock."""
        self.started = False
        self._readings = Readings()
        self._free_t0, self._free_tick = None, 0

    def _start(self, key: str, query: zenoh.Query) -> bytes:
        msg = codec.decode(key, query.payload, "start")
        m = self.model
        if not self.initialized:  # (acked, it went on to step a model that was never given its scene)
            raise ProtocolError(key, f"start before an init that succeeded: {self.model_id or self.name} has no run")
        m.tick, m.t = msg.tick, msg.t
        m.now = msg.t
        m.start()
        self.started = True
        self._arm_step_mode()
        return codec.encode("ack", ok=True)

    def _stop(self, key: str, query: zenoh.Query) -> bytes:
        codec.decode(key, query.payload, "stop")
        self.started = False
        release(self._mark, self._pub)  # the run's last message stood
        return codec.encode("ack", ok=True)

    def _release(self, key: str, query: zenoh.Query) -> bytes:
        msg, m = codec.decode(key, query.payload, "release"), self.model
        if (msg.entity, msg.attribute) not in m.owned:  # (the asker's error: counted as a malformed request)
            raise ProtocolError(key, f"{self.model_id} does not own {msg.entity}.{msg.attribute}")
        m.now = msg.t
        value, extra = m.release(msg.entity, msg.attribute)
        m.owned.discard((msg.entity, msg.attribute))
        self._readings.handed_on(msg.entity, msg.attribute, value)
        return codec.encode("release_reply", entity=msg.entity, attribute=msg.attribute,
                            value=value, extra=dict(extra or {}))

    def _acquire(self, key: str, query: zenoh.Query) -> bytes:
        msg, m = codec.decode(key, query.payload, "acquire"), self.model
        check_acquire(key, msg, m, self.model_id)
        m.now = msg.t
        m.acquire(msg.entity, msg.attribute, msg.value, msg.extra)
        m.owned.add((msg.entity, msg.attribute))
        self._readings.taken(msg.entity, msg.attribute)
        return codec.encode("ack", ok=True)

    def _rewind(self, key: str, query: zenoh.Query) -> bytes:
        """Back to the checkpoint of the last marked step message, then its ticks up to ``tick`` again (their
        answers were given: nothing is published or answered); the later ticks are as if never stepped."""
        msg, mark = codec.decode(key, query.payload, "rewind"), self._mark
        if mark is None:
            raise ValueError(f"{self.model_id} cannot go back to tick {msg.tick}: no step message marked for it since")
        self._stepped, self._seen = mark.rewind(self.model, msg.tick, self._stepped)
        release(mark, self._pub, msg.tick)
        self._answered = {j: a for j, a in self._answered.items() if j < mark.steps[0][0]}  # that answer is void
        self._mark = None
        return codec.encode("ack", ok=True)

    def _call(self, key: str, query: zenoh.Query) -> bytes:
        """``eval/<name>`` (an evaluator) or ``call/<name>`` (a service)."""
        kind, name = key[self._prefix_len:].split("/", 1)
        table = self._evals if kind == "eval" else self._services
        if name not in table:
            raise KeyError(f"{self.model_id} has no {'evaluator' if kind == 'eval' else 'service'} {name!r}")
        msg = codec.decode(key, query.payload, kind)
        value = getattr(self.model, table[name])(*msg.args, **(msg.get("kwargs") or {}))
        return codec.encode("value_reply", value=value)

    # ---------------------------------------------------------------- steps
    def step(self, tick: int, t: float, dt: float, telemetry: Telemetry, inputs: Inputs
             ) -> tuple[dict[str, Any], list[tuple[str, bytes]]]:
        """Step the model for one tick, publish what it produced (``state/<id>``, ``out/<id>/<name>``,
        ``event/<id>/<name>``) and return the ``step_reply`` with those publications. Never raises: a
        failure in the model's ``step`` is ``status: error`` (``warning`` for :class:`StepWarning`) with
        what it owns still read; a failure outside it (e.g. an output that cannot be encoded) is an error
        reply with nothing published, so the conductor is answered either way."""
        try:
            rep, pubs = self._step_model(tick, t, dt, telemetry, inputs)
            if self._mark is not None:  # a marked message's: published once it stands (release)
                self._mark.held.append((tick, pubs))
            else:
                for key, data in pubs:
                    self._pub(key, data)
        except Exception as e:
            log.exception("step %d failed", tick)
            return {"v": PROTOCOL_VERSION, "type": "step_reply", "tick": tick, "status": "error", "state": {},
                    "outputs": {}, "events": [], "message": f"{type(e).__name__}: {e}", "step_s": 0.0}, []
        return rep, pubs

    def _step_model(self, tick: int, t: float, dt: float, telemetry: Telemetry, inputs: Inputs
                    ) -> tuple[dict[str, Any], list[tuple[str, bytes]]]:
        """Step once; the reply and the publications someone listens to. A service-stepped model's step reply
        carries its state, outputs and events to the conductor (and the run log): they are published again on
        ``state``/``out``/``event`` only while a subscriber matches (a clock-driven model reading them, a viewer),
        so each result crosses the wire once."""
        rep = step_reply(self.model, tick, t, dt, telemetry, inputs)
        return rep, publications(self.keys, self.model_id or self.name, rep, t, self._wanted)

    def _wanted(self, key: str) -> bool:
        """Whether a subscriber matches ``key`` (its publisher declared on first use; a clock-driven or
        free-running model publishes whatever matches: the conductor subscribes to its results)."""
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(key)
        if self.step_mode != "service":
            return True
        matching: bool = pub.matching_status.matching  # type: ignore[attr-defined]  # a property in zenoh 1.x
        return matching

    def _on_step_broadcast(self, req: Request) -> None:
        """The conductor's step broadcast (one tick, or a batch of ticks in ``more``): step every tick that
        has a section for this model, in order, and answer once on done/<id>."""
        sample: zenoh.Sample = req.item
        key = sample.key_expr
        try:
            msg = codec.decode_hot(key, sample.payload, "tick")  # the batch's ticks are checked too
            steps = sections(self.model_id or "", key, msg)
        except ProtocolError as e:
            self._count_malformed(str(key), e)
            return
        if not steps or not self.started:
            return  # not due on these ticks, or one that came after the run's stop (never stepped)
        done_pub = self._done_pub
        assert done_pub is not None  # declared at start, with the subscription
        again = self._answered.get(steps[0][0])
        if again is not None:
            # the same message again (its first tick for this model is one it answered): the conductor lost our
            # answer (its network went down); publish those steps' messages and answer again, without stepping twice
            if self._mark is None or self._mark.steps[0][0] != again.tick:  # (a marked message's are held yet)
                for k, data in again.pubs:
                    self._pub(k, data)
            done_pub.put(again.done)
            return
        try:
            check_sequence(key, steps, self._stepped, self.rate)
        except ProtocolError as e:
            self._count_malformed(str(key), e)
            return
        try:
            until = until_for(self.model_id or "", key, msg)
        except ProtocolError as e:
            self._count_malformed(str(key), e)
            return
        # a checkpoint before a message marked for it; any other message it steps leaves nothing to go back to
        marked = self.model_id in (msg.get("mark") or ()) and type(self.model).rewinds()
        release(self._mark, self._pub)  # the conductor went on: the last marked message stood
        self._mark = Checkpoint.keep(self.model, steps, self._stepped, self._seen) if marked else None
        reps, pubs = step_until(self.step, steps, until, self._seen)
        self._stepped = steps[len(reps) - 1][0]
        stopped = len(reps) < len(steps)
        try:
            data = _pack_answer(_batch(reps, stopped))
        except Exception:  # a result msgpack cannot carry (a model's bug): that tick alone is an error
            data = _pack_answer(_batch([_encodable(r) for r in reps], stopped))
        remember(self._answered, _Answered(steps[0][0], pubs, data))
        done_pub.put(data)

    def _on_clock(self, req: Request) -> None:
        """A clock tick: step once and answer on done/<id> (a repeated or older tick: answer, no step)."""
        sample: zenoh.Sample = req.item
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, "clock")
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        if not self.started:
            return
        done_pub = self._done_pub
        assert done_pub is not None  # declared at start, with the subscription
        if self._last.tick is not None and msg.tick <= self._last.tick:
            # an old or repeated tick (the conductor asks again when our answer got lost): answer, no step
            done_pub.put(self._last.done)
            return
        try:
            check_sequence(key, [(msg.tick, msg.t, msg.dt, [], {}, None)], self._stepped, self.rate)
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        self._stepped = msg.tick
        tel, inputs = self._take_telemetry()
        rep, _ = self.step(msg.tick, msg.t, msg.dt, tel, inputs)
        # tell the conductor how far we are (a replay waits for clock-driven models within clock.max_lag);
        # what the step produced went out on state/out/event already, so the answer leaves it out
        data = _pack_answer({**rep, "state": {}, "outputs": {}, "events": []})
        self._last = _Answered(msg.tick, [], data)
        done_pub.put(data)

    def _free_run(self) -> None:
        """Free running: step if the next step is due (at the init's rate, counted from the start)."""
        assert self._free_t0 is not None
        period = self._free_period
        if time.monotonic() < self._free_t0 + self._free_tick * period:
            return
        tel, inputs = self._take_telemetry()
        tick = self._free_tick
        rep, _ = self.step(tick, tick * period, period, tel, inputs)
        self._free_tick += 1
        if self._done_pub is not None:  # that it stepped, and how (its results went out on state/out/event)
            self._done_pub.put(codec.pack(dict(rep, state={}, outputs={}, events=[])))

    def _arm_step_mode(self) -> None:
        """Subscribe to what the step mode steps on (once; a second start keeps the subscriptions)."""
        s, armed = self.session, {str(sub.key_expr) for sub in self._subscribers}
        if self._done_pub is None:  # (a free-running model's steps are said there too: the conductor counts them)
            self._done_pub = s.declare_publisher(self.keys.done(self.model_id or self.name), congestion_control=BLOCK)
        if self.step_mode == "service" and self.keys.step_all not in armed:
            # (ordered: the broadcast and the messages addressed to this model come on two subscriptions, and a
            # message for tick 219 queued before the one for 187 sent earlier left 187 out of sequence: refused,
            # its answer never given, the run failed at the step timeout; seen once in a loaded CI)
            for key in (self.keys.step_all, self.keys.step_for(self.model_id or self.name)):
                self._subscribers.append(s.declare_subscriber(key, self._enqueue("step", True)))
        elif self.step_mode == "clock" and self.keys.clock not in armed:
            self._subscribers.append(s.declare_subscriber(self.keys.clock, self._enqueue("clock", True)))
            self._subscribe_readings()
        if self.step_mode == "free" and self._free_t0 is None:
            self._free_period = 1.0 / self.rate if self.rate > 0 else 0.01
            self._free_t0 = time.monotonic()
            self._subscribe_readings()

    def _subscribe_readings(self) -> None:
        if self._reading:
            return  # a warm agent's second run keeps its subscriptions
        self._reading = True
        s = self.session
        self._subscribers.append(s.declare_subscriber(self.keys.telemetry("**"), self._enqueue("telemetry", True)))
        self._subscribers.append(s.declare_subscriber(self.keys.state("*"), self._enqueue("state", True)))

    def _on_telemetry(self, req: Request) -> None:
        sample: zenoh.Sample = req.item
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, ("joint_state", "action"))
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        self._readings.telemetry(msg)

    def _on_state(self, req: Request) -> None:
        sample: zenoh.Sample = req.item
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, "state")
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        if msg.model != self.model_id:
            self._readings.state(msg["values"])

    def _take_telemetry(self) -> tuple[Telemetry, Inputs]:
        """The telemetry and inputs gathered since the last step (clock and free modes)."""
        return self._readings.take(self.model.owned)


def open_session(opts: ZenohOptions, register_timeout: float, signalled: Callable[[], bool]) -> zenoh.Session | None:
    """An agent's session, tried a second at a time while no router answers: a signal ends the wait, and so does
    ``register_timeout`` > 0 (None then, said)."""
    session = opts.open_patiently(signalled, register_timeout,  # (said at once: a refused certificate was silent)
                                  waiting=lambda why: log.warning("%s; waiting (Ctrl-C stops)", why))
    if session is None and not signalled():
        log.error("%s", opts.unanswered(register_timeout))
    return session


def resolve_params(model: type[Model], given: dict[str, Any], rate: float | None = None) -> dict[str, Any]:
    """Every parameter ``model`` declares: the scene's value (coerced to its type) or a copy of its default.
    Given the model's ``rate`` (Hz), a ``within_period`` parameter longer than its step period is refused."""
    out = {}
    declared = model.params
    for name, p in declared.items():
        if name in given:
            out[name] = p.coerce(name, given[name])
        elif p.required:
            raise KeyError(f"missing required parameter {name!r}")
        else:
            out[name] = copy.deepcopy(p.default)  # a model may change its params: not the class's
    for name in given:
        if name not in declared:
            raise KeyError(f"unknown parameter {name!r} (declared: {', '.join(declared) or 'none'})")
    for name, p in declared.items():
        v = out[name]
        if rate and p.within_period and isinstance(v, float) and v > (1.0 / rate) * (1 + 1e-9):
            raise ValueError(f"parameter {name!r} is {v:g} s, longer than the model's step period {1.0 / rate:g} s "
                             f"(rate {rate:g} Hz)")
    return out


def sections(mid: str, key: zenoh.KeyExpr, msg: dict[str, Any]) -> list[_Step]:
    """Model ``mid``'s steps in a validated tick message: (tick, t, dt, actions, inputs, joints) each."""
    out = []
    more = msg.get("more")
    for i, body in enumerate((msg, *more) if more is not None else (msg,)):
        sec = body["models"].get(mid)
        if sec is None:
            due = body.get("due")
            if due is None or mid not in due:
                continue
            sec = body.get("shared")
        if sec.__class__ is not dict or sec.get("dt").__class__ not in _NUM \
                or sec.get("actions").__class__ is not list or sec.get("inputs").__class__ is not dict:
            where = "tick" if i == 0 else f"tick.more[{i - 1}]"
            raise ProtocolError(key, f"{where}: the section of {mid} must be {{dt, actions, inputs}}")
        out.append((body["tick"], body["t"], sec["dt"], sec["actions"], sec["inputs"], body.get("joints")))
    return out


def close_quietly(m: Model, when: str) -> None:
    """Close model ``m``; what its close raises is logged, not raised (a model closed twice, one half opened)."""
    try:
        m.close()
    except Exception as e:
        log.warning("close %s failed: %s: %s", when, type(e).__name__, e)


def check_init(key: object, msg: Message, cls: type[Model]) -> None:
    """Raise :class:`ProtocolError` unless ``msg`` (an ``init``) is one a model of class ``cls`` can take: owned
    [entity, attribute] pairs of attributes it can own and entities of the scene, a step mode it has (one it did not
    know subscribed to nothing: it never stepped)."""
    if any(not (isinstance(o, list) and len(o) == 2 and all(isinstance(x, str) for x in o)) for o in msg.owned):
        raise ProtocolError(key, f"init.owned must be [entity, attribute] pairs, got {msg.owned!r:.80}")
    entities = msg.scene.get("entities") if isinstance(msg.scene, dict) else None
    for entity, attribute in msg.owned:  # (as an acquire of them would be refused: every step would fail)
        if attribute not in cls.attributes:
            raise ProtocolError(key, f"init.owned: a {cls.kind} model cannot own attribute {attribute!r} "
                                     f"(of {entity}; it can own: {', '.join(cls.attributes) or 'nothing'})")
        if isinstance(entities, dict) and entity not in entities:
            raise ProtocolError(key, f"init.owned: no entity {entity!r} in this run's scene")
    if msg.step_mode not in cls.step_modes:
        raise ProtocolError(key, f"init.step_mode {msg.step_mode!r} is not one of this model's "
                                 f"({', '.join(cls.step_modes)})")


def check_acquire(key: object, msg: Message, m: Model, who: str | None) -> None:
    """Raise :class:`ProtocolError` unless model ``m`` can take ``msg`` (an ``acquire``): an attribute it can own,
    of an entity of its run's scene (one that is not was acked, and reported in its state), handed over as a value
    (a NaN pose went into the physics world, and came back every step)."""
    if msg.attribute not in type(m).attributes:
        raise ProtocolError(key, f"{who} ({m.kind}) cannot own attribute {msg.attribute!r}")
    entities = m.scene.get("entities") if isinstance(m.scene, dict) else None
    if isinstance(entities, dict) and msg.entity not in entities:
        raise ProtocolError(key, f"no entity {msg.entity!r} in this run's scene")
    why = unusable(msg.attribute, msg.value) if msg.value is not None else None
    if why is not None:
        raise ProtocolError(key, f"{msg.entity}.{msg.attribute} handed over as no value: {why}")


def check_sequence(key: object, steps: list[_Step], after: int | None, rate: float) -> None:
    """Raise :class:`ProtocolError` unless ``steps`` continue the conductor's sequence: each tick after the last
    one stepped (``after``) and after the one before it, a finite time, ``0 < dt <=`` the longest step a model at
    ``rate`` Hz is given (:data:`MAX_STEP_DT`), finite joint values. A step out of sequence is not stepped."""
    max_dt = max(MAX_STEP_DT, 4.0 / rate) if rate > 0 else MAX_STEP_DT
    for tick, t, dt, _, _, joints in steps:
        if after is not None and tick <= after:
            raise ProtocolError(key, f"tick {tick} is out of sequence (this run has stepped up to tick {after})")
        if not math.isfinite(t):
            raise ProtocolError(key, f"tick {tick}: time {t!r} is not finite")
        if not 0.0 < dt <= max_dt:  # NaN fails too
            raise ProtocolError(key, f"tick {tick}: dt {dt!r} is not in (0, {max_dt:g}] s")
        if joints:
            _check_joints(key, tick, joints)
        after = tick


def _check_joints(key: object, tick: int, joints: Any) -> None:
    """A step's joint state: lists of finite numbers, a value per name or none in each field (one that is not, a
    model indexed out of range or paired the wrong values: it is malformed, counted)."""
    names = joints.get("name") if isinstance(joints, dict) else None
    if not isinstance(joints, dict) or not isinstance(names if names is not None else [], list):
        raise ProtocolError(key, f"tick {tick}: joints is not a joint state")
    n = len(names or ())
    for field in ("position", "velocity", "effort"):
        values = joints.get(field)
        if values is None:
            continue
        if not isinstance(values, list):
            raise ProtocolError(key, f"tick {tick}: joints.{field} is not a list")
        if not all(v.__class__ in _NUM and math.isfinite(v) for v in values):
            raise ProtocolError(key, f"tick {tick}: joints.{field} holds a value that is not a finite number")
        if len(values) not in (0, n):  # (as a joint_state message: protocol.messages)
            raise ProtocolError(key, f"tick {tick}: joints.{field} has {len(values)} values for {n} joints")


def check_agent_name(name: str) -> str:
    """``name`` if an agent may be called so; ValueError if not: a key chunk (a ``*`` or ``$*`` in it made the
    agent answer queries meant for other models, a ``/`` never reached the conductor) that does not start with
    ``_`` (the conductor's own names in keys, such as its liveliness token ``alive/_conductor``)."""
    check_name("agent", name)
    if name.startswith("_"):
        raise ValueError(f"invalid agent name {name!r}: names starting with '_' are the conductor's")
    return name


def run_agent(model: Model, name: str | None = None, options: ZenohOptions | None = None,
              register_timeout: float = 0.0) -> int:
    """Run ``model`` as an agent until SIGINT/SIGTERM; returns a process exit code. A model that closed a native
    library which must not be torn down at interpreter exit (``_exit_at_once``: an FMU's) ends the process here."""
    try:
        check_agent_name(name or model.kind)
    except ValueError as e:
        log.error("%s", e)
        return 2
    code = AgentRuntime(model, name or model.kind, options or ZenohOptions(), register_timeout).run()
    if getattr(model, "_exit_at_once", False):
        exit_at_once(code)
    return code


def exit_at_once(code: int) -> None:
    """End the process with ``code`` without the interpreter's teardown (output flushed, logging shut down): a
    pythonfmu unit's library runs C++ teardown when the process exits after Python's, and once in a few dozen
    runs it corrupted the heap and the agent died of SIGABRT instead of exiting 0."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    os._exit(code)
