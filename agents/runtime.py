"""The agent runtime: connects one :class:`~agents.model.Model` to an ensemble over Zenoh.

:func:`run_agent` does everything around the model: liveliness token, registration with retry, the
params -> init -> start handshake, the three step modes (the conductor's step broadcast, an external
clock, free running) at the rate the scene chose, one batched ``state/<id>`` message per step,
handover, evaluators and services, error replies instead of crashes, and a clean exit on SIGINT/SIGTERM.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
import traceback
from typing import Any

from msgpack import packb as _packb

from protocol import codec
from protocol.config import ZenohOptions
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import PROTOCOL_VERSION

from .model import Model, StepWarning

_NUM = (int, float)

log = logging.getLogger("twin.agent")


class AgentRuntime:
    """Connects one :class:`Model` to an ensemble over Zenoh."""

    def __init__(self, model: Model, name: str, options: ZenohOptions, register_timeout: float = 0.0):
        self.model = model
        self.name = name
        self.options = options
        self.keys = Keys(options.ensemble)
        self.register_timeout = register_timeout
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.session = None
        self.model_id: str | None = None
        self.step_mode = "service"
        self.initialized = False
        self.started = False
        self.malformed = 0
        self._queryable = None
        self._clock_sub = None
        self._tele_sub = None
        self._latest_joints = None
        self._pending_actions: list = []
        self._inputs: dict = {}
        self._evals = model.evaluators()
        self._services = model.services()
        self._reregister = threading.Event()
        self._last_pubs: list[tuple[str, bytes]] = []  # what the last step published
        # the last broadcast tick answered: (tick, its publications, its done/<id> payload)
        self._last_step: tuple[int | None, list, bytes] = (None, [], b"")
        self._conductor_seen = False
        self._free_thread = None
        self._publishers: dict[str, Any] = {}

    # ----------------------------------------------------------- plumbing
    def descriptor(self) -> dict:
        m = type(self.model)
        return {
            "name": self.name, "kind": m.kind, "role": m.role, "step_modes": list(m.step_modes),
            "params": {k: p.describe() for k, p in m.params.items()},
            "attributes": list(m.attributes), "outputs": list(m.outputs), "events": list(m.events),
            "evaluators": sorted(self._evals), "services": sorted(self._services),
            "pid": os.getpid(), "host": socket.gethostname(), "telemetry": bool(m.wants_telemetry),
            "reads": list(m.reads), "clock_ack": True, "batch": True,
        }

    def _count_malformed(self, key: str, err: Exception) -> None:
        self.malformed += 1
        log.warning("malformed message on %s: %s (total %d)", key, err, self.malformed)

    def _pub(self, key: str, payload: bytes) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(key)
        pub.put(payload)

    # ------------------------------------------------------- registration
    def register(self) -> bool:
        """Ask the conductor for our id, retrying until one answers (or the timeout passes)."""
        desc = codec.encode("register", self.descriptor())
        deadline = time.monotonic() + self.register_timeout if self.register_timeout > 0 else None
        delay = 0.05
        while not self.stop_event.is_set():
            for reply in self.session.get(self.keys.register, payload=desc, timeout=2.0):
                if reply.ok is None:
                    continue
                try:
                    msg = codec.decode(self.keys.register, reply.ok.payload, "register_reply")
                except ProtocolError as e:
                    self._count_malformed(self.keys.register, e)
                    continue
                if not msg.accepted:
                    log.error("conductor refused registration of %r: %s", self.name, msg.get("reason", ""))
                    raise SystemExit(2)
                self._bind(msg.id)
                log.info("registered as %s", msg.id)
                return True
            if deadline is not None and time.monotonic() > deadline:
                return False
            self.stop_event.wait(delay)
            delay = min(delay * 2, 1.0)
        return False

    CONTROL_OPS = ("health", "params", "init", "start", "stop", "release", "acquire", "eval/*", "call/*")

    def _bind(self, model_id: str) -> None:
        """Serve model/<id>/...: a queryable per control operation."""
        with self.lock:
            if self.model_id == model_id and self._queryable is not None:
                return
            for q in self._queryable or []:
                q.undeclare()
            self.model_id = model_id
            self.model.id = model_id
            self._prefix_len = len(self.keys.model(model_id, ""))
            qs = []
            for op in self.CONTROL_OPS:
                qs.append(self.session.declare_queryable(self.keys.model(model_id, op), self._on_query))
            self._queryable = qs

    def _on_conductor_alive(self, sample) -> None:
        import zenoh

        if sample.kind == zenoh.SampleKind.PUT:
            if self._conductor_seen:
                self._reregister.set()
            self._conductor_seen = True

    # -------------------------------------------------------------- queries
    def _on_query(self, query) -> None:
        key = str(query.key_expr)
        op = key[self._prefix_len:]
        try:
            reply = self._handle_control(key, op, query.payload)
            query.reply(query.key_expr, reply)
        except ProtocolError as e:
            self._count_malformed(key, e)
            query.reply_err(codec.encode("error", kind="ProtocolError", message=str(e)))
        except Exception as e:  # model bugs become error replies, never crashes
            log.exception("error answering %s", key)
            query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e),
                                         traceback=traceback.format_exc(limit=8)))
        finally:
            query.drop()

    def _do_step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> dict:
        m = self.model
        values: dict = {}
        with self.lock:
            # what acquire/release/evaluators emitted since the last step goes out with this one
            outputs, events = m._outputs, m._events
            m.tick, m.t = tick, t
            status = "ok"
            t0 = time.perf_counter()
            try:
                m.step(tick, t, dt, telemetry, inputs)
            except StepWarning as w:
                status, message = "warning", str(w)
            except Exception as e:
                log.exception("step %d failed", tick)
                status, message = "error", f"{type(e).__name__}: {e}"
            step_s = time.perf_counter() - t0
            for ent, attr in m.owned:
                try:
                    values.setdefault(ent, {})[attr] = m.read(ent, attr)
                except Exception as e:
                    status, message = "error", f"read {ent}.{attr}: {e}"
            m._outputs, m._events = {}, []
        mid = self.model_id
        pubs = []
        if values:
            pubs.append((self.keys.state(mid), codec.encode_unchecked(
                "state", {"model": mid, "tick": tick, "t": t, "values": values})))
        for name, value in outputs.items():
            pubs.append((self.keys.out(mid, name), codec.encode_unchecked(
                "out", {"model": mid, "name": name, "tick": tick, "t": t, "value": value})))
        for ev in events:
            pubs.append((self.keys.event(mid, ev["name"]), codec.encode_unchecked(
                "event", {"model": mid, "name": ev["name"], "tick": tick, "t": t, "data": ev["data"]})))
        for key, data in pubs:
            self._pub(key, data)
        self._last_pubs = pubs
        rep = {"v": PROTOCOL_VERSION, "type": "step_reply", "tick": tick, "status": status, "state": values,
               "outputs": outputs, "events": events, "step_s": step_s}
        if status != "ok":
            rep["message"] = message
        return rep

    def _step_or_fail(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> dict:
        """:meth:`_do_step`, or a ``status: error`` reply when the step fails outside the model's own
        ``step`` (e.g. an output that cannot be encoded): the conductor is still answered."""
        try:
            return self._do_step(tick, t, dt, telemetry, inputs)
        except Exception as e:
            log.exception("step %d failed", tick)
            self._last_pubs = []
            return {"v": PROTOCOL_VERSION, "type": "step_reply", "tick": tick, "status": "error", "state": {},
                    "outputs": {}, "events": [], "message": f"{type(e).__name__}: {e}", "step_s": 0.0}

    def _handle_control(self, key: str, op: str, payload) -> bytes:
        m = self.model
        if payload is not None and op in ("params", "health") and len(payload.to_bytes()) > 0:
            codec.decode(key, payload, "query")
        if op == "health":
            return codec.encode("value_reply", value={"malformed": self.malformed, "pid": os.getpid(),
                                                      "name": self.name, "started": self.started})
        if op == "params":
            return codec.encode("params_reply", params={k: p.describe() for k, p in type(m).params.items()})
        if op == "init":
            msg = codec.decode(key, payload, "init")
            with self.lock:
                params = self._resolve_params(msg.params)
                m.scene, m.models, m.rate = msg.scene, msg.models, float(msg.rate)
                m.owned = {(e, a) for e, a in msg.owned}
                self.step_mode = msg.step_mode
                self.rate = float(msg.rate)
                m.init(params, msg.scene)
                self.initialized = True
                self._last_step = (None, [], b"")  # a new run (or a rejoin) counts ticks afresh
            return codec.encode("ack", ok=True)
        if op == "start":
            msg = codec.decode(key, payload, "start")
            with self.lock:
                m.tick, m.t = msg.tick, msg.t
                m.start()
                self.started = True
            self._arm_step_mode()
            return codec.encode("ack", ok=True)
        if op == "stop":
            codec.decode(key, payload, "stop")
            self.started = False
            return codec.encode("ack", ok=True)
        if op == "release":
            msg = codec.decode(key, payload, "release")
            with self.lock:
                if (msg.entity, msg.attribute) not in m.owned:
                    raise KeyError(f"{self.model_id} does not own {msg.entity}.{msg.attribute}")
                value, extra = m.release(msg.entity, msg.attribute)
                m.owned.discard((msg.entity, msg.attribute))
            return codec.encode("release_reply", entity=msg.entity, attribute=msg.attribute,
                                value=value, extra=dict(extra or {}))
        if op == "acquire":
            msg = codec.decode(key, payload, "acquire")
            with self.lock:
                if msg.attribute not in type(m).attributes:
                    raise KeyError(f"{self.model_id} ({m.kind}) cannot own attribute {msg.attribute!r}")
                m.acquire(msg.entity, msg.attribute, msg.value, msg.extra)
                m.owned.add((msg.entity, msg.attribute))
            return codec.encode("ack", ok=True)
        if op.startswith("eval/") or op.startswith("call/"):
            kind, name = op.split("/", 1)
            table = self._evals if kind == "eval" else self._services
            if name not in table:
                raise KeyError(f"{self.model_id} has no {'evaluator' if kind == 'eval' else 'service'} {name!r}")
            msg = codec.decode(key, payload, kind)
            with self.lock:
                fn = getattr(m, table[name])
                value = fn(*msg.args, **(msg.get("kwargs") or {}))
            return codec.encode("value_reply", value=value)
        raise KeyError(f"unknown operation {op!r}")

    def _resolve_params(self, given: dict) -> dict:
        out = {}
        declared = type(self.model).params
        for name, p in declared.items():
            if name in given:
                out[name] = p.coerce(name, given[name])
            elif p.required:
                raise KeyError(f"missing required parameter {name!r}")
            else:
                out[name] = p.default
        for name in given:
            if name not in declared:
                raise KeyError(f"unknown parameter {name!r} (declared: {', '.join(declared) or 'none'})")
        return out

    # ------------------------------------------------------ clock / free
    def _on_broadcast(self, sample) -> None:
        """The conductor's step broadcast (one tick, or a batch of ticks in ``more``): step every tick that
        has a section for this model, in order, and answer once on done/<id>."""
        try:
            key = sample.key_expr
            msg = codec.decode_hot(key, sample.payload, "tick")  # the batch's ticks are checked too
            steps = self._sections(key, msg)
            if not steps:
                return  # not due on these ticks
            if msg["tick"] == self._last_step[0]:
                # the same message again: the conductor lost our answer (its network went down); publish
                # those steps' messages and answer again, without stepping twice
                _, pubs, done = self._last_step
                for k, data in pubs:
                    self._pub(k, data)
                self._done_pub.put(done)
                return
            reps, pubs = [], []
            for tick, t, dt, actions, inputs, joints in steps:  # a failed tick does not end the batch
                reps.append(self._step_or_fail(tick, t, dt, {"joints": joints, "actions": actions}, inputs))
                pubs += self._last_pubs
        except ProtocolError as e:
            self._count_malformed(str(sample.key_expr), e)
            return
        except Exception:
            log.exception("step broadcast failed")
            return
        rep = reps[0]
        if len(reps) > 1:
            rep["more"] = reps[1:]
        data = _packb(rep, **codec._packer_opts)
        self._last_step = (msg["tick"], pubs, data)
        self._done_pub.put(data)

    def _sections(self, key, msg: dict) -> list[tuple]:
        """This model's steps in a validated tick message: (tick, t, dt, actions, inputs, joints) each."""
        mid = self.model_id
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

    def _arm_step_mode(self) -> None:
        if self.step_mode == "service" and getattr(self, "_step_sub", None) is None:
            self._done_pub = self.session.declare_publisher(self.keys.done(self.model_id))
            self._step_sub = self.session.declare_subscriber(self.keys.step_all, self._on_broadcast)
        if self.step_mode == "clock" and self._clock_sub is None:
            self._done_pub = self.session.declare_publisher(self.keys.done(self.model_id))
            self._clock_sub = self.session.declare_subscriber(self.keys.clock, self._on_clock)
        if self.step_mode in ("clock", "free") and self._tele_sub is None:
            self._tele_sub = self.session.declare_subscriber(self.keys.telemetry("**"), self._on_telemetry)
            self._state_sub = self.session.declare_subscriber(self.keys.state("*"), self._on_state)
        if self.step_mode == "free" and self._free_thread is None:
            self._free_thread = threading.Thread(target=self._free_loop, daemon=True, name="free-run")
            self._free_thread.start()

    def _on_telemetry(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, ("joint_state", "action"))
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        with self.lock:
            if msg.mtype == "joint_state":
                self._latest_joints = msg
            else:
                self._pending_actions.append(msg)

    def _on_state(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, "state")
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        if msg.model == self.model_id:
            return
        with self.lock:
            for ent, attrs in msg["values"].items():
                if isinstance(attrs, dict):
                    self._inputs.setdefault(ent, {}).update(attrs)

    def _take_telemetry(self) -> tuple[dict, dict]:
        with self.lock:
            tel = {"joints": self._latest_joints, "actions": self._pending_actions}
            self._pending_actions = []
            inputs = {e: dict(a) for e, a in self._inputs.items()}
        return tel, inputs

    def _on_clock(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, "clock")
        except ProtocolError as e:
            self._count_malformed(key, e)
            return
        if not self.started:
            return
        if self._last_step[0] is not None and msg.tick <= self._last_step[0]:
            # an old or repeated tick (the conductor asks again when our answer got lost): answer, no step
            self._done_pub.put(self._last_step[2])
            return
        tel, inputs = self._take_telemetry()
        rep = self._step_or_fail(msg.tick, msg.t, msg.dt, tel, inputs)
        # tell the conductor how far we are (a replay waits for clock-driven models within clock.max_lag);
        # what the step produced went out on state/out/event already, so the answer leaves it out
        data = _packb({**rep, "state": {}, "outputs": {}, "events": []}, **codec._packer_opts)
        self._last_step = (msg.tick, [], data)
        self._done_pub.put(data)

    def _free_loop(self) -> None:
        period = 1.0 / self.rate if self.rate > 0 else 0.01
        tick = 0
        t0 = time.monotonic()
        while not self.stop_event.is_set():
            if self.started:
                tel, inputs = self._take_telemetry()
                self._do_step(tick, tick * period, period, tel, inputs)
                tick += 1
            nxt = t0 + tick * period
            self.stop_event.wait(max(0.0, nxt - time.monotonic()) if self.started else 0.05)

    # ------------------------------------------------------------- main
    EXIT_GRACE = 5.0  # seconds a stop request may take before the process exits regardless

    def _on_signal(self, *_):
        """Stop cleanly; and if closing hangs (e.g. the router is gone mid-close), exit anyway after
        ``EXIT_GRACE`` seconds: an agent must never outlive its launcher."""
        if not self.stop_event.is_set():
            self.stop_event.set()
            t = threading.Timer(self.EXIT_GRACE, lambda: os._exit(0))
            t.daemon = True
            t.start()

    def run(self) -> int:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        self.session = self.options.open()
        try:
            # serve model/<name>/** before registering: the conductor queries it as soon as it answers
            self._bind(self.name)
            token = self.session.liveliness().declare_token(self.keys.alive(self.name))
            watch = self.session.liveliness().declare_subscriber(
                self.keys.alive("_conductor"), self._on_conductor_alive, history=True)
            if not self.register():
                log.error("no conductor answered on %s", self.keys.register)
                return 3
            while not self.stop_event.is_set():
                if self._reregister.wait(0.2):
                    self._reregister.clear()
                    log.info("conductor (re)appeared: registering again as %s", self.name)
                    self.register()
            del token, watch
            return 0
        finally:
            with self.lock:
                try:
                    self.model.close()
                except Exception:
                    log.exception("close failed")
            self.session.close()


def run_agent(model: Model, name: str | None = None, options: ZenohOptions | None = None,
              register_timeout: float = 0.0) -> int:
    """Run ``model`` as an agent until SIGINT/SIGTERM; returns a process exit code."""
    return AgentRuntime(model, name or model.kind, options or ZenohOptions(), register_timeout).run()
