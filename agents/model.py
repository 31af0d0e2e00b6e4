"""The model author's API: subclass :class:`Model`, declare what it needs and owns, implement ``step``.

A model is a class with a few declarations and a few methods::

    class Bouncer(Model):
        kind = "bouncer"
        role = "simulation"                 # or "observer" (owns nothing)
        params = {"gravity": Param(float, -9.81, "m/s^2")}
        attributes = ("pose",)              # attributes it can own
        outputs = ("height",)
        events = ("bounced",)
        reads = ("*.pose",)                 # values of others it wants each step

        def init(self, params, scene): ...
        def step(self, tick, t, dt, telemetry, inputs): ...
        def read(self, entity, attribute): ...            # value of an owned attribute
        def acquire(self, entity, attribute, value, extra): ...
        def release(self, entity, attribute): return value, extra

        @evaluator("height_of")
        def height_of(self, entity): ...

:func:`agents.run_agent` (in :mod:`agents.runtime`) connects it to an ensemble; the author never
touches Zenoh, msgpack or key strings.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable

_TYPE_NAMES = {float: "float", int: "int", str: "str", bool: "bool", list: "list", dict: "map"}


@dataclass(frozen=True)
class Param:
    """A parameter a model needs at init: type, default (``REQUIRED`` if none) and a doc line."""

    type: type = float
    default: Any = None
    doc: str = ""
    required: bool = False

    @property
    def type_name(self) -> str:
        return _TYPE_NAMES.get(self.type, "any")

    def describe(self) -> dict:
        return {"type": self.type_name, "default": self.default, "doc": self.doc, "required": self.required}

    def coerce(self, name: str, value: Any) -> Any:
        t = self.type
        if value is None:
            return None
        if t is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if t is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if t in (str, bool, dict) and isinstance(value, t):
            return value
        if t is list and isinstance(value, (list, tuple)):
            return list(value)
        if t is object:
            return value
        raise TypeError(f"parameter {name!r} must be {_TYPE_NAMES.get(t, t)}, got {value!r}")


def evaluator(name: str | None = None) -> Callable:
    """Mark a method as an evaluator: ``model/<id>/eval/<name>`` calls it with the query's args."""

    def deco(fn):
        fn._twin_evaluator = name or fn.__name__
        return fn

    return deco


def service(name: str | None = None) -> Callable:
    """Mark a method as a service: ``model/<id>/call/<name>`` (trigger effects) calls it."""

    def deco(fn):
        fn._twin_service = name or fn.__name__
        return fn

    return deco


class StepWarning(Exception):
    """Raise from ``step`` to report a recoverable problem; the run goes on."""


class Model:
    """Base class of every model. Override what you need; the defaults are inert."""

    kind: str = "model"
    role: str = "simulation"
    step_modes: tuple[str, ...] = ("service", "clock", "free")
    params: dict[str, Param] = {}
    attributes: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    events: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()
    wants_telemetry: bool = True

    def __init__(self) -> None:
        self.id: str = ""
        self.owned: set[tuple[str, str]] = set()
        self.scene: dict = {}
        self.models: dict = {}
        self.rate: float = 0.0
        self.tick: int = 0
        self.t: float = 0.0
        self._outputs: dict[str, Any] = {}
        self._events: list[dict] = []
        self.log = logging.getLogger(f"twin.model.{self.kind}")

    # ---------------------------------------------------------------- hooks
    def init(self, params: dict, scene: dict) -> None:
        """Called once with resolved parameters and the scene (entities, shapes, poses, owners)."""

    def start(self) -> None:
        """Called when the run starts."""

    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        """Advance by ``dt`` seconds to time ``t``. ``telemetry`` holds ``joints`` (latest joint
        state or None) and ``actions`` (annotations since the last step); ``inputs`` maps
        entity -> attribute -> value for the attributes this model reads but does not own."""

    def read(self, entity: str, attribute: str) -> Any:
        """Current value of an attribute this model owns (goes into ``state/<id>``)."""
        raise KeyError(f"{self.kind} cannot read {entity}.{attribute}")

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict) -> None:
        """Become the owner of ``entity.attribute``, seeded with its current ``value``."""

    def release(self, entity: str, attribute: str) -> tuple[Any, dict]:
        """Stop owning ``entity.attribute``; return its current value and extras (e.g. velocity)."""
        return self.read(entity, attribute), {}

    def close(self) -> None:
        """Free resources at exit."""

    # ------------------------------------------------------------- helpers
    def emit(self, name: str, **data: Any) -> None:
        """Raise an event (published on ``event/<id>/<name>`` and returned with the step)."""
        self._events.append({"name": name, "data": data})

    def output(self, name: str, value: Any) -> None:
        """Set an output value for this step (published on ``out/<id>/<name>``)."""
        self._outputs[name] = value

    def owns(self, entity: str, attribute: str) -> bool:
        return (entity, attribute) in self.owned

    # ------------------------------------------------------------ registry
    @classmethod
    def evaluators(cls) -> dict[str, str]:
        return {getattr(f, "_twin_evaluator"): n for n, f in _members(cls) if hasattr(f, "_twin_evaluator")}

    @classmethod
    def services(cls) -> dict[str, str]:
        return {getattr(f, "_twin_service"): n for n, f in _members(cls) if hasattr(f, "_twin_service")}


def _members(cls):
    seen = set()
    for klass in cls.__mro__:
        for n, f in vars(klass).items():
            if n not in seen and callable(f):
                seen.add(n)
                yield n, f


