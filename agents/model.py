"""The model author's API: subclass :class:`Model`, declare what it needs and owns, implement ``step``.

A model is a class with a few declarations and a few methods::

    class Bouncer(Model):
        kind = "bouncer"                          # a ball that falls to the floor and stays there
        role = "simulation"                       # or "observer" (owns nothing)
        params = {"gravity": Param(float, -9.81, "m/s^2")}
        attributes = ("pose",)                    # attributes it can own (then it must define read)
        outputs = ("height",)
        events = ("landed",)
        reads = ("*.pose",)                       # values of others it wants each step

        def init(self, params, scene):
            self.g = params["gravity"]
            self.poses = {n: list(e["pose"]) for n, e in scene["entities"].items()}
            self.vz = dict.fromkeys(self.poses, 0.0)

        def step(self, tick, t, dt, telemetry, inputs):
            for entity, _ in self.owned:
                pose = self.poses[entity]
                if pose[2] > 0.0:
                    self.vz[entity] += self.g * dt
                    pose[2] = max(0.0, pose[2] + self.vz[entity] * dt)
                    if pose[2] == 0.0:
                        self.emit("landed", entity=entity)
            self.output("height", {e: p[2] for e, p in self.poses.items()})

        def read(self, entity, attribute):        # the value of an owned attribute
            return self.poses[entity]

        def acquire(self, entity, attribute, value, extra):
            self.poses[entity], self.vz[entity] = list(value), 0.0

        @evaluator("height_of")
        def height_of(self, entity):
            return self.poses[entity][2]

``python -m agents module:Bouncer --name ball`` (or :func:`agents.run_agent`) connects it to an ensemble;
the author never touches Zenoh, msgpack or key strings. The declarations are checked when the class is
defined (:meth:`Model.__init_subclass__`), and :func:`agents.testing.check_model` runs a model as a real
agent process and checks the rest of the contract.
"""
from __future__ import annotations

import inspect
import logging
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar, TypeVar

from protocol.geometry import finite_number
from protocol.messages import ROLES, STEP_MODES, ParamInfo

__all__ = ["NAME_KINDS", "Inputs", "Model", "Param", "StepWarning", "Telemetry", "evaluator", "service"]

Telemetry = dict[str, Any]
"""What a step gets from the robot: ``joints``, the latest joint state (``{stamp, name, position, velocity,
effort}``, see :class:`protocol.messages.JointState`) or None, and ``actions``, the action annotations since
the model's last step (:class:`protocol.messages.Action`)."""

Inputs = dict[str, dict[str, Any]]
"""``entity -> attribute -> value`` of what a model reads (``reads``) and others own."""

F = TypeVar("F", bound=Callable[..., Any])

_TYPE_NAMES: dict[type, str] = {float: "float", int: "int", str: "str", bool: "bool", list: "list", dict: "map",
                                object: "any"}


@dataclass(frozen=True)
class Param:
    """A parameter a model needs at init: its ``type`` (``float``, ``int``, ``str``, ``bool``, ``list``,
    ``dict`` or ``object`` for anything), its ``default`` and a ``doc`` line with the unit.

    A parameter with ``required=True`` must be given by the scene (its ``default`` is not used); any other
    takes ``default`` when the scene gives none, and its default must fit its type (or be None).
    """

    type: type = float
    default: Any = None
    doc: str = ""
    required: bool = False
    choices: tuple[Any, ...] = ()  # the only values it takes (empty: any of its type)
    positive: bool = False  # a number that must be finite and above 0
    within_period: bool = False  # seconds, at most the model's step period (1 / its rate): the scene check says so

    @property
    def type_name(self) -> str:
        """The type's word on the wire (``float``, ``int``, ``str``, ``bool``, ``list``, ``map`` or ``any``)."""
        return _TYPE_NAMES.get(self.type, "any")

    def describe(self) -> ParamInfo:
        """The parameter as the register descriptor and ``model/<id>/params`` declare it."""
        info: ParamInfo = {"type": self.type_name, "default": self.default, "doc": self.doc, "required": self.required}
        if self.choices:
            info["choices"] = list(self.choices)
        if self.positive:
            info["positive"] = True
        if self.within_period:
            info["within_period"] = True
        return info

    def coerce(self, name: str, value: Any) -> Any:
        """``value`` as this parameter's type (an int for a float becomes a float, a tuple for a list a
        list; None stays None); TypeError naming the parameter if it does not fit."""
        value = self._coerced(name, value)
        if value is not None and self.choices and value not in self.choices:
            raise ValueError(f"parameter {name!r} must be one of {', '.join(map(str, self.choices))}, got {value!r}")
        if value is not None and self.positive and not finite_number(value, positive=True):  # as the scene check
            raise ValueError(f"parameter {name!r} must be a finite number above 0, got {value!r}")
        return value

    def _coerced(self, name: str, value: Any) -> Any:
        t = self.type
        if value is None or t is object:
            return value
        if t is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):  # (NaN passed every comparison a model makes, and is no JSON)
                raise ValueError(f"parameter {name!r} must be a finite number, got {value!r}")
            return float(value)
        if t is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if t in (str, bool, dict) and isinstance(value, t):
            return value
        if t is list and isinstance(value, (list, tuple)):
            return list(value)
        raise TypeError(f"parameter {name!r} must be {_TYPE_NAMES.get(t, t)}, got {value!r}")


NAME_KINDS: Mapping[str, str] = MappingProxyType({
    "entity": "an entity of the scene",
    "tag": "a tag the scene's entities carry",
    "body": "an entity, a robot link, or hand / tip (the robot's hand link, the point between its fingertips)",
})
"""What an evaluator's parameter may name (:func:`evaluator`'s ``names``), so that the scene checker can check a
string written there."""


def _with_parentheses(what: str, name: object) -> None:
    """``@evaluator`` without its parentheses took the method for its name and put ``mark`` in its place: the method
    was gone from the class without a word."""
    if callable(name):
        raise TypeError(f"@{what} on {getattr(name, '__name__', name)!r}: write @{what}() with parentheses")
    if name is not None and not isinstance(name, str):
        raise TypeError(f"@{what}(name): the name must be a string, got {name!r}")


def evaluator(name: str | None = None, *, names: Mapping[str, str] | None = None) -> Callable[[F], F]:
    """Mark a method as an evaluator: ``model/<id>/eval/<name>`` calls it with the query's arguments and
    answers with what it returns (the scene's expressions and triggers use it). ``name`` defaults to the
    method's name. ``names``: its parameters that take a name of the scene, each with what it names
    (:data:`NAME_KINDS`): a string the scene writes there is checked before anything starts (``twin check``, the
    conductor at registration), since a misspelt tag would make ``closest`` answer as if nothing carried it."""
    _with_parentheses("evaluator", name)

    def mark(fn: F) -> F:
        setattr(fn, "_twin_evaluator", name or fn.__name__)  # noqa: B010 (a function has no such attribute)
        if names:
            params = [p for p in inspect.signature(fn).parameters.values()
                      if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)][1:]  # (after self)
            unknown = [p for p in names if p not in {q.name for q in params}]
            bad = {p: k for p, k in names.items() if k not in NAME_KINDS}
            if unknown or bad:
                why = ([f"no parameter {', '.join(unknown)}"] if unknown else []) + \
                    ([f"kinds are {', '.join(NAME_KINDS)}"] if bad else [])
                raise TypeError(f"evaluator {fn.__name__}: names {dict(names)!r}: {'; '.join(why)}")
            setattr(fn, "_twin_names", [names.get(p.name) for p in params])  # noqa: B010 (as above)
        return fn

    return mark


def service(name: str | None = None) -> Callable[[F], F]:
    """Mark a method as a service: ``model/<id>/call/<name>`` (a trigger's effect) calls it with the
    query's positional and keyword arguments. ``name`` defaults to the method's name."""
    _with_parentheses("service", name)

    def mark(fn: F) -> F:
        setattr(fn, "_twin_service", name or fn.__name__)  # noqa: B010 (a function has no such attribute)
        return fn

    return mark


class StepWarning(Exception):
    """Raise from ``step`` to report a recoverable problem: the step's status is ``warning`` with this
    message, what the model owns is still published, and the run goes on."""


class Model:
    """Base class of every model. Declare the class attributes, override the hooks you need (the defaults
    are inert), and use the helpers from ``step``.

    Declarations (class attributes, checked when the class is defined):

    - ``kind``: the model kind's name (e.g. ``physics``);
    - ``role``: ``simulation`` (may own attributes) or ``observer`` (owns nothing: no ``attributes``);
    - ``step_modes``: the step modes it supports, among ``service``, ``clock`` and ``free``;
    - ``params``: name -> :class:`Param`;
    - ``attributes``: the attributes it can own (a model that declares some must define :meth:`read`);
    - ``outputs``, ``events``: the names it publishes with :meth:`output` and :meth:`emit`;
    - ``owner_events``: those of its ``events`` it raises only about what it owns, never while it owns nothing
      (the conductor then steps batches of ticks past its steps while it owns nothing; raising one anyway makes
      the run ``degraded``);
    - ``reads``: ``entity.attribute`` patterns of others' values it wants in each step's ``inputs``;
    - ``wants_telemetry``: whether its steps get the robot's joint states and actions.

    The runtime keeps these instance attributes up to date: ``id`` (its model id), ``owned`` (the
    ``(entity, attribute)`` pairs it owns), ``scene``, ``models`` (name -> kind of every model of the
    scene), ``rate`` (its step rate, Hz), ``tick`` and ``t`` (the current tick and time), ``log``.
    Every hook runs on the agent's main thread, one at a time: a model needs no locks.
    """

    kind: ClassVar[str] = "model"
    role: ClassVar[str] = "simulation"
    step_modes: ClassVar[tuple[str, ...]] = ("service", "clock", "free")
    # read-only: a subclass declares its own mapping instead of filling a dict all subclasses share
    params: ClassVar[Mapping[str, Param]] = MappingProxyType({})
    attributes: ClassVar[tuple[str, ...]] = ()
    outputs: ClassVar[tuple[str, ...]] = ()
    events: ClassVar[tuple[str, ...]] = ()
    owner_events: ClassVar[tuple[str, ...]] = ()
    reads: ClassVar[tuple[str, ...]] = ()
    wants_telemetry: ClassVar[bool] = True

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Check the declarations when a subclass is defined: TypeError naming the class otherwise."""
        super().__init_subclass__(**kwargs)
        _check_declarations(cls)

    def __init__(self) -> None:
        self.id: str = ""
        self.owned: set[tuple[str, str]] = set()
        self.scene: dict[str, Any] = {}
        self.models: dict[str, str] = {}
        self.rate: float = 0.0
        self.tick: int = 0
        self.t: float = 0.0
        self.now: float = 0.0
        """The time (s) of the request being answered: a step's ``t``, a handover's (``acquire``, ``release``). A
        model stepping slower than the conductor's ticks may be asked for a handover after its last step's ``t``."""
        self._outputs: dict[str, Any] = {}
        self._events: list[dict[str, Any]] = []
        self.log: logging.Logger = logging.getLogger(f"twin.model.{self.kind}")

    # ---------------------------------------------------------------- hooks
    def init(self, params: dict[str, Any], scene: dict[str, Any]) -> None:
        """Called once per run (again after a rejoin) with the resolved parameters (every declared one:
        the scene's value or the default) and the scene (``name``, ``entities`` with shape, pose, tags and
        owners, ``main``, ``rate``, ``robot``); ``owned`` already holds what it owns at the start."""

    def start(self) -> None:
        """Called when the run starts (``tick`` and ``t`` are the first tick's)."""

    def step(self, tick: int, t: float, dt: float, telemetry: Telemetry, inputs: Inputs) -> None:
        """Advance by ``dt`` seconds to time ``t``. ``telemetry`` holds ``joints`` (the latest joint state or
        None) and ``actions`` (annotations since the last step); ``inputs`` maps entity -> attribute ->
        value for the attributes this model reads but does not own. Raise :class:`StepWarning` for a
        recoverable problem; any other exception makes the step's status ``error``."""

    def read(self, entity: str, attribute: str) -> Any:
        """Current value of an attribute this model owns (published on ``state/<id>`` after every step).
        A model that declares ``attributes`` must override it."""
        raise KeyError(f"{self.kind} cannot read {entity}.{attribute}")

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict[str, Any]) -> None:
        """Become the owner of ``entity.attribute``, seeded with the last owner's ``value`` and ``extra``
        (e.g. ``{"velocity": [...]}``). Raise to refuse: the last owner keeps it."""

    def release(self, entity: str, attribute: str) -> tuple[Any, dict[str, Any]]:
        """Stop owning ``entity.attribute``; return its value at ``now`` and extras for the next owner.
        The default returns :meth:`read`'s value and no extras."""
        return self.read(entity, attribute), {}

    def close(self) -> None:
        """Free resources: at exit, and before a second ``init`` (a warm agent of ``twin serve`` is initialised
        again for every run; ``init`` after ``close`` must build the model afresh)."""

    def snapshot(self) -> Any:
        """Optional: everything :meth:`step`, :meth:`read`, :meth:`release` and the evaluators depend on, as a
        value :meth:`restore` takes back (the runtime keeps ``owned``, ``tick`` and ``t`` itself). A model that
        defines both can be stepped ahead of a model that reads it and set back when that one's event ends the
        window earlier (the conductor's data-flow order, ``tick.mark``); it must then step again exactly as the
        first time. Not defined: the model is never asked to."""
        raise NotImplementedError

    def restore(self, state: Any) -> None:
        """Optional: be again what :meth:`snapshot` returned ``state`` from (it is not used afterwards)."""
        raise NotImplementedError

    @classmethod
    def rewinds(cls) -> bool:
        """Whether it defines :meth:`snapshot` and :meth:`restore`."""
        return cls.snapshot is not Model.snapshot and cls.restore is not Model.restore

    # ------------------------------------------------------------- helpers
    def emit(self, name: str, **data: Any) -> None:
        """Raise an event: published on ``event/<id>/<name>`` and returned with the step's reply. Raised
        outside ``step`` (in ``acquire``, an evaluator...), it goes out with the next step."""
        self._events.append({"name": name, "data": data})

    def output(self, name: str, value: Any) -> None:
        """Set an output for this step: published on ``out/<id>/<name>`` and returned with the reply."""
        self._outputs[name] = value

    def owns(self, entity: str, attribute: str) -> bool:
        """Whether this model owns ``entity.attribute`` now."""
        return (entity, attribute) in self.owned

    # ------------------------------------------------------------ registry
    @classmethod
    def evaluators(cls) -> dict[str, str]:
        """Evaluator name -> method name, for the methods marked with :func:`evaluator`."""
        return {f._twin_evaluator: n for n, f in _members(cls) if hasattr(f, "_twin_evaluator")}

    @classmethod
    def evaluator_names(cls) -> dict[str, list[str | None]]:
        """Evaluator name -> what each of its arguments names, position by position (:data:`NAME_KINDS`, None:
        anything), for the evaluators that declare ``names``."""
        return {f._twin_evaluator: list(f._twin_names) for _, f in _members(cls)
                if hasattr(f, "_twin_evaluator") and hasattr(f, "_twin_names")}

    @classmethod
    def services(cls) -> dict[str, str]:
        """Service name -> method name, for the methods marked with :func:`service`."""
        return {f._twin_service: n for n, f in _members(cls) if hasattr(f, "_twin_service")}


def arity(method: Callable[..., Any]) -> list[int | None]:
    """``[least, most]`` positional arguments a bound evaluator or service method takes (``most`` None: any number,
    ``*args``): what a scene's call must give it, checked before anything starts."""
    least, most = 0, 0
    for p in inspect.signature(method).parameters.values():
        if p.kind == p.VAR_POSITIONAL:
            return [least, None]
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            most += 1
            least += p.default is p.empty
    return [least, most]


def arities(model: Model, methods: Mapping[str, str]) -> dict[str, list[int | None]]:
    """:func:`arity` of each of ``model``'s evaluators or services (name -> method name)."""
    return {n: arity(getattr(model, f)) for n, f in methods.items()}


def _members(cls: type) -> Iterator[tuple[str, Any]]:
    """Callable class members by name, the most derived definition of each."""
    seen: set[str] = set()
    for klass in cls.__mro__:
        for n, f in vars(klass).items():
            if n not in seen and callable(f):
                seen.add(n)
                yield n, f


def _check_declarations(cls: type[Model]) -> None:
    """The class-definition checks of :meth:`Model.__init_subclass__`: what the conductor would refuse at
    registration, or what would fail on every step, fails here instead, naming the class."""
    name = cls.__qualname__
    if cls.role not in ROLES:
        raise TypeError(f"{name}.role must be one of {', '.join(ROLES)}, got {cls.role!r}")
    if not cls.step_modes or any(m not in STEP_MODES for m in cls.step_modes):
        raise TypeError(f"{name}.step_modes must list some of {', '.join(STEP_MODES)}, got {cls.step_modes!r}")
    if cls.attributes and cls.role == "observer":
        raise TypeError(f"{name} is an observer but declares attributes {cls.attributes!r}: an observer owns "
                        "nothing (make it role = 'simulation', or drop its attributes)")
    if cls.attributes and cls.read is Model.read:
        raise TypeError(f"{name} declares attributes {cls.attributes!r} but does not define read(entity, "
                        "attribute): the runtime reads every owned attribute after each step")
    extra = [e for e in cls.owner_events if e not in cls.events]
    if extra:
        raise TypeError(f"{name}.owner_events {extra!r} are not among its events {cls.events!r}")
    if cls.owner_events and cls.role == "observer":
        raise TypeError(f"{name} is an observer (it owns nothing) but declares owner_events {cls.owner_events!r}")
    if not isinstance(cls.params, Mapping):
        raise TypeError(f"{name}.params must map parameter names to Param, got {type(cls.params).__name__}")
    for pname, p in cls.params.items():
        if not isinstance(p, Param):
            raise TypeError(f"{name}.params[{pname!r}] must be a Param, got {p!r}")
        if p.type not in _TYPE_NAMES:
            raise TypeError(f"{name}.params[{pname!r}]: type must be one of "
                            f"{', '.join(t.__name__ for t in _TYPE_NAMES)}, got {p.type!r}")
        if p.positive and p.type not in (int, float):
            raise TypeError(f"{name}.params[{pname!r}]: positive is for an int or float parameter")
        if p.within_period and p.type is not float:
            raise TypeError(f"{name}.params[{pname!r}]: within_period is for a float parameter (seconds)")
        if not p.required and p.default is not None:
            try:
                p.coerce(pname, p.default)
            except (TypeError, ValueError) as e:
                raise TypeError(f"{name}.params[{pname!r}]: default {p.default!r} does not fit: {e}") from None
