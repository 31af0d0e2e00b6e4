"""When the conductor itself loses the network (a client or peer conductor; the embedded router never does),
agents whose tokens vanish are not dead: the run pauses and waits for the network instead.

:meth:`NetworkWatch.wait` pauses until the network and every ready agent of the run are back (their tokens
seen again), or ``timeout`` passes. What the agents did meanwhile is kept for the tick loop to take in at the
end of the step message (never in the middle of one); the agents still missing when the network is back come
out as :class:`~conductor.registry.Vanished` events, and only they count as lost. A network that does not come
back within ``timeout`` ends the run (:class:`~protocol.errors.RunAborted`: failed).
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from protocol.errors import RunAborted

from .link import AgentLink
from .registry import Event, Registry, Rejoin, Vanished
from .stepping import Clock

log = logging.getLogger("twin.conductor")


class NetworkWatch:
    """The conductor's own network: ``down`` while it waits for it."""

    def __init__(self, link: AgentLink, registry: Registry, clock: Clock, timeout: float, stop: threading.Event,
                 event: Callable[[str, dict[str, Any]], None], record: Any, live: Callable[[], bool]) -> None:
        self.link, self.registry, self.clock, self.timeout, self.stop = link, registry, clock, timeout, stop
        self._event, self._record, self._live = event, record, live
        self.down = False
        self._down_at = 0.0
        self.exits: dict[str, str] = {}  # agent -> how its process ended (the launcher's word), once said
        self._gave_up: set[str] = set()  # agents waited for in vain (the run ends: not waited for twice)

    def lost(self) -> None:
        """The conductor itself has lost the network (said once, with the ``network_lost`` event)."""
        if not self.down:
            self.down = True
            self._down_at = time.monotonic()
            log.warning("network lost at tick %d: waiting up to %.0f s for it instead of declaring agents dead",
                        self.clock.tick, self.timeout)
            self._event("network_lost", {"tick": self.clock.tick, "t": self.clock.t})

    def wait(self, need: set[str], running: bool) -> list[Event]:
        """Wait for the network and the agents ``need``; returns the events to take in at the window's end."""
        self.lost()
        deferred: list[Event] = []

        def keep(events: list[Event]) -> None:  # a token vanishing while the network is down is no death
            deferred.extend(e for e in events if not isinstance(e, Vanished))

        deadline = self._down_at + self.timeout
        while time.monotonic() < deadline and not self.stop.is_set():
            keep(self.registry.drain(self.link.inbox, running, block=0.1))
            if not self.link.cut_off() and not self.link.gone(need):
                break
        keep(self.registry.drain(self.link.inbox, running))
        down_s = round(time.monotonic() - self._down_at, 3)
        if not self.stop.is_set() and self.link.cut_off():  # (it said "restored", and waited again, for ever)
            raise RunAborted(f"the conductor's network did not come back within {self.timeout:g} s (lost at "
                             f"t={self.clock.t:.2f} s): no model could be reached since, so what the run would have "
                             "concluded is unknown")
        self.down = False
        missing = sorted(self.link.gone(need))
        self._tell(down_s)
        if self.stop.is_set():
            return deferred
        self._event("network_restored", {"tick": self.clock.tick, "t": self.clock.t, "down_s": down_s,
                                         "missing": missing})
        log.warning("network restored after %.1f s%s", down_s, f"; missing: {', '.join(missing)}" if missing else "")
        for name in missing:
            self.registry.agents[name].alive = False
            deferred.append(Vanished(name, "it did not come back with the network"))
        return deferred

    def heal(self, ready: Callable[[str], bool], running: bool) -> list[Event]:
        """An outage seen only in vanished tokens (between a step's answers and its window's end) whose network is
        back before a step missed anyone: no step waits for it, so it is ended here as :meth:`wait` ends one (said
        in the record; the ready agents still missing come out as Vanished). Left ``down``, it took every later
        death for the network's, and the clock gate stopped waiting for anyone."""
        if not self.down or self.link.cut_off():
            return []
        return self.wait({n for n in self.registry.agents if ready(n)}, running)

    def _tell(self, down_s: float) -> None:
        """Say an outage in the run's record: a live robot's messages sent while the conductor was cut off reached
        nothing (its router had no subscriber for them), so the run is degraded; a replay paused meanwhile and lost
        nothing (a note)."""
        what = f"the conductor lost its network for {down_s:.1f} s at t={self.clock.t:.2f} s"
        if self._live():
            self._record.degraded.append(f"{what}: what the robot sent meanwhile did not reach the twin")
        else:
            self._record.notes.append(f"{what}: the replay paused meanwhile and went on where it was")

    def wait_for(self, name: str, timeout: float, running: bool,
                 check: Callable[[set[str], bool], None] | None = None) -> tuple[bool, float, list[Event]]:
        """Wait up to ``timeout`` s for agent ``name`` (one nothing can replace: the main model) whose token
        vanished while the conductor's own network is fine: a paused process, or a link of its own that broke.
        Returns whether the same process came back, how long it took, and the events to take in meanwhile
        (without that agent's vanishing when it came back; a new process of it is no return). ``check`` is the
        launcher's (``Conductor.agent_check``): a process it started that has exited is not waited for."""
        t0 = time.monotonic()
        deferred: list[Event] = []
        if name in self._gave_up:  # (the step that missed it and its token's event both come here)
            return False, 0.0, deferred
        renewed = False
        gone = exited(check, name)
        if not gone:
            log.warning("%s vanished at tick %d: waiting up to %.0f s for it to come back", name, self.clock.tick,
                        timeout)
        while not gone and time.monotonic() < t0 + timeout and not self.stop.is_set():
            for ev in self.registry.drain(self.link.inbox, running, block=0.1):
                renewed = renewed or (isinstance(ev, Rejoin) and ev.name == name)
                deferred.append(ev)
            if renewed or not self.link.gone({name}):
                break
            gone = exited(check, name)
        if gone and name not in self.exits:  # (said once: the step that missed it and its token's event both
            self.exits[name] = gone  # come here)
            log.warning("%s vanished at tick %d, it cannot come back: %s", name, self.clock.tick, gone)
        time.sleep(0.05)  # its registration follows its token
        deferred += self.registry.drain(self.link.inbox, running)
        renewed = renewed or any(isinstance(ev, Rejoin) and ev.name == name for ev in deferred)
        back = not renewed and not self.link.gone({name})
        if back:
            deferred = [ev for ev in deferred if not (isinstance(ev, Vanished) and ev.name == name)]
        elif not self.stop.is_set():
            self._gave_up.add(name)
            self.exits.setdefault(name, f"its liveliness token vanished and a new process of it came back after "
                                        f"{time.monotonic() - t0:.1f} s (a restart: what it held is lost)" if renewed
                                  else f"its liveliness token vanished and it did not come back within {timeout:g} s "
                                        "(it ended, is stopped, or lost its network)")
        return back, time.monotonic() - t0, deferred


def exited(check: Callable[[set[str], bool], None] | None, name: str) -> str | None:
    """How the process of agent ``name`` ended, if the launcher's ``check`` knows that it has (with the end of its
    log); None while it runs, or when there is no launcher to ask (an agent started elsewhere)."""
    if check is None:
        return None
    try:
        check({name}, False)
    except RunAborted as e:
        return str(e)
    return None
