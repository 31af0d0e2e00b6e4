"""The validated scene: what :func:`conductor.scene.parse_scene` returns.

Every class is a frozen dataclass except :class:`ModelSpec`, so nobody re-binds a part of a checked scene;
the one sanctioned change after loading is :meth:`Scene.apply_perception`, which replaces entities by
updated copies. The maps and lists inside stay Python containers (the conductor reads them as such).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from protocol.errors import Problem, SceneError
from protocol.geometry import full_pose, validate_shape
from protocol.robot import Robot

from .expr import Expr
from .load import Lines, fmt_path


@dataclass(frozen=True)
class ModelSpec:
    """One entry of ``models:``."""

    name: str
    kind: str
    step: str
    rate: float
    period: int  # it steps every ``period`` ticks of the clock (1 unless service-stepped slower)
    args: dict[str, Any]
    reads: list[str]  # the scene's ``reads:`` only; :func:`reads_of` adds what the agent declares
    line: int | None = None


@dataclass(frozen=True)
class EntitySpec:
    """One entry of ``entities:``; ``pose`` always has 7 numbers, ``extra`` holds color, mass, friction."""

    name: str
    shape: dict[str, Any]
    pose: list[float]
    tags: list[str]
    attributes: dict[str, str]  # attribute -> the model that owns it at start
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class EvaluatorSpec:
    """One entry of ``evaluators:``: expressions call ``name``, the conductor asks ``model`` for ``remote``."""

    name: str
    model: str
    remote: str
    args: list[Any]


@dataclass(frozen=True)
class Effect:
    """One effect of a trigger's ``do:``.

    ``kind`` is ``transfer`` (``fields``: entity, attribute, to, each an :class:`Expr`) or ``call``
    (``fields``: model and service names, args a list of :class:`Expr`); ``path`` and ``line`` say where
    it is written (``triggers[0].do[1].call``).
    """

    kind: str
    fields: dict[str, Any]
    path: str
    line: int | None


@dataclass(frozen=True)
class TriggerSpec:
    """One entry of ``triggers:``; ``let`` keeps the order its variables are bound in."""

    name: str
    on: dict[str, Any]
    when: Expr | None
    let: list[tuple[str, Expr]]
    do: list[Effect]
    once: bool
    line: int | None


@dataclass(frozen=True)
class Scene:
    """A checked scene. ``raw`` is the YAML as loaded and ``lines`` the line of every key path in it."""

    file: str
    name: str
    rate: float
    main: str
    models: dict[str, ModelSpec]
    entities: dict[str, EntitySpec]
    evaluators: dict[str, EvaluatorSpec]
    triggers: list[TriggerSpec]
    semantics: dict[str, Expr]
    raw: dict[str, Any]
    lines: Lines
    max_lag: float | None = 0.1  # replay waits for clock-driven models this far behind (None: never)
    batch: int = 32  # at most this many ticks in one step message of a replay (1: one message per tick)
    robot: Robot | None = None  # the resolved robot block (None only for scenes built by hand in tests)
    uncertain: dict[tuple[str, str], tuple[float, float]] = field(default_factory=dict)  # (entity, mass|friction)
    perception_missed: list[str] = field(default_factory=list)  # a perception that placed none of the entities
    perception_notes: list[str] = field(default_factory=list)  # one that placed some: the others it left alone

    @property
    def declared_robot(self) -> Robot | None:
        """The robot when the scene has a ``robot:`` block (the telemetry is then checked against it), else None
        (a scene of toy joints: the models still get the default robot)."""
        return self.robot if self.raw.get("robot") else None

    def line(self, *path: Any) -> int | None:
        """The line of a key path (or of its nearest ancestor that has one)."""
        return self.lines.get(tuple(path))

    def problem(self, path: tuple[Any, ...], problem: str) -> Problem:
        """A problem at a key path of this scene (``file:line: key.path: problem``)."""
        return Problem(self.file, self.lines.get(path), fmt_path(path), problem)

    def error(self, path: tuple[Any, ...], problem: str) -> SceneError:
        """:meth:`problem` as an error to raise."""
        return SceneError(self.file, self.lines.get(path), fmt_path(path), problem)

    def _say_placed(self, seen: set[str]) -> None:
        """:attr:`perception_missed` when a perception places none of the entities, :attr:`perception_notes` when
        it places some: the others (a virtual entity, a fluid's particles, is never seen) stay where they are."""
        placed = [n for n, spec in self.entities.items() if n in seen or spec.extra.get("perceived_as") in seen]
        self.perception_missed[:] = [] if placed else [  # the perception of another scene: nothing moves
            f"the perception names {', '.join(sorted(map(str, seen)))}, none of this scene's entities "
            f"({', '.join(sorted(self.entities)) or 'none'}): they stay where the scene puts them (a recording "
            "of another scene?)"]
        alone = sorted(n for n, spec in self.entities.items() if n not in placed and "virtual" not in spec.tags)
        one = len(alone) == 1
        self.perception_notes[:] = [
            f"the perception places {', '.join(sorted(placed))} but not {', '.join(alone)}: "
            f"{'it stays' if one else 'they stay'} where the scene puts {'it' if one else 'them'}"] \
            if placed and alone else []

    def apply_perception(self, perceived: dict[str, Any]) -> None:
        """Place entities where the robot perceived them in a recording (``twin.scene`` metadata):
        ``{"entities": {name: {"pose": [...], "shape": {...}}}}``, checked by :func:`check_perception`.
        Unknown names are ignored. Each perceived entity is replaced by an updated copy. An entity with
        ``perceived_as: OTHER`` takes the pose the perception gives ``OTHER`` (its own shape stays: e.g. a mug the
        recording's perception calls a ball). A perception that names entities but none of this scene's is noted in
        :attr:`perception_missed` (a run of the scene is then ``degraded``: it did not start from what the robot
        perceived)."""
        seen = perceived.get("entities") or {}
        named = perceived.get("perceived")  # a sample's (conductor.sampling): what the perception drawn around named
        names = set(named) if isinstance(named, list) and all(isinstance(n, str) for n in named) else set(seen)
        if names:  # the latest perception decides (said once, however often one is applied)
            self._say_placed(names)
        for spec in list(self.entities.values()):
            alias = spec.extra.get("perceived_as")
            seen_as = seen.get(alias) if alias else None
            if isinstance(seen_as, dict) and "pose" in seen_as:
                self.entities[spec.name] = replace(spec, pose=full_pose(seen_as["pose"], spec.pose[3:]))
        for name, upd in seen.items():
            ent = self.entities.get(name)
            if ent is None or not isinstance(upd, dict):
                continue
            pose, shape, extra = ent.pose, ent.shape, dict(ent.extra)
            if "pose" in upd:
                pose = full_pose(upd["pose"], ent.pose[3:])  # (a position alone keeps the scene's orientation)
            if "shape" in upd and validate_shape(upd["shape"]) is None:
                shape = dict(upd["shape"])
            for k in ("mass", "friction", "position_sigma"):
                if k in upd:
                    extra[k] = upd[k]
            self.entities[name] = replace(ent, pose=pose, shape=shape, extra=extra)

    def initial_owners(self) -> dict[tuple[str, str], str]:
        """``(entity, attribute) -> model`` at the start of a run."""
        return {(e.name, a): m for e in self.entities.values() for a, m in e.attributes.items()}

    def geometry(self) -> dict[str, Any]:
        """Entities as sent to models at init and to the viewer."""
        return {n: {"shape": e.shape, "pose": e.pose, "tags": e.tags, "attributes": e.attributes, **e.extra}
                for n, e in self.entities.items()}
