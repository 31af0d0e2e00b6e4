"""Moving a responsibility between agents, between ticks (the paper's §3.1, DESIGN §5).

:meth:`Handovers.transfer`: ``release`` on the old owner returns the current value and its extras (e.g. the
velocity) and stops it writing; ``acquire`` seeds the new owner; then the map changes (version bumped), the
new ``ownership`` is published and the ``handover`` event raised. If the new owner refuses, the old one takes
the value back and nothing changes (if it cannot, the main model is given it). :meth:`Handovers.fallback`: a
lost agent's responsibilities go to the main model with their last known values.
"""
from __future__ import annotations

import logging
from typing import Any

from protocol import codec
from protocol.errors import AgentError, ProtocolError, RunAborted
from protocol.messages import unusable

from .link import AgentLink
from .record import RunRecord
from .registry import Registry
from .responsibility import Handover, Responsibilities

log = logging.getLogger("twin.conductor")


class Handovers:
    """Transfers and fallbacks of one run. ``clock`` is read for the current tick and time."""

    def __init__(self, link: AgentLink, registry: Registry, rmap: Responsibilities, record: RunRecord,
                 main: str, clock: Any) -> None:
        self.link, self.registry, self.map, self.record = link, registry, rmap, record
        self.main = main
        self.clock = clock  # has .tick and .t
        self.lost: set[str] = set()  # the models that fell back (out of the run until they are ready again)

    def publish_ownership(self, change: dict[str, Any] | None = None) -> None:
        """Publish the whole map (on start, and after every change)."""
        c = self.clock
        self.link.publish(self.link.keys.ownership, codec.encode(
            "ownership", version=self.map.version, tick=c.tick, t=c.t, owners=self.map.ownership_map(),
            change=change))

    def _changed(self, h: Handover) -> None:
        change = h.as_dict()
        self.publish_ownership(change)
        self.link.event("handover", change, self.clock.tick, self.clock.t)

    def problem(self, trigger: str, text: str) -> None:
        """A trigger could not do what it said: logged, listed in the summary, raised as an event."""
        c = self.clock
        log.warning("trigger %s: %s", trigger, text)
        self.record.error(f"tick {c.tick}: {trigger}: {text}")
        self.link.event("trigger_error", {"trigger": trigger, "problem": text}, c.tick, c.t)

    def transfer(self, e: str, a: str, dst: str, trigger: str, variables: dict[str, Any] | None = None) -> bool:
        """Move ``e.a`` to ``dst``; True if it moved. Problems are reported, never raised."""
        variables = variables or {}
        src = self.map.owner(e, a)
        if src is None:
            self.problem(trigger, f"no responsibility {e}.{a} in the scene")
            return False
        if src == dst:
            return False
        if dst not in self.map.scene.models or not self.registry.ready(dst):
            self.problem(trigger, f"cannot hand {e}.{a} to {dst!r}: not a live model of this scene")
            return False
        if a not in self.registry.declares(dst, "attributes"):
            self.problem(trigger, f"{dst} cannot own attribute {a!r}")
            return False
        c = self.clock
        value, extra = self.map.value(e, a), {}
        if self.registry.ready(src):
            try:
                rep = self.link.ask(src, "release", codec.encode("release", entity=e, attribute=a, tick=c.tick, t=c.t),
                                    "release_reply")
                value, extra = rep.value, rep.extra
            except (AgentError, ProtocolError) as ex:
                self.problem(trigger, f"release of {e}.{a} by {src} failed: {ex}")
                return False
            why = unusable(a, value)
            if why is not None:  # (a NaN pose handed to physics stayed NaN to the end of the run)
                self.problem(trigger, f"{src} released {e}.{a} as no value ({why}): {dst} is given its last value "
                                      "instead")
                value, extra = self.map.value(e, a), {}  # (that release's velocity is no better than its pose)
            extra = self._usable_extra(trigger, src, f"{e}.{a}", extra)
        acquire = codec.encode("acquire", entity=e, attribute=a, value=value, extra=extra, tick=c.tick, t=c.t)
        try:
            self.link.ask(dst, "acquire", acquire, "ack")
        except (AgentError, ProtocolError) as ex:
            refused = f"{dst} failed to acquire {e}.{a}: {ex}"
            info = self.registry.get(src)
            if info is not None and info.alive:
                try:
                    self.link.ask(src, "acquire", acquire, "ack")
                except (AgentError, ProtocolError) as back:
                    self._to_main(e, a, value, src, dst, trigger, acquire,
                                  f"{refused}; {src} could not take it back either ({back})")
                    return False
                self.map.values[(e, a)] = value  # (what it holds again: what it released)
            self.problem(trigger, f"{refused}; ownership stays with {src}")
            return False
        self.map.values[(e, a)] = value
        self._changed(self.map.set_owner(e, a, dst, c.tick, c.t, trigger, variables))
        return True

    def _to_main(self, e: str, a: str, value: Any, src: str, dst: str, trigger: str, acquire: bytes, why: str) -> None:
        """Neither ``dst`` nor ``src`` holds ``e.a`` after a refused handover: it goes to the main model, as a lost
        model's would, so the map names a model that moves it; if the main model cannot take it either, the map
        keeps naming ``src`` and the run is degraded saying so."""
        if self.main in (src, dst) or a not in self.registry.declares(self.main, "attributes") \
                or not self.registry.ready(self.main):
            self.problem(trigger, f"{why}: no live model moves it now")
            return
        try:
            self.link.ask(self.main, "acquire", acquire, "ack")
        except (AgentError, ProtocolError) as ex:
            self.problem(trigger, f"{why}, nor could {self.main} ({ex}): no live model moves it now")
            return
        self.problem(trigger, f"{why}: it went to the main model {self.main}")
        self.map.values[(e, a)] = value  # (what it was handed)
        c = self.clock
        self._changed(self.map.set_owner(e, a, self.main, c.tick, c.t, f"{trigger} (refused: to {self.main})", {}))

    def _usable_extra(self, trigger: str, src: str, what: str, extra: Any) -> dict[str, Any]:
        """What of a release's extra state (a velocity...) can be handed on: a part that is no value (a NaN
        velocity beside a good pose made the body NaN in physics, frozen to the end) is left out and said; None is
        a value there (the SPU's ``connected_to`` when it is not)."""
        if not isinstance(extra, dict):
            return {}
        bad = {k: why for k, v in extra.items() if v is not None and (why := unusable(str(k), v)) is not None}
        for k, why in sorted(bad.items()):
            self.problem(trigger, f"{src} released {what} with {k} as no value ({why}): it is not handed on")
        return {k: v for k, v in extra.items() if k not in bad}

    def fallback(self, name: str, why: str = "its liveliness token vanished") -> None:
        """``name`` is gone: its responsibilities go to the main model with their last values. Raises
        :class:`RunAborted` if ``name`` is the main model (nothing can take its responsibilities)."""
        c = self.clock
        main = name == self.main
        info = self.registry.get(name)
        if not main and name in self.lost and info is not None and not info.ready:  # (not rejoined since)
            log.info("%s, already out of the run, is gone too: %s", name, why)  # (one loss, said once)
            return
        self.lost.add(name)
        self.link.event("agent_lost", {"model": name, "tick": c.tick, "t": c.t, "main": main}, c.tick, c.t)
        log.warning("lost agent %s at tick %d", name, c.tick)
        if not main:
            self.record.degraded.append(f"model {name} lost at tick {c.tick} ({why}): what it owned fell back to "
                                        f"{self.main}")
        if info is not None:
            info.ready = False
        if main:
            self.record.error(f"main model {self.main} lost at tick {c.tick}")
            how = "died" if why.startswith(f"agent {name} ") else "was lost"  # (the launcher saw its process end)
            raise RunAborted(f"the main model {self.main!r} {how} at tick {c.tick}, and nothing can take its "
                             f"responsibilities: {why}")
        for (e, a), m in sorted(self.map.owners.items()):
            if m != name:
                continue
            if a not in self.registry.declares(self.main, "attributes"):  # (the map would name a non-owner)
                self.record.degraded.append(f"{e}.{a} of lost {name} cannot fall back: {self.main} cannot own "
                                            f"{a!r}; its last value stays, moved by no model")
                continue
            acquire = codec.encode("acquire", entity=e, attribute=a, value=self.map.value(e, a), extra={},
                                   tick=c.tick, t=c.t)
            try:
                self.link.ask(self.main, "acquire", acquire, "ack")
            except (AgentError, ProtocolError) as ex:
                self.record.degraded.append(f"{e}.{a} of lost {name} could not fall back to {self.main} ({ex}): "
                                            "its last value stays, moved by no model")
                continue
            self._changed(self.map.set_owner(e, a, self.main, c.tick, c.t, f"fallback:{name} lost", {"model": name}))
