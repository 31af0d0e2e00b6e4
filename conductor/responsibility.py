"""Who is responsible for what, and the values they report: pure data, no Zenoh.

The responsibility map ``(entity, attribute) -> model`` has exactly one owner per entry at every tick (the
paper's §3.1; checked by :meth:`Responsibilities.invariant_holds`). Only the owner's value is authoritative:
a model's report of an attribute it does not own is counted as an unauthorized write and dropped. A change of
owner is a :class:`Handover` record; the procedure that moves a value between two agents is in
:mod:`conductor.handover`.

:class:`Responsibilities` is also the :class:`conductor.builtins.World` that scene expressions read.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from typing import Any

from protocol import codec
from protocol.messages import unusable

from .scene import Scene

Key = tuple[str, str]  # (entity, attribute)


@dataclass
class Handover:
    """One change of owner: at ``tick`` (time ``t``), ``entity.attribute`` went from ``src`` to ``dst`` because
    of ``trigger`` (a trigger's name, or ``fallback:<model> lost``), with the trigger's bound variables."""

    tick: int
    t: float
    entity: str
    attribute: str
    src: str
    dst: str
    trigger: str
    variables: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The form the run summary, the ``ownership`` message and the viewer use."""
        return {"tick": self.tick, "t": round(self.t, 6), "entity": self.entity, "attribute": self.attribute,
                "from": self.src, "to": self.dst, "trigger": self.trigger, "variables": self.variables}


class _Missing:
    pass


_MISSING = _Missing()


def differs(old: Any, new: Any) -> bool:
    """Whether an output changed (``old`` may be missing: :func:`protocol.codec.differs` otherwise)."""
    return old is _MISSING or codec.differs(old, new)


class Responsibilities:
    """Owners, values, outputs and event counts of one run, and the history of handovers.

    ``version`` counts changes of the map (0 at start). Nothing here talks to the network.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.owners: dict[Key, str] = scene.initial_owners()
        self.expected = frozenset(self.owners)
        self.values: dict[Key, Any] = {(e.name, "pose"): list(e.pose) for e in scene.entities.values()}
        self.outputs: dict[tuple[str, str], Any] = {}
        self.event_counts: dict[tuple[str, str], int] = {}
        self.handovers: list[Handover] = []
        self.version = 0
        self.unauthorized_writes = 0
        self.unauthorized_by: dict[str, int] = {}  # model -> values it reported of attributes it did not own
        self.late_writes = 0  # a clock-driven or free model's values of attributes handed away before they came
        self.released: set[tuple[str, str, str]] = set()  # (model, entity, attribute) it owned and handed away
        self.bad_values: dict[str, int] = {}  # model -> values it owned that were no values (NaN, None): left out
        self.bad_examples: list[str] = []  # the first few, said
        # model -> (outputs, events) it declared at registration (a model missing here: everything it sends is
        # taken, as in bench.limit); one it did not declare no trigger or predicate can use: counted, left out
        self.declared: dict[str, tuple[frozenset[str], frozenset[str]]] = {}
        self.undeclared: dict[str, dict[str, int]] = {}  # model -> "output NAME"/"event NAME" -> times sent
        # poses the scene declares fixed (tag ``static``): they do not end a batch of ticks (their readers need
        # no fresh value), so a report that moves one is noted (the run is then degraded, saying which)
        self.static: frozenset[Key] = frozenset((e.name, "pose") for e in scene.entities.values() if "static" in e.tags)
        self.static_moved: dict[str, float] = {}

    # ------------------------------------------------------------------------------ the map
    def owner(self, entity: str, attribute: str) -> str | None:
        return self.owners.get((entity, attribute))

    def owned(self, model: str, attribute: str = "pose") -> list[str]:
        """The entities whose ``attribute`` ``model`` owns, sorted."""
        return sorted(e for (e, a), m in self.owners.items() if m == model and a == attribute)

    def owned_by(self, model: str) -> list[Key]:
        """Everything ``model`` owns, in the scene's order."""
        return [k for k, m in self.owners.items() if m == model]

    def set_owner(self, entity: str, attribute: str, dst: str, tick: int, t: float, trigger: str,
                  variables: dict[str, Any]) -> Handover:
        """Record that ``dst`` owns ``entity.attribute`` from now; returns the handover (version bumped)."""
        src = self.owners[(entity, attribute)]
        self.released.add((src, entity, attribute))
        self.owners[(entity, attribute)] = dst
        self.version += 1
        h = Handover(tick, t, entity, attribute, src, dst, trigger, variables)
        self.handovers.append(h)
        return h

    def ownership_map(self) -> dict[str, dict[str, str]]:
        """entity -> attribute -> owner (a snapshot: safe to call from another thread)."""
        out: dict[str, dict[str, str]] = {}
        for (e, a), m in sorted(dict(self.owners).items()):
            out.setdefault(e, {})[a] = m
        return out

    def invariant_holds(self) -> bool:
        """Exactly the scene's responsibilities, each owned by one model of the scene."""
        return set(self.owners) == self.expected and all(m in self.scene.models for m in self.owners.values())

    # ----------------------------------------------------------------------------- values
    def value(self, entity: str, attribute: str) -> Any:
        return self.values.get((entity, attribute))

    def _bad(self, model: str, what: str, value: Any, why: str) -> None:
        """Count a value that is no value (:func:`unusable`) of ``what`` (an attribute or an output), keeping the
        first few to say."""
        self.bad_values[model] = self.bad_values.get(model, 0) + 1
        if len(self.bad_examples) < 3:
            self.bad_examples.append(f"{model}'s {what} = {_short(value)} ({why})")

    def absorb_state(self, model: str, values: Mapping[str, Any], stepped: bool = True) -> None:
        """Take the values ``model`` reported; those of attributes it does not own are counted, not kept: as
        unauthorized writes from a step answer (the model stepped knowing what it owned), as late ones from a
        clock-driven or free model's publication of one it owned and handed away (``stepped`` False: it may have
        published before the release came); one it never owned is unauthorized from either."""
        for e, attrs in values.items():
            if not isinstance(attrs, dict):
                continue
            for a, v in attrs.items():
                if self.owners.get((e, a)) == model:
                    why = unusable(a, v)
                    if why is not None:  # (the name is formatted only then: this runs for every value of every tick)
                        self._bad(model, f"{e}.{a}", v, why)
                        continue
                    if (e, a) in self.static:
                        self._check_static(e, v)
                    self.values[(e, a)] = v
                elif not stepped and (model, e, a) in self.released:  # (it may have left before the release)
                    self.late_writes += 1
                else:
                    self.unauthorized_writes += 1
                    self.unauthorized_by[model] = self.unauthorized_by.get(model, 0) + 1

    def _check_static(self, entity: str, pose: Any) -> None:
        """Note how far a ``static`` entity's reported pose is from where the scene put it (beyond 1 mm)."""
        try:
            moved = max(abs(float(a) - float(b)) for a, b in zip(pose[:3], self.scene.entities[entity].pose[:3]))
        except (TypeError, ValueError, IndexError):
            moved = math.inf
        if moved > 1e-3 and moved > self.static_moved.get(entity, 0.0):
            self.static_moved[entity] = moved

    def set_output(self, model: str, name: str, value: Any) -> bool:
        """Record an output; True if its value changed (topic triggers fire on changes only). One that is no value
        (a NaN: every comparison a trigger makes with it is false) is counted and left out."""
        if self._undeclared(model, 0, name):
            return False
        why = unusable("", value)  # (an output named pose is no entity's pose)
        if why is not None:
            self._bad(model, f"output {name}", value, why)
            return False
        old = self.outputs.get((model, name), _MISSING)
        self.outputs[(model, name)] = value
        return differs(old, value)

    def changes(self, model: str, name: str, value: Any) -> bool:
        """Whether ``value`` would change the output (what :meth:`set_output` would answer), recording nothing."""
        return differs(self.outputs.get((model, name), _MISSING), value)

    def output(self, model: str, name: str, default: Any = None) -> Any:
        return self.outputs.get((model, name), default)

    def count_event(self, model: str, name: str) -> bool:
        """Count an event ``model`` raised; False (and counted apart) if it never declared it."""
        if self._undeclared(model, 1, name):
            return False
        self.event_counts[(model, name)] = self.event_counts.get((model, name), 0) + 1
        return True

    def declare(self, descs: Mapping[str, Mapping[str, Any]]) -> None:
        """The outputs and events each model declared at registration (its register descriptor)."""
        self.declared = {n: (frozenset(d.get("outputs") or ()), frozenset(d.get("events") or ()))
                         for n, d in descs.items()}

    def _undeclared(self, model: str, kind: int, name: str) -> bool:
        """Whether ``name`` is an output (``kind`` 0) or event (1) ``model`` did not declare (then counted)."""
        names = self.declared.get(model)
        if names is None or name in names[kind]:
            return False
        seen = self.undeclared.setdefault(model, {})
        what = f"{('output', 'event')[kind]} {name}"
        seen[what] = seen.get(what, 0) + 1
        return True

    def event_count(self, model: str, name: str) -> int:
        return self.event_counts.get((model, name), 0)

    def inputs_for(self, model: str, reads: Iterable[str]) -> dict[str, dict[str, Any]]:
        """What ``model`` reads and others own: entity -> attribute -> value (patterns as ``ball.*``)."""
        reads = list(reads)
        if not reads:
            return {}
        out: dict[str, dict[str, Any]] = {}
        for (e, a), m in self.owners.items():
            if m == model:
                continue
            if any(fnmatchcase(f"{e}.{a}", pat) for pat in reads):
                v = self.values.get((e, a))
                if v is not None:
                    out.setdefault(e, {})[a] = v
        return out

    def owners_read_by(self, model: str, reads: Iterable[str]) -> set[str]:
        """The other models that own something ``model`` reads (the poses of ``static`` entities aside: they
        do not change)."""
        reads = list(reads)
        return {m for (e, a), m in self.owners.items()
                if m != model and (e, a) not in self.static and any(fnmatchcase(f"{e}.{a}", pat) for pat in reads)}

    # ----------------------------------------------------------------- the World of expressions
    def shape(self, entity: str) -> dict[str, Any] | None:
        ent = self.scene.entities.get(entity)
        return None if ent is None else ent.shape

    def tagged(self, tag: str) -> list[str]:
        return [n for n, e in self.scene.entities.items() if tag in e.tags]


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
