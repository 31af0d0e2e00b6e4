"""The conductor: registry, handshake, multi-rate tick loop, responsibility map, handover,
triggers, fallback on agent loss, run log and run summary (DESIGN.md sections 4 to 6)."""
from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from typing import Any, Callable

import numpy as np
import zenoh

from protocol import codec
from protocol.errors import ProtocolError, RemoteError, SceneError, TwinError
from protocol.geometry import inside_container
from protocol.keys import Keys

from .runlog import RunLog
from .scene import Scene
from .scene.expr import ExprError

log = logging.getLogger("twin.conductor")

CONDUCTOR = "_conductor"


@dataclass
class AgentInfo:
    name: str
    desc: dict
    alive: bool = True
    ready: bool = False
    registered_at: float = 0.0
    rejoin_pending: bool = False
    steps: int = 0
    step_s: float = 0.0
    errors: int = 0
    last_error: str = ""
    failed: int = 0  # steps that raised (status "error"; warnings are only counted in errors)


@dataclass
class Handover:
    tick: int
    t: float
    entity: str
    attribute: str
    src: str
    dst: str
    trigger: str
    variables: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"tick": self.tick, "t": round(self.t, 6), "entity": self.entity, "attribute": self.attribute,
                "from": self.src, "to": self.dst, "trigger": self.trigger, "variables": self.variables}


class RunAborted(TwinError):
    pass


class Conductor:
    """Runs one scene on one ensemble.

    ``session`` is an open Zenoh session (the embedded router's own session in ``twin run``).
    ``source`` is a ReplaySource or LiveSource (or None: run ``max_ticks`` ticks without telemetry).
    """

    def __init__(self, scene: Scene, session, keys: Keys, source=None, *, run_log: str | None = None,
                 rtf: float | None = None, max_ticks: int | None = None, step_timeout: float = 10.0,
                 register_timeout: float = 60.0, on_event: Callable[[str, dict], None] | None = None,
                 metadata: dict | None = None, progress: Callable[[dict], None] | None = None,
                 network_mode: str | None = None,
                 network_timeout: float = 30.0):
        self.scene = scene
        self.session = session
        self.keys = keys
        self.source = source
        self.rtf = rtf
        self.max_ticks = max_ticks
        self.step_timeout = step_timeout
        self.register_timeout = register_timeout
        self.on_event = on_event or (lambda kind, data: None)
        self.progress = progress
        self.agent_check: Callable[[set], None] | None = None
        # a client/peer conductor can lose the network itself: then vanished agents are not dead
        self.network_mode = network_mode
        self.network_timeout = network_timeout
        self.network_down = False
        self._network_down_at = 0.0
        self._done_q: queue.SimpleQueue = queue.SimpleQueue()
        self._model_order = list(scene.models)
        self._dead_now: set[str] = set()
        self._done_prefix_len = len(keys.done(""))
        # clock-driven models answer each clock tick on done/<id>: how far each got, and how far behind
        # it fell (a replay waits for them within scene.max_lag; a live run only reports the lag)
        self._clock_models = frozenset(n for n, m in scene.models.items() if m.step == "clock")
        self._clock_done: dict[str, int] = {}
        self._clock_evt = threading.Event()
        self._clock_lag: dict[str, dict] = {}
        self._clock_behind: set[str] = set()  # waited for in vain: not waited for again until caught up
        self._last_clock: bytes | None = None
        self.dt = 1.0 / scene.rate
        self.agents: dict[str, AgentInfo] = {}
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.owners: dict[tuple[str, str], str] = scene.initial_owners()
        self.values: dict[tuple[str, str], Any] = {}
        for e in scene.entities.values():
            self.values[(e.name, "pose")] = list(e.pose)
        self.outputs: dict[tuple[str, str], Any] = {}
        self.event_counts: dict[tuple[str, str], int] = {}
        self.version = 0
        self.tick = 0
        self.t = 0.0
        self.handovers: list[Handover] = []
        self.trigger_log: list[dict] = []
        self.malformed = 0
        self.malformed_by_key: dict[str, int] = {}
        self.unauthorized_writes = 0
        self.errors: list[str] = []
        self.invariant_violations = 0
        self.stop_requested = threading.Event()
        self.running = False
        self.wall_s = 0.0
        self.run_log_path = run_log
        self.run_log: RunLog | None = RunLog(run_log, metadata) if run_log else None
        self._pending_actions: dict[str, list] = {m: [] for m in scene.models}
        self.latest_joints: dict | None = None
        self._publishers: dict[str, Any] = {}
        self._decl: list = []
        self._fired_once: set[str] = set()
        self._tick_times: list[float] = []
        self._declare()

    # ----------------------------------------------------------------- network
    def _declare(self) -> None:
        s, k = self.session, self.keys
        if self.run_log:
            self._decl.append(s.declare_subscriber(k.everything, self.run_log.on_sample))
        self._decl.append(s.declare_queryable(k.register, self._on_register))
        for op in ("start", "stop", "status"):
            self._decl.append(s.declare_queryable(k.conductor(op), self._on_control))
        self._decl.append(s.liveliness().declare_subscriber(k.alive_all, self._on_alive, history=True))
        self._decl.append(s.liveliness().declare_token(k.alive(CONDUCTOR)))
        self._decl.append(s.declare_subscriber(k.done("*"), self._on_done))
        for sub_key in (k.state("*"), k.out("*", "*"), k.event("*", "*")):
            self._decl.append(s.declare_subscriber(sub_key, self._on_async))

    def _pub(self, key: str, payload: bytes) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(key)
        pub.put(payload)

    def _malformed(self, key: str, err: Exception) -> None:
        self.malformed += 1
        self.malformed_by_key[key] = self.malformed_by_key.get(key, 0) + 1
        log.warning("malformed message #%d on %s: %s", self.malformed, key, err)

    def _on_register(self, query) -> None:
        key = str(query.key_expr)
        with query:
            try:
                msg = codec.decode(key, query.payload, "register")
            except ProtocolError as e:
                self._malformed(key, e)
                query.reply_err(codec.encode("error", kind="ProtocolError", message=str(e)))
                return
            name = msg.name
            try:
                from protocol.keys import check_name
                check_name("agent", name)
            except ValueError as e:
                query.reply(key, codec.encode("register_reply", id="", accepted=False, reason=str(e)))
                return
            if msg.role == "observer" and msg.attributes:
                reason = (f"{name} ({msg.kind}) is an observer but declares attributes {list(msg.attributes)}: "
                          "an observer owns nothing")
                log.warning("refused registration: %s", reason)
                query.reply(key, codec.encode("register_reply", id="", accepted=False, reason=reason))
                return
            prev = self.agents.get(name)
            same = prev is not None and prev.desc.get("pid") == msg.get("pid") and prev.desc.get("host") == msg.get("host")
            if prev is not None and prev.alive and prev.ready and not same:
                reason = f"a live agent already holds the name {name!r} (pid {prev.desc.get('pid')} on {prev.desc.get('host')})"
                log.warning("refused registration: %s", reason)
                query.reply(key, codec.encode("register_reply", id="", accepted=False, reason=reason))
                return
            query.reply(key, codec.encode("register_reply", id=name, accepted=True))
            self.inbox.put(("register", name, dict(msg)))

    def _on_alive(self, sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if name == CONDUCTOR:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        if alive:
            self._dead_now.discard(name)
        else:
            self._dead_now.add(name)  # seen at once by a tick waiting for this model
        self.inbox.put(("alive", name, alive))

    def _on_async(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = codec.decode(key, sample.payload, ("state", "out", "event"))
        except ProtocolError as e:
            self._malformed(key, e)
            return
        spec = self.scene.models.get(msg.model)
        if spec is None or spec.step == "service":
            return  # service-stepped models report in their step reply (deterministic)
        self.inbox.put(("async", msg.model, msg))

    def _on_control(self, query) -> None:
        key = str(query.key_expr)
        op = key.rsplit("/", 1)[-1]
        with query:
            try:
                if query.payload is not None and len(query.payload.to_bytes()) > 0:
                    codec.decode(key, query.payload, ("control", "stop", "query"))
            except ProtocolError as e:
                self._malformed(key, e)
                query.reply_err(codec.encode("error", kind="ProtocolError", message=str(e)))
                return
            if op == "stop":
                self.stop_requested.set()
                query.reply(key, codec.encode("ack", ok=True, message="stopping"))
            elif op == "start":
                query.reply(key, codec.encode("ack", ok=True, message="running" if self.running else "starting"))
            else:
                try:
                    query.reply(key, codec.encode("status", {"fields": self.status()}))
                except Exception as e:  # never leave a query unanswered
                    log.exception("status failed")
                    query.reply_err(codec.encode("error", kind=type(e).__name__, message=str(e)))

    def status(self) -> dict:
        return {
            "scene": self.scene.name, "ensemble": self.keys.ensemble, "running": self.running,
            "tick": self.tick, "t": self.t, "version": self.version,
            "ownership": self.ownership_map(),
            "agents": {n: {"alive": a.alive, "ready": a.ready, "kind": a.desc.get("kind"),
                           "host": a.desc.get("host"), "pid": a.desc.get("pid"), "steps": a.steps}
                       for n, a in self.agents.items()},
            "handovers": len(self.handovers), "malformed_messages": self.malformed,
        }

    def ownership_map(self) -> dict:
        out: dict[str, dict[str, str]] = {}
        for (e, a), m in sorted(self.owners.items()):
            out.setdefault(e, {})[a] = m
        return out

    # --------------------------------------------------------------- queries
    def _get(self, key: str, payload: bytes, expect: str, timeout: float | None = None) -> dict:
        replies = self.session.get(key, payload=payload, timeout=timeout or self.step_timeout)
        return self._collect(key, replies, expect)

    def _collect(self, key: str, replies, expect: str) -> dict:
        result = None
        for reply in replies:
            if result is not None:
                continue
            ok = reply.ok
            if ok is not None:
                try:
                    result = (codec.decode_hot(key, ok.payload, expect) if expect == "step_reply"
                              else codec.decode(key, ok.payload, expect))
                except ProtocolError as e:
                    self._malformed(key, e)
                    raise
            else:
                try:
                    err = codec.decode(key, reply.err.payload, "error")
                    raise RemoteError(key, err.kind, err.message, err.get("traceback", ""))
                except ProtocolError as e:
                    self._malformed(key, e)
                    raise RemoteError(key, "error", "undecodable error reply") from None
        if result is None:
            raise RemoteError(key, "Timeout", "no reply (agent gone or too slow)")
        return result

    def _event(self, name: str, data: dict) -> None:
        """Publish a conductor event (run log, viewer) and tell the caller's hook."""
        payload = codec.encode("event", model=CONDUCTOR, name=name, tick=self.tick, t=self.t, data=data)
        self._pub(self.keys.event(CONDUCTOR, name), payload)
        self.on_event(name, data)

    # ------------------------------------------------------------ lifecycle
    def _drain_inbox(self, block: float = 0.0) -> None:
        try:
            item = self.inbox.get(timeout=block) if block > 0 else self.inbox.get_nowait()
        except queue.Empty:
            return
        while True:
            self._handle_inbox(item)
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                return

    def _handle_inbox(self, item) -> None:
        kind = item[0]
        if kind == "register":
            _, name, desc = item
            prev = self.agents.get(name)
            if (prev is not None and self.running and prev.ready and prev.desc.get("pid") == desc.get("pid")
                    and prev.desc.get("host") == desc.get("host")):
                # the same process registering again after the network came back: it never left the run
                prev.alive = True
                log.info("%s registered again (same process): still in the run", name)
                return
            info = AgentInfo(name, desc, alive=True, registered_at=time.monotonic())
            if prev is not None and self.running:
                info.rejoin_pending = True
                info.steps, info.step_s = prev.steps, prev.step_s
            self.agents[name] = info
            log.info("registered %s (%s, pid %s on %s)", name, desc.get("kind"), desc.get("pid"), desc.get("host"))
            if info.rejoin_pending:
                self._rejoin(name)
        elif kind == "alive":
            _, name, alive = item
            info = self.agents.get(name)
            if info is None:
                return
            if not alive and info.alive:
                info.alive = False
                if self.running and name in self.scene.models:
                    if self.network_down or self._cut_off(grace=0.5):
                        self._note_network_lost()  # not a death: wait for the network (next tick)
                    else:
                        self._fallback(name)
            elif alive and not info.alive:
                info.alive = True  # registration follows and re-initialises it
        elif kind == "async":
            _, model, msg = item
            self._absorb(model, msg)
        elif kind == "clock_done":
            _, name, rep = item
            info = self.agents.get(name)
            if info is not None:
                self._count_step(info, name, rep["tick"], rep)

    def wait_for_agents(self) -> None:
        need = set(self.scene.models)
        deadline = time.monotonic() + self.register_timeout
        last_report = 0.0
        while True:
            self._drain_inbox(block=0.05)
            have = {n for n, a in self.agents.items() if a.alive}
            missing = need - have
            if not missing:
                return
            if self.stop_requested.is_set():
                raise RunAborted("stopped while waiting for agents")
            now = time.monotonic()
            if now > deadline:
                raise RunAborted(f"agents never registered: {', '.join(sorted(missing))} "
                                 f"(start them with 'twin agent KIND --name NAME')")
            if now - last_report > 5:
                log.info("waiting for agents: %s", ", ".join(sorted(missing)))
                last_report = now
            if self.agent_check is not None:
                self.agent_check(missing)  # the launcher raises if an agent process already died

    def _init_model(self, name: str, owned: list[tuple[str, str]]) -> None:
        spec = self.scene.models[name]
        info = self.agents[name]
        if ":" not in spec.kind and info.desc.get("kind") != spec.kind:
            log.warning("%s: scene asks for kind %r, agent is %r", name, spec.kind, info.desc.get("kind"))
        declared = self._get(self.keys.model(name, "params"), codec.encode("query"), "params_reply").params
        for arg in spec.args:
            if arg not in declared:
                raise SceneError(self.scene.file, self.scene.line("models", name, "args", arg),
                                 f"models.{name}.args.{arg}",
                                 f"unknown parameter {arg!r} of {spec.kind} (it declares: {', '.join(declared) or 'none'})")
        for arg, d in declared.items():
            if d.get("required") and arg not in spec.args:
                raise SceneError(self.scene.file, self.scene.line("models", name), f"models.{name}.args",
                                 f"missing required parameter {arg!r} of {spec.kind}: {d.get('doc', '')}")
        modes = info.desc.get("step_modes", [])
        if spec.step not in modes:
            raise SceneError(self.scene.file, self.scene.line("models", name, "step"), f"models.{name}.step",
                             f"{spec.kind} cannot step in mode {spec.step!r} (it supports: {', '.join(modes)})")
        params = dict(spec.args)
        params.setdefault("_main", self.scene.main) if "_main" in declared else None
        init = codec.encode("init", params=params, scene={"name": self.scene.name, "entities": self.scene.geometry(),
                                                          "main": self.scene.main, "rate": self.scene.rate,
                                                          "robot": self.scene.raw.get("robot") or {}},
                            owned=[list(o) for o in owned], rate=spec.rate, step_mode=spec.step, models={m: s.kind for m, s in self.scene.models.items()})
        self._get(self.keys.model(name, "init"), init, "ack")

    def prepare(self) -> None:
        """Wait for every agent, check ownership against what they declare, init them all."""
        self.wait_for_agents()
        for (e, a), m in self.owners.items():
            desc = self.agents[m].desc
            if a not in desc.get("attributes", []):
                raise SceneError(self.scene.file, self.scene.line("entities", e, "attributes", a),
                                 f"entities.{e}.attributes.{a}",
                                 f"model {m!r} ({desc.get('kind')}) cannot own {a!r} (it can own: {', '.join(desc.get('attributes', [])) or 'nothing'})")
        for ev in self.scene.evaluators.values():
            if ev.remote not in self.agents[ev.model].desc.get("evaluators", []):
                raise SceneError(self.scene.file, self.scene.line("evaluators", ev.name), f"evaluators.{ev.name}",
                                 f"unknown evaluator {ev.remote!r} of model {ev.model!r} (it has: {', '.join(self.agents[ev.model].desc.get('evaluators', [])) or 'none'})")
        for name, spec in self.scene.models.items():
            # what a model reads: its own declaration plus the scene's `reads:` list
            spec.reads = list(dict.fromkeys(list(spec.reads) + [str(r) for r in self.agents[name].desc.get("reads", [])]))
        for name in self.scene.models:
            owned = [k for k, m in self.owners.items() if m == name]
            self._init_model(name, owned)
            self.agents[name].ready = True

    def _start_model(self, name: str) -> None:
        self._get(self.keys.model(name, "start"), codec.encode("start", tick=self.tick, t=self.t), "ack")

    def _rejoin(self, name: str) -> None:
        """A known agent came back (restart or restored link): init it owning nothing, start it."""
        try:
            self._init_model(name, [])
            self._start_model(name)
            self.agents[name].ready = True
            self.agents[name].rejoin_pending = False
            if name in self._clock_models:  # a new process: it starts from the next clock tick
                self._clock_done[name] = self.tick
                self._clock_behind.discard(name)
            log.warning("%s rejoined the run at tick %d", name, self.tick)
            self._event("rejoin", {"model": name, "tick": self.tick})
        except (RemoteError, ProtocolError, SceneError) as e:
            log.error("%s could not rejoin: %s", name, e)

    def _cut_off(self, grace: float = 0.0) -> bool:
        """Has this conductor itself lost the network (no router and no peer left)? Only a client or
        peer conductor can; the embedded router never is. With ``grace``, keep looking that long: a
        vanished router's liveliness withdrawals can arrive before its link is seen closed."""
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

    def _note_network_lost(self) -> None:
        if not self.network_down:
            self.network_down = True
            self._network_down_at = time.monotonic()
            log.warning("network lost at tick %d: waiting up to %.0f s for it instead of declaring agents dead",
                        self.tick, self.network_timeout)
            self._event("network_lost", {"tick": self.tick, "t": self.t})

    def _wait_network(self) -> None:
        """Pause the run until the network and every agent of the run are back (tokens seen again),
        or ``network_timeout`` passes: then the missing agents are treated as dead."""
        self._note_network_lost()
        need = {n for n in self.scene.models if n in self.agents and self.agents[n].ready}
        deadline = self._network_down_at + self.network_timeout
        while time.monotonic() < deadline and not self.stop_requested.is_set():
            self._drain_inbox(block=0.1)
            if not self._cut_off() and not (need & self._dead_now):
                break
        self._drain_inbox()
        self.network_down = False
        missing = sorted(need & self._dead_now)
        down_s = round(time.monotonic() - self._network_down_at, 3)
        if self.stop_requested.is_set():
            return
        self._event("network_restored", {"tick": self.tick, "t": self.t, "down_s": down_s, "missing": missing})
        log.warning("network restored after %.1f s%s", down_s, f"; missing: {', '.join(missing)}" if missing else "")
        for name in missing:
            self.agents[name].alive = False
            self._fallback(name)

    def _fallback(self, name: str) -> None:
        """``name`` lost liveliness: its responsibilities go to the main model with their last values."""
        main = self.scene.main
        self._event("agent_lost", {"model": name, "tick": self.tick})
        log.warning("lost agent %s at tick %d", name, self.tick)
        self.agents[name].ready = False
        if name == main:
            self.errors.append(f"main model {main} lost at tick {self.tick}")
            raise RunAborted(f"the main model {main!r} died at tick {self.tick}; nothing can take its responsibilities")
        for (e, a), m in sorted(self.owners.items()):
            if m != name:
                continue
            value = self.values.get((e, a))
            try:
                self._get(self.keys.model(main, "acquire"),
                          codec.encode("acquire", entity=e, attribute=a, value=value, extra={}, tick=self.tick, t=self.t), "ack")
            except (RemoteError, ProtocolError) as ex:
                log.error("fallback of %s.%s to %s failed: %s", e, a, main, ex)
            self._set_owner(e, a, main, f"fallback:{name} lost", {"model": name})

    def _set_owner(self, e: str, a: str, dst: str, trigger: str, variables: dict) -> None:
        src = self.owners[(e, a)]
        self.owners[(e, a)] = dst
        self.version += 1
        h = Handover(self.tick, self.t, e, a, src, dst, trigger, variables)
        self.handovers.append(h)
        change = h.as_dict()
        self._pub(self.keys.ownership, codec.encode("ownership", version=self.version, tick=self.tick, t=self.t,
                                                   owners=self.ownership_map(), change=change))
        self._event("handover", change)

    def handover(self, e: str, a: str, dst: str, trigger: str, variables: dict | None = None) -> bool:
        """Move ``e.a`` to ``dst`` between ticks (release on the old owner, acquire on the new one)."""
        variables = variables or {}
        if (e, a) not in self.owners:
            self._trigger_error(trigger, f"no responsibility {e}.{a} in the scene")
            return False
        src = self.owners[(e, a)]
        if src == dst:
            return False
        dinfo = self.agents.get(dst)
        if dst not in self.scene.models or dinfo is None or not dinfo.alive or not dinfo.ready:
            self._trigger_error(trigger, f"cannot hand {e}.{a} to {dst!r}: not a live model of this scene")
            return False
        if a not in dinfo.desc.get("attributes", []):
            self._trigger_error(trigger, f"{dst} cannot own attribute {a!r}")
            return False
        sinfo = self.agents.get(src)
        value, extra = self.values.get((e, a)), {}
        if sinfo is not None and sinfo.alive and sinfo.ready:
            try:
                rep = self._get(self.keys.model(src, "release"),
                                codec.encode("release", entity=e, attribute=a, tick=self.tick, t=self.t), "release_reply")
                value, extra = rep.value, rep.extra
            except (RemoteError, ProtocolError) as ex:
                self._trigger_error(trigger, f"release of {e}.{a} by {src} failed: {ex}")
                return False
        try:
            self._get(self.keys.model(dst, "acquire"),
                      codec.encode("acquire", entity=e, attribute=a, value=value, extra=extra, tick=self.tick, t=self.t), "ack")
        except (RemoteError, ProtocolError) as ex:
            self._trigger_error(trigger, f"{dst} failed to acquire {e}.{a}: {ex}; ownership stays with {src}")
            if sinfo is not None and sinfo.alive:
                try:
                    self._get(self.keys.model(src, "acquire"),
                              codec.encode("acquire", entity=e, attribute=a, value=value, extra=extra, tick=self.tick, t=self.t), "ack")
                except (RemoteError, ProtocolError):
                    log.error("%s could not take back %s.%s", src, e, a)
            return False
        self.values[(e, a)] = value
        self._set_owner(e, a, dst, trigger, variables)
        return True

    def _trigger_error(self, trigger: str, problem: str) -> None:
        log.warning("trigger %s: %s", trigger, problem)
        self.errors.append(f"tick {self.tick}: {trigger}: {problem}")
        self._event("trigger_error", {"trigger": trigger, "problem": problem})

    # --------------------------------------------------------- expressions
    def _functions(self) -> dict[str, Callable]:
        def pose(e):
            return self.values.get((e, "pose"))

        def position(e):
            if isinstance(e, (list, tuple)):
                return list(e[:3])
            p = pose(e)
            if p is None:
                raise ExprError(f"no pose known for {e!r}")
            return list(p[:3])

        def distance(a, b):
            return float(np.linalg.norm(np.subtract(position(a), position(b))))

        def inside(container, obj):
            ent = self.scene.entities.get(container)
            if ent is None or ent.shape.get("type") != "container":
                raise ExprError(f"{container!r} is not a container")
            return inside_container(ent.shape, pose(container), position(obj))

        def at(e, offset):
            """The world point at ``offset`` in entity e's frame."""
            from protocol.geometry import quat_to_matrix

            p = pose(e)
            if p is None:
                raise ExprError(f"no pose known for {e!r}")
            return list(np.asarray(p[:3]) + quat_to_matrix(p[3:7]) @ np.asarray(offset, float))

        def output(model, name, default=None):
            return self.outputs.get((model, name), default)

        def owner(e, a="pose"):
            return self.owners.get((e, a))

        def owned(model, a="pose"):
            return sorted(e for (e, attr), m in self.owners.items() if m == model and attr == a)

        fns: dict[str, Callable] = {
            "owned": owned, "at": at,
            "pose": pose, "position": position, "distance": distance, "inside": inside, "output": output,
            "owner": owner, "event_count": lambda m, n: self.event_counts.get((m, n), 0),
            "tagged": lambda tag: [n for n, e in self.scene.entities.items() if tag in e.tags],
            "abs": abs, "min": min, "max": max, "len": len, "str": str, "float": float, "int": int,
            "bool": bool, "any": any, "all": all, "norm": lambda v: float(np.linalg.norm(v)),
        }
        for ev in self.scene.evaluators.values():
            fns[ev.name] = self._make_evaluator(ev)
        return fns

    def _make_evaluator(self, ev):
        def call(*args):
            payload = codec.encode("eval", args=list(ev.args) + list(args), tick=self.tick, t=self.t)
            try:
                return self._get(self.keys.eval(ev.model, ev.remote), payload, "value_reply").value
            except RemoteError as e:
                raise ExprError(f"evaluator {ev.name} failed: {e}") from None

        return call

    def _resolver(self, scope: dict) -> Callable[[str], Any]:
        def resolve(name):
            if name in scope:
                return scope[name]
            if name in self.scene.entities or name in self.scene.models:
                return name
            raise ExprError(f"undefined variable {name!r}")

        return resolve

    # -------------------------------------------------------------- triggers
    def _fire(self, kind: str, match: Callable[[dict], bool], context: dict) -> None:
        for trig in self.scene.triggers:
            on = trig.on
            if kind not in on or not match(on):
                continue
            if trig.once and trig.name in self._fired_once:
                continue
            scope = dict(context, tick=self.tick, t=self.t, trigger=trig.name)
            fns = self._functions()
            resolve = self._resolver(scope)
            record = {"trigger": trig.name, "tick": self.tick, "t": self.t, "on": kind, "fired": False}
            try:
                for var, ex in trig.let:
                    scope[var] = ex.evaluate(resolve, fns)
                if trig.when is not None and not trig.when.evaluate(resolve, fns):
                    record["variables"] = _plain({v: scope[v] for v, _ in trig.let})
                    record["reason"] = f"precondition false: {trig.when.source}"
                    self.trigger_log.append(record)
                    self._event("trigger", record)
                    continue
                variables = _plain({v: scope[v] for v, _ in trig.let})
                record.update(fired=True, variables=variables)
                self.trigger_log.append(record)
                self._event("trigger", record)
                if trig.once:
                    self._fired_once.add(trig.name)
                for eff in trig.do:
                    if eff.kind == "transfer":
                        e = eff.fields["entity"].evaluate(resolve, fns)
                        a = eff.fields["attribute"].evaluate(resolve, fns)
                        dst = eff.fields["to"].evaluate(resolve, fns)
                        if e is None:
                            self._trigger_error(trig.name, f"{eff.path}: entity evaluated to null")
                            continue
                        for one in (e if isinstance(e, list) else [e]):  # a list transfers each entity
                            self.handover(str(one), str(a), str(dst), trig.name, variables)
                    else:
                        args = [x.evaluate(resolve, fns) for x in eff.fields["args"]]
                        try:
                            payload = codec.encode("call", args=args, kwargs={}, tick=self.tick, t=self.t)
                            self._get(self.keys.call(eff.fields["model"], eff.fields["service"]), payload, "value_reply")
                        except (RemoteError, ProtocolError) as ex:
                            self._trigger_error(trig.name, f"{eff.path}: {ex}")
            except ExprError as ex:
                self._trigger_error(trig.name, f"line {trig.line}: {ex}")

    def _on_action(self, msg: dict) -> None:
        op, phase = msg["operation"], msg["phase"]
        self._fire("action", lambda on: on["action"] == op and on.get("phase", "start") in (phase, "any"),
                   {"action": msg})

    def _on_output(self, model: str, name: str, value: Any) -> None:
        ref = f"{model}.{name}"
        self._fire("topic", lambda on: on["topic"] == ref, {"value": value})

    def _on_model_event(self, model: str, name: str, data: dict) -> None:
        ref = f"{model}.{name}"
        self.event_counts[(model, name)] = self.event_counts.get((model, name), 0) + 1
        self._fire("event", lambda on: on["event"] == ref, {"event": {"model": model, "name": name, "data": data}})

    # -------------------------------------------------------------- step data
    def _absorb(self, model: str, msg: dict) -> None:
        """Take in a model's state/outputs/events (from a step reply or an async publication)."""
        mtype = msg.get("type")
        if mtype in ("step_reply", "state"):
            values = msg["state"] if mtype == "step_reply" else msg["values"]
            for e, attrs in values.items():
                if not isinstance(attrs, dict):
                    continue
                for a, v in attrs.items():
                    if self.owners.get((e, a)) == model:
                        self.values[(e, a)] = v
                    else:
                        self.unauthorized_writes += 1
        if mtype == "step_reply":
            for n, v in msg["outputs"].items():
                self._set_output(model, n, v)
            for ev in msg["events"]:
                if isinstance(ev, dict) and "name" in ev:
                    self._on_model_event(model, str(ev["name"]), ev.get("data") or {})
        elif mtype == "out":
            self._set_output(model, msg["name"], msg["value"])
        elif mtype == "event":
            self._on_model_event(model, msg["name"], msg["data"])

    def _set_output(self, model: str, name: str, value: Any) -> None:
        old = self.outputs.get((model, name), _MISSING)
        self.outputs[(model, name)] = value
        if _differs(old, value):
            self._on_output(model, name, value)

    def _inputs_for(self, name: str, reads: list[str]) -> dict:
        if not reads:
            return {}
        out: dict = {}
        for (e, a), m in self.owners.items():
            if m == name:
                continue
            key = f"{e}.{a}"
            if any(fnmatchcase(key, pat) for pat in reads):
                v = self.values.get((e, a))
                if v is not None:
                    out.setdefault(e, {})[a] = v
        return out

    def check_invariant(self) -> None:
        expected = set(self.scene.initial_owners())
        if set(self.owners) != expected or any(m not in self.scene.models for m in self.owners.values()):
            self.invariant_violations += 1
            log.error("ownership invariant violated at tick %d", self.tick)

    # ------------------------------------------------------------------ run
    def run(self) -> dict:
        """Run to the end of the source (or max_ticks / stop); returns the run summary."""
        wall0 = time.perf_counter()
        try:
            self.prepare()
            self._pub(self.keys.ownership, codec.encode("ownership", version=self.version, tick=0, t=0.0,
                                                       owners=self.ownership_map(), change=None))
            for name in self.scene.models:
                self._start_model(name)
            self._event("run_start", {"scene": self.scene.name, "models": list(self.scene.models)})
            if self.source is not None and self.source.live:
                log.info("live: waiting for telemetry on %s", self.keys.telemetry("**"))
                self.source.wait_for_data(self.stop_requested)
            self.running = True
            self._loop()
        except RunAborted as e:
            self.errors.append(str(e))
            log.error("run aborted: %s", e)
        finally:
            self.running = False
            self.wall_s = time.perf_counter() - wall0
        return self.finish()

    def _loop(self) -> None:
        scene = self.scene
        service = [(n, s) for n, s in scene.models.items() if s.step == "service"]
        has_clock = any(s.step == "clock" for s in scene.models.values())
        keys = self.keys
        step_pub = self.session.declare_publisher(keys.step_all)
        telemetry_for = {n for n in scene.models if self.agents[n].desc.get("telemetry", True)}
        checked_version = -1
        live = self.source is not None and self.source.live
        replay = self.source is not None and not live
        # a run not paced by a live robot waits for clock-driven models that fall further behind than this
        clock_slack = (None if live or scene.max_lag is None
                       else int(math.floor(scene.max_lag * scene.rate + 1e-9)))
        # Batches: an unpaced run sends several ticks in one step message when nothing can intervene
        # between them (no clock-driven or free-running model, whose answers are not in step replies).
        # A batch ends at a tick after which a trigger may fire (an action is due, or a model that
        # triggers listen to is stepped), before a model that reads an attribute whose owner was
        # stepped in it, and at clock.batch ticks. Every model then sees exactly what one message per
        # tick would have given it.
        # (only if every agent said it steps batches: an agent of another make sees one tick per message)
        batch = 1
        if scene.batch > 1 and not live and not self.rtf and len(service) == len(scene.models):
            unable = sorted(n for n in scene.models if not self.agents[n].desc.get("batch"))
            if unable:
                log.info("one step message per tick: %s do not step batches of ticks", ", ".join(unable))
            else:
                batch = scene.batch
        trigger_sources = {trig.on[k].split(".", 1)[0] for trig in scene.triggers for k in ("topic", "event")
                           if k in trig.on}
        readers = [(n, s) for n, s in service if s.reads]
        read_owners: dict[str, set] = {}
        read_owners_version = -1
        dt = self.dt
        start_wall = time.perf_counter()
        loop_start = time.perf_counter()
        self._run_wall0 = loop_start
        last_progress = loop_start
        tick = 0
        while True:
            if self.stop_requested.is_set():
                break
            if self.max_ticks is not None and tick >= self.max_ticks:
                break
            if self.source is not None and self.source.exhausted(tick * dt):
                break
            if batch > 1 and readers and read_owners_version != self.version:
                read_owners = {n: {m for (e, a), m in self.owners.items() if m != n
                                   and any(fnmatchcase(f"{e}.{a}", pat) for pat in s.reads)} for n, s in readers}
                read_owners_version = self.version
            window = []  # (tick, t, body, {model: tick stepped}, actions) per tick of this step message
            stepped: set = set()
            j = tick
            while True:
                t = j * dt
                self.tick, self.t = j, t
                actions = []
                if self.source is not None:
                    for kind, msg in self.source.due(t):
                        if replay:  # validated when the recording was read: skip the checks on the hot path
                            self._pub(keys.telemetry("joint_states" if kind == "joint_state" else "action"),
                                      codec.encode_unchecked(kind, dict(msg)))
                        if kind == "joint_state":
                            self.latest_joints = msg
                        else:
                            actions.append(msg)
                            for n in telemetry_for:
                                self._pending_actions[n].append(msg)
                if has_clock:
                    self._clock_gate(j, clock_slack)
                    self._last_clock = codec.encode_unchecked("clock", {"tick": j, "t": t, "dt": dt})
                    self._pub(keys.clock, self._last_clock)
                body, names = self._tick_body(j, t, service, telemetry_for)
                window.append((j, t, body, names, actions))
                stepped.update(names)
                nj = j + 1
                if (len(window) >= batch or actions or not trigger_sources.isdisjoint(names)
                        or (self.max_ticks is not None and nj >= self.max_ticks)
                        or (self.source is not None and self.source.exhausted(nj * dt))
                        or self.stop_requested.is_set()
                        or any(not nj % s.period and not read_owners[n].isdisjoint(stepped) for n, s in readers)):
                    break
                j = nj
            got = self._step_window(step_pub, window)
            last = window[-1][0]
            for j, t, body, names, actions in window:
                if True:
                    self.tick, self.t = j, t
                    for name in self._model_order:  # in scene order, whatever the arrival order
                        rep = got.get(name)
                        if rep is not None and j in rep:
                            self._take_step_reply(name, j, rep[j])
                    if j == last:
                        # agents lost or back while the message was out count from its last tick, when
                        # every answer of the batch is in
                        self._drain_inbox()
                for a in actions:
                    self._on_action(a)
                if self.version != checked_version:  # the map only changes through _set_owner
                    self.check_invariant()
                    checked_version = self.version
            tick = last + 1
            if self.progress is not None:
                now = time.perf_counter()
                if now - last_progress > 1.0:
                    last_progress = now
                    el = now - loop_start
                    self.progress({"tick": self.tick, "t": self.t, "duration": getattr(self.source, "duration", None),
                                   "rtf": self.t / el if el > 0 else None})
            if self.rtf:
                target = loop_start + (tick * dt) / self.rtf
                delay = target - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            elif live:
                target = loop_start + tick * dt
                delay = target - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
        if has_clock and clock_slack is not None and not self.stop_requested.is_set():
            # the replay's last ticks count in full: wait for the clock-driven models' answers to every
            # tick sent and take in what they published (outputs may still fire triggers)
            self._clock_gate(tick, 0)
            time.sleep(0.01)  # their publications left before their answers; let them land in the inbox
            self._drain_inbox()
        self.tick = tick
        self.t = tick * dt
        self.loop_wall_s = time.perf_counter() - start_wall

    def _tick_body(self, tick: int, t: float, service, telemetry_for) -> tuple[dict | None, tuple]:
        """One tick of the step broadcast: shared joints and a section per service model due (or None)."""
        agents = self.agents
        dt = self.dt
        sections = {}
        due = []
        want_joints = False
        for name, spec in service:
            if tick % spec.period or not agents[name].ready:
                continue
            if name in telemetry_for:
                acts = self._pending_actions[name]
                self._pending_actions[name] = []
                want_joints = True
            elif not spec.reads and spec.period == 1:
                due.append(name)  # nothing of its own: shares one section
                continue
            else:
                acts = []
            sections[name] = {"dt": dt * spec.period, "actions": acts,
                              "inputs": self._inputs_for(name, spec.reads) if spec.reads else {}}
        if not sections and not due:
            return None, ()
        body = {"tick": tick, "t": t, "joints": self.latest_joints if want_joints else None, "models": sections}
        if due:
            body["due"] = due
            body["shared"] = {"dt": dt, "actions": [], "inputs": {}}
        return body, (*sections, *due)

    def _step_window(self, step_pub, window: list) -> dict[str, dict[int, dict]]:
        """Send the ticks of ``window`` in one step message; returns every model's answers
        (model -> tick -> reply)."""
        bodies = [w[2] for w in window if w[2] is not None]
        got: dict[str, dict[int, dict]] = {}
        if not bodies:
            return got
        first = dict(bodies[0])
        if len(bodies) > 1:
            first["more"] = bodies[1:]
        payload = codec.encode_unchecked("tick", first)
        expected: dict[str, list[int]] = {}
        for j, _, _, names, _ in window:
            for n in names:
                expected.setdefault(n, []).append(j)
        for _ in range(3):  # a step message interrupted by the conductor's own network loss is sent again
            step_pub.put(payload)
            lost = self._collect_done(expected, got)
            if not lost or not (self.network_down or self._cut_off(grace=0.5)):
                break
            self._wait_network()
            expected = {n: expected[n] for n in lost if self.agents[n].ready and n not in self._dead_now}
            if not expected:
                break
        return got

    def _on_done(self, sample) -> None:
        """Decoded in Zenoh's thread (in parallel with the tick loop), queued for the loop."""
        key = str(sample.key_expr)
        try:
            rep = codec.decode_hot(key, sample.payload, "step_reply")
        except ProtocolError as e:
            self._malformed(key, e)
            return
        name = key[self._done_prefix_len:]
        if name in self._clock_models:  # a clock-driven model's progress, not a reply a tick waits for
            if rep["tick"] > self._clock_done.get(name, -1):
                self._clock_done[name] = rep["tick"]
                self.inbox.put(("clock_done", name, rep))
            self._clock_evt.set()
            return
        self._done_q.put((name, rep))

    def _clock_gate(self, tick: int, slack: int | None) -> None:
        """Before clock tick ``tick`` goes out, wait (unless ``slack`` is None: live) until every
        clock-driven model has answered all but at most ``slack`` of the ticks already sent, and note the
        most each had left unanswered. One that does not catch up within the step timeout is reported
        (summary ``errors``) and not waited for again until it has caught up by itself."""
        for name in self._clock_models:
            info = self.agents.get(name)
            if info is None or not info.ready or not info.alive or not info.desc.get("clock_ack"):
                continue
            stats = self._clock_lag.get(name)
            if stats is None:
                stats = self._clock_lag[name] = {"max_lag_ticks": 0, "waited_s": 0.0}
            need = tick - 1 - (slack or 0)  # the oldest tick it must have answered
            if slack is not None and self._clock_done.get(name, -1) < need and name not in self._clock_behind \
                    and name not in self._dead_now and not self.network_down:
                stats["waited_s"] += self._clock_wait(name, info, need)
            done = self._clock_done.get(name, -1)
            if done >= need:
                self._clock_behind.discard(name)
            lag = tick - 1 - done
            if lag > stats["max_lag_ticks"]:
                stats["max_lag_ticks"] = lag

    def _clock_wait(self, name: str, info: AgentInfo, need: int) -> float:
        """Wait until ``name`` has answered tick ``need``; returns the seconds waited."""
        t0 = time.monotonic()
        nudge, deadline = t0 + 0.5, t0 + self.step_timeout
        while not self.stop_requested.is_set():
            self._clock_evt.clear()
            if self._clock_done.get(name, -1) >= need or name in self._dead_now:
                break
            now = time.monotonic()
            if now >= nudge:
                if self._cut_off():
                    break  # our own network is gone: the next step finds out and waits for it
                if self._last_clock is not None:  # a clock tick or its answer may have been dropped
                    self._pub(self.keys.clock, self._last_clock)
                nudge = now + 0.5
            if now >= deadline:
                self._clock_behind.add(name)
                behind = self.tick - 1 - self._clock_done.get(name, -1)
                info.errors += 1
                info.last_error = (f"{behind} clock ticks unanswered after waiting {self.step_timeout} s; "
                                   "the replay no longer waits for it")
                log.warning("%s: %s", name, info.last_error)
                self.errors.append(f"tick {self.tick}: clock-driven model {name}: {info.last_error}")
                break
            self._clock_evt.wait(0.05)
        return time.monotonic() - t0

    def _collect_done(self, expected: dict[str, list[int]], got: dict) -> set:
        """Wait for done/<id> of every model in ``expected`` (model -> the ticks it was stepped in this
        message) and put each answer in ``got`` (model -> tick -> reply). Returns the models given up on
        because their liveliness token vanished meanwhile. The caller takes the answers in once all are
        in, tick by tick and in the scene's model order whatever the arrival order, so a run does not
        depend on which agent answered first."""
        expected = dict(expected)
        # the step timeout is per tick: a model answers a batch once it has stepped all of its ticks
        deadline = time.monotonic() + self.step_timeout * max(len(ticks) for ticks in expected.values())
        q = self._done_q
        given_up: set[str] = set()
        while expected:
            try:
                name, rep = q.get(timeout=0.05) if self._dead_now.isdisjoint(expected) else q.get_nowait()
            except queue.Empty:
                gone = self._dead_now.intersection(expected)
                if gone:
                    for name in gone:
                        del expected[name]
                    given_up |= gone
                    continue
                if time.monotonic() > deadline:
                    for name, ticks in expected.items():
                        info = self.agents[name]
                        info.errors += 1
                        info.last_error = f"no step result for tick {ticks[0]} within {self.step_timeout} s"
                        log.warning("%s: %s", name, info.last_error)
                    return given_up
                continue
            ticks = expected.get(name)
            if ticks is None or rep["tick"] != ticks[0]:
                continue  # a late answer to an earlier message, or a model not stepped now
            more = rep.get("more")
            if more is None:
                more = ()
            if len(more) != len(ticks) - 1 or any(r["tick"] != j for r, j in zip(more, ticks[1:])):
                info = self.agents[name]
                info.errors += 1
                info.last_error = (f"answered ticks {[rep['tick']] + [r['tick'] for r in more]} of a message "
                                   f"that stepped it on ticks {ticks}")
                log.warning("%s: %s", name, info.last_error)
                continue
            del expected[name]
            got[name] = {rep["tick"]: rep, **{r["tick"]: r for r in more}}
        return given_up

    def _take_step_reply(self, name: str, tick: int, rep: dict) -> None:
        self._count_step(self.agents[name], name, tick, rep)
        if rep["state"] or rep["outputs"] or rep["events"]:
            self._absorb(name, rep)

    def _count_step(self, info: AgentInfo, name: str, tick: int, rep: dict) -> None:
        info.steps += 1
        info.step_s += rep.get("step_s", 0.0) or 0.0
        if rep["status"] != "ok":
            info.errors += 1
            if rep["status"] == "error":
                info.failed += 1
            info.last_error = rep.get("message", rep["status"])
            if info.errors <= 5:
                log.warning("%s step %d: %s: %s", name, tick, rep["status"], info.last_error)

    def semantic_state(self) -> dict:
        out = {}
        fns = self._functions()
        resolve = self._resolver({})
        for label, ex in self.scene.semantics.items():
            try:
                out[label] = _plain(ex.evaluate(resolve, fns))
            except ExprError as e:
                out[label] = None
                self.errors.append(f"semantics {label}: {e}")
        return out

    def finish(self) -> dict:
        try:
            sem = self.semantic_state() if self.tick > 0 else {}
        except Exception as e:
            sem = {}
            self.errors.append(f"semantics: {e}")
        loop_wall = getattr(self, "loop_wall_s", self.wall_s)
        sim_s = self.tick * self.dt
        summary = {
            "scene": self.scene.name,
            "ensemble": self.keys.ensemble,
            "ticks": self.tick,
            "sim_s": round(sim_s, 6),
            "wall_s": round(loop_wall, 4),
            "setup_s": round(self.wall_s - loop_wall, 4),
            "rtf": round(sim_s / loop_wall, 4) if loop_wall > 0 else None,
            "handovers": [h.as_dict() for h in self.handovers],
            "final_ownership": {f"{e}.{a}": m for (e, a), m in sorted(self.owners.items())},
            "semantic_state": sem,
            "malformed_messages": self.malformed,
            "unauthorized_writes": self.unauthorized_writes,
            "invariant_violations": self.invariant_violations,
            "triggers_fired": sum(1 for r in self.trigger_log if r.get("fired")),
            "models": {n: {"steps": a.steps, "mean_step_ms": round(1e3 * a.step_s / a.steps, 4) if a.steps else None,
                           "rate_hz": self.scene.models[n].rate if n in self.scene.models else None,
                           "achieved_hz": round(a.steps / loop_wall, 2) if loop_wall > 0 else None,
                           "alive": a.alive, "errors": a.errors, "failed_steps": a.failed,
                           "last_error": a.last_error or None, **self._clock_lag.get(n, {})}
                       for n, a in self.agents.items()},
            "errors": (self.errors + [f"model {n}: {a.failed} of {a.steps} steps failed (last: {a.last_error})"
                                      for n, a in self.agents.items() if a.failed])[:50],
            "run_log": self.run_log_path,
        }
        if self.source is not None and self.source.live:
            summary["lag"] = self.source.lag_stats()
        rec = getattr(self.source, "rec", None)
        if rec is not None and getattr(rec, "skipped", None):
            summary["input_warnings"] = rec.warnings()  # malformed messages the replay left out
        self._event("run_end", {"ticks": self.tick, "rtf": summary["rtf"], "semantic_state": sem})
        for name in self.scene.models:
            info = self.agents.get(name)
            if info is not None and info.alive:
                try:
                    self._get(self.keys.model(name, "stop"), codec.encode("stop", reason="run ended"), "ack", timeout=2.0)
                except (RemoteError, ProtocolError):
                    pass
        time.sleep(0.05)  # let the last publications reach the run log
        if self.run_log:
            import json
            self.run_log.close({"twin.summary": {"json": json.dumps(summary, default=str)}})
        return summary

    def close(self) -> None:
        for d in self._decl:
            try:
                d.undeclare()
            except Exception:
                pass
        self._decl = []


class _Raw:
    """bytes with the ZBytes-like to_bytes() the hot decoder expects."""

    __slots__ = ("data",)

    def __init__(self, data: bytes):
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Missing:
    pass


_MISSING = _Missing()


def _differs(a, b) -> bool:
    if a is _MISSING:
        return True
    try:
        r = a != b
        if isinstance(r, np.ndarray):
            return bool(r.any())
        return bool(r)
    except Exception:
        return True


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and math.isnan(v):
        return None
    return v
