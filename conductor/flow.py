"""Stepping in the order the data flows: fewer step messages where triggers listen to a model's results.

The batch rule (:mod:`~conductor.stepping`) ends a window after every step of a model a ``topic``/``event``
trigger listens to, since the ticks after it must wait for the triggers it may fire. Most of those steps fire
nothing. Here such a model (a *lead*) steps first, alone, told by ``tick.until`` to stop after the first tick
at which it raises an event or changes an output that a trigger listens to; the other models (the
*followers*) then step up to that tick, given per tick what the leads reported before it. The window ends
where a trigger may fire, not at every step that might have fired one. What every model is given, tick by
tick, is what one message per tick gives it (``tests/test_batch.py`` compares the two).

The followers step in tiers (:meth:`FlowScheduler._tiers`), in the order their values flow while the map stands
as it does: a reader after the model that owns what it reads, given per tick what that one reported at the ticks
before, a message per tier. Those that read each other's changing values share the last tier, where the batch
rule ends the window at every step of what they read.

Two kinds of lead:

- a *free* lead reads nothing, owns nothing (from the start either), is never given anything by a trigger (an
  effect that names its model by a variable or an expression may name any), is called by none, and
  its evaluators are asked only at actions (which end every window): nothing the others do can change its
  steps. It steps ahead to the window's planned end, and its answers wait for their ticks;
- the *coupled* lead (at most one) is any other model triggers listen to, while they do (an ``owner_events``
  model only while it owns something). A trigger fired by a free lead may change what it owns, so it steps
  only up to the free leads' first stop, and the followers only up to its own.

A lead may read (at most one, the *reader*) what the coupled lead owns, if that one can go back (its model
defines ``snapshot``/``restore``): insertion's connector reads the DIP pose in_hand holds, and its events take
that pose from in_hand. The coupled lead steps first (``tick.mark``: it keeps a checkpoint), the reader next,
given per tick what the coupled lead reported, up to its own first stop; the coupled lead, stepped past that
stop, is sent back to it (``model/<id>/rewind``). Its answers reach the run log once the window has ended, as
they stand. While the reader reads what a follower owns, it follows, and its steps end the window.

Otherwise (leads that read, several coupled leads, the main model a lead, an agent that cannot stop early)
the run keeps the batch rule: :func:`flow_roles` says which.
"""
from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field, replace
from fnmatch import fnmatchcase
from typing import Any

from protocol import codec
from protocol.errors import AgentError

from .responsibility import Responsibilities, differs
from .stepping import BatchRule, TickPlan, owner_events

log = logging.getLogger("twin.conductor")

Replies = dict[str, dict[int, dict[str, Any]]]
"""model -> tick -> its step reply."""

REACH = 4
"""How many windows' worth of ticks (``clock.batch`` each) a free lead steps ahead in one message."""


@dataclass(frozen=True)
class FlowRoles:
    """Who leads: ``free`` leads, the ``coupled`` lead (or None) and where each stops (``until``)."""

    free: tuple[str, ...]
    coupled: str | None
    until: dict[str, dict[str, list[str]]]
    fences: tuple[tuple[str, str], ...] = ()  # (operation, phase) of the action triggers that ask a free lead
    coupled_ahead: bool = False  # the coupled lead may step ahead where no trigger can fire (no service triggers)
    reader: str | None = None  # the lead that reads what the coupled lead owns (it steps after it)


def _named(expr: Any, models: Collection[str]) -> str | None:
    """The model an effect's field names, if it is a model's name (None: an expression or a variable, which may
    be any model; no variable is named as a model is)."""
    src = str(getattr(expr, "source", expr)).strip()
    return src if src in models else None


def flow_roles(scene: Any, registry: Any, reads: Mapping[str, list[str]], rule: BatchRule) -> FlowRoles | None:
    """The leads of a run that batches (``rule.limit`` > 1), or None when it keeps the batch rule."""
    sources = rule.trigger_sources | rule.while_owning
    if rule.limit <= 1 or not sources or scene.main in sources:
        return None
    readers = sorted(m for m in sources if reads.get(m))
    if len(readers) > 1 or any(not registry.agents[m].desc.get("until") for m in sources):
        return None  # leads that read each other would need each other's values: no order of steps serves them
    until, targets, asked, at_actions = _trigger_facts(scene, sources)
    free = _free_leads(scene, registry, reads, rule, targets, asked)
    coupled = sorted(sources - set(free) - set(readers))
    if len(coupled) > 1 or (readers and coupled and not _goes_back(coupled[0], registry, reads)):
        return None
    free_evaluators = {name for name, ev in scene.evaluators.items() if ev.model in free}
    fences = tuple(sorted({on for on, calls in at_actions if calls & free_evaluators}))
    return FlowRoles(free, coupled[0] if coupled else None, until, fences,
                     not readers and not any("service" in trig.on for trig in scene.triggers),
                     readers[0] if readers else None)


def _free_leads(scene: Any, registry: Any, reads: Mapping[str, list[str]], rule: BatchRule,
                targets: set[str | None], asked: set[str]) -> tuple[str, ...]:
    """The models triggers listen to that nothing the others do can change (the free leads, in scene order)."""
    if None in targets:  # an effect names its model by an expression: it may give anything to any model
        return ()
    asked_models = {ev.model for name, ev in scene.evaluators.items() if name in asked}
    owning = set(scene.initial_owners().values())
    return tuple(m for m in scene.models if m in rule.trigger_sources and m not in targets and m not in asked_models
                 and m not in owning and not owner_events(registry, m) and not reads.get(m))


def _goes_back(coupled: str, registry: Any, reads: Mapping[str, list[str]]) -> bool:
    """Whether a reader can lead after the coupled lead: that one reads nothing, and can go back to where the
    reader stops (its agent keeps checkpoints: ``register.rewind``)."""
    return not reads.get(coupled) and bool(registry.agents[coupled].desc.get("rewind"))


def _trigger_facts(scene: Any, sources: Collection[str]) -> tuple[dict[str, dict[str, list[str]]], set[str | None],
                                                                   set[str], list[tuple[tuple[str, str], set[str]]]]:
    """What the triggers tell: where each lead stops (the events and outputs they listen to), the models their
    effects name (None: one is named by an expression), the functions called by triggers that an action does not
    fire (evaluators among them), and those an action trigger calls ((operation, phase) -> functions)."""
    until: dict[str, dict[str, list[str]]] = {m: {"events": [], "outputs": []} for m in sources}
    targets: set[str | None] = set()
    asked: set[str] = set()
    at_actions: list[tuple[tuple[str, str], set[str]]] = []
    for trig in scene.triggers:
        for kind, field_ in (("topic", "outputs"), ("event", "events")):
            if kind in trig.on:
                model, _, name = str(trig.on[kind]).partition(".")
                if name not in until[model][field_]:
                    until[model][field_].append(name)
        for eff in trig.do:
            if eff.kind != "warn":  # (a warning is given to no model)
                targets.add(_named(eff.fields.get("to") if eff.kind == "transfer" else eff.fields.get("model"),
                                   scene.models))
        exprs = [trig.when, *(e for _, e in trig.let),  # (a call effect's args are a list of expressions)
                 *(x for eff in trig.do for v in eff.fields.values() for x in (v if isinstance(v, list) else [v]))]
        calls = {c for e in exprs for c in (getattr(e, "calls", None) or ())}
        if "action" in trig.on:
            at_actions.append(((str(trig.on["action"]), str(trig.on.get("phase", "start"))), calls))
        else:
            asked.update(calls)
    return until, targets, asked, at_actions


@dataclass
class Planned:
    """A tick taken from the feed: its time, actions, joints (None unless a model wanting them is due) and
    each due model's section without its inputs (computed when it is sent)."""

    tick: int
    t: float
    actions: list[dict[str, Any]]
    joints: Any
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)


def plan_tick(tick: int, t: float, dt: float, actions: list[dict[str, Any]],
              service: Mapping[str, tuple[int, bool, bool]], ready: Callable[[str], bool],
              take_actions: Callable[[str], list[dict[str, Any]]], joints: Any) -> Planned:
    """Tick ``tick`` as the feed gave it: a section per service model due and ready (``service``: model ->
    (period, wants telemetry, reads something)); the joints only if a model wanting them is due."""
    secs: dict[str, dict[str, Any]] = {}
    want = False
    for name, (period, telemetry, _) in service.items():
        if tick % period or not ready(name):
            continue
        secs[name] = {"dt": dt * period, "actions": take_actions(name) if telemetry else []}
        want |= telemetry
    return Planned(tick, t, actions, joints if want else None, secs)


class FlowScheduler:
    """The windows of a run stepped in data-flow order (see the module). The conductor gives it the ways to
    send a step message and collect its answers (``send``), to know whether the run is over before a tick
    (``over``) and whether a model is ready, and the list of what degraded the run (``problems``). It takes
    the ticks from the ``feed`` and sets the ``clock`` (``service``: model -> (period, wants telemetry,
    reads something), of the service-stepped models)."""

    name = "data-flow"  # (the run summary's schedule)

    def __init__(self, roles: FlowRoles, rmap: Responsibilities, reads: Mapping[str, list[str]], clock: Any,
                 feed: Any, service: Mapping[str, tuple[int, bool, bool]],
                 send: Callable[[list[TickPlan], dict[str, Any] | None, bool], Replies],
                 over: Callable[[int], bool], ready: Callable[[str], bool], problems: list[str], link: Any = None
                 ) -> None:
        self.roles, self.map, self.reads, self.clock, self.feed, self.service = roles, rmap, reads, clock, feed, service
        self._send, self._over, self._ready = send, over, ready
        self.pending: collections.deque[Planned] = collections.deque()  # taken from the feed, not yet stepped
        self._ahead: dict[str, dict[int, dict[str, Any]]] = {m: {} for m in roles.free}  # free leads' answers
        self._done: dict[str, int] = {m: -1 for m in roles.free}  # each free lead has stepped through this tick
        self._stop: dict[str, int] = {}  # free lead -> the tick of an answer waiting there that may fire a trigger
        self.problems = problems  # where the run is degraded: a lead that did not stop where it was to
        self._lead: dict[int, dict[str, Any]] = {}  # the coupled lead's answers ahead of the window
        self._lead_done = -1  # the coupled lead has stepped through this tick
        self.link = link  # (a reader's coupled lead goes back through it, and its answers reach the run log by it)
        self._held = roles.coupled if roles.reader is not None and roles.coupled is not None else None
        if self._held is not None and link is not None:
            link.held.add(self._held)

    def over(self, tick: int, stopping: bool) -> bool:
        """Whether the run ends before ``tick`` (ticks already taken from the feed are stepped first)."""
        return stopping if self.pending else self._over(tick)

    def window(self, tick: int, rule: BatchRule) -> tuple[list[TickPlan], Replies]:
        """Step the next window from ``tick`` (``rule``: the batch rule now): its ticks and every answer."""
        coupled, reader = self._leading(rule)
        leads = {*self.roles.free, *([coupled] if coupled else []), *([reader] if reader else [])}
        # a reader that follows ends the window at each of its steps: tiers would only split such short windows
        # into more messages, so its followers step as the batch rule steps them, in one
        ends = frozenset(m for m in rule.trigger_sources if m == self.roles.reader and m not in leads)
        tiers = self._tiers(leads) if not ends else [[n for n in self.service if n not in leads]]
        before = {n: set().union(*tiers[:i]) for i, tier in enumerate(tiers) for n in tier}
        read_owners = {n: self.map.owners_read_by(n, self.reads[n]) - leads - before.get(n, set())
                       for n, _ in rule.readers}
        plans = self._plan(tick, replace(rule, trigger_sources=ends), leads, read_owners)
        got: Replies = {}
        stop = self._free_leads(plans, rule)
        if coupled is not None:
            got[coupled], stop = self._coupled(plans, coupled, stop)
        elif self._lead:  # it no longer leads (it was lost): what it stepped ahead is void
            self._lead.clear()
        if reader is not None:
            got[reader], stop = self._reading(plans, reader, coupled, stop, got)
        done = [p for p in plans if p.tick <= stop]
        for p in plans[len(done):]:  # later ticks wait for the next window, less what the free leads stepped
            for m in self.roles.free:
                if self._done[m] >= p.tick:
                    p.sections.pop(m, None)
        self.pending.extendleft(reversed(plans[len(done):]))
        due = {n for p in plans for n in p.sections}
        self._follow(plans, [[n for n in tier if n in due] for tier in tiers], stop, coupled, rule, got)
        self._settle(got, stop)
        return [TickPlan(p.tick, p.t, None, tuple(p.sections), p.actions) for p in done], got

    # -------------------------------------------------------------------------------------- parts
    def _settle(self, got: Replies, stop: int) -> None:
        """The window ends at ``stop``: the free leads' answers up to it into ``got`` (the later ones wait), and
        the answers of the lead that may go back into the run log (they stand now)."""
        for m in self.roles.free:
            ahead = self._ahead[m]
            got[m] = {j: ahead.pop(j) for j in sorted(ahead) if j <= stop}
            if self._stop.get(m, stop + 1) <= stop:
                del self._stop[m]
        if self._held is not None and self.link is not None:
            self.link.log_answers(self._held, got.get(self._held, {}))

    def _leading(self, rule: BatchRule) -> tuple[str | None, str | None]:
        """The coupled lead and the reader that lead this window (None: not now). The reader follows while it
        reads what a follower owns (the window then ends at its steps)."""
        coupled = self.roles.coupled if self.roles.coupled in rule.trigger_sources else None
        reader = self.roles.reader if self.roles.reader in rule.trigger_sources else None
        if reader is not None and self.map.owners_read_by(reader, self.reads[reader]) - {coupled}:
            reader = None
        return coupled, reader

    def _tiers(self, leads: Collection[str]) -> list[list[str]]:
        """The followers in the order their values flow, now: each tier reads nothing that a model of its own tier
        or a later one owns (those that read each other's values share the last tier, where the batch rule ends
        the window at every step of what they read)."""
        left = [n for n in self.service if n not in leads]
        owners = {n: self.map.owners_read_by(n, self.reads.get(n, ())) & set(left) for n in left}
        tiers: list[list[str]] = []
        placed: set[str] = set()
        while left:
            now = [n for n in left if owners[n] <= placed]
            if not now:
                return [*tiers, left]
            tiers.append(now)
            placed.update(now)
            left = [n for n in left if n not in placed]
        return tiers

    def _follow(self, plans: list[Planned], tiers: list[list[str]], stop: int, coupled: str | None, rule: BatchRule,
                got: Replies) -> None:
        """Step the followers up to ``stop`` (into ``got``): a message per tier, each given per tick what the
        coupled lead and the tiers before it reported; the leads' next ticks ride along with the first."""
        last = next(p for p in reversed(plans) if p.tick <= stop)
        given = {m: got[m] for m in (coupled, self.roles.reader) if m in got}
        bodies = self._bodies(plans, tiers[0] if tiers else [], stop, given)
        lead_upto = self._lead_reach(coupled, stop, rule, last, got.get(coupled or "", {}))  # before todo's answers
        todo, span = self._ride_along(stop, rule, self._fence(last))  # the free leads' next ticks, with them
        riding = {**{m: span[-1].tick for m in todo}, **({coupled: lead_upto} if coupled and lead_upto > stop else {})}
        if riding:
            after = {**self._done, **({coupled: self._lead_done} if coupled else {})}
            bodies += self._bodies([p for p in self.pending if p.tick > stop], list(riding), max(riding.values()), {},
                                   after=after, upto=riding)
        if bodies:
            answers = self._send(bodies, {m: self.roles.until[m] for m in riding} or None, True)
            got.update((n, r) for n, r in answers.items() if n not in riding)
            self._note_free(todo, answers, span, stop)
            if coupled in riding:
                self._note_lead(coupled, answers.get(coupled, {}), riding[coupled])
        for i in range(1, len(tiers)):
            given.update((n, got.get(n, {})) for n in tiers[i - 1])
            bodies = self._bodies(plans, tiers[i], stop, given)
            if bodies:
                got.update(self._send(bodies, None, True))

    def _coupled(self, plans: list[Planned], coupled: str, stop: int) -> tuple[dict[int, dict[str, Any]], int]:
        """Step the coupled lead up to ``stop`` (what it stepped ahead before counts); its answers for the window
        and the tick at which the window must end."""
        done, cut = self._lead_done, stop
        if done < stop:
            bodies = self._bodies(plans, [coupled], stop, {}, after={coupled: done})
            if bodies and self._held == coupled:  # it keeps a checkpoint: the reader may end the window earlier
                bodies[0].body["mark"] = [coupled]  # type: ignore[index]
            mine = self._send(bodies, {coupled: self.roles.until[coupled]}, False).get(coupled, {})
            self._lead.update(mine)
            sent = [p.tick for p in plans if done < p.tick <= stop and coupled in p.sections]
            cut = max(mine) if mine and len(mine) < len(sent) else stop  # it stopped early
            self._lead_done = max(done, cut)
        replies = {j: self._lead[j] for j in sorted(self._lead) if j <= stop}
        stop = self._ends(coupled, replies, stop, cut)
        return {j: self._lead.pop(j) for j in list(replies) if j <= stop}, stop

    def _ends(self, lead: str, replies: Mapping[int, Mapping[str, Any]], stop: int, cut: int) -> int:
        """Where the window ends after a lead's ``replies``: ``stop``, or earlier where it stopped (``cut``) or at
        its first answer that may fire a trigger (one past that: the run is degraded)."""
        first = self._first_stop(lead, replies)
        if first is not None and max(replies) > first:
            self.problems.append(f"{lead} stepped on past tick {first}, where it was to stop")
        return min(stop, cut, stop if first is None else first)

    def _reading(self, plans: list[Planned], reader: str, coupled: str | None, stop: int,
                 got: Replies) -> tuple[dict[int, dict[str, Any]], int]:
        """Step the reader up to ``stop``, given per tick what the coupled lead reported before; its answers and the
        tick at which the window must end. Where it stops early (an event or an output a trigger listens to), the
        coupled lead, stepped past that tick, goes back to it (:meth:`_rewind`)."""
        given = {coupled: got[coupled]} if coupled in got else {}
        mine = self._send(self._bodies(plans, [reader], stop, given), {reader: self.roles.until[reader]},
                          False).get(reader, {})
        sent = [p.tick for p in plans if p.tick <= stop and reader in p.sections]
        cut = max(mine) if mine and len(mine) < len(sent) else stop  # it stopped early
        stop = self._ends(reader, mine, stop, cut)
        if coupled is not None and self._lead_done > stop:
            self._rewind(coupled, stop, got)
        return {j: r for j, r in mine.items() if j <= stop}, stop

    def _rewind(self, coupled: str, tick: int, got: Replies) -> None:
        """The coupled lead has stepped past ``tick``, where the window ends: back to it (``model/<id>/rewind``);
        its answers after it are void. If it cannot, the run is degraded."""
        for j in [j for j in got.get(coupled, {}) if j > tick]:
            del got[coupled][j]
        for j in [j for j in self._lead if j > tick]:
            del self._lead[j]
        try:
            if self.link is None:  # (a scheduler made without one, in a test)
                raise ValueError("no link to the agents")
            self.link.ask(coupled, "rewind", codec.encode("rewind", tick=tick), "ack")
        except (AgentError, ValueError) as e:
            self.problems.append(f"{coupled} could not go back to tick {tick}: {e}")
        self._lead_done = tick

    def _lead_reach(self, coupled: str | None, stop: int, rule: BatchRule, last: Planned,
                    replies: Mapping[int, Mapping[str, Any]]) -> int:
        """How far the coupled lead may step ahead with the followers' message: only where no trigger can fire at
        the window's end (no action there, no free lead's or its own answer that may fire one) and the scene has no
        service triggers, and then up to what the free leads have stepped without such an answer, the first tick
        with an action and :data:`REACH` windows (``stop``: else)."""
        if coupled is None or not self.roles.coupled_ahead or not self._ready(coupled) or last.actions \
                or self._lead_done < stop or any(t <= stop for t in self._stop.values()) \
                or self._first_stop(coupled, replies) is not None or not self.pending:
            return stop
        upto = min([stop + REACH * rule.limit, self.pending[-1].tick, *self._done.values(), *self._stop.values()])
        for p in self.pending:
            if p.tick > upto:
                break
            if p.actions:
                return p.tick
        return upto

    def _note_lead(self, coupled: str, replies: dict[int, dict[str, Any]], upto: int) -> None:
        """Keep the coupled lead's answers ahead until their ticks; note how far it has stepped."""
        self._lead.update(replies)
        sent = [p.tick for p in self.pending if self._lead_done < p.tick <= upto and coupled in p.sections]
        self._lead_done = max(replies) if replies and len(replies) < len(sent) else upto

    def _enter(self, tick: int) -> Planned:
        """Take tick ``tick`` from the feed."""
        self.clock.set(tick)
        dt = self.clock.dt
        actions = self.feed.enter(tick, dt)
        return plan_tick(tick, self.clock.t, dt, actions, self.service, self._ready, self.feed.take_actions,
                         self.feed.latest)

    def _plan(self, tick: int, rule: BatchRule, leads: Collection[str],
              read_owners: Mapping[str, Collection[str]]) -> list[Planned]:
        """The window's ticks as far as the followers allow (the batch rule without trigger sources; the leads'
        values come with each tick, so they do not end it)."""
        plans: list[Planned] = []
        stepped: set[str] = set()
        j = tick
        while True:
            p = self.pending.popleft() if self.pending else self._enter(j)
            plans.append(p)
            now = [n for n in p.sections if n not in leads]
            stepped.update(now)
            j += 1
            if self.over(j, False) or rule.ends_after(len(plans), bool(p.actions), now, stepped, j, read_owners):
                return plans

    def _free_leads(self, plans: list[Planned], rule: BatchRule) -> int:
        """Step, alone, the free leads that have not stepped this far and have no answer waiting that may fire a
        trigger (the first window, or after such an answer), ahead of the window up to :data:`REACH` windows or the
        first tick with an action; the first tick at which one of them may fire a trigger (else the window's last)."""
        end = plans[-1].tick
        todo = [m for m in self.roles.free if m not in self._stop and self._done[m] < end and self._ready(m)]
        if todo:
            extra = self._reach(plans, REACH * rule.limit)
            span = [p for p in plans + extra if p.tick > min(self._done[m] for m in todo)]
            got = self._send(self._bodies(span, todo, span[-1].tick, {}, after=self._done),
                             {m: self.roles.until[m] for m in todo}, False)
            self._note_free(todo, got, span, plans[0].tick - 1)
        return min([end, *self._stop.values()])

    def _note_free(self, todo: list[str], got: Replies, span: list[Planned], taken: int) -> None:
        """Keep the free leads' answers over ``span`` until their ticks, and note how far each has stepped and
        the first tick after ``taken`` (the last tick whose answers the map holds, or will before these) at which
        one may fire a trigger."""
        for m in todo:
            replies = got.get(m, {})
            self._ahead[m].update(replies)
            stepped = [p.tick for p in span if m in p.sections and p.tick > self._done[m]]
            first = self._first_stop(m, self._ahead[m], taken)
            if replies and len(replies) < len(stepped):  # it stopped early
                first = max(replies) if first is None else min(first, max(replies))
            if first is not None:
                self._stop[m], self._done[m] = first, max(first, max(replies, default=first))
            else:
                self._done[m] = span[-1].tick

    def _ride_along(self, stop: int, rule: BatchRule, action: bool) -> tuple[list[str], list[Planned]]:
        """The free leads that may step on with the followers' message, and the ticks they may step: those waiting
        after the window and more from the feed, up to :data:`REACH` windows past ``stop``, not past a tick with an
        action. None if the window ends with an ``action`` (its triggers may ask a free lead's evaluators once the
        answers are in); else a free lead rides along only if it has stepped at least to ``stop``, has no answer
        waiting after ``stop`` that may fire a trigger, and no action waits at or before the tick it has stepped to."""
        if action:
            return [], []
        todo = [m for m in self.roles.free if self._ready(m) and self._done[m] >= stop
                and self._stop.get(m, stop) <= stop and not any(self._fence(p) for p in self.pending
                                                                if p.tick <= self._done[m])]
        if not todo:
            return [], []
        ahead = self._waiting(stop + 1, stop + REACH * rule.limit)
        self.clock.set(stop)
        low = min(self._done[m] for m in todo)
        span = [p for p in ahead if p.tick > low]
        return (todo, span) if span else ([], [])

    def _reach(self, plans: list[Planned], most: int) -> list[Planned]:
        """The ticks after the window a free lead may step now: up to ``most`` ticks from the window's first, not
        past a tick with a fencing action (:meth:`_fence`), not past the run's end. (They stay waiting.)"""
        if self._fence(plans[-1]):
            return []
        extra = self._waiting(plans[-1].tick + 1, plans[0].tick + most - 1)
        self.clock.set(plans[-1].tick)
        return extra

    def _waiting(self, first: int, last: int) -> list[Planned]:
        """The waiting ticks ``first``..``last`` (entering more from the feed as needed: the clock is left at the
        last one entered), up to and including the first with a fencing action, never past the run's end."""
        out: list[Planned] = []
        for p in self.pending:
            if p.tick > last:
                return out
            if p.tick >= first:
                out.append(p)
            if self._fence(p):
                return out
        j = self.pending[-1].tick + 1 if self.pending else first
        while j <= last and not self._over(j):
            p = self._enter(j)
            self.pending.append(p)
            out.append(p)
            if self._fence(p):
                break
            j += 1
        return out

    def _fence(self, p: Planned) -> bool:
        """Whether a free lead must not step past tick ``p``: one of its actions fires a trigger that asks a free
        lead's evaluator (after the tick's answers are in, so the free lead must be where one message per tick
        would have it)."""
        return any(a["operation"] == op and phase in (a["phase"], "any") for a in p.actions
                   for op, phase in self.roles.fences)

    def _first_stop(self, model: str, replies: Mapping[int, Mapping[str, Any]], after: int = -1) -> int | None:
        """The first tick of ``replies`` after ``after`` at which ``model`` raised an event or changed an output a
        trigger listens to (None if none; changes judged as the triggers judge them: against what the map holds,
        then each answer against the one before)."""
        until = self.roles.until[model]
        seen: dict[str, Any] = {}
        for j in sorted(replies):
            rep = replies[j]
            hit = any(isinstance(ev, dict) and ev.get("name") in until["events"] for ev in rep["events"])
            for name, value in rep["outputs"].items():
                if name in until["outputs"]:
                    hit |= (self.map.changes(model, name, value) if name not in seen
                            else differs(seen[name], value))
                    seen[name] = value
            if hit and j > after:
                return j
        return None

    def _bodies(self, plans: list[Planned], models: list[str], last: int,
                given: Mapping[str, Mapping[int, Mapping[str, Any]]], after: Mapping[str, int] | None = None,
                upto: Mapping[str, int] | None = None) -> list[TickPlan]:
        """The step message of ``models`` over ``plans`` up to tick ``last`` (each after its ``after`` tick and up
        to its ``upto`` tick): a body per tick, a reader's inputs from the map and what the models that stepped
        the window before them (``given``: model -> tick -> answer) reported at earlier ticks of what they own."""
        out = []
        overlay: dict[tuple[str, str], tuple[str, Any]] = {}  # (entity, attribute) -> (its owner, its newest value)
        owner = self.map.owners.get
        inputs: dict[str, tuple[int, dict[str, Any]]] = {}  # a reader's inputs, while the overlay is the same
        version = 0
        for p in plans:
            if p.tick > last:
                break
            secs = {}
            for n in models:
                sec = p.sections.get(n)
                if sec is None or (after is not None and p.tick <= after[n]) or not self._ready(n) \
                        or (upto is not None and p.tick > upto[n]):
                    continue
                if self.reads.get(n):
                    if inputs.get(n, (-1,))[0] != version:
                        inputs[n] = (version, self._inputs(n, overlay))
                    secs[n] = {**sec, "inputs": inputs[n][1]}
                else:
                    secs[n] = {**sec, "inputs": {}}
            if secs:
                out.append(TickPlan(p.tick, p.t, {"tick": p.tick, "t": p.t, "joints": p.joints, "models": secs},
                                    tuple(secs), []))
            for m, replies in given.items():
                rep = replies.get(p.tick)
                if rep is not None and rep["state"]:
                    version += 1
                    for e, attrs in rep["state"].items():
                        if isinstance(attrs, dict):
                            for a, v in attrs.items():
                                if owner((e, a)) == m:
                                    overlay[(e, a)] = (m, v)
        return out

    def _inputs(self, name: str, overlay: Mapping[tuple[str, str], tuple[str, Any]]) -> dict[str, dict[str, Any]]:
        """What ``name`` reads: the map's values, with what their owners reported since (what the map will hold
        once those answers are taken in)."""
        out = self.map.inputs_for(name, self.reads[name])
        for (e, a), (m, v) in overlay.items():
            if m != name and any(fnmatchcase(f"{e}.{a}", pat) for pat in self.reads[name]):
                if v is not None:
                    out.setdefault(e, {})[a] = v
                elif a in out.get(e, {}):  # as the map leaves out a value reported as None
                    del out[e][a]
        return out


# ------------------------------------------------------------------------------------ one window ahead
def uncoupled(scene: Any, rmap: Responsibilities, reads: Mapping[str, list[str]], rule: BatchRule) -> bool:
    """Whether no window's step message can depend on the answers to an earlier one, so that windows may go out
    one ahead (:class:`Pipeline`): an unpaced replay (windows of more than one tick), no triggers (nothing
    changes who owns what or asks a model anything between windows), no model that reads what another owns,
    every model stepped by the conductor. The single-model baselines are such scenes."""
    return (rule.limit > 1 and not scene.triggers and all(m.step == "service" for m in scene.models.values())
            and not any(rmap.owners_read_by(n, r) for n, r in reads.items()))


class Pipeline:
    """The windows of an :func:`uncoupled` run, each sent before the answers to the one before it are taken:
    the models step the next window while the conductor takes in this one's answers (and their answers cross
    the wire meanwhile). What each model is given, tick by tick, is what the batch rule gives it; only the
    order of sending and taking in differs.

    ``fill(tick, rule)`` takes a window from the feed from ``tick`` on; ``step(window, ..., sent=, wait=)``
    sends it and collects its answers (:meth:`conductor.core.Conductor._step`); ``over(tick)`` says whether the
    run ends before ``tick``. A window whose answers did not all come (a model lost or too slow) ends the
    pipelining for the run: the window already out is sent again when its turn comes (an agent answers a
    message it has answered again without stepping twice), and the run goes on as the batch rule steps it."""

    name = "one ahead"  # (the run summary's schedule)

    def __init__(self, fill: Callable[[int, BatchRule], list[TickPlan]], step: Callable[..., Replies],
                 over: Callable[[int], bool]) -> None:
        self._fill, self._step, self._over = fill, step, over
        self._out: list[TickPlan] | None = None  # the window sent ahead, its answers not yet taken
        self._again = False  # it is to be sent again (pipelining ended while it was out)
        self.on = True

    def over(self, tick: int, stopping: bool) -> bool:
        """Whether the run ends before ``tick``: never while a window is out (its models have stepped it)."""
        return False if self._out is not None else self._over(tick)

    def window(self, tick: int, rule: BatchRule) -> tuple[list[TickPlan], Replies]:
        """Step the next window from ``tick``: the one out already, or a new one; send the one after it (unless
        the run ends there), then wait for this one's answers."""
        window, sent = (self._out, not self._again) if self._out is not None else (self._fill(tick, rule), False)
        self._out, self._again = None, False
        if not sent:
            self._step(window, wait=False)
        nxt = window[-1].tick + 1
        if self.on and not self._over(nxt):
            self._out = self._fill(nxt, rule)
            self._step(self._out, wait=False)
        replies = self._step(window, ahead=False, sent=True)
        if any(n not in replies for p in window for n in p.names):
            self.on = False
            self._again = self._out is not None
        return window, replies
