"""A scene's ``uncertain:`` block: the ranges of entity properties the twin does not know for sure (drawn by
``--samples``, :mod:`conductor.sampling`)."""
from __future__ import annotations

import math
from typing import Any

from protocol.geometry import is_static

__all__ = ["UNCERTAIN_KEYS", "check_uncertain", "static"]

UNCERTAIN_KEYS = ("mass", "friction")
"""The entity properties a scene may declare ranges for."""


def check_uncertain(raw: Any, entities: dict[str, Any], broken: set[str] | frozenset[str] = frozenset()
                    ) -> tuple[dict[tuple[str, str], tuple[float, float]], list[tuple[tuple[Any, ...], str]]]:
    """A scene's ``uncertain:`` block (``{entity.property: [low, high]}``) checked against the scene's good
    ``entities`` (:class:`~conductor.scene.spec.EntitySpec`; the ``broken`` ones are said already): the ranges, and
    the problems as (key path, problem)."""
    out: dict[tuple[str, str], tuple[float, float]] = {}
    problems: list[tuple[tuple[Any, ...], str]] = []
    if raw is None:
        return out, problems
    if not isinstance(raw, dict):
        return out, [(("uncertain",), "uncertain maps entity.property (mass, friction) to [low, high]")]
    for key, rng in raw.items():
        path = ("uncertain", key)
        ent, _, prop = str(key).rpartition(".")  # (an entity name may have a dot in it, a property not)
        if ent in broken:
            continue
        if not ent:
            problems.append((path, "an uncertain key is entity.property, e.g. ball.mass"))
            continue
        problem = _range_problem(entities.get(ent), ent, prop, rng, entities)
        if problem:
            problems.append((path, problem))
        else:
            out[(ent, prop)] = (float(rng[0]), float(rng[1]))
    return out, problems


def _range_problem(spec: Any, ent: str, prop: str, rng: Any, entities: dict[str, Any]) -> str | None:
    """What is wrong with ``rng`` as the range of ``ent``'s ``prop`` (``spec`` its entity, None if unknown)."""
    if spec is None:
        return f"unknown entity {ent!r} (entities: {', '.join(entities)})"
    if prop not in UNCERTAIN_KEYS:
        return f"{prop!r} cannot be uncertain here (use {', '.join(UNCERTAIN_KEYS)})"
    if not (isinstance(rng, list) and len(rng) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                             and math.isfinite(v) for v in rng)):
        return "must be [low, high], two finite numbers"
    if not 0 <= rng[0] <= rng[1]:
        return f"must have 0 <= low <= high, got {rng}"
    if prop == "mass" and static(spec):
        return f"{ent} is static (a container or socket, tagged static, or of mass 0): its mass varies nothing"
    if prop == "mass" and rng[0] <= 0:
        return f"a mass must be above 0 (a body of mass 0 is static), got {rng}"
    return None


def static(spec: Any) -> bool:
    """Whether the models hold the entity ``spec`` still (:func:`protocol.geometry.is_static`)."""
    return is_static(spec.shape, spec.tags, spec.extra.get("mass"))
