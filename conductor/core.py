"""The conductor: runs one scene on one ensemble. Set-up, the tick loop, tear-down; nothing else.

The parts it drives never call back into it: :mod:`~conductor.link` (the wire), :mod:`~conductor.registry`
(who is there), :mod:`~conductor.responsibility` (who owns what: pure data), :mod:`~conductor.handover`,
:mod:`~conductor.triggers`, :mod:`~conductor.stepping` (which ticks go in one message, the step broadcast,
the clock gate) and :mod:`~conductor.record` (counters and the summary). Every effect between them passes
through the loop below as a value, at points the loop chooses: a trigger fires only between ticks, never
inside a step message, and an agent's loss or return is taken in only at the end of a step message.

::

    with Conductor(scene, session, keys, ReplaySource(rec), RunOptions(run_log="run.mcap")) as c:
        summary = c.run()
"""
from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from protocol import codec
from protocol.errors import AgentError, ProtocolError, RunAborted, SceneError
from protocol.keys import Keys
from protocol.messages import Message

from .flow import FlowScheduler, Pipeline, flow_roles, uncoupled
from .handover import Handovers
from .link import AgentLink, Answered, Published, ServiceCall
from .network import NetworkWatch
from .record import RunRecord, input_report
from .registry import Registry, Rejoin, Vanished
from .responsibility import Responsibilities
from .runlog import RunLog
from .scene import Scene, check_against_agents, reads_of
from .sources.feed import Feeder
from .sources.fit import JointFit
from .stepping import (
    BatchRule,
    BroadcastStepper,
    Clock,
    ClockGate,
    Pacer,
    TickPlan,
    batch_rule,
    clock_slack,
    deadline_timer,
    owner_event_breaches,
    tick_body,
    window_payload,
)
from .triggers import TriggerEngine

log = logging.getLogger("twin.conductor")


@dataclass
class RunOptions:
    """How to run: pacing, limits, timeouts and the run log."""

    rtf: float | None = None  # pace a replay at this real-time factor (None: as fast as the models allow)
    max_ticks: int | None = None
    step_timeout: float = 10.0  # seconds a model may take per tick before it is a problem of the run
    register_timeout: float = 60.0  # seconds to wait for the scene's agents
    run_log: str | None = None  # MCAP file of everything the ensemble publishes
    metadata: dict[str, Any] = field(default_factory=dict)  # written into the run log
    network_mode: str | None = None  # the conductor's own Zenoh mode (a client/peer can lose the network)
    network_timeout: float = 30.0  # how long a lost network is waited for before missing agents count as dead
    deadline: float | None = None  # wall seconds the whole run may take (then it is truncated)


class Conductor:
    """Runs one scene on one ensemble over an open Zenoh ``session``.

    ``source`` is a replay or live source (or None: run ``max_ticks`` ticks without telemetry); ``on_event``
    hears the conductor's own events (handover, agent_lost, ...); ``progress`` gets ``{tick, t, duration, rtf}``
    about once a second; ``agent_check(missing)`` may raise while agents are awaited (a launcher whose agent
    process already died)."""

    def __init__(self, scene: Scene, session: Any, keys: Keys, source: Any = None, options: RunOptions | None = None,
                 *, on_event: Callable[[str, dict[str, Any]], None] | None = None,
                 progress: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.scene, self.keys, self.source = scene, keys, source
        self.opts = opts = options or RunOptions()
        self.progress = progress
        self.agent_check: Callable[[set[str], bool], None] | None = None
        self.clock = Clock(1.0 / scene.rate)
        self.stop_requested = threading.Event()
        self.link = AgentLink(session, keys, step_timeout=opts.step_timeout, on_event=on_event,
                              network_mode=opts.network_mode, clock=self.clock)
        self.registry = Registry(scene.models)
        self.map = Responsibilities(scene)
        self.record = RunRecord(scene)
        self.handovers = Handovers(self.link, self.registry, self.map, self.record, scene.main, self.clock)
        self.triggers = TriggerEngine(scene, self.map, self.link, self.handovers, self.record, self.clock)
        self.stepper = BroadcastStepper(self.record, opts.step_timeout)
        self.clock_models = frozenset(n for n, m in scene.models.items() if m.step == "clock")
        self.async_models = frozenset(n for n, m in scene.models.items() if m.step != "service")  # (+ free)
        self.network = NetworkWatch(self.link, self.registry, self.clock, opts.network_timeout, self.stop_requested,
                                    self._event, self.record, self._live)
        self.gate = ClockGate(self.clock_models, self.record, opts.step_timeout,
                              lambda payload: self.link.publish(keys.clock, payload), self.link.cut_off,
                              slack=clock_slack(self.scene, self._live()), waitable=self.registry.acks_clock,
                              stop=self.stop_requested, gone=self.link.gone)
        rec = getattr(source, "rec", None)  # a replayed recording: the log's clock starts where it starts
        self.run_log = (RunLog(opts.run_log, opts.metadata, on_error=self.fail, dt=self.clock.dt, prefix=keys.prefix,
                               origin_ns=getattr(rec, "origin_ns", None),
                               entities={n: {"shape": e.shape, "attributes": sorted(e.attributes)}
                                         for n, e in scene.entities.items()},
                               models=list(scene.models)) if opts.run_log else None)
        if (run_log := self.run_log) is not None and self._live():  # a live run's time 0: its robot's first stamp
            run_log.take_origin_from(source)
        self.reads: dict[str, list[str]] = {n: list(m.reads) for n, m in scene.models.items()}
        self.running = self._open = self.ended = False  # (ended: the loop got to its end without being stopped)
        self.wall_s = self.loop_wall_s = 0.0
        self._deferred: list[Any] = []  # agent events seen while waiting for the network, taken in after
        self._refused_before: dict[str, int] = {}  # agent -> messages it had refused when the run began
        self.fit = JointFit(scene.declared_robot, source, self.record.degraded.extend, triggers=scene.triggers,
                            note=self.record.notes.extend)
        self.feed = Feeder(source, self.fit, keys, self.link.publish,
                           lambda: [n for n in scene.models if self._wants_telemetry(n)], scene.models,
                           defer=any(m.step != "service" for m in scene.models.values()))
        self._lookahead, self._addressed = 0, False  # ticks fetched ahead (unpaced replays); agents addressed (prepare)

    # --------------------------------------------------------------------------------- life cycle
    def open(self) -> Conductor:
        """Declare the conductor on Zenoh (queryables, subscriptions, its liveliness token)."""
        if not self._open:
            self.link.serve(admit=self.registry.admit, status=self.status,
                            stop=lambda: self.stop("a conductor/stop request"),
                            on_done=self._on_done, run_log=self.run_log, source=self.source,
                            async_models=self.async_models)
            self._open = True
        return self

    def close(self) -> None:  # (a run log that never ran, the set-up around it having failed, is ended whole too)
        self.link.close()
        self._open = False
        if self.run_log is not None:  # (closed by finish already: nothing then)
            self.run_log.close()

    def __enter__(self) -> Conductor:  # it declares itself when it runs (a refusal then is a failed run, summed up)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self) -> dict[str, Any]:
        """Run to the end of the source (or ``max_ticks`` / a stop); returns the run summary."""
        wall0 = time.perf_counter()
        timer = deadline_timer(self.opts.deadline, self.stop)  # (it counts the waits for the agents and the robot)
        try:
            self.prepare()
            self.start()
            self.loop()
        except (RunAborted, SceneError, AgentError) as e:  # the summary says why (a stop asked for: truncated)
            self.record.abort(str(e), bad_input=isinstance(e, SceneError))  # (an init refused, an agent lost: failed)
            log.log(logging.ERROR if self.record.failure else logging.INFO, "run %s: %s",
                    "refused" if isinstance(e, SceneError) else "aborted", e)
        except Exception as e:  # a fault of ours or an answer nothing expected: failed, and still a summary
            log.exception("run failed")
            self.record.abort(f"the conductor failed at tick {self.clock.tick}: {type(e).__name__}: {e}")
        finally:
            self.running, self.wall_s = False, time.perf_counter() - wall0
            if timer is not None:
                timer.cancel()
        return self.finish()

    def prepare(self) -> None:
        """Wait for every agent, check the scene against what they declare, initialise them all."""
        self.open()
        self.registry.wait(self.link.inbox, self.opts.register_timeout, self.stop_requested, self.agent_check)
        declared = {n: a.desc for n, a in self.registry.agents.items()}
        problems = check_against_agents(self.scene, declared)
        if problems:
            raise SceneError.of(problems)
        self.reads = reads_of(self.scene, declared)
        self.map.declare(declared)
        self._addressed = all(d.get("addressed") for d in declared.values())  # (Keys.step_to)
        self.fit.before_run()

        def init(name: str) -> None:  # an agent whose link lapses meanwhile is waited for (nothing is lost yet)
            self._init_model(name, self.map.owned_by(name), lost_wait=self.opts.step_timeout)
            self._refused_before[name] = self.link.refused(name) or 0
        with ThreadPoolExecutor(len(self.scene.models)) as pool:  # the models build their worlds side by side
            list(pool.map(init, self.scene.models))
        for name in self.scene.models:
            self.registry.agents[name].ready = True

    def start(self) -> None:
        """Publish the initial ownership, start every model, and (live) wait for the robot's first data."""
        self.handovers.publish_ownership()
        for name in self.scene.models:
            self.link.ask(name, "start", codec.encode("start", tick=self.clock.tick, t=self.clock.t), "ack",
                          lost_wait=self.opts.step_timeout)
        self._event("run_start", {"scene": self.scene.name, "models": list(self.scene.models)})
        if self._live():
            log.info("live: waiting for telemetry on %s", self.keys.telemetry("**"))
            self.source.wait_for_data(self.stop_requested)

    def finish(self) -> dict[str, Any]:
        """The run summary; stops the agents' run and closes the run log (with the summary in it)."""
        sem = self.triggers.semantics() if self.clock.tick > 0 else {}  # (each predicate that fails: None)
        if self._open and self.clock.tick > 0:
            self.record.degraded += self.registry.refusals(self.link.refused, self._refused_before)
        self.fit.finish()  # (a live robot's joints, if the run ended before they were checked)
        summary = self.record.summary(
            ticks=self.clock.tick, dt=self.clock.dt, loop_wall=self.loop_wall_s or self.wall_s, wall=self.wall_s,
            rmap=self.map, registry=self.registry, semantic_state=sem, malformed=self.link.malformed,
            ensemble=self.keys.ensemble, run_log=self.opts.run_log, **input_report(self.source),
            log_dropped=self.run_log.dropped if self.run_log is not None else {})
        if self._live():
            summary["lag"] = self.source.lag_stats()
        if self._open:  # (not when refused before it declared anything: another conductor has the ensemble)
            self._event("run_end", {"ticks": self.clock.tick, "rtf": summary["rtf"], "semantic_state": sem})
            for name in self.scene.models:
                info = self.registry.get(name)
                if info is not None and info.alive:
                    try:
                        self.link.ask(name, "stop", codec.encode("stop", reason="run ended"), "ack", timeout=2.0)
                    except (AgentError, ProtocolError):
                        pass
            # let the last publications reach the run log: 15 ms without any, at most 50 ms
            self.run_log.settle(quiet=0.015, limit=0.05) if self.run_log else time.sleep(0.05)
        if self.run_log:  # a log that could not be finished is a failed run, whatever the summary in it says
            self.run_log.close({"twin.summary": {"json": json.dumps(summary, default=str)}})
            return self.record.unfinished_log(summary, self.run_log.problem())
        return summary

    def stop(self, reason: str = "a stop request", *, signal: str | None = None) -> None:
        """End the run at the next tick (thread/signal-safe): interrupted by ``signal``, else truncated; or, once
        the loop has ended (the run is being summed up), nothing."""
        if self.ended:
            log.info("%s after the run's last tick: the run is complete all the same", signal or reason)
        elif signal is not None:
            self.record.interrupted = self.record.interrupted or f"interrupted by {signal} at tick {self.clock.tick}"
        elif self.record.stopped is None:
            self.record.stopped = f"stopped at tick {self.clock.tick} by {reason}"
        self.stop_requested.set()

    def fail(self, reason: str) -> None:
        """End the run at the next tick as ``failed`` (e.g. its run log cannot be written)."""
        self.record.failure = self.record.failure or reason
        self.stop_requested.set()

    def status(self) -> dict[str, Any]:
        """What ``conductor/status`` answers (called from a Zenoh thread: snapshots only)."""
        agents = {n: {**a, "steps": self.record.stats(n).steps} for n, a in self.registry.snapshot().items()}
        return {"scene": self.scene.name, "ensemble": self.keys.ensemble, "running": self.running,
                "ended": self.wall_s > 0, "tick": self.clock.tick, "t": self.clock.t, "version": self.map.version,
                "ownership": self.map.ownership_map(), "agents": agents, "handovers": len(self.map.handovers),
                "malformed_messages": self.link.malformed}

    # ------------------------------------------------------------------------------------- set-up
    def _init_model(self, name: str, owned: list[tuple[str, str]], lost_wait: float = 0.0) -> None:
        """Initialise ``name`` with the scene's arguments, the scene and what it owns at start."""
        spec, scene = self.scene.models[name], self.scene
        declared = self.link.ask(name, "params", codec.encode("query"), "params_reply", lost_wait=lost_wait).params
        params = dict(spec.args)
        if "_main" in declared:
            params.setdefault("_main", scene.main)
        init = codec.encode("init", params=params, scene={"name": scene.name, "entities": scene.geometry(),
                                                          "main": scene.main, "rate": scene.rate,
                                                          "robot": scene.robot.as_dict() if scene.robot else {}},
                            owned=[list(o) for o in owned], rate=spec.rate, step_mode=spec.step,
                            models={m: s.kind for m, s in scene.models.items()})
        self.link.ask(name, "init", init, "ack", lost_wait=lost_wait)

    # ---------------------------------------------------------------------------------- the loop
    def loop(self) -> None:
        """Tick until the source is exhausted, ``max_ticks`` or a stop: fill a window of ticks, step it, take
        the answers in tick by tick, then the agents' comings and goings; pace. (After :meth:`prepare` and
        :meth:`start`; :meth:`run` does all three and :meth:`finish`.)"""
        self.running = True
        rule = batch_rule(self.scene, self.registry, self.reads, self._live() or bool(self.opts.rtf))  # where to batch
        service = {n: (s.period, self._wants_telemetry(n), bool(self.reads[n]))
                   for n, s in self.scene.models.items() if s.step == "service"}
        pacer = Pacer.of(self)
        flow = self._flow(rule, service)
        self.record.schedule = flow.name if flow else "batch" if rule.limit > 1 else "one per tick"
        tick = 0
        self._lookahead = rule.limit if rule.limit > 1 else 0
        while not (flow.over(tick, self.stop_requested.is_set()) if flow else self._over(tick)):
            now = rule.now(lambda m: bool(self.map.owned_by(m)))
            if flow is not None:
                window, replies = flow.window(tick, now)
            else:
                replies = self._step(window := self._fill(tick, now, service))
            self._take(window, replies)
            if rule.while_owning:
                self.record.degraded += owner_event_breaches(window, replies, rule.while_owning -
                                                             now.trigger_sources, self.registry)
            tick = window[-1].tick + 1
            pacer.after(tick, self.stop_requested)
        self._drain_clock(tick)  # (a stop meanwhile cuts it short: the run is then cut short too)
        self.ended = not self.stop_requested.is_set()  # (a stop from now on comes after the run's last tick)
        self.clock.set(tick)
        if self._over_by_limit():
            self.record.stopped = self.record.stopped or (
                f"stopped at max_ticks {self.opts.max_ticks}: the source goes on "
                f"(to {getattr(self.source, 'duration', 0.0):.2f} s)")
        self.loop_wall_s = time.perf_counter() - pacer.start

    def _over_by_limit(self) -> bool:
        """Did ``max_ticks`` end a run whose source had more to give?"""
        m = self.opts.max_ticks
        return (m is not None and self.clock.tick >= m and self.source is not None
                and not self.feed.exhausted(self.clock.tick, self.clock.dt))

    def _over(self, tick: int) -> bool:
        return (self.stop_requested.is_set() or (self.opts.max_ticks is not None and tick >= self.opts.max_ticks)
                or self.feed.exhausted(tick, self.clock.dt))

    def _flow(self, rule: BatchRule, service: dict[str, tuple[int, bool, bool]]) -> FlowScheduler | Pipeline | None:
        """Windows stepped in data-flow order, or one ahead, when the scene allows (:mod:`~conductor.flow`)."""
        roles = flow_roles(self.scene, self.registry, self.reads, rule)
        if roles is None:  # (Pipeline: windows that cannot depend on each other's answers go out one ahead)
            return Pipeline(lambda j, r: self._fill(j, r, service), self._step, self._over) if uncoupled(
                self.scene, self.map, self.reads, rule) else None
        return FlowScheduler(roles, self.map, self.reads, self.clock, self.feed, service, self._step, self._over,
                             self._is_ready, self.record.degraded, self.link)

    def _fill(self, tick: int, rule: BatchRule, service: dict[str, tuple[int, bool, bool]]) -> list[TickPlan]:
        """The ticks of the next step message, from ``tick`` on: telemetry fed and the clock published for
        each, until ``rule`` (or the run's end) closes the window."""
        read_owners = {n: self.map.owners_read_by(n, self.reads[n]) for n, _ in rule.readers} if rule.limit > 1 else {}
        window: list[TickPlan] = []
        stepped: set[str] = set()
        j = tick
        while True:
            self.clock.set(j)
            actions = self.feed.enter(j, self.clock.dt)
            if self.clock_models:
                self.gate.send(j, self.clock.t, self.clock.dt, self.network.down)
            body, names = tick_body(j, self.clock.t, self.clock.dt, service, self._is_ready,
                                    self.feed.take_actions, self._inputs, self.feed.latest)
            window.append(TickPlan(j, self.clock.t, body, names, actions))
            stepped.update(names)
            nj = j + 1
            if self._over(nj) or rule.ends_after(len(window), bool(actions), names, stepped, nj, read_owners):
                return window
            j = nj

    def _wants_telemetry(self, name: str) -> bool:
        return bool(self.registry.agents[name].desc.get("telemetry", True))

    def _is_ready(self, name: str) -> bool:
        info = self.registry.get(name)
        return info is not None and info.ready

    def _inputs(self, name: str) -> dict[str, Any]:
        return self.map.inputs_for(name, self.reads[name])

    def _step(self, window: list[TickPlan], until: dict[str, Any] | None = None, ahead: bool = True, *,
              sent: bool = False, wait: bool = True) -> dict[str, Any]:
        """Send the window in one step message (``until``: models may stop early; ``ahead``: the feed fetches ahead
        meanwhile; ``wait=False``: only send it, ``sent=True``: only wait) and take every model's answers (model ->
        tick -> reply). One cut off by our network loss goes again."""
        got: dict[str, dict[int, dict[str, Any]]] = {}
        first = window_payload(window)
        if first is None:
            return got
        if until:
            first["until"] = until
        payload = codec.encode_unchecked("tick", first)
        expected: dict[str, list[int]] = {}
        for plan in window:
            for n in plan.names:
                expected.setdefault(n, []).append(plan.tick)
        last = window[-1].tick
        upto = last + self._lookahead if self.opts.max_ticks is None else min(last + self._lookahead,
                                                                               self.opts.max_ticks - 1)
        key = self.keys.step_to(expected) if self._addressed else self.keys.step_all  # wake only those stepped
        def send() -> None:
            self.link.publish(key, payload)
            self.record.step_messages += 1
        if not wait:
            send()
        for attempt in range(3 if wait else 0):
            if attempt or not sent:
                send()
            lost = self.stepper.collect(expected, got, self.link.gone, resend=send, partial=until or (), idle=None
                                        if not ahead else lambda: self.feed.ahead(last + 1, upto, self.clock.dt))
            for name in sorted(self.stepper.timed_out & set(expected)):  # a token alone does not keep it in
                self._deferred.append(Vanished(name, f"no answer within the {self.opts.step_timeout:g} s step timeout"))
            if self.scene.main in lost and not self.network.down and not self.link.cut_off(grace=0.5):
                if not self._main_back():
                    break  # it did not come back: its Vanished event ends the run
                expected = {self.scene.main: expected[self.scene.main]}
                continue
            if not lost or not (self.network.down or self.link.cut_off(grace=0.5)):
                break
            self._deferred += self.network.wait({n for n in self.scene.models if self._is_ready(n)}, self.running)
            expected = {n: expected[n] for n in lost if self._is_ready(n) and not self.link.gone({n})}
            if not expected:
                break
        return got

    def _take(self, window: list[TickPlan], replies: dict[str, dict[int, dict[str, Any]]]) -> None:
        """Take the answers in tick by tick, each tick's in scene order whatever the arrival order, then that
        tick's actions; the agents' comings and goings count from the window's last tick."""
        checked = self.map.version
        last = window[-1].tick
        for plan in window:
            self.clock.set(plan.tick)
            reps = [(n, rep) for n in self.scene.models if (rep := replies.get(n, {}).get(plan.tick)) is not None]
            for name, rep in reps:
                self.record.stats(name).count(name, plan.tick, rep)
            self.triggers.absorb_tick(reps)  # every state of the tick before the triggers its outputs fire
            if plan.tick == last:
                self._agent_events()
            for a in plan.actions:
                self.triggers.on_action(a)
            if self.map.version != checked:  # the map only changes through handovers
                if not self.map.invariant_holds():
                    self.record.invariant_violations += 1
                    log.error("ownership invariant violated at tick %d", plan.tick)
                checked = self.map.version

    # ------------------------------------------------------------------------ agents come and go
    def _agent_events(self) -> None:
        """Take in what the agents did since the last time: publications, rejoins, losses."""
        events, self._deferred = [*self._deferred, *self.network.heal(self._is_ready, self.running)], []
        events += self.registry.drain(self.link.inbox, self.running)
        for ev in events:
            if isinstance(ev, Published):
                if ev.model in self.async_models and ev.msg.mtype == "step_reply":
                    self.record.stats(ev.model).count(ev.model, ev.msg["tick"], ev.msg)
                else:
                    self.triggers.absorb(ev.model, ev.msg)
            elif isinstance(ev, ServiceCall):
                self.triggers.on_service(ev)
            elif isinstance(ev, Rejoin):
                self._rejoin(ev.name)
            elif isinstance(ev, Vanished):
                if self.network.down or self.link.cut_off(grace=0.5):
                    self.network.lost()  # not a death: the next step waits for the network
                elif ev.name != self.scene.main or not self._main_back(ev.why):
                    self.handovers.fallback(ev.name, self.network.exits.get(ev.name, ev.why))

    def _main_back(self, why: str = "its liveliness token vanished") -> bool:
        """The main model vanished: nothing can take its place, so the run waits (up to the step timeout) for
        the same process to come back, then goes on, degraded. False: it did not (or came back as a new one)."""
        main, tick = self.scene.main, self.clock.tick
        if why != "its liveliness token vanished":
            return False  # it is there but does not answer: waiting longer is no help
        back, waited, events = self.network.wait_for(main, self.opts.step_timeout, self.running, self.agent_check)
        self._deferred += events
        if back:
            self.record.degraded.append(f"the main model {main} was unreachable at tick {tick} (its token vanished) "
                                        f"and came back; the run waited {waited:.1f} s for it")
            self._event("rejoin", {"model": main, "tick": self.clock.tick, "waited_s": round(waited, 3)})
        return back

    def _rejoin(self, name: str) -> None:
        """A known agent came back (restart or restored link): init it owning nothing, start it."""
        if self.map.owned_by(name):  # its token's end with the network down was no death: what it owned falls back
            self.handovers.fallback(name, "it registered again while the network was down, to be initialised anew")
        try:
            self._init_model(name, [])
            self.link.ask(name, "start", codec.encode("start", tick=self.clock.tick, t=self.clock.t), "ack")
            info = self.registry.agents[name]
            self.stepper.timed_out.discard(name)  # (a new process of one taken out: its answers are step answers)
            info.ready, info.rejoin_pending = True, False
            if name in self.clock_models:  # a new process: it starts from the next clock tick
                self.gate.rejoined(name, self.clock.tick)
            log.warning("%s rejoined the run at tick %d", name, self.clock.tick)
            self._event("rejoin", {"model": name, "tick": self.clock.tick})
        except (AgentError, ProtocolError, SceneError) as e:
            log.error("%s could not rejoin: %s", name, e)

    def _on_done(self, name: str, reply: dict[str, Any]) -> None:
        """A ``done/<id>`` answer (Zenoh thread): a clock-driven model's progress, a free one's step, a step answer."""
        if name in self.async_models:
            if name not in self.clock_models or self.gate.note(name, reply["tick"]):
                self.link.inbox.put(Published(name, Message(reply)))
        elif name in self.stepper.timed_out:  # taken out for being too slow: it is back
            self.stepper.timed_out.discard(name)
            self.link.inbox.put(Answered(name))
        else:
            self.stepper.put(name, reply)

    def _drain_clock(self, tick: int) -> None:
        """At the end of a replay the last ticks count in full: wait for the clock-driven models' answers to
        every tick sent and take in what they published (outputs may still fire triggers)."""
        if self.clock_models and self.gate.slack is not None and not self.stop_requested.is_set():
            self.gate.wait(tick, 0, self.network.down)
            time.sleep(0.01)  # their publications left before their answers; let them land in the inbox
            self._agent_events()

    def _live(self) -> bool:
        return self.source is not None and bool(self.source.live)

    def _event(self, name: str, data: dict[str, Any]) -> None:
        self.link.event(name, data, self.clock.tick, self.clock.t)
