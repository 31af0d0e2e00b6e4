"""Which agents are there: registration, liveliness, rejoining. State only; the tick loop decides what to do.

The link's Zenoh callbacks queue :class:`~conductor.link.Registered` and :class:`~conductor.link.Liveliness`
items; :meth:`Registry.drain` takes them in when the tick loop asks (never from a callback, so nothing about a
run changes in the middle of a step) and returns what the loop must act on, in arrival order:

- :class:`Rejoin`: a known agent came back as a new process during the run: initialise it owning nothing;
- :class:`Vanished`: a ready agent of the run lost its liveliness token: it died, or the network is gone;
- :class:`~conductor.link.Published`: what a clock-driven or free-running model published, passed through.

The same process registering again (its token came back after a network cut) simply stays in the run.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from protocol.errors import RunAborted
from protocol.messages import Message

from .link import Answered, Inbound, Liveliness, Published, Registered, ServiceCall

log = logging.getLogger("twin.conductor")


@dataclass
class AgentInfo:
    """An agent as the conductor knows it: its register descriptor and where it is in the life cycle."""

    name: str
    desc: dict[str, Any] = field(default_factory=dict)
    alive: bool = True
    ready: bool = False  # initialised for this run
    rejoin_pending: bool = False

    @property
    def kind(self) -> str:
        return str(self.desc.get("kind", "?"))

    def same_process(self, desc: dict[str, Any]) -> bool:
        return self.desc.get("pid") == desc.get("pid") and self.desc.get("host") == desc.get("host")


@dataclass(frozen=True)
class Rejoin:
    """A known agent came back (restart or a new process) while the run goes on."""

    name: str


@dataclass(frozen=True)
class Vanished:
    """A ready agent of the run is gone: its liveliness token vanished, or it did not answer a step in time."""

    name: str
    why: str = "its liveliness token vanished"


Event = Rejoin | Vanished | Published | ServiceCall


class Registry:
    """The agents of one ensemble, by name (= the scene's model name)."""

    def __init__(self, models: Iterable[str]) -> None:
        self.models = frozenset(models)
        self.agents: dict[str, AgentInfo] = {}
        self.never_registered: set[str] = set()  # the models still missing when the wait for them ended (time, stop)
        self._lock = threading.Lock()

    def admit(self, msg: Message, lapsed: bool = False) -> str | None:
        """None to accept a registration, else why not (called from a Zenoh thread). ``lapsed``: the name's
        liveliness token vanished since its agent registered, so a new process under it replaces a dead one (a
        supervisor's restart), not a live one."""
        if msg.role == "observer" and msg.attributes:
            return (f"{msg.name} ({msg.kind}) is an observer but declares attributes {list(msg.attributes)}: "
                    "an observer owns nothing")
        with self._lock:
            prev = self.agents.get(msg.name)
        if prev is not None and prev.alive and prev.ready and not prev.same_process(msg) and not lapsed:
            return (f"a live agent already holds the name {msg.name!r} "
                    f"(pid {prev.desc.get('pid')} on {prev.desc.get('host')})")
        return None

    def get(self, name: str) -> AgentInfo | None:
        return self.agents.get(name)

    def ready(self, name: str) -> bool:
        info = self.agents.get(name)
        return info is not None and info.alive and info.ready

    def acks_clock(self, name: str) -> bool:
        """Whether ``name`` is in the run and answers each clock tick (a clock-driven model the gate may wait for)."""
        info = self.agents.get(name)
        return info is not None and info.ready and info.alive and bool(info.desc.get("clock_ack"))

    def missing(self) -> set[str]:
        """The scene's models without a live agent."""
        return {n for n in self.models if not (n in self.agents and self.agents[n].alive)}

    def declares(self, name: str, what: str) -> list[str]:
        """What agent ``name`` declared under ``what`` (attributes, evaluators, ...)."""
        info = self.agents.get(name)
        return list(info.desc.get(what, [])) if info is not None else []

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """Every agent as ``conductor/status`` shows it (safe from another thread), and every model of the scene
        that no agent has registered for yet (``registered`` false: while a run waits for its agents, its status
        named only those that had come, and not the one it waited for)."""
        with self._lock:
            agents = list(self.agents.values())
        out = {a.name: {"alive": a.alive, "ready": a.ready, "registered": True, "kind": a.desc.get("kind"),
                        "host": a.desc.get("host"), "pid": a.desc.get("pid")} for a in agents}
        return out | {m: {"alive": False, "ready": False, "registered": False, "kind": None, "host": None, "pid": None}
                      for m in sorted(self.models - out.keys())}

    def refusals(self, refused: Callable[[str], int | None], before: dict[str, int]) -> list[str]:
        """What the scene's live agents refused since the run began (``refused(name)``: their count now; ``before``:
        at the start): a message an agent refused was not the conductor's, or was damaged."""
        out = []
        for name in sorted(self.models):
            info = self.agents.get(name)
            n = refused(name) if info is not None and info.alive else None
            if n is not None and n > before.get(name, 0):
                out.append(f"model {name} refused {n - before.get(name, 0)} malformed or out-of-sequence messages")
        return out

    def wait(self, inbox: queue.SimpleQueue[Inbound], timeout: float, stop: threading.Event,
             check: Callable[[set[str], bool], None] | None = None) -> None:
        """Take registrations in until every model of the scene has a live agent (before the run). Raises
        :class:`RunAborted` on a stop or after ``timeout``; ``check(missing, final)`` may raise too (a launcher
        whose agent process already died; ``final``: the time is up, the launcher says what its agents did)."""
        deadline = time.monotonic() + timeout
        last_report = 0.0
        while True:
            self.drain(inbox, running=False, block=0.05)
            missing = self.missing()
            if not missing:
                return
            if stop.is_set():
                self.never_registered = set(missing)
                raise RunAborted("stopped while waiting for agents")
            now = time.monotonic()
            if now > deadline:
                self.never_registered = set(missing)
                if check is not None:
                    check(missing, True)
                raise RunAborted(f"agents never registered: {', '.join(sorted(missing))} "
                                 f"(start them with 'twin agent KIND --name NAME')")
            if now - last_report > 5:
                log.info("waiting for agents: %s", ", ".join(sorted(missing)))
                last_report = now
            if check is not None:
                check(missing, False)

    # ------------------------------------------------------------------------------ inbox
    def drain(self, inbox: queue.SimpleQueue[Inbound], running: bool, block: float = 0.0) -> list[Event]:
        """Take in everything queued (waiting up to ``block`` seconds for the first item)."""
        events: list[Event] = []
        try:
            item = inbox.get(timeout=block) if block > 0 else inbox.get_nowait()
        except queue.Empty:
            return events
        while True:
            ev = self._take(item, running)
            if ev is not None:
                events.append(ev)
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                return events

    def _take(self, item: Inbound, running: bool) -> Event | None:
        if isinstance(item, Registered):
            return self._registered(item.name, item.desc, running)
        if isinstance(item, Liveliness):
            return self._liveliness(item.name, item.alive, running)
        if isinstance(item, Answered):
            return self._answered(item.name, running)
        return item  # Published: the loop takes it in

    def _registered(self, name: str, desc: dict[str, Any], running: bool) -> Event | None:
        prev = self.agents.get(name)
        if prev is not None and running and prev.ready and prev.same_process(desc):
            prev.alive = True  # the same process after the network came back: it never left the run
            log.info("%s registered again (same process): still in the run", name)
            return None
        log.info("registered %s (%s, pid %s on %s)", name, desc.get("kind"), desc.get("pid"), desc.get("host"))
        info = AgentInfo(name, desc, alive=True, rejoin_pending=prev is not None and running)
        with self._lock:
            self.agents[name] = info
        return Rejoin(name) if info.rejoin_pending else None

    def _answered(self, name: str, running: bool) -> Event | None:
        """A late answer from an agent taken out of the run for not answering in time: it is back, so it is
        initialised again, owning nothing (as a restarted agent is)."""
        info = self.agents.get(name)
        if info is None or not running or info.ready or info.rejoin_pending or not info.alive:
            return None
        info.rejoin_pending = True
        return Rejoin(name)

    def _liveliness(self, name: str, alive: bool, running: bool) -> Event | None:
        info = self.agents.get(name)
        if info is None:
            return None
        if not alive and info.alive:
            info.alive = False
            if running and name in self.models:
                return Vanished(name)
        elif alive and not info.alive:
            info.alive = True  # its registration follows and re-initialises it
        return None
