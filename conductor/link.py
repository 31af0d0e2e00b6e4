"""The conductor's side of the wire: everything it declares on Zenoh, and every way it talks to agents.

Zenoh calls back on its own threads. The callbacks here only decode and queue, never act on the run:

- registrations and liveliness changes, and what clock-driven and free-running models publish, go into
  :attr:`AgentLink.inbox` as typed items (:class:`Registered`, :class:`Liveliness`, :class:`Published`),
  which the tick loop takes in at points of its own choosing (:mod:`conductor.registry`);
- ``done/<id>`` answers go to the ``on_done`` callable given to :meth:`AgentLink.serve` (the stepper's queue
  and the clock gate);
- the register queryable answers at once, asking ``admit`` (thread-safe) whether the name may be taken;
- ``conductor/status`` answers from ``status`` (a snapshot), ``conductor/stop`` calls ``stop`` (which only
  sets an event).

Queries to agents (:meth:`AgentLink.ask`) return a validated message or raise :class:`AgentError` (the agent
answered with an error), :class:`AgentTimeout` (no answer in time), :class:`AgentLost` (no agent serves the key)
or :class:`ProtocolError` (the answer was malformed).
Malformed messages are counted by key, logged, and never stop the conductor.
"""
from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import zenoh

from protocol import codec
from protocol.errors import AgentError, AgentLost, AgentTimeout, ProtocolError, RunAborted
from protocol.keys import CONDUCTOR, Keys, check_name
from protocol.messages import Message

log = logging.getLogger("twin.conductor")


# ----------------------------------------------------------------------------------- inbound items
@dataclass(frozen=True)
class Registered:
    """An agent registered (the register queryable already accepted it)."""

    name: str
    desc: dict[str, Any]


@dataclass(frozen=True)
class Liveliness:
    """An agent's liveliness token appeared (``alive``) or vanished."""

    name: str
    alive: bool


@dataclass(frozen=True)
class Published:
    """A clock-driven or free-running model published ``state``/``out``/``event`` (service-stepped models
    report in their step replies instead, which keeps the run deterministic)."""

    model: str
    msg: Message


@dataclass(frozen=True)
class Answered:
    """A step answer came from an agent that the loop no longer waits for (it was too late)."""

    name: str


@dataclass
class ServiceCall:
    """A client called ``conductor/trigger/<name>`` with ``args``: the loop fires the scene's triggers on
    ``{service: name}`` between two ticks and answers with what they did (:meth:`answer`), or refuses with the
    reason (:meth:`refuse`). The query is kept open until then."""

    name: str
    args: dict[str, Any]
    query: Any
    record: Callable[[str, bytes], None] | None = None  # the run log's, for the answer
    deadline: float | None = None  # (monotonic) when its caller stops waiting: not fired after that

    def expired(self) -> bool:
        """Whether the caller has stopped waiting: a call the run takes too late is refused, never fired (the
        caller was told that nothing answered)."""
        return self.deadline is not None and time.monotonic() > self.deadline

    def answer(self, value: Any) -> None:
        self._close(codec.encode("value_reply", value=value), ok=True)

    def refuse(self, reason: str) -> None:
        self._close(codec.encode("error", kind="Refused", message=reason), ok=False)

    def _close(self, payload: bytes, ok: bool) -> None:
        try:
            if self.record is not None:
                self.record(reply_key(str(self.query.key_expr)), payload)
            if ok:
                self.query.reply(self.query.key_expr, payload)
            else:
                self.query.reply_err(payload)
        except Exception:  # the caller gave up waiting: nothing to tell
            log.warning("could not answer the service call %s", self.name)
        finally:
            self.query.drop()


Inbound = Registered | Liveliness | Published | Answered | ServiceCall


def call_deadline(timeout: str | None) -> float | None:
    """When a service call whose caller waits ``timeout`` seconds (the selector's ``?timeout=``, as ``twin trigger``
    sends it) must have been taken to be fired: a margin before the caller stops waiting, for the answer's way
    back (None: no timeout given, the call waits for the run). ValueError for a timeout that is no number > 0."""
    if timeout is None:
        return None
    try:
        wait = float(timeout)
    except ValueError:
        wait = math.nan
    if not (math.isfinite(wait) and wait > 0):
        raise ValueError(f"?timeout={timeout}: give the seconds the caller waits, a number above 0")
    return time.monotonic() + wait - min(0.5, wait / 4)


UNLOGGED = frozenset({"health"})
"""Queries to a model the run log leaves out: they change nothing."""


def reply_key(key: str) -> str:
    """Where the run log keeps the answer to a query of ``key``: ``.../model/<id>/<op>`` -> ``.../reply/<id>/<op>``,
    ``.../conductor/<op>`` -> ``.../reply/conductor/<op>``."""
    head, sep, tail = key.partition("/model/")
    if sep:
        return f"{head}/reply/{tail}"
    head, sep, tail = key.partition("/conductor/")
    return f"{head}/reply/conductor/{tail}" if sep else key + "/reply"


class AgentLink:
    """Queries, publications and declarations of one conductor on one ensemble.

    ``network_mode`` is the conductor's own Zenoh mode: a client or peer conductor can lose the network
    itself (:meth:`cut_off`); the embedded router's conductor never does.
    """

    LOST_RETRY = 0.2
    """Seconds between two queries to an agent that is gone, while :meth:`ask` waits for it (``lost_wait``)."""

    def __init__(self, session: Any, keys: Keys, *, step_timeout: float = 10.0,
                 on_event: Callable[[str, dict[str, Any]], None] | None = None,
                 network_mode: str | None = None, clock: Any = None) -> None:
        self.session = session
        self.keys = keys
        self._step_to = keys.step_all + "/"  # the step messages addressed to some models (Keys.step_to)
        self.step_timeout = step_timeout
        self.on_event = on_event or (lambda kind, data: None)
        self.network_mode = network_mode
        self.inbox: queue.SimpleQueue[Inbound] = queue.SimpleQueue()
        self.malformed = 0
        self.malformed_by_key: dict[str, int] = {}
        self.silent: set[str] = set()  # models a query timed out on, or found gone (asked, and no answer in time)
        self.clock = clock  # its .tick is named in AgentErrors
        self._publishers: dict[str, Any] = {}
        self._decl: list[Any] = []
        self._record: Callable[[str, bytes], None] | None = None
        self._take: Callable[[str, bytes], None] | None = None  # the run log's: step messages and answers
        self.held: set[str] = set()  # models whose answers reach the run log through log_answers only
        self._lock = threading.Lock()
        self._dead: set[str] = set()
        self._lapsed: set[str] = set()  # whose token vanished since they last registered: a new process may take over

    # ------------------------------------------------------------------------------- serving
    def serve(self, *, admit: Callable[[Message, bool], str | None], status: Callable[[], dict[str, Any]],
              stop: Callable[[], None], on_done: Callable[[str, dict[str, Any]], None], async_models: frozenset[str],
              run_log: Any = None, source: Any = None) -> None:
        """Declare the conductor's queryables, subscriptions and liveliness token.

        Refuses (:class:`RunAborted`) when the ensemble already has a conductor. ``admit(register_msg, lapsed)``
        returns None to accept a registration or the reason to refuse it (``lapsed``: the name's liveliness token
        vanished since it last registered); ``async_models`` are the models whose
        ``state``/``out``/``event`` publications are taken in (the clock-driven and free-running ones);
        a live ``source`` hands the run log the telemetry it hears (:meth:`~conductor.sources.live.LiveSource.log_to`),
        what came before the log opened included (a subscription of the log's own would miss that)."""
        s, k = self.session, self.keys
        others = [r for r in s.liveliness().get(k.alive(CONDUCTOR), timeout=2.0) if r.ok is not None]
        if others:  # two conductors on one ensemble would step, and hand over, the same agents
            raise RunAborted(f"ensemble {k.ensemble!r} already has a conductor on this network: stop it, or run "
                             "this one with another ensemble name (--ensemble)")
        self._admit, self._status, self._stop, self._on_done = admit, status, stop, on_done
        self._async_models = async_models
        self._done_prefix_len = len(k.done(""))
        self._prefix_len = len(k.prefix) + 1
        self._telemetry = k.telemetry("")
        self._record = run_log.record if run_log is not None else None  # queries and their replies too
        self._take = run_log.take if run_log is not None else None
        heard = getattr(source, "log_to", lambda *_: False)(run_log.take if run_log is not None else None,
                                                             self._telemetry)
        if run_log is not None:  # everything but service models' state/out/event: their step answers carry those
            # (the step answers come from the stepper's subscription, this conductor's step messages from publish:
            # one Python callback less per message; a step message from another process is still logged)
            # (a replay's telemetry republished by the conductor comes from publish too: it goes to other sessions
            # only, so this subscription takes another process's, or a live source's in this one)
            self._decl.append(s.declare_subscriber(k.step_all, run_log.on_sample, allowed_origin=zenoh.Locality.REMOTE))
            for key in (k.clock, k.ownership, *([] if heard else [k.telemetry("**")]), k.event(CONDUCTOR, "*"),
                        *(x for m in sorted(async_models) for x in (k.state(m), k.out(m, "*"), k.event(m, "*")))):
                self._decl.append(s.declare_subscriber(key, run_log.on_sample))
        self._decl.append(s.declare_queryable(k.register, self._on_register))
        for op in ("start", "stop", "status"):
            self._decl.append(s.declare_queryable(k.conductor(op), self._on_control))
        self._decl.append(s.declare_queryable(k.conductor("trigger/*"), self._on_trigger))
        self._decl.append(s.liveliness().declare_subscriber(k.alive_all, self._on_alive, history=True))
        self._decl.append(s.liveliness().declare_token(k.alive(CONDUCTOR)))
        self._decl.append(s.declare_subscriber(k.done("*"), self._on_done_sample))
        for m in sorted(async_models):  # a service model's results come in its step answers
            for sub_key in (k.state(m), k.out(m, "*"), k.event(m, "*")):
                self._decl.append(s.declare_subscriber(sub_key, self._on_published))

    def close(self) -> None:
        """Undeclare everything :meth:`serve` and :meth:`publish` declared; refuse the service calls the run did not
        take (they came after its last look at its inbox: their callers would wait for their own timeout)."""
        while True:
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, ServiceCall):
                item.refuse("not fired: the run ended before it could take the call")
        for d in [*self._decl, *self._publishers.values()]:
            try:
                d.undeclare()
            except Exception:  # the session may be closing: nothing left to undeclare
                pass
        self._decl, self._publishers = [], {}

    # --------------------------------------------------------------------------- callbacks
    def count_malformed(self, key: str, err: Exception) -> None:
        with self._lock:
            self.malformed += 1
            self.malformed_by_key[key] = self.malformed_by_key.get(key, 0) + 1
            n = self.malformed
        log.warning("malformed message #%d on %s: %s", n, key, err)

    def refused(self, name: str) -> int | None:
        """How many messages agent ``name`` has refused so far (malformed, or steps out of the conductor's
        sequence: see ``agents.runtime.check_sequence``); None if it does not answer."""
        try:
            reply = self.ask(name, "health", codec.encode("query"), "value_reply", timeout=2.0)
        except (AgentError, ProtocolError):
            return None
        n = reply.value.get("malformed") if isinstance(reply.value, dict) else None
        return n if isinstance(n, int) else None

    def _on_register(self, query: Any) -> None:
        key = str(query.key_expr)
        with query:
            try:
                msg = codec.decode(key, query.payload, "register")
            except ProtocolError as e:
                self.count_malformed(key, e)
                query.reply_err(codec.encode_error(e))
                return
            try:
                check_name("agent", msg.name)
                claimed = key.rsplit("/", 1)[-1]
                with self._lock:
                    lapsed = msg.name in self._lapsed
                reason = (f"registration on {key} names model {msg.name!r}: a model registers on "
                          f"conductor/register/<its name>" if claimed != msg.name else self._admit(msg, lapsed))
            except ValueError as e:
                reason = str(e)
            if reason is not None:
                log.warning("refused registration: %s", reason)
                query.reply(key, codec.encode("register_reply", id="", accepted=False, reason=reason))
                return
            with self._lock:
                self._lapsed.discard(msg.name)
            query.reply(key, codec.encode("register_reply", id=msg.name, accepted=True))
            if self._record is not None:  # what it declared (parameters, attributes, services...) goes in the log
                self._record(key, query.payload.to_bytes())
            self.inbox.put(Registered(msg.name, dict(msg)))

    def _on_alive(self, sample: Any) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if name.startswith("_"):  # (the conductor's own, a listener's: no model's name starts so)
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:  # seen at once by a step or a clock gate waiting for this model
            (self._dead.discard if alive else self._dead.add)(name)
            if not alive:
                self._lapsed.add(name)
        self.inbox.put(Liveliness(name, alive))

    def gone(self, names: Any) -> set[str]:
        """Which of ``names`` have no liveliness token right now (thread-safe)."""
        with self._lock:
            return self._dead.intersection(names)

    def _on_published(self, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, ("state", "out", "event"))
        except ProtocolError as e:
            self.count_malformed(key, e)
            return
        sender = key[self._prefix_len:].split("/", 2)[1:2]  # state/<id>, out/<id>/<name>, event/<id>/<name>
        if sender != [msg.model]:  # a model writes only as itself: the key is what access control vouches for
            self.count_malformed(key, ProtocolError(key, f"a message of model {msg.model!r} on another model's key"))
        elif msg.model in self._async_models:
            self.inbox.put(Published(msg.model, msg))

    def _on_done_sample(self, sample: Any) -> None:
        """Decoded in Zenoh's thread (in parallel with the tick loop), handed on at once (and to the run log)."""
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()  # once, for the run log and the decoder
        if self._take is not None and key[self._done_prefix_len:] not in self.held:
            self._take(key, data)
        try:
            rep = codec.decode_hot(key, data, "step_reply")
        except ProtocolError as e:
            self.count_malformed(key, e)
            return
        self._on_done(key[self._done_prefix_len:], rep)

    def _on_control(self, query: Any) -> None:
        key = str(query.key_expr)
        op = key.rsplit("/", 1)[-1]
        with query:
            try:
                if query.payload is not None and len(query.payload.to_bytes()) > 0:
                    codec.decode(key, query.payload, ("control", "stop", "query"))
            except ProtocolError as e:
                self.count_malformed(key, e)
                query.reply_err(codec.encode_error(e))
                return
            try:
                if op == "stop":
                    self._stop()
                    query.reply(key, codec.encode("ack", ok=True, message="stopping"))
                elif op == "start":
                    running = bool(self._status().get("running"))
                    query.reply(key, codec.encode("ack", ok=True, message="running" if running else "starting"))
                else:
                    query.reply(key, codec.encode("status", {"fields": self._status()}))
            except Exception as e:  # never leave a query unanswered
                log.exception("%s failed", key)
                query.reply_err(codec.encode_error(e))

    def _on_trigger(self, query: Any) -> None:
        """``conductor/trigger/<name>``: queued for the loop (which answers), or refused now if no run goes."""
        key = str(query.key_expr)
        try:
            args: dict[str, Any] = {}
            if query.payload is not None and len(query.payload.to_bytes()) > 0:
                args = dict(codec.decode(key, query.payload, ("control", "query")).get("args") or {})
            if query.parameters.get("run") is not None:  # (twin trigger --run: meant for a twin serve)
                raise ValueError(f"this is the conductor of one run (ensemble {self.keys.ensemble!r}), not a twin "
                                 "serve: call without --run")
            deadline = call_deadline(query.parameters.get("timeout"))
            status = self._status()
            if not status.get("running"):  # a service trigger fires between two ticks of a run
                raise ValueError("the run has ended: a service trigger fires while a run ticks" if status.get("ended")
                                 else "the run has not begun to tick yet (it waits for its agents or, live, for the "
                                      "robot's first message): call again when it has")
        except (ProtocolError, ValueError) as e:
            if isinstance(e, ProtocolError):
                self.count_malformed(key, e)
            with query:
                query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e)))
            return
        if self._record is not None:
            self._record(key, codec.encode("control", args=args))
        self.inbox.put(ServiceCall(key.rsplit("/", 1)[-1], args, query, self._record, deadline))

    # ----------------------------------------------------------------------------- talking
    def publish(self, key: str, payload: bytes) -> None:
        """Put ``payload`` on ``key`` through a publisher declared once per key. The step broadcast and a replay's
        telemetry go to the run log directly and on the wire to other processes only: delivered to this session's
        own subscriber, each took a Python callback, and the tick loop waited for the interpreter to come back
        from it."""
        step = key == self.keys.step_all or key.startswith(self._step_to)
        take = self._take if self._take is not None and (step or key.startswith(self._telemetry)) else None
        pub = self._publishers.get(key)
        if pub is None:
            # the step broadcast and the clock are waited on, and a clock-driven model steps on a replay's
            # telemetry: under congestion they wait for room, never dropped (Zenoh's default for a publication),
            # which would cost a step timeout and the model, or a tick stepped on stale joints
            block = step or key == self.keys.clock or key.startswith(self._telemetry)
            pub = self._publishers[key] = self.session.declare_publisher(
                key, allowed_destination=zenoh.Locality.REMOTE if take is not None else None,
                congestion_control=zenoh.CongestionControl.BLOCK if block else None)
        if take is not None:  # (they go to other sessions only: the run log's own subscriptions do not get them)
            take(self.keys.step_all if step else key, payload)  # one topic for every step message
        pub.put(payload)

    def log_answers(self, model: str, replies: Mapping[int, Mapping[str, Any]]) -> None:
        """Into the run log, the answers of a :attr:`held` model that stand (a model stepped on past the end of a
        window goes back to it: its answers after that end were never taken), as one answer on its channel."""
        if self._take is None or not replies:
            return
        reps = [{k: v for k, v in replies[j].items() if k not in ("more", "stopped")}
                for j in sorted(replies)]
        first = reps[0]
        if len(reps) > 1:
            first["more"] = reps[1:]
        self._take(self.keys.done(model), codec.encode_unchecked("step_reply", first))

    def event(self, name: str, data: dict[str, Any], tick: int, t: float) -> None:
        """Publish one of the conductor's own events (``event/_conductor/<name>``) and tell the hook."""
        payload = codec.encode("event", model=CONDUCTOR, name=name, tick=tick, t=t, data=data)
        self.publish(self.keys.event(CONDUCTOR, name), payload)
        self.on_event(name, data)

    def ask(self, model: str, op: str, payload: bytes, expect: str, timeout: float | None = None,
            lost_wait: float = 0.0) -> Message:
        """Query ``model/<model>/<op>`` and return its validated answer of type ``expect``. No answer is
        :class:`AgentTimeout` when Zenoh ended the query with its timeout reply, :class:`AgentLost` when it ended
        without any reply (no agent serves the key: Zenoh ends a query at once when nothing matches it). With
        ``lost_wait``, an agent that is gone is asked again every 0.2 s for up to that long (a link that lapsed
        comes back: before a run, nothing is lost by waiting for it)."""
        deadline = time.monotonic() + lost_wait
        warned = False
        while True:  # bounded by the deadline: each round takes LOST_RETRY at least
            try:
                return self._ask_once(model, op, payload, expect, timeout)
            except AgentLost as e:
                if time.monotonic() + self.LOST_RETRY > deadline:
                    self.silent.add(model)
                    raise
                if not warned:
                    log.warning("%s; asking again every %g s for up to %.0f s", e, self.LOST_RETRY, lost_wait)
                    warned = True
                time.sleep(self.LOST_RETRY)

    def _ask_once(self, model: str, op: str, payload: bytes, expect: str, timeout: float | None) -> Message:
        key = self.keys.model(model, op)
        timeout = timeout or self.step_timeout
        record = self._record if op not in UNLOGGED else None
        if record is not None:
            record(key, payload)
        replies = self.session.get(key, payload=payload, timeout=timeout)
        timed_out = False
        result: Message | None = None
        failure: Exception | None = None
        for reply in replies:  # drain every reply, keep the first
            if result is not None or failure is not None:
                continue
            if reply.ok is None and reply.err.payload.to_bytes() == codec.ZENOH_TIMEOUT:
                timed_out = True  # Zenoh's own: the query timed out (not an agent's answer, nor a malformed one)
                continue
            if record is not None:
                record(reply_key(key), (reply.ok if reply.ok is not None else reply.err).payload.to_bytes())
            if reply.ok is not None:
                try:
                    result = codec.decode(key, reply.ok.payload, expect)
                except ProtocolError as e:
                    self.count_malformed(key, e)
                    failure = e
                continue
            try:
                err = codec.decode(key, reply.err.payload, "error")
                failure = AgentError(model, key, self._tick(), err.kind, err.message, err.get("traceback", ""))
            except ProtocolError as e:
                self.count_malformed(key, e)
                failure = AgentError(model, key, self._tick(), "error", "undecodable error reply")
        if failure is not None:
            raise failure
        if result is None:
            if timed_out:
                self.silent.add(model)
                raise AgentTimeout(model, key, self._tick(), timeout)
            raise AgentLost(model, key, self._tick())  # ended without a word: nothing served the key
        return result

    def _tick(self) -> int | None:
        return None if self.clock is None else int(self.clock.tick)

    def cut_off(self, grace: float = 0.0) -> bool:
        """Has this conductor itself lost the network (no router and no peer left)? With ``grace``, keep
        looking that long: a vanished router's liveliness withdrawals can arrive before its link is seen
        closed."""
        if self.network_mode not in ("client", "peer"):
            return False
        info = self.session.info
        deadline = time.monotonic() + grace
        while True:
            if not list(info.routers_zid()) and not list(info.peers_zid()):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
