"""The validated scene: what :func:`conductor.scene.parse_scene` returns."""
from __future__ import annotations

from dataclasses import dataclass, field

from protocol.errors import SceneError
from protocol.geometry import validate_shape

from .expr import Expr
from .load import Lines, fmt_path


@dataclass
class ModelSpec:
    name: str
    kind: str
    step: str
    rate: float
    period: int
    args: dict
    reads: list[str]
    line: int | None = None


@dataclass
class EntitySpec:
    name: str
    shape: dict
    pose: list[float]
    tags: list[str]
    attributes: dict[str, str]
    extra: dict = field(default_factory=dict)


@dataclass
class EvaluatorSpec:
    name: str
    model: str
    remote: str
    args: list


@dataclass
class Effect:
    kind: str  # transfer | call
    fields: dict  # values are Expr
    path: str
    line: int | None


@dataclass
class TriggerSpec:
    name: str
    on: dict
    when: Expr | None
    let: list[tuple[str, Expr]]
    do: list[Effect]
    once: bool
    line: int | None


@dataclass
class Scene:
    file: str
    name: str
    rate: float
    main: str
    models: dict[str, ModelSpec]
    entities: dict[str, EntitySpec]
    evaluators: dict[str, EvaluatorSpec]
    triggers: list[TriggerSpec]
    semantics: dict[str, Expr]
    raw: dict
    lines: Lines
    max_lag: float | None = 0.1  # replay waits for clock-driven models this far behind (None: never)
    batch: int = 32  # at most this many ticks in one step message of a replay (1: one message per tick)

    def line(self, *path) -> int | None:
        return self.lines.get(tuple(path))

    def error(self, path: tuple, problem: str) -> SceneError:
        return SceneError(self.file, self.lines.get(path), fmt_path(path), problem)

    def apply_perception(self, perceived: dict) -> None:
        """Place entities where the robot perceived them in a recording (``twin.scene`` metadata):
        ``{"entities": {name: {"pose": [...], "shape": {...}}}}``, checked by :func:`check_perception`.
        Unknown names are ignored."""
        for name, upd in (perceived.get("entities") or {}).items():
            ent = self.entities.get(name)
            if ent is None or not isinstance(upd, dict):
                continue
            if "pose" in upd:
                pose = [float(v) for v in upd["pose"]]
                ent.pose = pose + ([0.0, 0.0, 0.0, 1.0] if len(pose) == 3 else [])
            if "shape" in upd and validate_shape(upd["shape"]) is None:
                ent.shape = dict(upd["shape"])
            for k in ("mass", "friction"):
                if k in upd:
                    ent.extra[k] = upd[k]

    def initial_owners(self) -> dict[tuple[str, str], str]:
        return {(e.name, a): m for e in self.entities.values() for a, m in e.attributes.items()}

    def geometry(self) -> dict:
        """Entities as sent to models at init and to the viewer."""
        return {n: {"shape": e.shape, "pose": e.pose, "tags": e.tags, "attributes": e.attributes, **e.extra}
                for n, e in self.entities.items()}


