"""Scene files: loading and validation.

A scene is YAML::

    name: ball_drop
    clock: {rate: 120, max_lag: 0.1, batch: 32}
                                       # conductor ticks per simulated second; how far (simulated s)
                                       # a clock-driven model may fall behind in a replay; at most how
                                       # many ticks one step message may carry when nothing can intervene
    main: physics                      # the main model: owns every pose at start, takes back orphans
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

Every problem is a :class:`~protocol.errors.SceneError` naming the file, the line and the key path.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from protocol.errors import SceneError
from protocol.geometry import finite_number, valid_pose, validate_shape
from protocol.keys import check_name
from protocol.messages import STEP_MODES

from .expr import Expr, ExprError, parse
from .load import Lines, fmt_path, load_yaml
from .spec import Effect, EntitySpec, EvaluatorSpec, ModelSpec, Scene, TriggerSpec

# functions the conductor itself provides to expressions (see conductor.core.Builtins)
BUILTIN_FUNCTIONS = {
    "owner", "owned", "at", "pose", "position", "distance", "inside", "output", "event_count", "tagged",
    "abs", "min", "max", "len", "norm", "str", "float", "int", "bool", "any", "all",
}
CONTEXT_NAMES = {"action", "event", "value", "tick", "t", "trigger"}
TOP_KEYS = {"name", "description", "clock", "main", "models", "entities", "evaluators", "triggers",
            "semantics", "robot", "recording"}
MODEL_KEYS = {"kind", "step", "rate", "args", "reads", "doc"}
ENTITY_KEYS = {"shape", "pose", "tags", "attributes", "color", "doc", "mass", "friction"}
TRIGGER_KEYS = {"name", "on", "when", "let", "do", "once", "doc"}


def load_scene(path: str | Path) -> Scene:
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


def _name(v: Any) -> bool:
    return isinstance(v, str) and bool(v)


def parse_scene(text: str, file: str = "<scene>") -> Scene:
    """Parse and validate a scene; every problem is a :class:`SceneError` naming file, line and key."""
    data, lines = load_yaml(text, file)
    where: list[tuple] = [()]  # the part being checked, for errors nobody anticipated
    try:
        return _parse(data, lines, file, where)
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, IndexError, OverflowError, RecursionError) as e:
        raise SceneError(file, lines.get(where[0]), fmt_path(where[0]),
                         f"invalid value here ({type(e).__name__}: {e})") from None


def _parse(data: Any, lines: Lines, file: str, where: list) -> Scene:
    def err(path: tuple, problem: str) -> SceneError:
        return SceneError(file, lines.get(path), fmt_path(path), problem)

    if not isinstance(data, dict):
        raise err((), "a scene must be a map with 'models' and 'entities'")
    for k in data:
        if k not in TOP_KEYS:
            raise err((k,), f"unknown key {k!r} (allowed: {', '.join(sorted(TOP_KEYS))})")
    where[0] = ("name",)
    name = data.get("name", Path(file).stem)
    if not isinstance(name, (str, int, float)) or isinstance(name, bool):
        raise err(("name",), "name must be a string")
    name = str(name)
    clock = data.get("clock", {}) or {}
    if not isinstance(clock, dict):
        raise err(("clock",), "clock must be a map like {rate: 120}")
    rate = clock.get("rate", 120)
    if not finite_number(rate, positive=True, limit=1e6):
        raise err(("clock", "rate"), f"bad rate {rate!r}: the clock rate must be a positive number of Hz (at most 1 MHz)")
    for k in clock:
        if k not in ("rate", "max_lag", "batch"):
            raise err(("clock", k), f"unknown key {k!r} (allowed: batch, max_lag, rate)")
    max_lag = clock.get("max_lag", 0.1)
    if max_lag is not None and not (finite_number(max_lag) and max_lag >= 0):
        raise err(("clock", "max_lag"), f"bad max_lag {max_lag!r}: simulated seconds >= 0 that a clock-driven "
                                        "model may fall behind in a replay, or null to never wait for them")
    batch = clock.get("batch", 32)
    if batch.__class__ is not int or not 1 <= batch <= 1000:
        raise err(("clock", "batch"), f"bad batch {batch!r}: a whole number of ticks from 1 (one step message per "
                                      "tick) to 1000 that one step message of a replay may carry")

    models_raw = data.get("models")
    if not isinstance(models_raw, dict) or not models_raw:
        raise err(("models",), "a scene needs a 'models' map with at least one model")
    models: dict[str, ModelSpec] = {}
    for mname, m in models_raw.items():
        p = where[0] = ("models", mname)
        if not isinstance(mname, str):
            raise err(p, f"model name {mname!r} must be a string (quote it)")
        try:
            check_name("model", mname)
        except ValueError as e:
            raise err(p, str(e)) from None
        if mname.startswith("_"):
            raise err(p, "model names must not start with '_' (reserved for the conductor)")
        if not isinstance(m, dict):
            raise err(p, "a model must be a map with at least 'kind'")
        for k in m:
            if k not in MODEL_KEYS:
                raise err(p + (k,), f"unknown key {k!r} (allowed: {', '.join(sorted(MODEL_KEYS))})")
        kind = m.get("kind")
        if not isinstance(kind, str) or not kind:
            raise err(p + ("kind",), "missing model kind (e.g. 'kind: physics' or 'kind: package.module:Class')")
        step = m.get("step", "service")
        if not isinstance(step, str) or step not in STEP_MODES:
            raise err(p + ("step",), f"unknown step mode {step!r}: use one of {', '.join(STEP_MODES)}")
        mrate = m.get("rate", rate)
        if not finite_number(mrate, positive=True, limit=1e6):
            raise err(p + ("rate",), f"bad rate {mrate!r}: must be a positive number of Hz")
        period = 1
        if step == "service":
            if mrate > rate + 1e-9:
                raise err(p + ("rate",), f"bad rate {mrate}: a service-stepped model cannot step faster than the clock ({rate} Hz)")
            ratio = rate / mrate
            period = round(ratio)
            if abs(ratio - period) > 1e-6:
                raise err(p + ("rate",), f"bad rate {mrate}: the clock rate {rate} Hz must be a whole multiple of it")
        args = m.get("args", {}) or {}
        if not isinstance(args, dict):
            raise err(p + ("args",), "args must be a map of parameter names to values")
        reads = m.get("reads", []) or []
        if not isinstance(reads, list) or not all(isinstance(r, str) for r in reads):
            raise err(p + ("reads",), "reads must be a list of 'entity.attribute' patterns ('*' allowed)")
        models[mname] = ModelSpec(mname, kind, step, float(mrate), period, args, reads, lines.get(p))

    where[0] = ("main",)
    main = data.get("main", next(iter(models)))
    if not isinstance(main, str) or main not in models:
        raise err(("main",), f"unknown model {main!r} (models: {', '.join(models)})")

    entities: dict[str, EntitySpec] = {}
    ents_raw = data.get("entities", {}) or {}
    if not isinstance(ents_raw, dict):
        raise err(("entities",), "entities must be a map of names to entity specs")
    for ename, e in ents_raw.items():
        p = where[0] = ("entities", ename)
        if not isinstance(ename, str):
            raise err(p, f"entity name {ename!r} must be a string (quote it)")
        try:
            check_name("entity", ename)
        except ValueError as ex:
            raise err(p, str(ex)) from None
        if ename in models:
            raise err(p, f"entity {ename!r} has the name of a model; names must be distinct")
        if not isinstance(e, dict):
            raise err(p, "an entity must be a map with 'shape' and 'pose'")
        for k in e:
            if k not in ENTITY_KEYS:
                raise err(p + (k,), f"unknown key {k!r} (allowed: {', '.join(sorted(ENTITY_KEYS))})")
        problem = validate_shape(e.get("shape"))
        if problem:
            raise err(p + ("shape",), problem)
        pose = e.get("pose", [0, 0, 0])
        if not valid_pose(pose):
            raise err(p + ("pose",), "pose must be [x, y, z] or [x, y, z, qx, qy, qz, qw] (numbers)")
        pose = [float(v) for v in pose] + ([0.0, 0.0, 0.0, 1.0] if len(pose) == 3 else [])
        tags = e.get("tags", []) or []
        if not isinstance(tags, list) or not all(isinstance(t, str) for t in tags):
            raise err(p + ("tags",), "tags must be a list of strings")
        attrs = e.get("attributes", {"pose": main})
        if not isinstance(attrs, dict):
            raise err(p + ("attributes",), "attributes must map attribute names to their initial owner model")
        for a, owner in attrs.items():
            if not isinstance(a, str):
                raise err(p + ("attributes", a), f"attribute name {a!r} must be a string")
            if isinstance(owner, list):
                raise err(p + ("attributes", a), f"duplicate owner: {a!r} lists {len(owner)} owners; exactly one model owns an attribute")
            if not isinstance(owner, str) or owner not in models:
                raise err(p + ("attributes", a), f"unknown model {owner!r} as owner of {ename}.{a}")
        extra = {k: e[k] for k in ("color", "mass", "friction") if k in e}
        entities[ename] = EntitySpec(ename, e["shape"], pose, tags, dict(attrs), extra)

    evaluators: dict[str, EvaluatorSpec] = {}
    evs_raw = data.get("evaluators", {}) or {}
    if not isinstance(evs_raw, dict):
        raise err(("evaluators",), "evaluators must be a map of names to {model, name}")
    for ename, ev in evs_raw.items():
        p = where[0] = ("evaluators", ename)
        if not isinstance(ename, str) or not ename.isidentifier():
            raise err(p, f"evaluator name {ename!r} must be a name usable in expressions")
        if ename in BUILTIN_FUNCTIONS:
            raise err(p, f"evaluator {ename!r} shadows a built-in function")
        if not isinstance(ev, dict) or "model" not in ev:
            raise err(p, "an evaluator needs 'model' (and optionally 'name', 'args')")
        if not isinstance(ev["model"], str) or ev["model"] not in models:
            raise err(p + ("model",), f"unknown model {ev['model']!r}")
        remote = ev.get("name", ename)
        if not _name(remote):
            raise err(p + ("name",), "name must be the model's evaluator name (a string)")
        args = ev.get("args", []) or []
        if not isinstance(args, list):
            raise err(p + ("args",), "args must be a list")
        evaluators[ename] = EvaluatorSpec(ename, ev["model"], remote, list(args))

    known_funcs = BUILTIN_FUNCTIONS | set(evaluators)
    base_names = set(entities) | set(models) | CONTEXT_NAMES

    def expr(path: tuple, src: Any, names: set) -> Expr:
        try:
            ex = parse(src)
        except ExprError as e:
            raise err(path, f"bad expression {src!r}: {e}") from None
        for f in ex.calls:
            if f not in known_funcs:
                raise err(path, f"unknown evaluator or function {f!r} in {src!r}")
        for n in ex.names:
            if n not in names:
                raise err(path, f"undefined variable {n!r} in {src!r}")
        return ex

    triggers: list[TriggerSpec] = []
    trig_raw = data.get("triggers", []) or []
    if not isinstance(trig_raw, list):
        raise err(("triggers",), "triggers must be a list")
    seen_trig = set()
    for i, t in enumerate(trig_raw):
        p = where[0] = ("triggers", i)
        if not isinstance(t, dict):
            raise err(p, "a trigger must be a map with 'on' and 'do'")
        for k in t:
            if k not in TRIGGER_KEYS:
                raise err(p + (k,), f"unknown key {k!r} (allowed: {', '.join(sorted(TRIGGER_KEYS))})")
        tname = t.get("name", f"trigger{i}")
        if not _name(tname):
            raise err(p + ("name",), "a trigger's name must be a string")
        if tname in seen_trig:
            raise err(p + ("name",), f"duplicate trigger name {tname!r}")
        seen_trig.add(tname)
        on = t.get("on")
        if not isinstance(on, dict):
            raise err(p + ("on",), "'on' must be {action: NAME[, phase]} or {topic: model.output} or {event: model.event}")
        kinds = [k for k in ("action", "topic", "event") if k in on]
        if len(kinds) != 1:
            raise err(p + ("on",), "'on' needs exactly one of action, topic, event")
        kind = kinds[0]
        if kind == "action":
            if not isinstance(on["action"], str):
                raise err(p + ("on", "action"), "action must be an operation name")
            if not isinstance(on.get("phase", "start"), str) or on.get("phase", "start") not in ("start", "end", "any"):
                raise err(p + ("on", "phase"), "phase must be start, end or any")
        else:
            ref = on[kind]
            if not isinstance(ref, str) or ref.count(".") != 1:
                raise err(p + ("on", kind), f"{kind} must be 'model.name'")
            mref = ref.split(".")[0]
            if mref not in models:
                raise err(p + ("on", kind), f"unknown model {mref!r} in {kind} {ref!r}")
        names = set(base_names)
        lets: list[tuple[str, Expr]] = []
        let_raw = t.get("let", {}) or {}
        if not isinstance(let_raw, dict):
            raise err(p + ("let",), "let must map variable names to expressions")
        for var, src in let_raw.items():
            if not isinstance(var, str) or not var.isidentifier():
                raise err(p + ("let", var), f"variable {var!r} must be a name")
            if var in base_names:
                raise err(p + ("let", var), f"variable {var!r} shadows an entity, model or context name")
            lets.append((var, expr(p + ("let", var), src, names)))
            names.add(var)
        # 'when' may use the let variables (they are bound first)
        when = expr(p + ("when",), t["when"], names) if "when" in t else None
        do = t.get("do")
        if not isinstance(do, list) or not do:
            raise err(p + ("do",), "'do' must be a non-empty list of effects (transfer or call)")
        effects = []
        for j, eff in enumerate(do):
            q = p + ("do", j)
            if not isinstance(eff, dict) or len(eff) != 1:
                raise err(q, "an effect is {transfer: {entity, attribute, to}} or {call: {model, service, args}}")
            ekind, body = next(iter(eff.items()))
            q = q + (ekind,)
            if ekind == "transfer":
                if not isinstance(body, dict) or set(body) - {"entity", "attribute", "to"} or not {"entity", "to"} <= set(body):
                    raise err(q, "transfer needs entity, to (and attribute, default pose)")
                to, attr, ent = body["to"], body.get("attribute", "pose"), body["entity"]
                for key, v in (("to", to), ("attribute", attr), ("entity", ent)):
                    if not _name(v):
                        raise err(q + (key,), f"{key} must be a name or an expression (a string)")
                if to not in models and to not in names - set(entities) - set(models):
                    raise err(q + ("to",), f"unknown model {to!r}")
                if ent in entities and attr not in entities[ent].attributes:
                    raise err(q + ("attribute",), f"unknown attribute {attr!r} of entity {ent!r} (has: {', '.join(entities[ent].attributes)})")
                fields = {"entity": expr(q + ("entity",), ent, names),
                          "attribute": parse(repr(attr)) if attr in _attrs(entities) else expr(q + ("attribute",), attr, names),
                          "to": expr(q + ("to",), to, names)}
                if attr not in _attrs(entities) and attr not in names:
                    raise err(q + ("attribute",), f"unknown attribute {attr!r} (no entity has it)")
            elif ekind == "call":
                if not isinstance(body, dict) or "model" not in body or "service" not in body:
                    raise err(q, "call needs model and service (and optionally args)")
                if not isinstance(body["model"], str) or body["model"] not in models:
                    raise err(q + ("model",), f"unknown model {body['model']!r}")
                if not _name(body["service"]):
                    raise err(q + ("service",), "service must be the model's service name (a string)")
                args = body.get("args", []) or []
                if not isinstance(args, list):
                    raise err(q + ("args",), "args must be a list of expressions")
                fields = {"model": body["model"], "service": str(body["service"]),
                          "args": [expr(q + ("args", k), a, names) for k, a in enumerate(args)]}
            else:
                raise err(q, f"unknown effect {ekind!r}: use transfer or call")
            effects.append(Effect(ekind, fields, fmt_path(q), lines.get(q)))
        triggers.append(TriggerSpec(tname, dict(on), when, lets, effects, bool(t.get("once", False)), lines.get(p)))

    semantics: dict[str, Expr] = {}
    sem_raw = data.get("semantics", {}) or {}
    if not isinstance(sem_raw, dict):
        raise err(("semantics",), "semantics must map labels to expressions")
    for label, src in sem_raw.items():
        where[0] = ("semantics", label)
        if not isinstance(label, str):
            raise err(("semantics", label), f"label {label!r} must be a string (quote it)")
        semantics[label] = expr(("semantics", label), src, set(entities) | set(models))

    return Scene(file, name, float(rate), main, models, entities, evaluators, triggers, semantics, data, lines,
                 None if max_lag is None else float(max_lag), batch)


def _attrs(entities: dict[str, EntitySpec]) -> set[str]:
    return {a for e in entities.values() for a in e.attributes}
