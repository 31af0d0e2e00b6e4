"""Every message of the twin, one typed definition each, with a docstring per field.

A message is a msgpack map with ``v`` (:data:`PROTOCOL_VERSION`) and ``type`` (the name under which it is
listed in :data:`MESSAGES`) beside its fields. Each message is a :class:`~typing.TypedDict` whose fields are
``Annotated[type, "what it means"]``; :data:`SCHEMAS`, which the codec validates every decoded message
against, is derived from those definitions (:func:`schema_of`), so the two cannot drift apart. A field
that may be absent is ``NotRequired``; one that may be ``None`` is ``X | None``.

Value conventions shared by every model:

- ``pose``: ``[x, y, z, qx, qy, qz, qw]`` in metres, world frame (quaternion xyzw);
- handover values may carry ``extra`` (e.g. ``{"velocity": [vx, vy, vz, wx, wy, wz]}``);
- times: ``tick`` counts the conductor's clock from 0; ``t = tick / rate`` in simulated seconds.

:class:`Message` is the decoded, validated form: a dict whose fields also read as attributes.
"""
import math
import types
import typing
from collections.abc import Callable
from typing import Annotated, Any, NotRequired, TypedDict, Union

import numpy as np

from .errors import ProtocolError
from .geometry import FINITE_LIMIT, finite_numbers

__all__ = [
    # constants
    "PROTOCOL_VERSION", "STEP_STATUSES", "STEP_MODES", "ROLES", "BUILTIN_KINDS", "Value",
    # message definitions (and the types of their parts)
    "ParamInfo", "Register", "RegisterReply", "Query", "ParamsReply", "SceneInfo", "Init", "Ack", "Start", "Stop",
    "Section", "Until", "Tick", "StepReply", "Clock", "State", "Out", "Event", "Ownership", "Release", "ReleaseReply",
    "Acquire", "Rewind", "Eval", "Call", "ValueReply", "Error", "JointState", "Action", "Status", "Control",
    "MESSAGES",
    # schemas and validation
    "SCHEMAS", "schema_of", "field_docs", "check_fields", "json_schema", "Message", "unusable",
]

PROTOCOL_VERSION = 1

STEP_STATUSES = ("ok", "warning", "error")
"""A step's outcome (FMI's words): ``ok``; ``warning``, a recoverable problem the model reported with
``StepWarning`` (the run goes on); ``error``, the step raised (counted in the run summary's ``errors``)."""
STEP_MODES = ("service", "clock", "free")
"""``service``: the conductor steps the model and the tick waits for it; ``clock``: it steps on ``clock``
publications; ``free``: it runs at its own rate."""
BUILTIN_KINDS: frozenset[str] = frozenset(
    {"physics", "mujoco", "grasp_monitor", "in_hand", "spu", "fluid", "trivial", "fmu"})
"""The model kinds every agent process knows by name (``twin agent KIND``, a scene's ``kind: KIND``; any other
model is ``package.module:Class`` or ``fmu:PATH``): what the scene checker lets the twin start
(:func:`conductor.scene.check.launch_problems`), and what :mod:`agents.registry` maps to model classes."""
ROLES = ("simulation", "observer")
"""A ``simulation`` may own attributes; an ``observer`` owns nothing (one that declares attributes is
refused at registration)."""

Value = Any
"""Any msgpack value (numbers, strings, lists, maps, numpy arrays)."""


# ------------------------------------------------------------------------------------ registration
class ParamInfo(TypedDict):
    """One parameter a model declares (the conductor checks the scene's ``args`` against these)."""

    type: Annotated[str, "float, int, str, bool, list, map or any"]
    default: Annotated[Value, "the value used when the scene gives none"]
    doc: Annotated[str, "what it means, with its unit"]
    required: Annotated[bool, "the scene must give it"]
    choices: NotRequired[Annotated[list[Value], "the only values it takes (absent: any of its type)"]]
    positive: NotRequired[Annotated[bool, "a number that must be finite and above 0"]]
    within_period: NotRequired[Annotated[bool, "seconds, at most the model's step period (1 / its rate)"]]


class Register(TypedDict):
    """agent -> ``conductor/register/<name>``: who the agent is and everything its model declares, before any run
    (the part FMI's ``modelDescription.xml`` and mosaik's ``META`` play)."""

    name: Annotated[str, "the agent's name: the scene's model name, and the model id in every key"]
    kind: Annotated[str, "the model kind (e.g. physics), checked against the scene's models.<name>.kind"]
    role: Annotated[str, "simulation or observer (ROLES): an observer that declares attributes is refused"]
    step_modes: Annotated[list[str], "the step modes it supports (STEP_MODES); the scene's choice must be one"]
    params: Annotated[dict[str, ParamInfo], "its parameters by name"]
    attributes: Annotated[list[str], "the attributes it can own (e.g. pose)"]
    outputs: Annotated[list[str], "the outputs it publishes on out/<id>/<name>"]
    events: Annotated[list[str], "the events it raises on event/<id>/<name>"]
    evaluators: Annotated[list[str], "evaluators the scene may call (model/<id>/eval/<name>)"]
    evaluator_args: NotRequired[Annotated[dict[str, list[str | None]], "evaluator -> what each argument names, "
                                          "position by position (entity, tag, body; null: anything): the scene's "
                                          "strings there are checked"]]
    services: Annotated[list[str], "services trigger effects may call (model/<id>/call/<name>)"]
    arity: NotRequired[Annotated[dict[str, dict[str, list[int | None]]], "eval/call -> evaluator or service -> "
                                 "[least, most] positional arguments it takes (most null: any number)"]]
    pid: NotRequired[Annotated[int, "its process id (a restart is a new process)"]]
    host: NotRequired[Annotated[str, "its host name"]]
    telemetry: NotRequired[Annotated[bool, "it wants the robot's joint states and actions in its steps"]]
    reads: NotRequired[Annotated[list[str], "entity.attribute patterns of others' values it wants each step"]]
    clock_ack: NotRequired[Annotated[bool, "clock-driven, it answers each clock tick on done/<id>"]]
    batch: NotRequired[Annotated[bool, "service-stepped, it steps the batches of ticks in tick.more"]]
    owner_events: NotRequired[Annotated[list[str], "those of its events it raises only about what it owns: never "
                                                   "while it owns nothing"]]
    until: NotRequired[Annotated[bool, "service-stepped, it stops a batch early where tick.until tells it to"]]
    rewind: NotRequired[Annotated[bool, "service-stepped, it keeps a checkpoint where tick.mark tells it to and "
                                        "goes back to it on model/<id>/rewind"]]
    addressed: NotRequired[Annotated[bool, "service-stepped, it also hears the step messages addressed to it and "
                                           "others on step/<their ids>/... (Keys.step_for)"]]


class RegisterReply(TypedDict):
    """conductor -> agent: accepted (with the id to serve under) or refused (with the reason)."""

    id: Annotated[str, "the model id (= the agent's name); empty when refused"]
    accepted: Annotated[bool, "False: the agent exits with the reason"]
    reason: NotRequired[Annotated[str, "why it was refused"]]


# -------------------------------------------------------------------------------------- life cycle
class Query(TypedDict):
    """A request with nothing to say (``model/<id>/params``, ``model/<id>/health``)."""

    args: NotRequired[Annotated[Value, "unused"]]


class ParamsReply(TypedDict):
    """agent -> conductor: the parameters its model declares (as in :class:`Register`)."""

    params: Annotated[dict[str, ParamInfo], "parameters by name"]


class SceneInfo(TypedDict):
    """The scene as a model sees it at ``init``."""

    name: Annotated[str, "the scene's name"]
    entities: Annotated[dict[str, Any], "entity -> {shape, pose, tags, attributes, mass?, friction?, color?}"]
    main: Annotated[str, "the main model: owns every pose at start and takes back what a lost model owned"]
    rate: Annotated[float, "the conductor's clock rate (ticks per simulated second)"]
    robot: Annotated[dict[str, Any], "the scene's robot block ({} if none)"]


class Init(TypedDict):
    """conductor -> ``model/<id>/init``: resolved parameters, the scene and what the model owns at start."""

    params: Annotated[dict[str, Value], "the scene's args for it (checked against its declared params)"]
    scene: Annotated[dict[str, Any], "the scene (SceneInfo)"]
    owned: Annotated[list[list[str]], "[entity, attribute] pairs it owns at start"]
    rate: Annotated[float, "its own step rate (Hz)"]
    step_mode: Annotated[str, "the step mode the scene chose for it (one of its declared step_modes)"]
    models: Annotated[dict[str, str], "every model of the scene: name -> kind"]


class Ack(TypedDict):
    """A plain answer: done (``ok``), with an optional message."""

    ok: Annotated[bool, "it was done"]
    message: NotRequired[Annotated[str, "a word for the log"]]


class Start(TypedDict):
    """conductor -> ``model/<id>/start``: the run starts at this tick."""

    tick: Annotated[int, "the first tick"]
    t: Annotated[float, "its time (s)"]


class Stop(TypedDict):
    """conductor -> ``model/<id>/stop``: the run ended."""

    reason: NotRequired[Annotated[str, "why"]]


# ------------------------------------------------------------------------------------------- steps
class Section(TypedDict):
    """One model's part of a tick of the step broadcast."""

    dt: Annotated[float, "seconds to advance (its period)"]
    actions: Annotated[list[dict[str, Any]], "action annotations since its last step (Action)"]
    inputs: Annotated[dict[str, dict[str, Value]], "entity -> attribute -> value of what it reads and others own"]


class Until(TypedDict):
    """Where a model stops stepping a batch of ticks early: after the first tick at which it raises one of
    ``events`` or one of ``outputs`` takes a value other than the one it last reported (or its first). The
    ticks after it are not stepped; its answer carries ``stopped``."""

    events: Annotated[list[str], "events that stop it"]
    outputs: Annotated[list[str], "outputs whose change stops it"]


class Tick(TypedDict):
    """conductor -> ``step`` (broadcast to every service-stepped model): one tick, or a batch of ticks."""

    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]
    joints: Annotated[dict[str, Any] | None, "the latest joint state (JointState) for models that want telemetry"]
    models: Annotated[dict[str, Section], "a section per model due on this tick"]
    due: NotRequired[Annotated[list[str], "models due that share the 'shared' section (no telemetry, no inputs)"]]
    shared: NotRequired[Annotated[Section, "the section of the models listed in 'due'"]]
    more: NotRequired[Annotated[list[dict[str, Any]], "the following ticks of a batch, each a Tick (increasing)"]]
    until: NotRequired[Annotated[dict[str, Until], "model -> where it stops stepping this batch early"]]
    mark: NotRequired[Annotated[list[str], "models that keep a checkpoint before stepping this batch (Rewind)"]]


class StepReply(TypedDict):
    """agent -> ``done/<id>``: what one step produced (a clock-driven model sends it without the payload)."""

    tick: Annotated[int, "the tick stepped"]
    status: Annotated[str, "ok, warning or error (STEP_STATUSES)"]
    state: Annotated[dict[str, dict[str, Value]], "entity -> attribute -> value of everything it owns"]
    outputs: Annotated[dict[str, Value], "outputs set in this step"]
    events: Annotated[list[dict[str, Any]], "events raised in this step: {name, data}"]
    message: NotRequired[Annotated[str, "what went wrong (status warning or error)"]]
    step_s: NotRequired[Annotated[float, "wall seconds the model's step took"]]
    more: NotRequired[Annotated[list[dict[str, Any]], "the replies to its later ticks of a batch, in order"]]
    stopped: NotRequired[Annotated[bool, "it stopped the batch early, after its last reply (Tick.until)"]]


class Clock(TypedDict):
    """conductor -> ``clock``: a tick for clock-driven models."""

    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]
    dt: Annotated[float, "the conductor's tick length (s)"]


class State(TypedDict):
    """agent -> ``state/<id>``: the values of everything it owns after a step (one message per step)."""

    model: Annotated[str, "the model id"]
    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]
    values: Annotated[dict[str, dict[str, Value]], "entity -> attribute -> value"]


class Out(TypedDict):
    """agent -> ``out/<id>/<name>``: an output's value after a step."""

    model: Annotated[str, "the model id"]
    name: Annotated[str, "the output"]
    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]
    value: Annotated[Value, "its value"]


class Event(TypedDict):
    """agent (or the conductor, as ``_conductor``) -> ``event/<id>/<name>``: something happened."""

    model: Annotated[str, "who raised it"]
    name: Annotated[str, "the event"]
    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]
    data: Annotated[dict[str, Value], "what the event carries"]


class Ownership(TypedDict):
    """conductor -> ``ownership``: the responsibility map, published on every change."""

    version: Annotated[int, "bumped on every change"]
    tick: Annotated[int, "the tick of the change"]
    t: Annotated[float, "its time (s)"]
    owners: Annotated[dict[str, dict[str, str]], "entity -> attribute -> owning model"]
    change: Annotated[dict[str, Any] | None, "the handover that made this version (None for the first)"]


# ---------------------------------------------------------------------------------------- handover
class Release(TypedDict):
    """conductor -> ``model/<id>/release``: stop owning ``entity.attribute`` and hand its value over."""

    entity: Annotated[str, "the entity"]
    attribute: Annotated[str, "the attribute"]
    tick: Annotated[int, "the tick (handovers run between ticks)"]
    t: Annotated[float, "its time (s)"]


class ReleaseReply(TypedDict):
    """agent -> conductor: the released value and its extras."""

    entity: Annotated[str, "the entity"]
    attribute: Annotated[str, "the attribute"]
    value: Annotated[Value, "its current value"]
    extra: Annotated[dict[str, Value], "what the next owner may want too (e.g. velocity)"]


class Rewind(TypedDict):
    """conductor -> ``model/<id>/rewind``: undo the steps after ``tick`` of the last step message marked for it
    (``tick.mark``): back to the checkpoint kept before it, then its ticks up to ``tick`` stepped again, nothing
    published (the answers are those it gave the first time)."""

    tick: Annotated[int, "the last tick that stands (at least the one before the marked message's first)"]


class Acquire(TypedDict):
    """conductor -> ``model/<id>/acquire``: own ``entity.attribute`` from now, seeded with ``value``."""

    entity: Annotated[str, "the entity"]
    attribute: Annotated[str, "the attribute"]
    value: Annotated[Value, "the last owner's value"]
    extra: Annotated[dict[str, Value], "the last owner's extras"]
    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]


# --------------------------------------------------------------------------- evaluators and services
class Eval(TypedDict):
    """conductor -> ``model/<id>/eval/<name>``: call an evaluator."""

    args: Annotated[list[Value], "the scene's args, then the call's"]
    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]


class Call(TypedDict):
    """conductor -> ``model/<id>/call/<name>``: call a service (a trigger's effect)."""

    args: Annotated[list[Value], "positional arguments"]
    kwargs: Annotated[dict[str, Value], "keyword arguments"]
    tick: Annotated[int, "the tick"]
    t: Annotated[float, "its time (s)"]


class ValueReply(TypedDict):
    """The value an evaluator, a service or ``model/<id>/health`` returns."""

    value: Annotated[Value, "the result"]


class Error(TypedDict):
    """An error reply: the remote exception as data."""

    kind: Annotated[str, "the exception's type name (ProtocolError for a malformed request)"]
    message: Annotated[str, "its message"]
    traceback: NotRequired[Annotated[str, "its formatted traceback"]]


# --------------------------------------------------------------------------------------- telemetry
class JointState(TypedDict):
    """robot -> ``telemetry/joint_states``: one sample of the joints it names (lists of equal length); the joints
    it does not name keep their last values (an arm's and a gripper's driver may publish apart)."""

    stamp: Annotated[float, "seconds: since the recording's start (replay) or the epoch (live)"]
    name: Annotated[list[str], "joint names, each once"]
    position: Annotated[list[float], "rad or m"]
    velocity: Annotated[list[float], "rad/s or m/s (may be empty)"]
    effort: Annotated[list[float], "Nm or N (may be empty)"]


class Action(TypedDict):
    """robot -> ``telemetry/action``: an action annotation."""

    stamp: Annotated[float, "seconds, as JointState.stamp"]
    operation: Annotated[str, "e.g. move_hand, move_arm, release"]
    phase: Annotated[str, "start or end"]
    params: Annotated[dict[str, Value], "the operation's parameters (e.g. command: close)"]


# ------------------------------------------------------------------------------------------ control
class Status(TypedDict):
    """conductor -> ``conductor/status``: what it is doing (see the README for the fields)."""

    fields: Annotated[dict[str, Any], "scene, ensemble, running, tick, t, version, ownership, agents, ..."]


class Control(TypedDict):
    """A client -> the conductor's services: ``conductor/start``, ``stop``, ``status``, ``trigger/<name>``."""

    args: NotRequired[Annotated[dict[str, Value], "the request: a run to start (scene text, perception, source), "
                                "a run id to stop or ask about, a service trigger's arguments"]]


MESSAGES: dict[str, type] = {
    "register": Register, "register_reply": RegisterReply, "query": Query, "params_reply": ParamsReply,
    "init": Init, "ack": Ack, "start": Start, "stop": Stop, "tick": Tick, "step_reply": StepReply,
    "clock": Clock, "state": State, "out": Out, "event": Event, "ownership": Ownership, "release": Release,
    "release_reply": ReleaseReply, "acquire": Acquire, "rewind": Rewind, "eval": Eval, "call": Call,
    "value_reply": ValueReply, "error": Error, "joint_state": JointState, "action": Action, "status": Status,
    "control": Control,
}
"""Every message type by its wire name (the ``type`` field)."""


# ------------------------------------------------------------------------------- derived schemas
def _schema_type(tp: Any) -> str:
    """The codec's type word for a field's annotation (``str``, ``int``, ``num``, ``bool``, ``map``,
    ``list`` or ``any``; ``?`` appended when it may be ``None``)."""
    origin = typing.get_origin(tp)
    if origin in (NotRequired, typing.Required):
        return _schema_type(typing.get_args(tp)[0])
    if origin is Annotated:
        return _schema_type(typing.get_args(tp)[0])
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        base = _schema_type(args[0]) if len(args) == 1 else "any"
        return base if base == "any" or len(args) == len(typing.get_args(tp)) else base + "?"
    if tp is Any:
        return "any"
    if tp is str:
        return "str"
    if tp is bool:
        return "bool"
    if tp is int:
        return "int"
    if tp is float:
        return "num"
    if tp is dict or origin is dict or typing.is_typeddict(tp):
        return "map"
    if tp is list or origin is list:
        return "list"
    raise TypeError(f"no schema type for {tp!r}")


def schema_of(message: type) -> dict[str, str]:
    """The field -> type-word schema of a message definition (``name?`` for a field that may be absent).

    Raises TypeError for a field whose annotation has no type word (see :func:`_schema_type`)."""
    hints = typing.get_type_hints(message, include_extras=True)
    optional: frozenset[str] = getattr(message, "__optional_keys__", frozenset())
    return {(name + "?" if name in optional else name): _schema_type(tp) for name, tp in hints.items()}


def field_docs(message: type) -> dict[str, str]:
    """Each field's doc string (the ``Annotated`` text; empty for a field without one)."""
    out: dict[str, str] = {}
    for name, tp in typing.get_type_hints(message, include_extras=True).items():
        while typing.get_origin(tp) in (NotRequired, typing.Required):
            tp = typing.get_args(tp)[0]
        docs = [m for m in getattr(tp, "__metadata__", ()) if isinstance(m, str)]
        out[name] = docs[0] if docs else ""
    return out


SCHEMAS: dict[str, dict[str, str]] = {name: schema_of(m) for name, m in MESSAGES.items()}
"""The schema of every message type, derived from :data:`MESSAGES`."""

_JSON_SCALARS: dict[Any, str] = {str: "string", bool: "boolean", int: "integer", float: "number"}


def _json_type(tp: Any) -> dict[str, Any] | None:
    """The JSON Schema of a field's annotation, in the subset viewers build their field lists from (Lichtblick's
    and Foxglove's ``parseJsonSchema``: one ``type`` per property, arrays with typed ``items``, every object with
    ``properties``, which Foxglove Studio before late 2023 requires); None for a field
    that subset cannot state (``Value``, a value that may be ``None``, a list of mixed values): it is left out of
    ``properties``, so it is neither refused nor checked."""
    origin = typing.get_origin(tp)
    if origin in (NotRequired, typing.Required, Annotated):
        return _json_type(typing.get_args(tp)[0])
    if origin in (Union, types.UnionType) or tp is Any:
        return None
    if tp in _JSON_SCALARS:
        return {"type": _JSON_SCALARS[tp]}
    if typing.is_typeddict(tp):
        return _json_object(tp)
    if tp is dict or origin is dict:  # free-form: its fields are not listed (but "properties" must be there)
        return {"type": "object", "properties": {}}
    if origin is list:
        item = _json_type(typing.get_args(tp)[0])  # no arrays of arrays either
        return {"type": "array", "items": item} if item is not None and item["type"] != "array" else None
    return None


def _json_object(message: type) -> dict[str, Any]:
    docs = field_docs(message)
    optional: frozenset[str] = getattr(message, "__optional_keys__", frozenset())
    props: dict[str, Any] = {}
    required: list[str] = []
    for name, tp in typing.get_type_hints(message, include_extras=True).items():
        prop = _json_type(tp)
        if prop is not None:
            props[name] = {**prop, "description": docs[name]} if docs.get(name) else prop
        if name not in optional:
            required.append(name)
    return {"type": "object", "properties": props, "required": required}


def json_schema(mtype: str) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of message type ``mtype`` as the run log writes it in JSON (numpy arrays
    become lists, bytes base64 text, a non-finite number ``null``): the fields of :data:`MESSAGES` with their docs,
    in the subset Foxglove and Lichtblick read (see :func:`_json_type`).

    Raises KeyError for an unknown type."""
    body = _json_object(MESSAGES[mtype])
    props = {"v": {"type": "integer", "description": "protocol version"},
             "type": {"type": "string", "const": mtype, "description": "the message type"}, **body["properties"]}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": f"twin.{mtype}", "type": "object",
            "properties": props, "required": ["v", "type", *body["required"]]}


_TYPES: dict[str, type | tuple[type, ...]] = {
    "str": str,
    "int": int,
    "num": (int, float),
    "bool": bool,
    "map": dict,
    "list": (list, tuple, np.ndarray),
    "any": object,
}


_NUMERIC, _LIST = 1, 2

_Field = tuple[str, bool, bool, str, type | tuple[type, ...], int]
"""One field of a schema, ready for :func:`check_fields`: name; optional (may be absent); nullable (may be
None, as every ``any`` field may); the type word (for the error message); what ``isinstance`` accepts; its
kind: :data:`_NUMERIC` (``int`` or ``num``: a bool is refused although it is an int), :data:`_LIST` (a numpy
array stands for a list only with a dimension) or 0. A plain tuple, not a NamedTuple: unpacking an exact tuple
is the interpreter's fast path, and this runs for every field of every message."""


def _compile(schema: dict[str, str]) -> tuple[_Field, ...]:
    out: list[_Field] = []
    for fname, tname in schema.items():
        optional = fname.endswith("?")
        nullable = tname.endswith("?")
        base = tname[:-1] if nullable else tname
        out.append((fname[:-1] if optional else fname, optional, nullable or base == "any", base,
                    _TYPES[base], _NUMERIC if base in ("int", "num") else _LIST if base == "list" else 0))
    return tuple(out)


_COMPILED: dict[str, tuple[_Field, ...]] = {name: _compile(schema) for name, schema in SCHEMAS.items()}


def check_fields(key: object, mtype: str, obj: dict[str, Any]) -> None:
    """Raise :class:`ProtocolError` (on ``key``) if ``obj`` does not carry the fields of message type ``mtype``
    with the right types, or breaks that type's own rules (:data:`_RULES`; for a batch, each of its later
    ticks too). ``mtype`` must be a key of :data:`SCHEMAS` (KeyError otherwise). A list field may be a numpy
    array (a fluid's particles in a release_reply), of at least one dimension."""
    for name, optional, nullable, base, py, kind in _COMPILED[mtype]:
        if name not in obj:
            if optional:
                continue
            raise ProtocolError(key, f"{mtype} message lacks field {name!r}")
        val = obj[name]
        if val is None:
            if nullable:
                continue
            raise ProtocolError(key, f"{mtype}.{name} must not be null")
        if not isinstance(val, py) or (kind == _NUMERIC and isinstance(val, bool)):
            got = "bool" if isinstance(val, bool) else type(val).__name__
            raise ProtocolError(key, f"{mtype}.{name} must be {base}, got {got}")
        if kind == _LIST and val.__class__ is np.ndarray and val.ndim == 0:  # (len() and iterating it raise)
            raise ProtocolError(key, f"{mtype}.{name} must be a list, got a 0-d array of {val.dtype}")
    rule = _RULES.get(mtype)
    if rule is not None:
        try:
            rule(key, obj)
        except ProtocolError:
            raise
        except Exception as e:  # (a value of a shape the rule did not foresee: malformed all the same)
            raise ProtocolError(key, f"{mtype} message does not hold together ({type(e).__name__}: {e})") from None


def _check_tick(key: object, obj: dict[str, Any]) -> None:
    more = obj.get("more")
    if more is not None:
        _check_more(key, "tick", obj, more)


def _check_step_reply(key: object, obj: dict[str, Any]) -> None:
    if obj["status"] != "ok" and obj["status"] not in STEP_STATUSES:
        raise ProtocolError(key, f"step_reply.status must be one of {STEP_STATUSES}, got {obj['status']!r}")
    more = obj.get("more")
    if more is not None:
        _check_more(key, "step_reply", obj, more)


def _check_register(key: object, obj: dict[str, Any]) -> None:
    if obj["role"] not in ROLES:
        raise ProtocolError(key, f"register.role must be one of {ROLES}")
    bad = [m for m in obj["step_modes"] if m not in STEP_MODES]
    if bad or not obj["step_modes"]:
        raise ProtocolError(key, f"register.step_modes must list some of {STEP_MODES}, got {obj['step_modes']!r}")
    for name in ("attributes", "outputs", "events", "evaluators", "services", "owner_events", "reads"):
        if not all(isinstance(v, str) for v in obj.get(name) or ()):
            raise ProtocolError(key, f"register.{name} must list names (strings)")
    for name, info in obj["params"].items():  # (the scene's args are checked against each: one that is no map
        if not (isinstance(info, dict) and isinstance(info.get("type"), str)  # crashed the check)
                and isinstance(info.get("required", False), bool)):
            raise ProtocolError(key, f"register.params.{name} must be a map of type (a string), default, doc and "
                                     f"required (a boolean), got {info!r:.80}")
    for kind, table in (obj.get("arity") or {}).items():
        if not isinstance(table, dict):
            raise ProtocolError(key, f"register.arity.{kind} must map names to [least, most], got {table!r:.80}")
        for name, span in table.items():
            if not (isinstance(span, list) and len(span) == 2 and isinstance(span[0], int)
                    and (span[1] is None or isinstance(span[1], int))):
                raise ProtocolError(key, f"register.arity.{kind}.{name} must be [least, most] (most null: any), "
                                         f"got {span!r:.80}")
    for name, kinds in (obj.get("evaluator_args") or {}).items():
        if not isinstance(kinds, list):
            raise ProtocolError(key, f"register.evaluator_args.{name} must be a list, got {kinds!r:.80}")


def _check_joint_state(key: object, obj: dict[str, Any]) -> None:
    for f in ("name", "position", "velocity", "effort"):  # (a robot's numpy arrays: the lists they stand for)
        v = obj[f]
        if v.__class__ is np.ndarray:
            if v.ndim != 1 or v.dtype.kind not in "biuf":
                raise ProtocolError(key, f"joint_state.{f} must be a list, got a {v.ndim}-d array of {v.dtype}")
            obj[f] = v.tolist()
    n = len(obj["name"])
    if not all(isinstance(name, str) for name in obj["name"]):
        raise ProtocolError(key, "joint_state.name must hold the joints' names (strings)")
    if not math.isfinite(obj["stamp"]):
        raise ProtocolError(key, f"joint_state.stamp is {obj['stamp']}, not a finite number")
    if len(set(obj["name"])) != n:  # which value would be the joint's?
        raise ProtocolError(key, "joint_state.name names a joint twice")
    for f in ("position", "velocity", "effort"):
        if len(obj[f]) not in (0, n):
            raise ProtocolError(key, f"joint_state.{f} has {len(obj[f])} values for {n} names")
        if not finite_numbers(obj[f]):  # (a recording's are left out the same way)
            raise ProtocolError(key, f"joint_state.{f} holds a value that is not a finite number (or is beyond "
                                     f"{FINITE_LIMIT:g} in size: a unit or encoding error)")


def _check_action(key: object, obj: dict[str, Any]) -> None:
    if not math.isfinite(obj["stamp"]):
        raise ProtocolError(key, f"action.stamp is {obj['stamp']}, not a finite number")
    if obj["phase"] not in ("start", "end"):
        raise ProtocolError(key, f"action.phase must be 'start' or 'end', got {obj['phase']!r}")


_RULES: dict[str, Callable[[object, dict[str, Any]], None]] = {
    "tick": _check_tick,
    "step_reply": _check_step_reply,
    "register": _check_register,
    "joint_state": _check_joint_state,
    "action": _check_action,
}
"""The rules of a message type beyond its fields' types, run by :func:`check_fields` once the fields are
known to be there with the right types."""


def _check_more(key: object, mtype: str, obj: dict[str, Any], more: object) -> None:
    """The later ticks of a batch (``tick.more``, ``step_reply.more``): each one a message of the same type,
    in increasing tick order, none with a batch of its own."""
    if more.__class__ is not list:
        raise ProtocolError(key, f"{mtype}.more must be a list of {mtype} messages")
    last = obj["tick"]
    for i, item in enumerate(more):
        where = f"{mtype}.more[{i}]"
        if item.__class__ is not dict:
            raise ProtocolError(key, f"{where} must be a map")
        if "more" in item:
            raise ProtocolError(key, f"{where} must not carry a batch of its own")
        if mtype == "step_reply" and (item.get("v") != PROTOCOL_VERSION or item.get("type") != mtype):
            raise ProtocolError(key, f"{where} must be a step_reply of protocol version {PROTOCOL_VERSION}")
        try:
            check_fields(key, mtype, item)
        except ProtocolError as e:
            raise ProtocolError(key, f"in {where}: {e.problem}") from None
        if item["tick"] <= last:
            raise ProtocolError(key, f"{where}.tick {item['tick']} does not follow tick {last}")
        last = item["tick"]


class Message(dict[str, Any]):
    """A decoded, validated message: a dict whose fields also read as attributes (``msg.tick``)."""

    __slots__ = ()

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def mtype(self) -> str:
        """The message type (its ``type`` field, a key of :data:`MESSAGES`)."""
        return str(self["type"])


def unusable(attribute: str, value: Any) -> str | None:
    """Why a model's value is no value (None: it is one): None, a number that is not finite anywhere in it (a NaN
    pose, an estimate diverged), or a ``pose`` that is a flat list but not 7 numbers ([x, y, z, qx, qy, qz, qw]; a
    fluid's pose is a list of positions, each checked for finite numbers)."""
    if value is None:
        return "no value"
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, (float, np.floating)) and not math.isfinite(v):
            return "not a finite number"
        if isinstance(v, (list, tuple)):
            stack.extend(v)
        elif isinstance(v, dict):
            stack.extend(v.values())
        elif isinstance(v, np.ndarray) and v.dtype.kind in "fc" and not np.isfinite(v).all():  # (the codec's arrays)
            return "not a finite number"
    flat = value.ndim == 1 if isinstance(value, np.ndarray) else \
        isinstance(value, (list, tuple)) and bool(value) and not isinstance(value[0], (list, tuple, np.ndarray))
    if attribute == "pose" and flat and len(value) != 7:
        return f"a pose of {len(value)} numbers, not 7"
    return None
