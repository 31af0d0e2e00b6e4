"""Stepping the models: which ticks go in one step message, the step broadcast, and the clock gate.

- :class:`BatchRule` (pure): where a window of ticks must end so that nothing can change between its ticks
  that one message per tick would have let change: no trigger, evaluator, handover or input. A window ends
  after a tick with an action due, after a tick at which a model that a ``topic``/``event`` trigger listens
  to is stepped, before a tick on which a model that reads an attribute is due when that attribute's owner
  was stepped earlier in the window, and at ``clock.batch`` ticks.
- :func:`tick_body`: one tick of the step broadcast (shared joints, a section per service model due).
- :class:`BroadcastStepper`: sends a window's ticks in one ``step`` message and collects every model's
  ``done/<id>`` answers, each answer covering its ticks of the window.
- :class:`ClockGate`: a replay sends clock tick *k* only once each clock-driven model has answered tick
  *k* - 1 - *slack*, so a slow clock-driven model slows the replay instead of changing its outcome.
"""
from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from protocol import codec

from .record import RunRecord

log = logging.getLogger("twin.conductor")

RESEND_AFTER = 1.0
"""Seconds without an answer after which a step message goes out again (:meth:`BroadcastStepper.collect`)."""
TICK_ALLOWANCE_S = 1.0
"""Seconds a step message of several ticks gives a model for each tick after its first, beyond the step timeout
(at most the step timeout each): a hung model of a 32-tick window is found in 41 s, not 320 s, while the slowest
shipped model takes well under 0.1 s a tick on a loaded machine."""
LATER_PER_MODEL = 8
"""Answers to step messages not yet collected kept per model (a pipeline has one message ahead)."""


def deadline_timer(seconds: float | None, stop: Callable[[str], None]) -> threading.Timer | None:
    """A started timer that calls ``stop(reason)`` when a run's ``--deadline`` of ``seconds`` has passed (None:
    there is none): it ends a run waiting for its agents or its robot's first message too, not only its loop."""
    if seconds is None or seconds >= threading.TIMEOUT_MAX:  # (a longer wait fails in the timer's thread: 292 years)
        return None
    timer = threading.Timer(seconds, stop, (f"its deadline of {seconds:g} s",))
    timer.daemon = True
    timer.start()
    return timer


def step_deadline(step_timeout: float, ticks: int) -> float:
    """Seconds a model may take to answer a step message that carries ``ticks`` of its ticks."""
    return step_timeout + max(0, ticks - 1) * min(step_timeout, TICK_ALLOWANCE_S)


@dataclass
class Clock:
    """The conductor's clock: integer ticks, ``t = tick * dt``."""

    dt: float
    tick: int = 0
    t: float = 0.0

    def set(self, tick: int) -> None:
        self.tick, self.t = tick, tick * self.dt


# --------------------------------------------------------------------------------------- planning
@dataclass(frozen=True)
class BatchRule:
    """When a window of ticks must end (pure: the tick loop gives it what happened in the window).

    ``limit`` is the most ticks one message may carry (1: one message per tick); ``trigger_sources`` the
    models that ``topic``/``event`` triggers listen to; ``readers`` the service models that read others'
    attributes, with their periods in ticks."""

    limit: int
    trigger_sources: frozenset[str] = frozenset()
    readers: tuple[tuple[str, int], ...] = ()
    while_owning: frozenset[str] = frozenset()  # trigger sources only through events they raise about what they own

    def now(self, owning: Callable[[str], bool]) -> BatchRule:
        """The rule for the next window: a model of ``while_owning`` is a trigger source only while it owns
        something (``owning(model)``), since it cannot raise those events otherwise."""
        extra = frozenset(m for m in self.while_owning if owning(m))
        return replace(self, trigger_sources=self.trigger_sources | extra) if extra else self

    def ends_after(self, length: int, actions_due: bool, stepped_now: Collection[str], stepped: Collection[str],
                   next_tick: int, read_owners: Mapping[str, Collection[str]]) -> bool:
        """Whether the window must end after its ``length``-th tick, at which ``stepped_now`` were stepped
        (``stepped``: every model stepped in the window so far; ``read_owners``: reader -> the models that own
        what it reads)."""
        if length >= self.limit or actions_due or not self.trigger_sources.isdisjoint(stepped_now):
            return True
        return any(not next_tick % period and not set(read_owners[n]).isdisjoint(stepped)
                   for n, period in self.readers)


@dataclass
class TickPlan:
    """One tick of a window: its body in the step message (None if no service model is due), the models
    stepped, and the action annotations due at it."""

    tick: int
    t: float
    body: dict[str, Any] | None
    names: tuple[str, ...]
    actions: list[dict[str, Any]] = field(default_factory=list)


def tick_body(tick: int, t: float, dt: float, sections: Mapping[str, tuple[int, bool, bool]],
              ready: Callable[[str], bool], take_actions: Callable[[str], list[dict[str, Any]]],
              inputs: Callable[[str], dict[str, Any]], joints: dict[str, Any] | None) -> tuple[dict[str, Any] | None,
                                                                                              tuple[str, ...]]:
    """One tick of the step broadcast: the shared joints and a section per service model due (or None).

    ``sections`` maps each service model to (period, wants telemetry, reads something). A model without
    telemetry or inputs that steps every tick shares one section (listed in ``due``)."""
    out: dict[str, Any] = {}
    due = []
    want_joints = False
    for name, (period, telemetry, reads) in sections.items():
        if tick % period or not ready(name):
            continue
        if telemetry:
            acts = take_actions(name)
            want_joints = True
        elif not reads and period == 1:
            due.append(name)
            continue
        else:
            acts = []
        out[name] = {"dt": dt * period, "actions": acts, "inputs": inputs(name) if reads else {}}
    if not out and not due:
        return None, ()
    body: dict[str, Any] = {"tick": tick, "t": t, "joints": joints if want_joints else None, "models": out}
    if due:
        body["due"] = due
        body["shared"] = {"dt": dt, "actions": [], "inputs": {}}
    return body, (*out, *due)


def window_payload(window: list[TickPlan]) -> dict[str, Any] | None:
    """The step message of a window: its first tick's body with the later ones in ``more`` (None: nothing due)."""
    bodies = [w.body for w in window if w.body is not None]
    if not bodies:
        return None
    first = dict(bodies[0])
    if len(bodies) > 1:
        first["more"] = bodies[1:]
    return first


# --------------------------------------------------------------------------------------- stepping
class BroadcastStepper:
    """Collects the ``done/<id>`` answers to one step message (answers arrive on Zenoh threads: :meth:`put`)."""

    def __init__(self, record: RunRecord, step_timeout: float) -> None:
        self.record = record
        self.step_timeout = step_timeout
        self.timed_out: set[str] = set()  # models that did not answer in time (the loop takes them as lost)
        self._q: queue.SimpleQueue[tuple[str, dict[str, Any]]] = queue.SimpleQueue()
        self._later: collections.deque[tuple[str, dict[str, Any]]] = collections.deque()  # answers to a later message
        self.flooded: set[str] = set()  # models that answered more later messages than a pipeline has (said once)

    def put(self, name: str, reply: dict[str, Any]) -> None:
        self._q.put((name, reply))

    def collect(self, expected: dict[str, list[int]], got: dict[str, dict[int, dict[str, Any]]],
                gone: Callable[[Collection[str]], set[str]], idle: Callable[[], None] | None = None,
                resend: Callable[[], None] | None = None, partial: Collection[str] = ()) -> set[str]:
        """Wait for the answer of every model in ``expected`` (model -> the ticks it was stepped in this message)
        and put each in ``got`` (model -> tick -> reply). Returns the models given up on because their
        liveliness token vanished meanwhile. A model answers a batch once it has stepped all of its ticks: it has
        the step timeout, and :data:`TICK_ALLOWANCE_S` more for each tick after the first (:func:`step_deadline`).
        A late answer to an earlier message is ignored; an answer for the wrong ticks is a problem of that model;
        one to a later message (sent before this one was answered: a :class:`~conductor.flow.Pipeline`) is kept for
        the next call. ``idle()`` is done first, while the models step.

        With no answer for :data:`RESEND_AFTER` seconds, ``resend()`` sends the message again: a link that
        lapsed and came back between two liveliness checks loses what was on it, and an agent answers the same
        message again without stepping twice. A model of ``partial`` may answer a first part of its ticks and say
        it ``stopped`` (``tick.until``)."""
        expected = dict(expected)
        if idle is not None:
            idle()
        deadline = time.monotonic() + step_deadline(self.step_timeout, max(len(ticks) for ticks in expected.values()))
        nudge = time.monotonic() + RESEND_AFTER
        given_up: set[str] = set()
        later, self._later = self._later, collections.deque()
        newest = max(ticks[-1] for ticks in expected.values())
        while expected:
            try:
                name, rep = (later.popleft() if later else self._q.get(timeout=0.05) if not gone(expected)
                             else self._q.get_nowait())
            except queue.Empty:
                lost = gone(expected)
                if lost:
                    for name in lost:
                        del expected[name]
                    given_up |= lost
                    continue
                now = time.monotonic()
                if resend is not None and now > nudge and now < deadline:
                    log.info("no answer from %s for %.1f s: step message sent again", sorted(expected), RESEND_AFTER)
                    resend()
                    nudge = now + RESEND_AFTER
                if now > deadline:
                    for name, ticks in expected.items():
                        self.record.stats(name).problem(
                            name, f"no step result for tick {ticks[0]} within {self.step_timeout} s")
                    self.timed_out |= set(expected)
                    self._later.extendleft(reversed(later))
                    return given_up
                continue
            if name not in expected or rep["tick"] != expected[name][0]:
                if rep["tick"] > newest:
                    self._keep_for_later(name, rep)
                continue  # a late answer to an earlier message, or a model not stepped now
            ticks = expected[name]
            more = rep.get("more") or ()
            cut = name in partial and rep.get("stopped") is True and len(more) < len(ticks) - 1
            if (len(more) != len(ticks) - 1 and not cut) or any(r["tick"] != j for r, j in zip(more, ticks[1:])):
                self.record.stats(name).problem(
                    name, f"answered ticks {[rep['tick']] + [r['tick'] for r in more]} of a message that "
                          f"stepped it on ticks {ticks}")
                continue
            del expected[name]
            got[name] = {rep["tick"]: rep, **{r["tick"]: r for r in more}}
            if resend is not None:  # answers are coming: the message got through
                nudge = time.monotonic() + RESEND_AFTER
        self._later.extendleft(reversed(later))
        return given_up

    def _keep_for_later(self, name: str, rep: dict[str, Any]) -> None:
        """Keep ``name``'s answer to a message not yet collected: a pipeline is one message ahead, so a model has
        one such answer; more than :data:`LATER_PER_MODEL` of them (a model, or someone with its keys, answering
        what was never asked) are dropped and a problem of that model, said once, and never crowd out another
        model's answers."""
        if sum(1 for n, _ in self._later if n == name) < LATER_PER_MODEL:
            self._later.append((name, rep))
        elif name not in self.flooded:
            self.flooded.add(name)
            self.record.stats(name).problem(name, f"answered ticks {rep['tick']} and more that were never sent "
                                                  f"(over {LATER_PER_MODEL} answers ahead): left out")


def clock_slack(scene: Any, live: bool) -> int | None:
    """Unanswered clock ticks a replay of ``scene`` allows its clock-driven models (None: live, or never wait)."""
    if live or scene.max_lag is None:
        return None
    return int(math.floor(scene.max_lag * scene.rate + 1e-9))


class ClockGate:
    """The ``clock`` of clock-driven models: how far each has answered, and the wait that keeps a replay within
    ``slack`` ticks of the slowest of them. ``publish`` puts a clock message on the wire; ``cut_off`` says
    whether the conductor's own network is gone (then waiting is pointless)."""

    def __init__(self, models: frozenset[str], record: RunRecord, step_timeout: float,
                 publish: Callable[[bytes], None], cut_off: Callable[[], bool], *, slack: int | None,
                 waitable: Callable[[str], bool], stop: threading.Event,
                 gone: Callable[[Collection[str]], set[str]]) -> None:
        self.models = models
        self.record = record
        self.step_timeout = step_timeout
        self.slack = slack  # unanswered ticks a replay allows (None: live, or never wait)
        self._publish = publish
        self._cut_off = cut_off
        self._waitable = waitable  # whether a model is one to wait for (ready, alive, answers each tick)
        self._stop = stop
        self._gone = gone
        self._last: bytes | None = None
        self.done: dict[str, int] = {}
        self.behind: set[str] = set()  # waited for in vain: not waited for again until caught up
        self._heard: dict[str, float] = {}  # when each last answered a new tick (monotonic)
        self._sent = -1  # the last clock tick sent (an answer to a later one is none: stale, or forged)
        self._sent_at: collections.deque[tuple[int, float]] = collections.deque(maxlen=1 << 16)  # (tick, when)
        self._ahead: dict[str, int] = {}  # models that answered a tick never sent (said once, by wait)
        self._t0: float | None = None
        self._evt = threading.Event()

    def send(self, tick: int, t: float, dt: float, network_down: bool = False) -> None:
        """Wait as :meth:`wait` allows, then publish clock tick ``tick`` (remembered: while waiting for an
        answer, it is sent again every 0.5 s)."""
        self.wait(tick, self.slack, network_down)
        self._sent = tick
        self._sent_at.append((tick, time.monotonic()))
        self._last = codec.encode_unchecked("clock", {"tick": tick, "t": t, "dt": dt})
        self._publish(self._last)

    def note(self, name: str, tick: int) -> bool:
        """A clock-driven model answered ``tick`` (from a Zenoh thread); True if it is news. An answer to a tick
        not yet sent is none: taken, it would make the model seem ahead for the rest of the run (never waited
        for, its real answers no news)."""
        if tick > self._sent:
            self._ahead.setdefault(name, tick)
            return False
        new = tick > self.done.get(name, -1)
        if new:
            self.done[name] = tick
            self._heard[name] = time.monotonic()
        self._evt.set()
        return new

    def rejoined(self, name: str, tick: int) -> None:
        """A new process of ``name`` starts from the next clock tick."""
        self.done[name] = tick
        self._heard[name] = time.monotonic()
        self.behind.discard(name)

    def wait(self, tick: int, slack: int | None, network_down: bool = False) -> None:
        """Before clock tick ``tick`` goes out, wait (unless ``slack`` is None: live) until every clock-driven
        model to wait for has answered all but at most ``slack`` of the ticks already sent, and note the most
        each had left unanswered. One that does not catch up within the step timeout is a problem of the run
        and is not waited for again until it has caught up by itself. Where nothing waits (live, or ``max_lag:
        null``), one that answered no new tick for the step timeout while ticks were due is that problem too: a
        model that hung with its liveliness token alive."""
        gone, stop = self._gone, self._stop
        if self._t0 is None:
            self._t0 = time.monotonic()
        self._sent = max(self._sent, tick - 1)  # (every tick before went out)
        for name, ahead in list(self._ahead.items()):
            if ahead >= 0:
                self._ahead[name] = -1  # (said once)
                text = f"answered clock tick {ahead}, which was never sent: left out"
                self.record.stats(name).problem(name, text)
                self.record.error(f"tick {tick}: clock-driven model {name}: {text}")
        for name in self.models:
            if not self._waitable(name):
                continue
            stats = self.record.stats(name).clock
            stats.setdefault("max_lag_ticks", 0)
            stats.setdefault("waited_s", 0.0)
            need = tick - 1 - (slack or 0)  # the oldest tick it must have answered
            if slack is not None and self.done.get(name, -1) < need and name not in self.behind \
                    and not gone({name}) and not network_down:
                stats["waited_s"] += self._wait_for(name, need, tick, stop, gone)
            done = self.done.get(name, -1)
            if done >= need:
                self.behind.discard(name)
            elif slack is None and name not in self.behind and not network_down and not gone({name}):
                self._silent(name, tick, done)
            stats["max_lag_ticks"] = max(stats["max_lag_ticks"], tick - 1 - done)
        least = min((self.done.get(n, -1) for n in self.models), default=tick)
        while self._sent_at and self._sent_at[0][0] <= least:  # (answered by every model: no longer owed)
            self._sent_at.popleft()

    def _silent(self, name: str, tick: int, done: int) -> None:
        """Where nothing waits: ``name``, behind at ``tick``, is a problem once it has answered no new tick for
        the step timeout (said once, until it has caught up)."""
        now = time.monotonic()
        # silent since its last answer, or since the tick it owes went out if later (the conductor itself may
        # have paused: its network gone, a rejoin, a slow step; then it sends its ticks back to back)
        owed = next((at for k, at in self._sent_at if k > done), now)
        quiet = now - max(self._heard.get(name, self._t0 or now), owed)
        if quiet > self.step_timeout:
            self.behind.add(name)
            text = (f"answered no clock tick for {quiet:.1f} s, {tick - 1 - done} unanswered; it hung or fell "
                    "behind (nothing waits for it)")
            self.record.stats(name).problem(name, text)
            self.record.error(f"tick {tick}: clock-driven model {name}: {text}")

    def _wait_for(self, name: str, need: int, tick: int, stop: threading.Event,
                  gone: Callable[[Collection[str]], set[str]]) -> float:
        """Wait until ``name`` has answered tick ``need``; returns the seconds waited."""
        t0 = time.monotonic()
        nudge, deadline = t0 + 0.5, t0 + self.step_timeout
        while not stop.is_set():
            self._evt.clear()
            if self.done.get(name, -1) >= need or gone({name}):
                break
            now = time.monotonic()
            if now >= nudge:
                if self._cut_off():
                    break  # our own network is gone: the next step finds out and waits for it
                if self._last is not None:  # a clock tick or its answer may have been dropped
                    self._publish(self._last)
                nudge = now + 0.5
            if now >= deadline:
                self.behind.add(name)
                behind = tick - 1 - self.done.get(name, -1)
                text = (f"{behind} clock ticks unanswered after waiting {self.step_timeout} s; "
                        "the replay no longer waits for it")
                self.record.stats(name).problem(name, text)
                self.record.error(f"tick {tick}: clock-driven model {name}: {text}")
                break
            self._evt.wait(0.05)
        return time.monotonic() - t0


class Pacer:
    """Progress about once a second, and pacing: a replay at ``rtf`` times real time, or live at the wall clock
    (neither: as fast as the models allow)."""

    def __init__(self, dt: float, rtf: float | None, live: bool, progress: Callable[[dict[str, Any]], None] | None,
                 duration: float | None, record: RunRecord | None = None) -> None:
        self.dt, self.rtf, self.live, self.progress, self.duration = dt, rtf, live, progress, duration
        self.record = record  # (its ``pace``: how far a paced replay fell behind its pace)
        self.behind_s = 0.0
        self.start = self._last = time.perf_counter()

    @classmethod
    def of(cls, conductor: Any) -> Pacer:
        """The pacer of ``conductor``'s run (a :class:`~conductor.core.Conductor`)."""
        pacer = cls(conductor.clock.dt, conductor.opts.rtf, conductor._live(), conductor.progress,
                    getattr(conductor.source, "duration", None), conductor.record)
        came = getattr(conductor.source, "first_arrival", None)
        if pacer.live and came is not None:  # live: tick 0 is when the robot's first message came, so what it sent
            # while the agents started (a robot publishing before the twin began) is caught up as fast as the
            # models allow, then the wall clock is followed (it stayed that far behind to the end)
            pacer.start -= max(0.0, time.monotonic() - came)
        return pacer

    def after(self, tick: int, stop: threading.Event | None = None) -> None:
        """The loop has done every tick before ``tick``; a ``stop`` (a signal, a request) ends the wait at once."""
        now = time.perf_counter()
        if self.progress is not None and now - self._last > 1.0:
            self._last = now
            el = now - self.start
            t = (tick - 1) * self.dt
            self.progress({"tick": tick - 1, "t": t, "duration": self.duration, "rtf": t / el if el > 0 else None})
        if self.rtf or self.live:
            delay = self.start + tick * self.dt / (self.rtf or 1.0) - time.perf_counter()
            if -delay > self.behind_s + 0.05 and self.rtf and not self.live and self.record is not None:
                self.behind_s = -delay  # (then the replay goes as fast as the models allow until it has caught up)
                self.record.pace = {"rtf": self.rtf, "behind_max_s": round(-delay, 2), "at_t": round(tick * self.dt, 3)}
            if delay > 0 and stop is not None:
                stop.wait(delay)
            elif delay > 0:
                time.sleep(delay)


def owner_events(registry: Any, name: str) -> set[str]:
    """The events model ``name`` declared it raises only about what it owns (``Register.owner_events``)."""
    info = registry.get(name)
    return set(info.desc.get("owner_events") or []) if info is not None else set()


def batch_rule(scene: Any, registry: Any, reads: Mapping[str, list[str]], paced_or_live: bool) -> BatchRule:
    """When windows of ticks end, for an unpaced replay of service-stepped models only, every agent able to step
    batches (an agent of another make sees one tick per message): after an action, after a step of a model
    whose results a ``topic``/``event`` trigger listens to (of a model whose triggering events are all
    ``owner_events``: only while it owns something), before a step of a reader whose owners were stepped."""
    limit = 1
    only_service = all(m.step == "service" for m in scene.models.values())
    if scene.batch > 1 and not paced_or_live and only_service:
        unable = sorted(n for n in scene.models if not registry.agents[n].desc.get("batch"))
        if unable:
            log.info("one step message per tick: %s do not step batches of ticks", ", ".join(unable))
        else:
            limit = scene.batch
    always: set[str] = set()
    while_owning: set[str] = set()
    for trig in scene.triggers:
        for k in ("topic", "event"):
            if k in trig.on:
                model, _, name = trig.on[k].partition(".")
                (while_owning if k == "event" and name in owner_events(registry, model) else always).add(model)
    readers = tuple((n, s.period) for n, s in scene.models.items() if s.step == "service" and reads[n])
    return BatchRule(limit, frozenset(always), readers, frozenset(while_owning - always))


def owner_event_breaches(window: list[TickPlan], replies: Mapping[str, Mapping[int, Mapping[str, Any]]],
                         owned_nothing: Collection[str], registry: Any) -> list[str]:
    """What makes the run degraded when a model raised one of its ``owner_events`` while owning nothing before
    the last tick of a window: the ticks after it in that step message did not wait for the triggers it fired."""
    out = []
    for name in sorted(owned_nothing):
        declared = owner_events(registry, name)
        for plan in window[:-1]:
            for ev in (replies.get(name, {}).get(plan.tick) or {}).get("events") or []:
                if isinstance(ev, dict) and ev.get("name") in declared:
                    out.append(f"{name} raised {ev['name']!r} at tick {plan.tick} while it owned nothing, though it "
                               "declares it only about what it owns: the ticks after it in the same step message "
                               "did not wait for the triggers it fired")
    return out
