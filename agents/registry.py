"""Built-in model kinds, and resolution of ``module:Class`` kinds (e.g. test models)."""
from __future__ import annotations

import importlib

BUILTIN = {
    "physics": "agents.models.physics:Physics",
    "grasp_monitor": "agents.models.grasp_monitor:GraspMonitor",
    "in_hand": "agents.models.in_hand:InHand",
    "spu": "agents.models.spu:SPU",
    "fluid": "agents.models.fluid:Fluid",
    "trivial": "agents.models.trivial:Trivial",
}


def resolve_kind(kind: str):
    """Return the Model class for a built-in kind name or a ``package.module:Class`` path."""
    target = BUILTIN.get(kind, kind)
    if ":" not in target:
        raise ValueError(f"unknown model kind {kind!r}: use one of {', '.join(sorted(BUILTIN))} or 'module:Class'")
    mod, cls = target.split(":", 1)
    try:
        module = importlib.import_module(mod)
    except ImportError as e:
        raise ValueError(f"model kind {kind!r}: cannot import {mod}: {e}") from None
    try:
        return getattr(module, cls)
    except AttributeError:
        raise ValueError(f"model kind {kind!r}: {mod} has no {cls}") from None
