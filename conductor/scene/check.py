"""Scene files: loading and validation.

A scene is YAML::

    name: ball_drop
    clock: {rate: 120, max_lag: 0.1, batch: 32}
                                       # conductor ticks per simulated second; how far (simulated s)
                                       # a clock-driven model may fall behind in a replay; at most how
                                       # many ticks one step message may carry when nothing can intervene
    main: physics                      # the main model: owns every pose at start (unless an entity's
                                       # attributes give it to another, or it is virtual), takes back orphans
    robot: {urdf: franka_panda/panda.urdf, base: [0, 0, 0, 0, 0, 0, 1]}
    models:
      physics: {kind: physics, step: service, rate: 120, args: {...}}
      grasp_monitor: {kind: grasp_monitor, step: service, rate: 15}
    entities:
      ball: {shape: {type: sphere, radius: 0.033}, pose: [0.5, 0, 0.1], tags: [graspable]}
    evaluators:
      hand_free: {model: grasp_monitor, name: hand_free}
    triggers:
      - name: grasp
        on: {action: move_hand, phase: end}
        when: "hand_free('hand') == false"
        let: {obj: "closest('graspable', 'panda_hand')"}
        do:
          - transfer: {entity: obj, attribute: pose, to: in_hand}
    semantics:
      "in(container, ball)": "inside(container, ball)"

A scene is checked twice. :func:`parse_scene` checks it alone, before any process is touched; once every
agent has registered, :func:`check_against_agents` checks it against what the agents declare. Both report
every problem at once, each as ``file:line: key.path: what is wrong``: one
:class:`~protocol.errors.SceneError` (:meth:`~protocol.errors.SceneError.of`) or a list of
:class:`~protocol.errors.Problem`. A part that is broken is reported once; what depends on it is not
checked (with a broken ``models`` map, no trigger's ``to:`` is called an unknown model).
"""
from __future__ import annotations

import difflib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from protocol.errors import ExprError, Problem, SceneError
from protocol.geometry import finite_number, full_pose, pose_problem, valid_pose, validate_shape
from protocol.keys import RESERVED_IDENTITIES, check_name
from protocol.messages import BUILTIN_KINDS, STEP_MODES
from protocol.robot import Robot, check_robot, read_urdf, resolve_robot

from ..builtins import ARG_KINDS, ARITY, BUILTIN_NAMES
from .expr import Expr, parse
from .load import Lines, fmt_path, load_yaml
from .spec import Effect, EntitySpec, EvaluatorSpec, ModelSpec, Scene, TriggerSpec
from .uncertain import check_uncertain

CONTEXT_NAMES = {"action", "event", "value", "tick", "t", "trigger"}
WORLD_NAMES = {"table", "robot", "world"}  # what the simulations call parts of the world that are no entity
TOP_KEYS = {"name", "description", "clock", "main", "models", "entities", "evaluators", "triggers",
            "semantics", "robot", "uncertain"}
CLOCK_KEYS = {"rate", "max_lag", "batch"}
MODEL_KEYS = {"kind", "step", "rate", "args", "reads", "doc"}
ENTITY_KEYS = {"shape", "pose", "tags", "attributes", "color", "doc", "mass", "friction", "perceived_as"}
TRIGGER_KEYS = {"name", "on", "when", "let", "do", "once", "doc"}
EVALUATOR_KEYS = {"model", "name", "args", "doc"}

Path_ = tuple[Any, ...]  # a key path into the scene: ("triggers", 0, "do", 1, "transfer")

# what a checker may raise on a value nobody anticipated; the last-resort handler turns it into a problem
_UNEXPECTED = (TypeError, ValueError, KeyError, AttributeError, IndexError, OverflowError, RecursionError,
               OSError)


def load_scene(path: str | Path) -> Scene:
    """The scene in file ``path``, checked; a :class:`SceneError` listing every problem otherwise."""
    path = Path(path)
    file = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise SceneError(file, None, "", f"cannot read scene: {e.strerror}") from None
    except UnicodeDecodeError as e:
        line = path.read_bytes().count(b"\n", 0, e.start) + 1
        raise SceneError(file, line, "", f"not UTF-8 text (byte {e.object[e.start]:#04x})") from None
    return parse_scene(text, file)


def parse_scene(text: str, file: str = "<scene>") -> Scene:
    """The scene in ``text`` (read from ``file``), checked; a :class:`SceneError` listing every problem,
    each naming file, line and key path, otherwise. YAML the loader refuses (syntax, nesting, alias
    bombs, unreadable values) is one problem: nothing can be checked past it."""
    data, lines = load_yaml(text, file)
    return _Checker(data, lines, file).scene()


def _name(v: Any) -> bool:
    return isinstance(v, str) and bool(v)


@dataclass
class _Scope:
    """The names an expression may use: ``complete`` is False when a part they come from is broken,
    and then an unknown name is not reported (it may well be defined in that part)."""

    names: set[str]
    complete: bool = True


class _Checker:
    """One scene being checked: each section checker records its problems and goes on.

    Sections are checked in a fixed order (top-level keys, name, clock, models, main, entities,
    evaluators, triggers, semantics, robot), each after those it refers to, and problems are listed in
    the order found. What a later section needs from an earlier one is ``None`` (or an incomplete
    :class:`_Scope`) when the earlier one is broken, and the checks that need it are skipped.
    """

    def __init__(self, data: Any, lines: Lines, file: str) -> None:
        self.data, self.lines, self.file = data, lines, file
        self.robot: Robot | None = None
        self.uncertain: dict[tuple[str, str], tuple[float, float]] = {}
        self.problems: list[Problem] = []
        self.keys_with_problems: set[str] = set()
        self.found = 0  # problems seen, including those not listed because their key already has one
        self.where: Path_ = ()  # the part being checked, for the last-resort handler
        # what later sections refer to: None when the section it comes from is broken
        self.name: str | None = None
        self.rate: float | None = None
        self.rate_given: Any = None  # the clock rate as written, as messages quote it
        self.max_lag: float | None = None
        self.batch: int | None = None
        self.model_names: set[str] | None = None
        self.main: str | None = None
        self.entity_names: set[str] | None = None
        self.entity_attrs: dict[Any, list[Any]] = {}  # entity -> its attribute names, where readable
        self.attrs_complete = False  # every entity's attribute names are known (set when the section is done)
        self.attrs_unreadable = False  # some entity's attribute names could not be read
        self.funcs: frozenset[str] | None = None
        # the parts of the Scene, complete only if no problem was found
        self.models: dict[str, ModelSpec] = {}
        self.entities: dict[str, EntitySpec] = {}
        self.evaluators: dict[str, EvaluatorSpec] = {}
        self.triggers: list[TriggerSpec] = []
        self.semantics: dict[str, Expr] = {}

    # ------------------------------------------------------------------------------------ driving
    def scene(self) -> Scene:
        """The checked :class:`Scene`, or a :class:`SceneError` with every problem found."""
        if not isinstance(self.data, dict):
            raise SceneError(self.file, self.lines.get(()), "", "a scene must be a map with 'models' and 'entities'")
        for key, section in (("", lambda: self._unknown_keys((), self.data, TOP_KEYS)), ("name", self._name),
                             ("clock", self._clock), ("models", self._models), ("main", self._main),
                             ("entities", self._entities), ("evaluators", self._evaluators),
                             ("triggers", self._triggers), ("semantics", self._semantics), ("robot", self._robot),
                             ("uncertain", self._uncertain)):
            self._guarded(key, section)
        if self.problems:
            raise SceneError.of(self.problems)
        assert self.name is not None and self.rate is not None and self.main is not None and self.batch is not None
        return Scene(self.file, self.name, self.rate, self.main, self.models, self.entities, self.evaluators,
                     self.triggers, self.semantics, self.data, self.lines, self.max_lag, self.batch, self.robot,
                     self.uncertain)

    def _guarded(self, key: str, section: Callable[[], None]) -> None:
        """Run one section checker; a value that makes it raise is a problem where it was, and the
        section's results stay as far as they got (what depends on a part left unknown is skipped)."""
        self.where = (key,) if key else ()
        try:
            section()
        except _UNEXPECTED as e:
            self.problem(self.where, f"invalid value here ({type(e).__name__}: {e})")

    def problem(self, path: Path_, problem: str) -> None:
        """Record a problem at ``path``; a key that already has one keeps only its first."""
        self.found += 1
        try:
            key = fmt_path(path)
        except ValueError:  # a key Python refuses to print (an integer of thousands of digits)
            path = path[:1]
            key = fmt_path(path)
        if key in self.keys_with_problems:
            return
        self.keys_with_problems.add(key)
        self.problems.append(Problem(self.file, self.lines.get(path), key, problem))

    def _unknown_keys(self, path: Path_, given: Mapping[Any, Any], allowed: set[str]) -> None:
        for k in given:
            if k not in allowed:
                self.problem(path + (k,), f"unknown key {k!r} (allowed: {', '.join(sorted(allowed))})")

    def _expr(self, path: Path_, src: Any, scope: _Scope) -> Expr | None:
        """``src`` parsed, calling only known functions and reading only names in ``scope``; None (and a
        problem) otherwise. Unknown functions and names are only reported when what defines them is whole."""
        try:
            ex = parse(src)
        except ExprError as e:
            self.problem(path, f"bad expression {src!r}: {e}")
            return None
        for f in ex.calls:
            if self.funcs is not None and f not in self.funcs:
                self.problem(path, f"unknown evaluator or function {f!r} in {src!r}")
                return None
        wrong_count = next((f"{f}() {why}" for f, given in _calls(ex.tree) if f not in self.evaluators
                            and (why := _takes(*ARITY.get(f, (0, None)), given))), None)
        if wrong_count:
            self.problem(path, f"{wrong_count} in {src!r}")
            return None
        for n in ex.names:
            if scope.complete and n not in scope.names:
                self.problem(path, f"undefined variable {n!r} in {src!r}")
                return None
        for f, i, text in ex.literals:
            wrong = _literal(self, f, i, text) if f not in self.evaluators else None
            if wrong:
                self.problem(path, f"{wrong} in {src!r}")
                return None
        return ex

    # --------------------------------------------------------------------------- head of the file
    def _name(self) -> None:
        name = self.data.get("name", Path(self.file).stem)
        if not isinstance(name, (str, int, float)) or isinstance(name, bool):
            self.problem(("name",), "name must be a string")
            return
        self.name = str(name)

    def _clock(self) -> None:
        clock = self.data.get("clock", {}) or {}
        if not isinstance(clock, dict):
            self.problem(("clock",), "clock must be a map like {rate: 120}")
            return
        rate = clock.get("rate", 120)
        if finite_number(rate, positive=True, limit=1e6):
            self.rate, self.rate_given = float(rate), rate
        else:
            self.problem(("clock", "rate"), f"bad rate {rate!r}: the clock rate must be a positive number of Hz "
                                            "(below 1 MHz)")
        self._unknown_keys(("clock",), clock, CLOCK_KEYS)
        max_lag = clock.get("max_lag", 0.1)
        if max_lag is not None and not (finite_number(max_lag) and max_lag >= 0):
            self.problem(("clock", "max_lag"), f"bad max_lag {max_lag!r}: simulated seconds >= 0 that a "
                                               "clock-driven model may fall behind in a replay, or null to never "
                                               "wait for them")
        else:
            self.max_lag = None if max_lag is None else float(max_lag)
        batch = clock.get("batch", 32)
        if batch.__class__ is not int or not 1 <= batch <= 1000:
            self.problem(("clock", "batch"), f"bad batch {batch!r}: a whole number of ticks from 1 (one step "
                                             "message per tick) to 1000 that one step message of a replay may carry")
        else:
            self.batch = batch

    # ------------------------------------------------------------------------------------- models
    def _models(self) -> None:
        raw = self.data.get("models")
        if not isinstance(raw, dict) or not raw:
            self.problem(("models",), "a scene needs a 'models' map with at least one model")
            return
        # a model that has problems still has a name: references to it are not reported as unknown
        self.model_names = {n for n in raw if isinstance(n, str)}
        for mname, m in raw.items():
            self.where = path = ("models", mname)
            mark = self.found
            self._model_name(path, mname)
            spec = self._model(path, mname, m)
            if spec is not None and self.found == mark:
                self.models[mname] = spec

    def _named(self, path: Path_, what: str, name: Any) -> bool:
        """Whether a model's or an entity's name is one (its problem said otherwise)."""
        if not isinstance(name, str):
            self.problem(path, f"{what} name {name!r} must be a string (quote it)")
            return False
        try:
            check_name(what, name)
        except ValueError as e:
            self.problem(path, str(e))
            return False
        if name in CONTEXT_NAMES:
            self.problem(path, f"{what} name {name!r} is one a trigger's context binds: in a trigger it means that")
        return True

    def _model_name(self, path: Path_, mname: Any) -> None:
        if not self._named(path, "model", mname):
            return
        if mname.startswith("_"):
            self.problem(path, "model names must not start with '_' (reserved for the conductor)")
        elif mname in RESERVED_IDENTITIES:
            self.problem(path, f"a model may not be named {mname!r}: with access control on, it would share the "
                               f"{mname}'s certificate and rights (reserved: {', '.join(sorted(RESERVED_IDENTITIES))})")

    def _model(self, path: Path_, mname: Any, m: Any) -> ModelSpec | None:
        if not isinstance(m, dict):
            self.problem(path, "a model must be a map with at least 'kind'")
            return None
        mark = self.found
        self._unknown_keys(path, m, MODEL_KEYS)
        kind: Any = m.get("kind")
        if not isinstance(kind, str) or not kind:
            self.problem(path + ("kind",), "missing model kind (e.g. 'kind: physics' or 'kind: package.module:Class')")
        elif kind.startswith("fmu:"):
            kind = self._unit(path + ("kind",), kind[4:])
        step = m.get("step", "service")
        if not isinstance(step, str) or step not in STEP_MODES:
            self.problem(path + ("step",), f"unknown step mode {step!r}: use one of {', '.join(STEP_MODES)}")
            step = None
        timing = self._model_rate(path, m, step)
        args = m.get("args", {}) or {}
        if not isinstance(args, dict):
            self.problem(path + ("args",), "args must be a map of parameter names to values")
        reads = m.get("reads", []) or []
        if not isinstance(reads, list) or not all(isinstance(r, str) for r in reads):
            self.problem(path + ("reads",), "reads must be a list of 'entity.attribute' patterns ('*' allowed)")
        if self.found != mark or timing is None or step is None:
            return None
        return ModelSpec(mname, kind, step, timing[0], timing[1], dict(args), list(reads), self.lines.get(path))

    def _unit(self, path: Path_, unit: str) -> str:
        """``fmu:PATH`` with PATH made absolute (a relative one is relative to the scene file's folder)."""
        p = Path(unit)
        if not p.is_absolute() and self.file and not self.file.startswith("<"):
            p = Path(self.file).resolve().parent / p
        try:
            found = p.is_file()
        except (OSError, ValueError):  # a name too long for the file system, or with a NUL byte in it
            found = False
        if not found:
            self.problem(path, f"FMU unit {_short(unit, 200)} not found (looked for {_short(str(p), 300)})")
        return f"fmu:{p}"

    def _model_rate(self, path: Path_, m: dict[Any, Any], step: str | None) -> tuple[float, int] | None:
        """The model's rate and period in ticks; None if either is wrong or cannot be known (broken clock)."""
        if "rate" not in m and self.rate is None:
            return None
        mrate: Any = m.get("rate", self.rate)
        if not finite_number(mrate, positive=True, limit=1e6):
            self.problem(path + ("rate",), f"bad rate {mrate!r}: must be a positive number of Hz")
            return None
        rate = self.rate_given
        if step != "service" or rate is None:
            return float(mrate), 1
        if mrate > rate + 1e-9:
            self.problem(path + ("rate",), f"bad rate {mrate}: a service-stepped model cannot step faster than the "
                                           f"clock ({rate} Hz)")
            return None
        ratio = rate / mrate
        period = round(ratio)
        if abs(ratio - period) > 1e-6:
            self.problem(path + ("rate",), f"bad rate {mrate}: the clock rate {rate} Hz must be a whole multiple "
                                           "of it")
            return None
        return float(mrate), period

    def _main(self) -> None:
        raw = self.data.get("models")
        if self.model_names is None or not isinstance(raw, dict):
            return
        if "main" not in self.data:
            first = next(iter(raw))
            self.main = first if first in self.model_names else None  # a bad first name is reported already
            return
        main = self.data["main"]
        if not isinstance(main, str) or main not in self.model_names:
            self.problem(("main",), f"unknown model {main!r} (models: {', '.join(map(str, raw))})")
            return
        self.main = main

    # ----------------------------------------------------------------------------------- entities
    def _entities(self) -> None:
        raw = self.data.get("entities", {}) or {}
        if not isinstance(raw, dict):  # entity names and attributes stay unknown
            self.problem(("entities",), "entities must be a map of names to entity specs")
            return
        self.entity_names = {n for n in raw if isinstance(n, str)}
        for ename, e in raw.items():
            self.where = path = ("entities", ename)
            mark = self.found
            self._entity_name(path, ename)
            spec = self._entity(path, ename, e)
            if spec is not None and self.found == mark:
                self.entities[ename] = spec
        self.attrs_complete = not self.attrs_unreadable

    def _entity_name(self, path: Path_, ename: Any) -> None:
        if not self._named(path, "entity", ename):
            return
        if self.model_names is not None and ename in self.model_names:
            self.problem(path, f"entity {ename!r} has the name of a model; names must be distinct")
        elif ename in WORLD_NAMES:
            self.problem(path, f"entity name {ename!r} is one the models give part of the world (contact events "
                               "and collision values name the table and the robot so): call it something else")

    def _entity(self, path: Path_, ename: Any, e: Any) -> EntitySpec | None:
        if not isinstance(e, dict):
            self.problem(path, "an entity must be a map with 'shape' and 'pose'")
            self.attrs_unreadable = True
            return None
        mark = self.found
        self._unknown_keys(path, e, ENTITY_KEYS)
        problem = validate_shape(e.get("shape"))
        if problem:
            self.problem(path + ("shape",), problem)
        pose = e.get("pose", [0, 0, 0])
        if not valid_pose(pose):
            self.problem(path + ("pose",), pose_problem(pose))
        tags = e.get("tags", []) or []
        if not isinstance(tags, list) or not all(isinstance(t, str) for t in tags):
            self.problem(path + ("tags",), "tags must be a list of strings")
        _entity_extras(self, path, e)
        attrs = self._attributes(path, ename, e)
        if self.found != mark or attrs is None:
            return None
        pose = full_pose(pose)
        extra = {k: e[k] for k in ("color", "mass", "friction", "perceived_as") if k in e}
        return EntitySpec(ename, dict(e["shape"]), pose, list(tags), attrs, extra)

    def _attributes(self, path: Path_, ename: Any, e: dict[Any, Any]) -> dict[str, str] | None:
        """The entity's attribute -> initial owner map. Its pose is the main model's unless ``attributes`` gives it
        to another model, or the entity is ``virtual`` (no body: its pose is owned only if listed): a ball given
        a temperature kept no pose, so nothing moved it and ``inside`` read where the scene put it."""
        tags = e.get("tags")
        virtual = isinstance(tags, list) and "virtual" in tags
        if "attributes" not in e:
            self.entity_attrs[ename] = [] if virtual else ["pose"]
            if virtual:
                return {}
            return {"pose": self.main} if self.main is not None else None  # a bad main is reported already
        attrs = e["attributes"]
        if isinstance(attrs, dict) and "pose" not in attrs and not virtual:
            if self.main is None:
                return None
            attrs = {"pose": self.main, **attrs}
        if not isinstance(attrs, dict):
            self.problem(path + ("attributes",), "attributes must map attribute names to their initial owner model")
            self.attrs_unreadable = True
            return None
        self.entity_attrs[ename] = list(attrs)
        for a, owner in attrs.items():
            where = path + ("attributes", a)
            if not isinstance(a, str):
                self.problem(where, f"attribute name {a!r} must be a string")
            elif isinstance(owner, list):
                self.problem(where, f"duplicate owner: {a!r} lists {len(owner)} owners; exactly one model owns "
                                    "an attribute")
            elif not isinstance(owner, str) or (self.model_names is not None and owner not in self.model_names):
                self.problem(where, f"unknown model {owner!r} as owner of {ename}.{a}")
        return dict(attrs)

    # --------------------------------------------------------------------------------- evaluators
    def _evaluators(self) -> None:
        raw = self.data.get("evaluators", {}) or {}
        if not isinstance(raw, dict):
            self.problem(("evaluators",), "evaluators must be a map of names to {model, name}")
            return
        self.funcs = BUILTIN_NAMES | {n for n in raw if isinstance(n, str)}
        for ename, ev in raw.items():
            self.where = path = ("evaluators", ename)
            mark = self.found
            if not isinstance(ename, str) or not ename.isidentifier():
                self.problem(path, f"evaluator name {ename!r} must be a name usable in expressions")
            elif ename in BUILTIN_NAMES:
                self.problem(path, f"evaluator {ename!r} shadows a built-in function")
            spec = self._evaluator(path, ename, ev)
            if spec is not None and self.found == mark:
                self.evaluators[ename] = spec

    def _evaluator(self, path: Path_, ename: Any, ev: Any) -> EvaluatorSpec | None:
        if not isinstance(ev, dict) or "model" not in ev:
            self.problem(path, "an evaluator needs 'model' (and optionally 'name', 'args')")
            return None
        mark = self.found
        self._unknown_keys(path, ev, EVALUATOR_KEYS)
        model = ev["model"]
        if not isinstance(model, str) or (self.model_names is not None and model not in self.model_names):
            self.problem(path + ("model",), f"unknown model {model!r}")
        remote = ev.get("name", ename)  # without 'name', its own name (checked above)
        if "name" in ev and not _name(remote):
            self.problem(path + ("name",), "name must be the model's evaluator name (a string)")
        args = ev.get("args", []) or []
        if not isinstance(args, list):
            self.problem(path + ("args",), "args must be a list")
        if self.found != mark:
            return None
        return EvaluatorSpec(ename, model, remote, list(args))

    # ----------------------------------------------------------------------------------- triggers
    def _base_scope(self, context: Iterable[str]) -> _Scope:
        """Entity and model names (and ``context``): complete only if both sections are whole."""
        names = set(context) | (self.entity_names or set()) | (self.model_names or set())
        return _Scope(names, self.entity_names is not None and self.model_names is not None)

    def _triggers(self) -> None:
        raw = self.data.get("triggers", []) or []
        if not isinstance(raw, list):
            self.problem(("triggers",), "triggers must be a list")
            return
        seen: set[str] = set()
        for i, t in enumerate(raw):
            self.where = path = ("triggers", i)
            mark = self.found
            spec = self._trigger(path, i, t, seen)
            if spec is not None and self.found == mark:
                self.triggers.append(spec)

    def _trigger(self, path: Path_, i: int, t: Any, seen: set[str]) -> TriggerSpec | None:
        if not isinstance(t, dict):
            self.problem(path, "a trigger must be a map with 'on' and 'do'")
            return None
        mark = self.found
        self._unknown_keys(path, t, TRIGGER_KEYS)
        tname = t["name"] if "name" in t else _unnamed(i, self.data.get("triggers"))
        if not _name(tname):
            self.problem(path + ("name",), "a trigger's name must be a string")
        elif tname in seen:
            self.problem(path + ("name",), f"duplicate trigger name {tname!r}")
        else:
            seen.add(tname)
        params = self._on(path + ("on",), t.get("on"))
        lets, scope = self._lets(path, t, params)
        # 'when' may use the let variables (they are bound first)
        when = self._expr(path + ("when",), t["when"], scope) if "when" in t else None
        effects = self._effects(path + ("do",), t.get("do"), scope)
        if not isinstance(t.get("once", False), bool):
            self.problem(path + ("once",), f"once must be true or false, got {t['once']!r}")
        if self.found != mark or effects is None:
            return None
        return TriggerSpec(tname, dict(t["on"]), when, lets, effects, t.get("once", False),
                           self.lines.get(path))

    def _on(self, path: Path_, on: Any) -> list[str]:
        """Check a trigger's ``on``; the names a service call binds (its ``args``)."""
        if not isinstance(on, dict):
            self.problem(path, "'on' must be {action: NAME[, phase]}, {topic: model.output}, {event: model.event} "
                               "or {service: NAME[, args: [NAME, ...]]}")
            return []
        kinds = [k for k in ("action", "topic", "event", "service") if k in on]
        if len(kinds) != 1:
            self.problem(path, "'on' needs exactly one of action, topic, event, service")
            return []
        kind = kinds[0]
        if kind != "service":  # (a misspelt phase was dropped without a word: the trigger fired at the start)
            self._unknown_keys(path, on, {"action", "phase"} if kind == "action" else {kind})
        if kind == "action":
            if not isinstance(on["action"], str):
                self.problem(path + ("action",), "action must be an operation name")
            phase = on.get("phase", "start")
            if not isinstance(phase, str) or phase not in ("start", "end", "any"):
                self.problem(path + ("phase",), "phase must be start, end or any")
            return []
        if kind == "service":
            return self._on_service(path, on)
        ref = on[kind]
        if not isinstance(ref, str) or ref.count(".") != 1:
            self.problem(path + (kind,), f"{kind} must be 'model.name'")
            return []
        mref = ref.split(".")[0]
        if self.model_names is not None and mref not in self.model_names:
            self.problem(path + (kind,), f"unknown model {mref!r} in {kind} {ref!r}")
        return []

    def _on_service(self, path: Path_, on: dict[Any, Any]) -> list[str]:
        """``on: {service: NAME, args: [...]}``: fired by a client's call of ``conductor/trigger/NAME``."""
        extra = sorted(map(str, set(on) - {"service", "args"}))
        if extra:
            self.problem(path + (extra[0],), f"unknown key {extra[0]!r} (a service trigger has service and args)")
        try:
            check_name("service", on["service"])
        except ValueError as e:
            self.problem(path + ("service",), str(e))
        args = on.get("args", []) or []
        if not isinstance(args, list) or not all(isinstance(a, str) and a.isidentifier() for a in args):
            self.problem(path + ("args",), "args must be a list of names (the call's arguments, bound as variables)")
            return []
        clash = [a for a in args if a in self._base_scope(CONTEXT_NAMES).names]
        if clash:
            self.problem(path + ("args",), f"argument {clash[0]!r} shadows an entity, model or context name")
        return list(args)

    def _lets(self, path: Path_, t: dict[Any, Any], params: list[str]) -> tuple[list[tuple[str, Expr]], _Scope]:
        """The trigger's let variables, each bound after its expression is checked, and the scope they
        make for 'when' and 'do' (with a service call's ``params``)."""
        base = self._base_scope(CONTEXT_NAMES)
        scope = _Scope(set(base.names) | set(params), base.complete)
        raw = t.get("let", {}) or {}
        if not isinstance(raw, dict):
            self.problem(path + ("let",), "let must map variable names to expressions")
            scope.complete = False
            return [], scope
        lets: list[tuple[str, Expr]] = []
        for var, src in raw.items():
            where = path + ("let", var)
            if not isinstance(var, str) or not var.isidentifier():
                self.problem(where, f"variable {var!r} must be a name")
                continue
            if var in base.names:
                self.problem(where, f"variable {var!r} shadows an entity, model or context name")
                continue
            if var in params:  # (the caller's value was silently replaced by the let's)
                self.problem(where, f"variable {var!r} shadows the service's argument {var!r}")
                continue
            ex = self._expr(where, src, scope)
            scope.names.add(var)  # bound even if its expression is wrong: its uses are not errors too
            if ex is not None:
                lets.append((var, ex))
        return lets, scope

    def _effects(self, path: Path_, do: Any, scope: _Scope) -> list[Effect] | None:
        if not isinstance(do, list) or not do:
            self.problem(path, "'do' must be a non-empty list of effects (transfer, call or warn)")
            return None
        effects = []
        for j, eff in enumerate(do):
            effects.append(self._effect(path + (j,), eff, scope))
            bound = eff.get("call", {}).get("as") if isinstance(eff, dict) and isinstance(eff.get("call"), dict) \
                else None
            if isinstance(bound, str):
                scope.names.add(bound)  # a call's result, for the effects after it
        return [e for e in effects if e is not None]

    def _effect(self, path: Path_, eff: Any, scope: _Scope) -> Effect | None:
        if not isinstance(eff, dict) or len(eff) != 1:
            self.problem(path, "an effect is {transfer: {entity, attribute, to}}, {call: {model, service, args}} or "
                               "{warn: TEXT}")
            return None
        ekind, body = next(iter(eff.items()))
        path = path + (ekind,)
        if ekind == "transfer":
            fields = _transfer(self, path, body, scope)
        elif ekind == "call":
            fields = self._call(path, body, scope)
        elif ekind == "warn":  # the run is degraded, saying why: the twin's world disagrees with the robot's
            fields = {"text": body} if isinstance(body, str) and body.strip() else None
            if fields is None:
                self.problem(path, "warn takes the text the run's status says (a string)")
        else:
            self.problem(path, f"unknown effect {ekind!r}: use transfer, call or warn")
            return None
        if fields is None:
            return None
        return Effect(ekind, fields, fmt_path(path), self.lines.get(path))

    def _call(self, path: Path_, body: Any, scope: _Scope) -> dict[str, Any] | None:
        if not isinstance(body, dict) or "model" not in body or "service" not in body:
            self.problem(path, "call needs model and service (and optionally args, as)")
            return None
        mark = self.found
        extra = sorted(map(str, set(body) - {"model", "service", "args", "as"}))
        if extra:
            self.problem(path + (extra[0],), f"unknown key {extra[0]!r} (a call has model, service, args, as)")
        bind_as = body.get("as")
        if bind_as is not None and (not isinstance(bind_as, str) or not bind_as.isidentifier()):
            self.problem(path + ("as",), "as must be a variable name (the call's result, for the effects after it)")
        elif bind_as is not None and bind_as in scope.names:
            self.problem(path + ("as",), f"variable {bind_as!r} is bound already (entity, model, context or let name)")
        model = body["model"]
        if not isinstance(model, str) or (self.model_names is not None and model not in self.model_names):
            self.problem(path + ("model",), f"unknown model {model!r}")
        if not _name(body["service"]):
            self.problem(path + ("service",), "service must be the model's service name (a string)")
        args = body.get("args", []) or []
        if not isinstance(args, list):
            self.problem(path + ("args",), "args must be a list of expressions")
            return None
        exprs = [self._expr(path + ("args", k), a, scope) for k, a in enumerate(args)]
        if self.found != mark or None in exprs:
            return None
        return {"model": model, "service": str(body["service"]), "args": exprs, "as": bind_as}

    # ------------------------------------------------------------------------- semantics, robot
    def _semantics(self) -> None:
        raw = self.data.get("semantics", {}) or {}
        if not isinstance(raw, dict):
            self.problem(("semantics",), "semantics must map labels to expressions")
            return
        scope = self._base_scope(())
        for label, src in raw.items():
            self.where = path = ("semantics", label)
            if not isinstance(label, str):
                self.problem(path, f"label {label!r} must be a string (quote it)")
                continue
            ex = self._expr(path, src, scope)
            if ex is not None:
                self.semantics[label] = ex

    def _uncertain(self) -> None:
        broken = (self.entity_names or set()) - set(self.entities)
        self.uncertain, problems = check_uncertain(self.data.get("uncertain"), self.entities, broken)
        for path, problem in problems:
            self.problem(path, problem)

    def _robot(self) -> None:
        """The robot block against its description and URDF (``protocol.robot``); null keys take the defaults."""
        block = self.data.get("robot")
        if isinstance(block, dict):
            block = {k: v for k, v in block.items() if v is not None}
        problems = check_robot(block, Path(self.file).parent)
        for path, problem in problems:
            self.problem(path, problem)
        if not problems:
            self.robot = resolve_robot(block, Path(self.file).parent)


# ------------------------------------------------------------------------ against the agents
_TYPE_CHECKS: dict[str, Callable[[Any], bool]] = {
    "float": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "str": lambda v: isinstance(v, str),
    "bool": lambda v: isinstance(v, bool),
    "list": lambda v: isinstance(v, (list, tuple)),
    "map": lambda v: isinstance(v, dict),
    "any": lambda v: True,
}
"""Whether a scene value fits a declared parameter type (:class:`protocol.messages.ParamInfo` ``type``)."""


def _entity_extras(c: _Checker, path: Path_, e: dict[Any, Any]) -> None:
    """An entity's ``perceived_as``, ``mass``, ``friction`` and ``color``, checked."""
    if "perceived_as" in e and not _name(e["perceived_as"]):
        c.problem(path + ("perceived_as",), "perceived_as is the name the perception gives this entity")
    for k, what in (("mass", "kg; 0: a static body"), ("friction", "the friction coefficient")):
        if k in e and not (finite_number(e[k]) and e[k] >= 0):  # as a perception's (check_perception)
            c.problem(path + (k,), f"{k} must be a number >= 0 ({what}), got {_short(e[k])}")
    if "color" in e and not (isinstance(e["color"], list) and len(e["color"]) in (3, 4)
                             and all(finite_number(v) and 0 <= v <= 1 for v in e["color"])):
        c.problem(path + ("color",), f"color must be [r, g, b] or [r, g, b, a], each 0..1, got {_short(e['color'])}")


def _fits(value: Any, type_word: Any) -> bool:
    # null passes for every type, as the agent's runtime lets it through (Param.coerce); an unknown
    # type word cannot be judged here
    check = _TYPE_CHECKS.get(type_word) if isinstance(type_word, str) else None
    return value is None or check is None or check(value)


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


PLURAL = {"entity": "entities", "model": "models", "attribute": "attributes", "tag": "tags", "body": "bodies"}


def _attribute(c: _Checker, path: Path_, attr: str, scope: _Scope) -> Expr | None:
    """A transfer's attribute: an attribute some entity has, or an expression naming one."""
    known = {a for attrs in c.entity_attrs.values() for a in attrs}
    if attr in known:
        return parse(repr(attr))
    if not c.attrs_complete:  # it may be the attribute of an entity that could not be read
        return None
    if isinstance(attr, str) and attr.isidentifier() and scope.complete and attr not in scope.names:
        near = difflib.get_close_matches(attr, sorted(known), n=1)  # (not "undefined variable 'colour'")
        c.problem(path, f"unknown attribute {attr!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                  + f": no entity has it (the scene's attributes are {_listed(sorted(known))})")
        return None
    ex = c._expr(path, attr, scope)
    if ex is not None and ex.tree[0] == "lit" and ex.tree[1] not in known:  # (a quoted name: 'pose' is pose)
        near = difflib.get_close_matches(str(ex.tree[1]), sorted(known), n=1)
        c.problem(path, f"unknown attribute {ex.tree[1]!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                  + f": no entity has it (the scene's attributes are {_listed(sorted(known))})")
        return None
    return ex  # (an expression: which attribute it names, only the run knows)


def _literal(c: _Checker, function: str, position: int, text: str) -> str | None:
    """What is wrong with a name written as a string where a built-in takes an entity, model, attribute or tag
    (``owner('bal', 'pose')`` read null, and ``== 'in_hand'`` made it a silent false), or None (also while what
    it would be checked against is not whole)."""
    kinds = ARG_KINDS.get(function, ())
    kind = kinds[position] if position < len(kinds) else None
    known: Iterable[Any] | None = None
    if kind == "entity":
        known = c.entity_names
    elif kind == "model":
        known = c.model_names
    elif kind == "attribute" and c.attrs_complete:
        known = {a for attrs in c.entity_attrs.values() for a in attrs}
    elif kind == "tag" and c.entity_names is not None and set(c.entities) == c.entity_names:
        known = {t for e in c.entities.values() for t in e.tags}
    if kind is None or known is None:
        return None
    return _unknown_name(kind, text, {str(k) for k in known}, set(c.entities), f" in {function}()")


def _transfer(c: _Checker, path: Path_, body: Any, scope: _Scope) -> dict[str, Any] | None:
    """A transfer effect's fields, each checked (None, and the problems recorded, otherwise)."""
    if not isinstance(body, dict) or set(body) - {"entity", "attribute", "to"} or not {"entity", "to"} <= set(body):
        c.problem(path, "transfer needs entity, to (and attribute, default pose)")
        return None
    mark = c.found
    to, attr, ent = body["to"], body.get("attribute", "pose"), body["entity"]
    for key, v in (("to", to), ("attribute", attr), ("entity", ent)):
        if not _name(v):
            c.problem(path + (key,), f"{key} must be a name or an expression (a string)")
    if c.found != mark:
        return None
    models, entities = c.model_names, c.entity_names or set()
    if models is not None and scope.complete and to not in models and to not in scope.names - entities - models:
        c.problem(path + ("to",), f"unknown model {to!r}")
    named = attr[1:-1] if len(attr) > 2 and attr[0] == attr[-1] and attr[0] in "'\"" else \
        attr if attr not in scope.names else None  # (a quoted name is the name)
    if ent in c.entity_attrs and named is not None and named.isidentifier() and named not in c.entity_attrs[ent]:
        c.problem(path + ("attribute",), f"unknown attribute {named!r} of entity {ent!r} "
                                         f"(has: {', '.join(map(str, c.entity_attrs[ent]))})")
        return None
    fields = {"entity": c._expr(path + ("entity",), ent, scope),
              "attribute": _attribute(c, path + ("attribute",), attr, scope),
              "to": c._expr(path + ("to",), to, scope)}
    if c.found != mark or None in fields.values():
        return None
    entity = fields["entity"]
    assert entity is not None
    wrong = _not_an_entity(entity, c.entity_names, models or set())
    if wrong:  # (a model's name, a misspelt quoted name: no responsibility to move, found only at run time)
        c.problem(path + ("entity",), wrong)
        return None
    return fields


def _unnamed(i: int, triggers: Any) -> str:
    """The name of the ``i``-th trigger when it has none: ``trigger{i}``, unless another trigger is named that (the
    duplicate was said at a key its author never wrote)."""
    taken = {t.get("name") for t in triggers if isinstance(t, dict) and isinstance(t.get("name"), str)
             } if isinstance(triggers, list) else set()
    name, k = f"trigger{i}", 1
    while name in taken:
        name, k = f"trigger{i}_{k}", k + 1
    return name


def _not_an_entity(ex: Expr, entities: set[str] | None, models: set[str]) -> str | None:
    """What is wrong with a transfer's ``entity`` written as a name or a quoted name that is not an entity (None: it
    is one, or an expression whose value only the run knows, or the entities are not whole)."""
    node = ex.tree
    if entities is None or node[0] not in ("name", "lit") or not isinstance(node[1], str):
        return None
    text = node[1]
    if node[0] == "name" and (text in entities or text not in models):
        return None  # (an entity, or a variable: a let, a service argument, a call's result)
    if text in models and text not in entities:
        return f"{text!r} is a model, not an entity: transfer moves an entity's attribute to a model"
    return _unknown_name("entity", text, set(entities), set(entities))


def _listed(names: Iterable[Any], none: str = "none") -> str:
    return ", ".join(map(str, names)) or none


def launch_problems(scene: Scene) -> list[Problem]:
    """What keeps the twin from starting ``scene``'s agents itself (``twin run``, ``twin serve``; ``twin check``
    and ``twin submit`` say it before anything starts): a kind without ``:`` that is not one of the agents' built-in
    kinds (:data:`protocol.messages.BUILTIN_KINDS`), which ``twin agent KIND`` would refuse once started. A scene
    whose agents are started by hand may name kinds of its own: their agents say what they are at registration
    (:func:`check_against_agents`)."""
    out = []
    for name, spec in scene.models.items():
        if ":" in spec.kind or spec.kind in BUILTIN_KINDS:
            continue
        near = difflib.get_close_matches(spec.kind, sorted(BUILTIN_KINDS), n=1)
        out.append(scene.problem(("models", name, "kind"), f"unknown model kind {spec.kind!r}"
                                 + (f" (did you mean {near[0]!r}?)" if near else "")
                                 + f": twin agent knows {', '.join(sorted(BUILTIN_KINDS))}, 'package.module:Class' "
                                 "and 'fmu:PATH'"))
    return out


def check_launchable(scene: Scene) -> Scene:
    """``scene``, or :class:`SceneError` with every one of its :func:`launch_problems`."""
    problems = launch_problems(scene)
    if problems:
        raise SceneError.of(problems)
    return scene


def check_against_agents(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    """Every problem of ``scene`` against what its agents declared at registration, in scene order.

    ``agents`` maps each model name to its registration (:class:`protocol.messages.Register`). Checked:
    every model has an agent; a scene kind without ``:`` names the kind the agent reports; each scene arg
    is a declared parameter of a fitting type (float takes ints, map is a dict; null fits any) and every
    required parameter is given; the step mode is one the agent supports; every initial owner can own its
    attribute and is not an observer; every evaluator and every ``call`` effect's service is one its model
    declares, and so is every event and output (``topic``) a trigger listens to. The checks of a model whose
    agent is missing or of another kind are skipped. No problems: an empty list; the conductor raises
    ``SceneError.of(problems)`` otherwise.
    """
    problems: list[Problem] = []
    fitting: dict[str, Mapping[str, Any]] = {}
    for name, spec in scene.models.items():
        desc = agents.get(name)
        if desc is None:
            problems.append(scene.problem(("models", name), f"no agent registered as {name!r} (start one with "
                                                             f"'twin agent {spec.kind} --name {name}')"))
        elif ":" not in spec.kind and desc.get("kind") != spec.kind:
            problems.append(scene.problem(("models", name, "kind"), f"the scene asks for kind {spec.kind!r}, "
                                                                     f"the agent is {desc.get('kind')!r}"))
        else:
            fitting[name] = desc
            problems += _params_fit(scene, spec, desc)
            problems += _step_fits(scene, spec, desc)
    problems += _owners_fit(scene, fitting)
    problems += _evaluators_fit(scene, fitting)
    problems += _services_fit(scene, fitting)
    problems += _listens_fit(scene, fitting)
    problems += _counted_fit(scene, fitting)
    problems += _evaluator_names_fit(scene, fitting)
    problems += _arity_fit(scene, fitting)
    problems += _transfers_fit(scene, fitting)
    return problems


def _params_fit(scene: Scene, spec: ModelSpec, desc: Mapping[str, Any]) -> list[Problem]:
    declared: Mapping[str, Any] = desc.get("params") or {}
    out = []
    for arg, value in spec.args.items():
        path = ("models", spec.name, "args", arg)
        if arg not in declared:
            out.append(scene.problem(path, f"unknown parameter {arg!r} of {spec.kind} "
                                           f"(it declares: {_listed(declared)})"))
        elif not _fits(value, declared[arg].get("type", "any")):
            out.append(scene.problem(path, f"parameter {arg!r} of {spec.kind} must be {declared[arg].get('type')}, "
                                           f"got {_short(value)}"))
        elif value is not None and declared[arg].get("choices") and value not in declared[arg]["choices"]:
            out.append(scene.problem(path, f"parameter {arg!r} of {spec.kind} must be one of "
                                           f"{_listed(declared[arg]['choices'])}, got {_short(value)}"))
        elif value is not None and declared[arg].get("positive") and not finite_number(value, positive=True):
            out.append(scene.problem(path, f"parameter {arg!r} of {spec.kind} must be a finite number above 0, "
                                           f"got {_short(value)}"))
    out += _periods_fit(scene, spec, declared)
    for arg, info in declared.items():
        if info.get("required") and arg not in spec.args:
            doc = info.get("doc") or ""
            out.append(scene.problem(("models", spec.name, "args"), f"missing required parameter {arg!r} of "
                                                                    f"{spec.kind}" + (f": {doc}" if doc else "")))
    return out


def _periods_fit(scene: Scene, spec: ModelSpec, declared: Mapping[str, Any]) -> list[Problem]:
    """A time step the model declares ``within_period`` (an engine's substep) that is longer than the model's step
    period: some of its steps would move nothing, and its world's time would fall behind the clock."""
    out = []
    period = 1.0 / spec.rate if spec.rate > 0 else None
    for arg, info in declared.items():
        given = arg in spec.args
        value = spec.args[arg] if given else info.get("default")
        if (period is None or not info.get("within_period") or not finite_number(value, positive=True)
                or value <= period * (1 + 1e-9)):
            continue
        what = f"parameter {arg!r} of {spec.kind}" if given else f"the default {arg!r} of {spec.kind}"
        out.append(scene.problem(("models", spec.name, "args", arg) if given else ("models", spec.name, "rate"),
                                 f"{what} is {value:g} s, longer than the model's step period {period:g} s "
                                 f"(rate {spec.rate:g} Hz): give {arg} at most {period:g}, or a lower rate"))
    return out


def _step_fits(scene: Scene, spec: ModelSpec, desc: Mapping[str, Any]) -> list[Problem]:
    modes = list(desc.get("step_modes") or [])
    if spec.step in modes:
        return []
    return [scene.problem(("models", spec.name, "step"), f"{spec.kind} cannot step in mode {spec.step!r} "
                                                         f"(it supports: {_listed(modes)})")]


def _owners_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    out = []
    for (e, a), m in scene.initial_owners().items():
        desc = agents.get(m)
        if desc is None:
            continue
        path = ("entities", e, "attributes", a)
        can_own = list(desc.get("attributes") or [])
        if desc.get("role") == "observer":
            out.append(scene.problem(path, f"model {m!r} ({desc.get('kind')}) is an observer and cannot own "
                                           f"{a!r}: an observer owns nothing"))
        elif a not in can_own:
            out.append(scene.problem(path, f"model {m!r} ({desc.get('kind')}) cannot own {a!r} "
                                           f"(it can own: {_listed(can_own, 'nothing')})"))
    return out


def _evaluators_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    out = []
    for ev in scene.evaluators.values():
        desc = agents.get(ev.model)
        has = list((desc or {}).get("evaluators") or [])
        if desc is not None and ev.remote not in has:
            out.append(scene.problem(("evaluators", ev.name), f"unknown evaluator {ev.remote!r} of model "
                                                              f"{ev.model!r} (it has: {_listed(has)})"))
    return out


def _services_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    out = []
    for i, trig in enumerate(scene.triggers):
        for j, eff in enumerate(trig.do):
            if eff.kind != "call":
                continue
            model, service = eff.fields["model"], eff.fields["service"]
            desc = agents.get(model)
            has = list((desc or {}).get("services") or [])
            if desc is not None and service not in has:
                out.append(scene.problem(("triggers", i, "do", j, "call", "service"),
                                         f"unknown service {service!r} of model {model!r} (it has: {_listed(has)})"))
    return out


def _listens_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    """A trigger ``on: {event: MODEL.NAME}`` or ``{topic: MODEL.NAME}`` names an event or output its model declares
    (a misspelt one would never fire, and the run would end complete without it)."""
    out = []
    for i, trig in enumerate(scene.triggers):
        for kind, what in (("event", "events"), ("topic", "outputs")):
            ref = trig.on.get(kind)
            if not isinstance(ref, str) or ref.count(".") != 1:
                continue
            model, name = ref.split(".")
            desc = agents.get(model)
            has = [str(n) for n in (desc or {}).get(what) or []]
            if desc is not None and name not in has:
                near = difflib.get_close_matches(name, has, n=1)
                what_ = "event" if kind == "event" else "output"
                out.append(scene.problem(("triggers", i, "on", kind), f"model {model!r} ({desc.get('kind')}) declares "
                                         f"no {what_} {name!r}"
                                         + (f" (did you mean {near[0]!r}?)" if near else "")
                                         + f": it has {_listed(has)}; this trigger would never fire"))
    return out


def _counted_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    """``event_count(MODEL, 'NAME')`` and ``output(MODEL, 'NAME')`` in every expression of the scene (semantics, the
    triggers' conditions, ``let`` and effects) name an event or output that model declares (a misspelt one counts 0,
    or reads null, for ever)."""
    out = []
    for path, ex in _expr_sites(scene):
        for function, model, name in _model_calls(ex.tree):
            what = "events" if function == "event_count" else "outputs"
            desc = agents.get(model)
            has = [str(n) for n in (desc or {}).get(what) or []]
            if desc is not None and name not in has:
                near = difflib.get_close_matches(name, has, n=1)
                out.append(_at(scene, path, f"model {model!r} ({desc.get('kind')}) declares no {what[:-1]} "
                                            f"{name!r} in {ex.source!r}"
                                               + (f" (did you mean {near[0]!r}?)" if near else "")
                                               + f": it has {_listed(has)}"))
                break
    return out


def _transfers_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    """A transfer to a model named as it is written (``to: in_hand``) moves an attribute that model declares it
    can own: one to an observer, or of an attribute it cannot own, was refused only when the trigger fired (the
    run degraded, the trigger's effect lost)."""
    out = []
    for trig in scene.triggers:
        for eff in trig.do:
            if eff.kind != "transfer":
                continue
            to, attr = eff.fields["to"].tree, eff.fields["attribute"].tree
            model = to[1] if to[0] in ("name", "lit") and to[1] in scene.models else None
            desc = agents.get(model) if model is not None else None
            if desc is None or attr[0] != "lit":
                continue
            can_own = [str(a) for a in desc.get("attributes") or []]
            if desc.get("role") == "observer" or attr[1] not in can_own:
                why = ("is an observer and owns nothing" if desc.get("role") == "observer" else
                       f"cannot own {attr[1]!r} (it can own: {_listed(can_own, 'nothing')})")
                out.append(Problem(scene.file, eff.line, f"{eff.path}.to", f"trigger {trig.name}: model {model!r} "
                                   f"({desc.get('kind')}) {why}: this transfer would be refused when it fires"))
    return out


def _evaluator_names_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    """A string the scene gives an evaluator where its agent declares it takes a name (``evaluator_args``: an
    entity, a tag, a body) is one of the scene's (``closest('graspble')`` found nothing for the whole run, and the
    run ended complete). As for the built-ins, a tag none carries is a problem only when it is close to one that
    some entity carries, or is an entity's name."""
    known = _scene_names(scene)
    out: list[Problem] = []
    for ev in scene.evaluators.values():  # the arguments the evaluators block fixes come first
        for j, arg in enumerate(ev.args):
            wrong = _named(known, _arg_kind(agents, ev, j), arg) if isinstance(arg, str) else None
            if wrong:
                out.append(scene.problem(("evaluators", ev.name, "args", j), f"{ev.name}(): {wrong}"))
    for where, ex in _expr_sites(scene):
        for function, i, text in ex.literals:
            called = scene.evaluators.get(function)
            wrong = _named(known, _arg_kind(agents, called, len(called.args) + i), text) if called else None
            if wrong:
                out.append(_at(scene, where, f"in {ex.source!r}: {wrong}"))
    return out


def _expr_sites(scene: Scene) -> list[tuple[Any, Expr]]:
    """Every expression of the scene with where it is written: a scene path, or (effect, field) for an effect's."""
    sites: list[tuple[Any, Expr]] = [(("semantics", label), ex) for label, ex in scene.semantics.items()]
    for i, t in enumerate(scene.triggers):
        sites += [(("triggers", i, "let", var), ex) for var, ex in t.let]
        sites += [(("triggers", i, "when"), t.when)] if t.when is not None else []
        sites += [((eff, f), ex) for eff in t.do for f, v in eff.fields.items()
                  for ex in (v if isinstance(v, list) else [v]) if isinstance(ex, Expr)]
    return sites


def _at(scene: Scene, where: Any, msg: str) -> Problem:
    if isinstance(where[0], Effect):
        eff = where[0]
        return Problem(scene.file, eff.line, f"{eff.path}.{where[1]}", msg)
    return scene.problem(where, msg)


def _arity_fit(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> list[Problem]:
    """Every evaluator call of the scene's expressions (with the arguments its ``evaluators:`` entry fixes) and every
    ``call`` effect gives as many arguments as its agent's method takes (``arity`` of the registration): a wrong
    count failed only when the trigger fired, or left a predicate unevaluated at the end of the run."""
    def wrong(kind: str, model: str, name: str, given: int) -> str | None:
        span = (((agents.get(model) or {}).get("arity") or {}).get(kind) or {}).get(name)
        return _takes(span[0], span[1], given) if isinstance(span, list) and len(span) == 2 else None

    out: list[Problem] = []
    for where, ex in _expr_sites(scene):
        for function, given in _calls(ex.tree):
            ev = scene.evaluators.get(function)
            why = wrong("eval", ev.model, ev.remote, len(ev.args) + given) if ev else None
            if why:
                fixed = f" (the evaluators block gives {len(ev.args)} of them)" if ev and ev.args else ""
                out.append(_at(scene, where, f"in {ex.source!r}: {function}() {why}{fixed}"))
    for i, trig in enumerate(scene.triggers):
        for j, eff in enumerate(trig.do):
            if eff.kind == "call":
                why = wrong("call", eff.fields["model"], eff.fields["service"], len(eff.fields.get("args") or []))
                if why:
                    out.append(scene.problem(("triggers", i, "do", j, "call", "args"),
                                             f"service {eff.fields['service']!r} of model {eff.fields['model']!r} "
                                             f"{why}"))
    return out


def _takes(least: int, most: int | None, given: int) -> str | None:
    """What is wrong with ``given`` arguments to a function that takes ``least`` to ``most`` (None: any number)."""
    if given >= least and (most is None or given <= most):
        return None
    takes = f"{least}" if least == most else f"{least} or more" if most is None else f"{least} to {most}"
    return f"takes {takes} argument{'' if takes == '1' else 's'}, {given} given"


def _calls(node: Any) -> Iterable[tuple[str, int]]:
    """(function, how many arguments) of every call in an expression's tree."""
    if not isinstance(node, tuple):
        return
    if node[0] == "call" and isinstance(node[1], str) and isinstance(node[2], list):
        yield node[1], len(node[2])
    for part in node[1:]:
        for item in part if isinstance(part, list) else [part]:
            if isinstance(item, tuple):
                yield from _calls(item)


def _arg_kind(agents: Mapping[str, Mapping[str, Any]], ev: EvaluatorSpec, position: int) -> str | None:
    kinds = ((agents.get(ev.model) or {}).get("evaluator_args") or {}).get(ev.remote) or []
    kind = kinds[position] if isinstance(kinds, list) and position < len(kinds) else None
    return kind if isinstance(kind, str) else None


def _scene_names(scene: Scene) -> dict[str, set[str]]:
    """The names an evaluator's argument may take, by :data:`agents.model.NAME_KINDS` kind."""
    entities = set(scene.entities)
    links: set[str] = set()
    if scene.robot is not None:
        try:
            links = set(read_urdf(scene.robot.urdf_file).links)
        except (ValueError, OSError):  # (the robot block's own check says what is wrong with its URDF)
            links = set()
    return {"entity": entities, "tag": {t for e in scene.entities.values() for t in e.tags},
            "body": entities | links | {"hand", "tip"} if links else set()}


def _named(known: Mapping[str, set[str]], kind: str | None, text: str) -> str | None:
    """What is wrong with ``text`` as a name of ``kind``, or None (also for a kind it cannot check)."""
    names = known.get(kind or "")
    return _unknown_name(kind, text, names, known["entity"]) if kind is not None and names else None


def _unknown_name(kind: str, text: str, names: set[str], entities: set[str], where: str = "") -> str | None:
    """What is wrong with ``text`` written where a name of ``kind`` is taken (one of ``names``), or None. A tag none
    carries is a fair question ("anything fragile?"), unless it is close to one some entity carries (a typo) or is
    an entity's name; the scene's names are listed (at most 12)."""
    if text in names:
        return None
    near = difflib.get_close_matches(text, sorted(names), n=1)
    if kind == "tag" and not near and text not in entities:
        return None
    listed = sorted(names) if len(names) <= 12 else [*sorted(names)[:12], "..."]
    return (f"unknown {kind} {text!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
            + (" (an entity's name, not a tag)" if kind == "tag" and text in entities else "")
            + f"{where}: the scene's {PLURAL.get(kind, kind + 's')} are {_listed(listed)}")


def _model_calls(node: Any) -> Iterable[tuple[str, str, str]]:
    """(function, model, name) of every ``event_count`` / ``output`` call under ``node`` whose model is written as
    a name or a string and whose event or output as a string."""
    if not isinstance(node, tuple):
        return
    if node[0] == "call" and node[1] in ("event_count", "output") and len(node[2]) >= 2:
        first, second = node[2][0], node[2][1]
        model = first[1] if first[0] in ("lit", "name") and isinstance(first[1], str) else None
        if model is not None and second[0] == "lit" and isinstance(second[1], str):
            yield node[1], model, second[1]
    for part in node[1:]:
        if isinstance(part, tuple):
            yield from _model_calls(part)
        elif isinstance(part, list):
            for item in part:
                yield from _model_calls(item)


def reads_of(scene: Scene, agents: Mapping[str, Mapping[str, Any]]) -> dict[str, list[str]]:
    """What each model reads of others' values each step: its scene ``reads:`` then what its agent
    declares (``reads`` of its registration), in that order, each pattern once."""
    out = {}
    for name, spec in scene.models.items():
        declared = (agents.get(name) or {}).get("reads") or []
        out[name] = list(dict.fromkeys([*spec.reads, *(str(r) for r in declared)]))
    return out
