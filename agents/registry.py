"""Built-in model kinds, and resolution of ``module:Class`` kinds (e.g. test models)."""
from __future__ import annotations

import importlib

from .model import Model

__all__ = ["BUILTIN", "resolve_kind"]

BUILTIN: dict[str, str] = {
    "physics": "agents.models.physics:Physics",
    "mujoco": "agents.models.mujoco:MuJoCo",
    "grasp_monitor": "agents.models.grasp_monitor:GraspMonitor",
    "in_hand": "agents.models.in_hand:InHand",
    "spu": "agents.models.spu:SPU",
    "fluid": "agents.models.fluid:Fluid",
    "trivial": "agents.models.trivial:Trivial",
    "fmu": "agents.models.fmu:FMU",
}
"""Built-in kind name -> ``module:Class`` of its model (the names are :data:`protocol.messages.BUILTIN_KINDS`)."""


def resolve_kind(kind: str) -> type[Model]:
    """Return the Model class for a built-in kind name, a ``package.module:Class`` path or ``fmu:PATH`` (an FMI
    co-simulation unit, :mod:`agents.models.fmu`); ValueError saying what is wrong otherwise."""
    if kind.startswith("fmu:"):  # an FMI unit: the model class is made from its modelDescription.xml
        from .models.fmu import unit_kind

        return unit_kind(kind[4:])
    target = BUILTIN.get(kind, kind)
    if ":" not in target:
        raise ValueError(f"unknown model kind {kind!r}: use one of {', '.join(sorted(BUILTIN))} or 'module:Class'")
    mod, name = target.split(":", 1)
    try:
        module = importlib.import_module(mod)
    except ImportError as e:
        raise ValueError(f"model kind {kind!r}: cannot import {mod}: {e}") from None
    try:
        cls = getattr(module, name)
    except AttributeError:
        raise ValueError(f"model kind {kind!r}: {mod} has no {name}") from None
    if not (isinstance(cls, type) and issubclass(cls, Model)):
        raise ValueError(f"model kind {kind!r}: {mod}.{name} is not a subclass of agents.Model")
    return cls
