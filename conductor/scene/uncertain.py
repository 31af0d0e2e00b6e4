"""A scene's ``uncertain:`` block: the ranges of entity properties the twin does not know for sure (drawn by
``--samples``, :mod:`conductor.sampling`)."""
from __future__ import annotations

import math
from typing import Any

UNCERTAIN_KEYS = ("mass", "friction")
"""The entity properties a scene may declare ranges for."""


def check_uncertain(raw: Any, entities: dict[str, Any]) -> tuple[dict[tuple[str, str], tuple[float, float]],
                                                                  list[tuple[tuple[Any, ...], str]]]:
    """A scene's ``uncertain:`` block (``{entity.property: [low, high]}``) checked: the ranges, and the problems
    as (key path, problem)."""
    out: dict[tuple[str, str], tuple[float, float]] = {}
    problems: list[tuple[tuple[Any, ...], str]] = []
    if raw is None:
        return out, problems
    if not isinstance(raw, dict):
        return out, [(("uncertain",), "uncertain maps entity.property (mass, friction) to [low, high]")]
    for key, rng in raw.items():
        path = ("uncertain", key)
        ent, _, prop = str(key).partition(".")
        if ent not in entities:
            problems.append((path, f"unknown entity {ent!r} (entities: {', '.join(entities)})"))
        elif prop not in UNCERTAIN_KEYS:
            problems.append((path, f"{prop!r} cannot be uncertain here (use {', '.join(UNCERTAIN_KEYS)})"))
        elif not (isinstance(rng, list) and len(rng) == 2 and all(isinstance(v, (int, float)) and
                                                                   not isinstance(v, bool) and math.isfinite(v)
                                                                   for v in rng)):
            problems.append((path, "must be [low, high], two finite numbers"))
        elif not 0 <= rng[0] <= rng[1]:
            problems.append((path, f"must have 0 <= low <= high, got {rng}"))
        else:
            out[(ent, prop)] = (float(rng[0]), float(rng[1]))
    return out, problems
