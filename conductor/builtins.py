"""The functions a scene's expressions may call, in one table.

The scene checker accepts exactly the names of :data:`BUILTINS` (beside the scene's own evaluators), and the
trigger engine binds exactly these implementations to the run's current state through :func:`bind`: the two
cannot drift apart. Each implementation takes the :class:`World` it reads first, then the expression's
arguments.
"""
from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from protocol.errors import ExprError
from protocol.geometry import inside_container, quat_to_matrix


class World(Protocol):
    """What expressions may read of a run: values, owners, outputs, event counts and the scene's entities."""

    def value(self, entity: str, attribute: str) -> Any: ...
    def owner(self, entity: str, attribute: str) -> str | None: ...
    def owned(self, model: str, attribute: str) -> list[str]: ...
    def output(self, model: str, name: str, default: Any = None) -> Any: ...
    def event_count(self, model: str, name: str) -> int: ...
    def shape(self, entity: str) -> dict[str, Any] | None: ...
    def tagged(self, tag: str) -> list[str]: ...


def _pose(w: World, e: str) -> Any:
    """The entity's current pose ``[x, y, z, qx, qy, qz, qw]`` (None if unknown)."""
    return w.value(e, "pose")


def _position(w: World, e: Any) -> list[float]:
    """The entity's position, or the first three numbers of a point given as a list (a pose's position); a list
    of fewer than three numbers is no point (``[0.5]`` was broadcast to ``[0.5, 0.5, 0.5]``)."""
    if isinstance(e, (list, tuple)):
        if len(e) < 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in e[:3]):
            raise ExprError(f"a point is [x, y, z] (numbers), not {list(e)!r:.60}")
        return list(e[:3])
    p = w.value(e, "pose")
    if p is None:
        raise ExprError(f"no pose known for {e!r}")
    return list(p[:3])


def _distance(w: World, a: Any, b: Any) -> float:
    """Euclidean distance (m) between two entities or points."""
    return float(np.linalg.norm(np.subtract(_position(w, a), _position(w, b))))


def _inside(w: World, container: str, obj: Any) -> bool:
    """Whether ``obj`` (an entity or a point) is inside the container entity's interior."""
    shape = w.shape(container)
    if shape is None or shape.get("type") != "container":
        raise ExprError(f"{container!r} is not a container")
    return inside_container(shape, w.value(container, "pose"), _position(w, obj))


def _at(w: World, e: str, offset: Any) -> list[float]:
    """The world point at ``offset`` in entity e's frame."""
    p = w.value(e, "pose")
    if p is None:
        raise ExprError(f"no pose known for {e!r}")
    return list(np.asarray(p[:3]) + quat_to_matrix(p[3:7]) @ np.asarray(offset, float))


def _seated(w: World, peg: str, socket: str, offset: Any, lateral: float, depth: float,
            max_tilt_deg: float = 10.0) -> bool:
    """Whether ``peg`` sits in ``socket``: its centre within ``lateral`` (m) of the axis through the seat point
    ``offset`` (in the socket's frame, the axis along the socket's z), no more than ``depth`` (m) above that
    point, and its axis within ``max_tilt_deg`` of the socket's. The synthetic reality's own test of a
    connection, applied to whatever world the expression reads."""
    ps, pp = w.value(socket, "pose"), w.value(peg, "pose")
    if ps is None or pp is None:
        raise ExprError(f"no pose known for {socket!r} or {peg!r}")
    rot = quat_to_matrix(ps[3:7])
    local = rot.T @ (np.asarray(pp[:3], float) - np.asarray(ps[:3], float)) - np.asarray(offset, float)
    axis = rot.T @ quat_to_matrix(pp[3:7])[:, 2]
    tilt = math.degrees(math.acos(min(1.0, abs(float(axis[2])))))
    return bool(math.hypot(local[0], local[1]) < lateral and local[2] < depth and tilt < max_tilt_deg)


def _output(w: World, model: str, name: str, default: Any = None) -> Any:
    """A model's latest output value."""
    return w.output(model, name, default)


def _owner(w: World, e: str, a: str = "pose") -> str | None:
    """The model responsible for ``e.a`` now."""
    return w.owner(e, a)


def _owned(w: World, model: str, a: str = "pose") -> list[str]:
    """The entities whose attribute ``a`` the model owns, sorted."""
    return w.owned(model, a)


def _event_count(w: World, model: str, name: str) -> int:
    """How often the model has raised the event so far."""
    return w.event_count(model, name)


def _tagged(w: World, tag: str) -> list[str]:
    """The scene's entities with this tag."""
    return w.tagged(tag)


def _plain(fn: Callable[..., Any]) -> Callable[..., Any]:
    """A Python built-in that reads nothing of the world."""
    return lambda _w, *args: fn(*args)


BUILTINS: Mapping[str, Callable[..., Any]] = {
    "owner": _owner, "owned": _owned, "at": _at, "pose": _pose, "position": _position, "distance": _distance,
    "inside": _inside, "seated": _seated, "output": _output, "event_count": _event_count, "tagged": _tagged,
    "abs": _plain(abs), "min": _plain(min), "max": _plain(max), "len": _plain(len), "str": _plain(str),
    "float": _plain(float), "int": _plain(int), "bool": _plain(bool), "any": _plain(any), "all": _plain(all),
    "norm": _plain(lambda v: float(np.linalg.norm(v))),
}
"""Every built-in function by the name expressions call it by."""

BUILTIN_NAMES = frozenset(BUILTINS)


def _span(fn: Callable[..., Any]) -> tuple[int, int | None]:
    """The least and most arguments an expression gives a world built-in (its first parameter is the world)."""
    params = list(inspect.signature(fn).parameters.values())[1:]
    if any(p.kind == p.VAR_POSITIONAL for p in params):
        return sum(p.default is p.empty and p.kind != p.VAR_POSITIONAL for p in params), None
    return sum(p.default is p.empty for p in params), len(params)


ARITY: Mapping[str, tuple[int, int | None]] = {
    **{n: _span(fn) for n, fn in BUILTINS.items()},
    "abs": (1, 1), "min": (1, None), "max": (1, None), "len": (1, 1), "str": (0, 1), "float": (0, 1), "int": (0, 2),
    "bool": (0, 1), "any": (1, 1), "all": (1, 1), "norm": (1, 1),
}
"""The least and most arguments (None: any number) each built-in takes: a call with others is a scene problem."""

ARG_KINDS: Mapping[str, tuple[str, ...]] = {
    "owner": ("entity", "attribute"), "owned": ("model", "attribute"), "event_count": ("model",), "output": ("model",),
    "tagged": ("tag",), "pose": ("entity",), "position": ("entity",), "distance": ("entity", "entity"),
    "inside": ("entity", "entity"), "at": ("entity",), "seated": ("entity", "entity"),
}
"""What each built-in takes, argument by argument, that the scene checker looks up when it is written as a string
(an entity, model, attribute or tag of the scene; the events and outputs that ``event_count`` and ``output`` name
are checked against the agents' declarations)."""


def bind(world: World) -> dict[str, Callable[..., Any]]:
    """The built-ins bound to ``world``: the function table an expression is evaluated with."""
    def bound(fn: Callable[..., Any]) -> Callable[..., Any]:
        return lambda *args: fn(world, *args)

    return {name: bound(fn) for name, fn in BUILTINS.items()}
