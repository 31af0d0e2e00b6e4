"""Perception: where the robot saw the scene's objects before the run, checked before it is applied."""
from __future__ import annotations

import json
from typing import Any

from protocol.errors import InputError, SceneError
from protocol.geometry import finite_number, pose_problem, valid_pose, validate_shape

from ..sources.recording import load_recording
from .load import Lines, fmt_path, load_yaml

ENTITY_KEYS = ("pose", "shape", "mass", "friction", "position_sigma")


def check_perception(doc: Any, where: str, lines: Lines | None = None) -> dict[str, Any]:
    """``doc`` checked against ``{"entities": {name: {"pose": [3 or 7 finite numbers], "shape": {...},
    "mass": kg, "friction": mu, "position_sigma": m}}}`` (``position_sigma``: the position uncertainty the
    perception states, one standard deviation); a InputError naming ``where``, the line (given ``lines``, those
    of a file) and the key otherwise. A key it does not know is refused: a misspelt ``postion`` left the entity
    where the scene puts it, and the run said the perception had placed it."""

    def bad(path: tuple[Any, ...], problem: str) -> InputError:
        at = f"{where}:{lines.get(path)}" if lines is not None else where
        return InputError(f"{at}: {fmt_path(path)}: {problem}")

    if not isinstance(doc, dict) or not isinstance(doc.get("entities"), dict):
        raise InputError(f"{where}: a perception maps 'entities' to {{name: {{pose: [x, y, z, ...]}}}}")
    for name, ent in doc["entities"].items():
        path = ("entities", name)
        if not isinstance(ent, dict):
            raise bad(path, "must be a map such as {pose: [x, y, z]}")
        unknown = [k for k in ent if k not in ENTITY_KEYS]
        if unknown:
            raise bad(path + (unknown[0],), f"unknown key {unknown[0]!r} (allowed: {', '.join(ENTITY_KEYS)})")
        if "pose" in ent and not valid_pose(ent["pose"]):
            raise bad(path + ("pose",), pose_problem(ent["pose"]))
        problem = validate_shape(ent["shape"]) if "shape" in ent else None
        if problem:
            raise bad(path + ("shape",), problem)
        for k in ("mass", "friction", "position_sigma"):
            if k in ent and not (finite_number(ent[k]) and ent[k] >= 0):
                raise bad(path + (k,), "must be a number >= 0")
    return doc


def perception_from_metadata(meta: dict[str, Any], path: str) -> dict[str, Any]:
    """The perception a recording carries in its ``twin.scene`` metadata, checked."""
    try:
        doc = json.loads(meta.get("json", "{}"))
    except (ValueError, RecursionError) as e:
        raise InputError(f"{path}: metadata 'twin.scene' is not valid JSON ({e})") from None
    return check_perception(doc, f"{path}: metadata 'twin.scene'")


PERCEPTION_NONE = "none"
"""``--perception none``: no perception, not even the replayed recording's."""


def load_perception(path: str) -> dict[str, Any]:
    """What the robot perceived before the run (``{"entities": {name: {"pose": [...], ...}}}``): from a
    recording's ``twin.scene`` metadata (.mcap) or from a JSON / YAML file of that shape; ``none``
    (:data:`PERCEPTION_NONE`): nothing, the scene's own poses (a recording replayed for its arm alone, whose
    perception names another task's entities)."""
    if path == PERCEPTION_NONE:
        return {"entities": {}}
    if path.lower().endswith(".mcap"):
        meta = load_recording(path).metadata.get("twin.scene")
        if not meta:
            raise InputError(f"{path}: the recording carries no perceived scene (metadata 'twin.scene')")
        return perception_from_metadata(meta, path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read the perception file: {e}") from None
    if not text.strip():
        raise InputError(f"{path}: the perception file is empty")
    try:
        doc, lines = load_yaml(text, path)  # (JSON is YAML, but for tabs: JSON may indent with them)
    except SceneError as e:
        if not path.lower().endswith(".json"):  # (a YAML file's own error names its line and key)
            raise InputError(str(e)) from None
        return check_perception(_json(text, path), path)
    return check_perception(doc, path, lines)


def _json(text: str, path: str) -> Any:
    """A JSON document YAML cannot read (indented with tabs), a key given twice refused as YAML refuses it."""
    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in items]
        twice = next((k for k in keys if keys.count(k) > 1), None)
        if twice is not None:
            raise InputError(f"{path}: duplicate key {twice!r}")
        return dict(items)
    try:
        return json.loads(text, object_pairs_hook=pairs)
    except InputError:
        raise
    except (ValueError, RecursionError) as e:  # (json.JSONDecodeError says the line and column)
        raise InputError(f"{path}: not valid JSON: {e}") from None


NO_PERCEPTION = ("the recording carries no perception (twin.scene): the entities start at the scene's own poses "
                 "(give --perception FILE for where the robot saw them)")
"""Where a replay's entities start when neither ``--perception`` nor the recording says."""
NO_PERCEPTION_LIVE = ("no --perception: the entities start at the scene's own poses (a live robot's telemetry does "
                      "not say where it saw them: give --perception FILE, or a recording that carries twin.scene)")
"""Where a live run's entities start without ``--perception``."""


def perceive(scene, source, perception: str | None = None, *, live: bool = False) -> str | None:
    """Put the scene's entities where the robot perceived them: from ``--perception FILE`` if given,
    else from the replayed recording's ``twin.scene`` metadata. :data:`NO_PERCEPTION` when it is a replay that
    gives none (the scene's poses stay), :data:`NO_PERCEPTION_LIVE` for a live source (or ``live``: one made
    later) without ``--perception`` (either also kept in the scene's :attr:`~conductor.scene.Scene.perception_notes`,
    so that the run's summary says it); the scene's perception notes when the perception places only some of its
    entities; else None."""
    if perception:
        scene.apply_perception(load_perception(perception))
        return "; ".join(scene.perception_notes) or None
    rec = getattr(source, "rec", None)
    if rec is not None and "twin.scene" in rec.metadata:
        scene.apply_perception(perception_from_metadata(rec.metadata["twin.scene"], rec.path))
        return "; ".join(scene.perception_notes) or None
    note = NO_PERCEPTION if rec is not None else NO_PERCEPTION_LIVE if live or getattr(source, "live", False) else None
    if note is not None:
        scene.perception_notes.append(note)
    return note
