"""FMI co-simulation units (FMI 2 and 3, through FMPy) as models of the ensemble.

Two ways to name a unit:

- ``kind: "fmu:PATH"`` (PATH a ``.fmu`` file, or a Python source ``.py`` that is built into one on first use:
  a pythonfmu3 ``Fmi3Slave`` for FMI 3, a pythonfmu ``Fmi2Slave`` for FMI 2 (needs ``pip install pythonfmu``),
  cached under ``$XDG_CACHE_HOME/twin/fmu`` by the source's hash; a path in a scene is relative to the scene's
  folder). The model then *is* that unit: the unit's parameters and inputs
  (``modelDescription.xml``: names, types, units, start values, descriptions) are the model's parameters,
  listed by ``twin agent fmu:PATH --help`` and checked against the scene's ``args`` before a run; its output
  variables are the attributes it can own.
- ``kind: fmu`` with ``args: {unit: PATH, parameters: {name: value}}``: the same unit, its parameters in one
  map (checked when the agent initialises); it owns nothing.

**Attributes.** An output variable ``X`` of the unit is an attribute ``X`` the model can own, of one entity at
a time (e.g. ``coffee: {attributes: {temperature: cooling}}``). A unit cannot be told its states in the middle
of a run, so a value handed over (``acquire``) restarts the unit: it is reset and initialised again with its
parameter ``X_start`` set to that value (a unit without ``X_start`` refuses the handover); ``release`` and
``read`` give the output's current value.

**Inputs.** ``inputs: {VARIABLE: entity.attribute}`` sets a unit input from another owner's attribute before
each step (the scene's model entry must list those in ``reads``); an input not bound keeps its parameter value.

**Stepping.** Each step of the conductor is one ``doStep`` of ``dt`` (the unit's time starts at 0). Outputs
every step: ``variables`` {name: value} of every output and local variable. Evaluator ``value(name)``.
"""
from __future__ import annotations

import hashlib
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, ClassVar

from ..model import Model, Param, evaluator

_PY_TYPES = {"Float64": float, "Float32": float, "Real": float, "Int32": int, "Int64": int, "Integer": int,
             "Int8": int, "Int16": int, "UInt8": int, "UInt16": int, "UInt32": int, "UInt64": int,
             "Boolean": bool, "String": str, "Enumeration": int}


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "twin" / "fmu"


def unit_file(path: str | Path) -> Path:
    """The ``.fmu`` file of a unit: ``path`` itself, or the unit built from a pythonfmu3 source ``.py`` (once per
    source content, into the cache; concurrent builders do not clash)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"FMU unit {str(p)!r} does not exist")
    if p.suffix == ".fmu":
        return p
    if p.suffix != ".py":
        raise ValueError(f"FMU unit {str(p)!r}: give a .fmu file or a pythonfmu3 source .py")
    digest = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
    out_dir = cache_dir() / f"{p.stem}-{digest}"
    built = sorted(out_dir.glob("*.fmu")) if out_dir.is_dir() else []
    if built:
        return built[0]
    # an FMI 3 source is written against pythonfmu3, an FMI 2 one against pythonfmu: each has its own builder
    if re.search(r"^\s*(from|import)\s+pythonfmu3\b", p.read_text(), re.M):
        from pythonfmu3.builder import FmuBuilder
    else:
        try:
            from pythonfmu.builder import FmuBuilder  # type: ignore[import-not-found, no-redef]
        except ImportError:
            raise ValueError(f"FMU unit {str(p)!r}: an FMI 2 source needs the pythonfmu package "
                             "(pip install pythonfmu)") from None

    cache_dir().mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{p.stem}-", dir=cache_dir()))
    try:
        FmuBuilder.build_FMU(p, dest=tmp)
        try:
            tmp.rename(out_dir)
        except OSError:  # another process built it meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return sorted(out_dir.glob("*.fmu"))[0]


def describe(path: str | Path) -> Any:
    """FMPy's model description of a unit (built first if it is a source)."""
    from fmpy import read_model_description

    return read_model_description(str(unit_file(path)))


def _param_doc(v: Any) -> str:
    unit = getattr(v, "unit", None) or (v.declaredType.unit if getattr(v, "declaredType", None) is not None
                                         and getattr(v.declaredType, "unit", None) else None)
    words = [v.description or v.name]
    if unit:
        words.append(f"[{unit}]")
    words.append(f"(FMU {v.causality})")
    return " ".join(words)


def _start(v: Any, py: type) -> Any:
    if v.start is None:
        return None
    if py is bool:
        return str(v.start).lower() in ("true", "1")
    try:
        return py(v.start)
    except (TypeError, ValueError):
        return None


def unit_kind(path: str) -> type[Model]:
    """The model class of the unit at ``path`` (kind ``fmu:PATH``): its parameters and inputs as parameters, its
    outputs as attributes."""
    md = describe(path)
    params = dict(FMU.params)
    params.pop("unit")
    params.pop("parameters")
    for v in md.modelVariables:
        if v.causality in ("parameter", "input") and v.type in _PY_TYPES:
            py = _PY_TYPES[v.type]
            params[v.name] = Param(py, _start(v, py), _param_doc(v))
    outputs_ = tuple(v.name for v in md.modelVariables if v.causality == "output")
    doc = (f"FMU {md.modelName!r} (FMI {md.fmiVersion}): {md.description or 'no description'}. Its parameters and "
           f"inputs are the parameters below; its outputs ({', '.join(outputs_) or 'none'}) are attributes it can "
           "own. See agents.models.fmu.")
    return type("FMUUnit", (FMU,), {"kind": f"fmu:{path}", "params": params, "attributes": outputs_,
                                    "__doc__": doc, "unit_path": str(path)})


class FMU(Model):
    """An FMI co-simulation unit stepped by the conductor (see the module docstring)."""

    kind = "fmu"
    role = "simulation"
    unit_path: ClassVar[str | None] = None  # set on the class of kind fmu:PATH
    params = {
        "unit": Param(str, None, "kind fmu: the unit (.fmu, or a pythonfmu3 source .py)"),
        "parameters": Param(dict, {}, "kind fmu: values of the unit's parameters and inputs by name"),
        "inputs": Param(dict, {}, "unit input -> 'entity.attribute' of another owner, set before each step"),
    }
    attributes: ClassVar[tuple[str, ...]] = ()
    outputs = ("variables",)
    reads = ()

    def init(self, params: dict, scene: dict) -> None:
        from fmpy import extract

        self.close()  # a second init (a rejoin) starts a fresh instance
        path = self.unit_path or params.get("unit")
        if not path:
            raise ValueError("kind fmu needs args.unit (a .fmu or a pythonfmu3 .py), or use kind fmu:PATH")
        file = unit_file(path)
        self.md = describe(file)
        self.vars = {v.name: v for v in self.md.modelVariables}
        given = dict(params.get("parameters") or {}) if self.unit_path is None else \
            {k: v for k, v in params.items() if k in self.vars and v is not None}
        unknown = [k for k in given if k not in self.vars or self.vars[k].causality not in ("parameter", "input")]
        if unknown:
            settable = [n for n, v in self.vars.items() if v.causality in ("parameter", "input")]
            raise ValueError(f"unknown unit parameters {unknown} (the unit has: {', '.join(settable)})")
        self.settings = given
        self.bound: dict[str, tuple[str, str]] = {}
        for var, ref in (params.get("inputs") or {}).items():
            v = self.vars.get(var)
            if v is None or v.causality != "input":
                raise ValueError(f"inputs: {var!r} is not an input of the unit")
            ent, _, attr = str(ref).partition(".")
            if not ent or not attr:
                raise ValueError(f"inputs.{var}: {ref!r} must be 'entity.attribute'")
            self.bound[var] = (ent, attr)
        self.dir = extract(str(file))
        self.version = self.md.fmiVersion
        if self.md.coSimulation is None:
            raise ValueError(f"{file}: not a co-simulation unit")
        self.holder: dict[str, str] = {}  # attribute -> the entity whose value it is
        for ent, attr in self.owned:
            self.holder[attr] = ent
        self.slave: Any = None
        self._inputs: dict[str, float] = {}  # the bound inputs' last values (a restart goes on with them)
        self._start({})

    # ------------------------------------------------------------ the unit
    def _start(self, overrides: dict[str, Any]) -> None:
        """(Re)start the unit with the parameter values, then ``overrides``."""
        md = self.md
        if self.slave is None:
            if self.version.startswith("3"):
                from fmpy.fmi3 import FMU3Slave

                self.slave = FMU3Slave(guid=md.instantiationToken, unzipDirectory=self.dir,
                                       modelIdentifier=md.coSimulation.modelIdentifier, instanceName="twin")
            else:
                from fmpy.fmi2 import FMU2Slave

                self.slave = FMU2Slave(guid=md.guid, unzipDirectory=self.dir,
                                       modelIdentifier=md.coSimulation.modelIdentifier, instanceName="twin")
            self.slave.instantiate()
        else:
            self.slave.reset()
        s = self.slave
        if not self.version.startswith("3"):
            s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        for name, value in {**self.settings, **self._inputs, **overrides}.items():
            self._set(name, value)
        s.exitInitializationMode()
        self.time = 0.0
        self.failed = ""  # why the unit cannot be stepped again (a restart from handed-over values mends it)
        self._good: dict[str, Any] = {a: self._get(a) for a in self.attributes}

    def _accessor(self, v: Any) -> str:
        """The FMI type name of the calls that set and get variable ``v`` (``Float32``, ``Int64``, ``Real``...): FMI 3
        has a call per width, and an enumeration is an Int64 there (every integer went through Int32, and a unit
        with an Int64 parameter failed fatally)."""
        if not self.version.startswith("3"):
            return {"Enumeration": "Integer"}.get(v.type, v.type if v.type in ("Real", "Integer", "Boolean", "String")
                                                  else "Real")
        return {"Enumeration": "Int64"}.get(v.type, v.type if v.type in _PY_TYPES else "Float64")

    def _set(self, name: str, value: Any) -> None:
        v = self.vars[name]
        py = _PY_TYPES.get(v.type, float)
        getattr(self.slave, f"set{self._accessor(v)}")([v.valueReference], [py(value)])

    def _get(self, name: str) -> Any:
        v = self.vars[name]
        py = _PY_TYPES.get(v.type, float)
        return py(getattr(self.slave, f"get{self._accessor(v)}")([v.valueReference])[0])

    # ------------------------------------------------------------------ step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        if self.failed:  # (FMI allows no step after a discarded or failed one: its values are of no time)
            raise RuntimeError(self.failed)
        for var, (ent, attr) in self.bound.items():
            value = (inputs.get(ent) or {}).get(attr)
            if isinstance(value, (int, float)) and math.isfinite(value):
                self._set(var, value)
                self._inputs[var] = value
        try:
            self.slave.doStep(currentCommunicationPoint=self.time, communicationStepSize=dt)
        except Exception as e:
            self.failed = (f"the unit's step from t={t - dt:.3f} s failed ({type(e).__name__}: {e}): it is not "
                           "stepped again, and what it owns is handed over as it was before that step")
            raise RuntimeError(self.failed) from None
        self.time += dt
        self._good = {a: self._get(a) for a in self.attributes}  # (what a failed step leaves is no value)
        self.output("variables", {n: self._get(n) for n, v in self.vars.items()
                                  if v.causality in ("output", "local") and v.type in _PY_TYPES})

    # ------------------------------------------------------------- handover
    def read(self, entity: str, attribute: str) -> Any:
        if self.holder.get(attribute) != entity:
            raise KeyError(f"this unit does not hold {entity}.{attribute}")
        return self._read_now(attribute)

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict) -> None:
        if attribute not in self.attributes:
            raise KeyError(f"this unit has no output {attribute!r}")
        held = self.holder.get(attribute)
        if held is not None and held != entity:
            raise ValueError(f"this unit already holds {held}.{attribute}; one unit is one entity's {attribute}")
        if value is not None:
            start = f"{attribute}_start"
            if start not in self.vars:
                raise ValueError(f"the unit cannot start from a handed-over {attribute}: it has no {start!r}")
            py = _PY_TYPES.get(self.vars[start].type, float)
            if isinstance(value, bool) != (py is bool) or not isinstance(value, (int, float)) \
                    or (py is not bool and not math.isfinite(value)):  # (checked before the unit is touched)
                raise ValueError(f"the unit cannot start from {attribute} = {value!r}: {start} takes a finite "
                                 f"{py.__name__}")
            # a restart starts every state again: the other outputs go on from where they are (a handover of one
            # reset the others to their start values)
            going = {f"{a}_start": self._read_now(a) for a in self.attributes
                     if a != attribute and f"{a}_start" in self.vars}
            self._start({**going, start: value})
            self.settings[start] = value
        self.holder[attribute] = entity

    def _read_now(self, attribute: str) -> Any:
        return self._good[attribute] if self.failed else self._get(attribute)

    def release(self, entity: str, attribute: str) -> tuple[Any, dict]:
        value = self.read(entity, attribute)
        self.holder.pop(attribute, None)
        return value, {}

    @evaluator("value")
    def value(self, name: str) -> Any:
        """The current value of one of the unit's variables."""
        if name not in self.vars:
            raise KeyError(f"the unit has no variable {name!r}")
        return self._get(name)

    def close(self) -> None:
        s = getattr(self, "slave", None)
        if s is not None:
            try:
                s.terminate()
                # the instance is freed, its library stays loaded until the process ends: FMPy's freeInstance
                # would also dlclose it, and a pythonfmu3 unit's library runs C++ teardown (its interpreter
                # helper thread) on unload; once it aborted an agent on SIGTERM under load
                free: Any = getattr(s, "fmi3FreeInstance", None) or s.fmi2FreeInstance
                free(s.component)
            except Exception:
                pass
            self.slave = None
            self._exit_at_once = True  # nor at the interpreter's exit: the agent ends without it (run_agent)
        d = getattr(self, "dir", None)
        if d:
            shutil.rmtree(d, ignore_errors=True)
