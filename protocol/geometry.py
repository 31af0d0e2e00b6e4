"""Entity shapes shared by the physics model, the telemetry generator, the conductor's
semantic predicates and the Rerun stream, so that every process sees the same bodies.

Shape specs (scene ``shape:`` maps):
- ``{type: sphere, radius}``; ``{type: box, size: [x, y, z]}``; ``{type: cylinder, radius, length}``
- ``{type: container, style: bin|box|bowl|cup, size: [x, y, height] | radius + height, wall}``:
  an open container made of primitives (floor + walls), origin at the centre of its floor's underside.
- ``{type: socket, size: [x, y, z], hole, depth, chamfer}``: a block (origin at its centre, as a box) with an
  octagonal hole of apothem ``hole`` going ``depth`` down from its top, whose upper ``chamfer`` metres widen at
  45 degrees (the SPU of the insertion scenario): a static compound of the boxes of :func:`socket_parts`.
- ``{type: urdf, file}``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, TypeAlias, TypeGuard

import numpy as np
import numpy.typing as npt

__all__ = ["Vector", "Quaternion", "Pose", "Shape", "Part", "Matrix", "CONTAINER_DEFAULTS", "SHAPE_KEYS", "SHAPE_TYPES",
           "quat_from_axis_angle", "quat_mul", "quat_to_matrix", "to_local", "container_params", "container_parts",
           "inside_container", "wall_radius", "socket_parts", "bounding_radius", "FINITE_LIMIT", "finite_number",
           "finite_numbers", "STATIC_SHAPES", "is_static",
           "valid_pose", "full_pose", "pose_problem", "validate_shape"]

Vector: TypeAlias = Sequence[float] | npt.NDArray[np.floating[Any]]
"""``[x, y, z]``: a point (metres, world frame unless said otherwise) or an axis."""
Quaternion: TypeAlias = Sequence[float] | npt.NDArray[np.floating[Any]]
"""``[qx, qy, qz, qw]`` (xyzw, scalar last), of unit length."""
Pose: TypeAlias = Sequence[float] | npt.NDArray[np.floating[Any]]
"""``[x, y, z, qx, qy, qz, qw]``: position in metres and orientation (xyzw), world frame."""
Shape: TypeAlias = Mapping[str, Any]
"""A scene's ``shape:`` map (see above); :func:`validate_shape` says whether one is valid."""
Part: TypeAlias = dict[str, list[float]]
"""A box of a container: ``{size: [x, y, z], pos: [x, y, z], quat: [qx, qy, qz, qw]}`` in metres, in the
container's frame."""
Matrix: TypeAlias = npt.NDArray[np.float64]
"""A 3x3 rotation matrix."""

CONTAINER_DEFAULTS: dict[str, dict[str, float | list[float]]] = {
    "bin": {"size": [0.34, 0.26, 0.10], "wall": 0.006},
    "box": {"size": [0.20, 0.20, 0.15], "wall": 0.006},
    "bowl": {"radius": 0.12, "height": 0.07, "wall": 0.006, "segments": 14, "flare": 0.35},
    "cup": {"radius": 0.055, "height": 0.13, "wall": 0.005, "segments": 12, "flare": 0.0},
}
"""Each container style's parameters: ``size`` (m, bin and box), ``radius`` and ``height`` (m, bowl and cup),
``wall`` thickness (m), ``segments`` (wall panels of a round container) and ``flare`` (wall tilt outwards, rad)."""
SHAPE_TYPES = ("sphere", "box", "cylinder", "container", "socket", "urdf")
"""Every ``shape.type`` a scene may use."""
STATIC_SHAPES = ("container", "socket")
"""The shapes the world holds still whatever their mass (see :func:`is_static`)."""
SHAPE_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("radius",), "box": ("size",), "cylinder": ("radius", "length"),
    "container": ("style", "size", "radius", "height", "wall", "segments", "flare"),
    "socket": ("size", "hole", "depth", "chamfer"), "urdf": ("file",)}
"""The keys each ``shape.type`` takes besides ``type`` (any other is a mistake: a misspelt ``style`` left a
container a bin without a word)."""


def is_static(shape: Shape, tags: Sequence[str] = (), mass: object = None) -> bool:
    """Whether the world holds an entity still: a container or a socket, an entity tagged ``static``, or one
    of mass 0 (or below). Every model that builds bodies, and the conductor, decide it here and only here."""
    if shape.get("type") in STATIC_SHAPES or "static" in tags:
        return True
    return mass is not None and float(mass) <= 0  # type: ignore[arg-type]


def quat_from_axis_angle(axis: Vector, angle: float) -> list[float]:
    """The quaternion (xyzw) of a rotation by ``angle`` (rad) about ``axis`` (any non-zero length)."""
    ax = np.asarray(axis, float)
    ax = ax / np.linalg.norm(ax)
    s = math.sin(angle / 2)
    return [float(ax[0] * s), float(ax[1] * s), float(ax[2] * s), math.cos(angle / 2)]


def quat_mul(a: Quaternion, b: Quaternion) -> list[float]:
    """The Hamilton product ``a * b`` (xyzw): rotation ``b`` first, then ``a``."""
    x1, y1, z1, w1 = a
    x2, y2, z2, w2 = b
    return [w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]


def quat_to_matrix(q: Quaternion) -> Matrix:
    """The rotation matrix of the unit quaternion ``q`` (xyzw)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def to_local(pose: Pose, point: Vector) -> npt.NDArray[np.float64]:
    """Express a world point in the frame of ``pose`` ([x,y,z,qx,qy,qz,qw]); metres."""
    R = quat_to_matrix(pose[3:7])
    local: npt.NDArray[np.float64] = R.T @ (np.asarray(point, float) - np.asarray(pose[:3], float))
    return local


def container_params(shape: Shape) -> dict[str, Any]:
    """A container's parameters: its style's :data:`CONTAINER_DEFAULTS`, overridden by the shape's own, and
    ``style``. Raises KeyError for an unknown style (:func:`validate_shape` reports it first)."""
    style = shape.get("style", "bin")
    p: dict[str, Any] = dict(CONTAINER_DEFAULTS[style])
    for k in ("size", "radius", "height", "wall", "segments", "flare"):
        if k in shape:
            p[k] = shape[k]
    p["style"] = style
    return p


def container_parts(shape: Shape) -> list[Part]:
    """Primitive boxes making up an open container: ``{size, pos, quat}`` in the container frame (metres)."""
    p = container_params(shape)
    w = float(p["wall"])
    parts: list[Part] = []
    if p["style"] in ("bin", "box"):
        sx, sy, h = map(float, p["size"])
        parts.append({"size": [sx, sy, w], "pos": [0, 0, w / 2], "quat": [0, 0, 0, 1]})
        parts.append({"size": [w, sy, h], "pos": [sx / 2 - w / 2, 0, h / 2], "quat": [0, 0, 0, 1]})
        parts.append({"size": [w, sy, h], "pos": [-sx / 2 + w / 2, 0, h / 2], "quat": [0, 0, 0, 1]})
        parts.append({"size": [sx, w, h], "pos": [0, sy / 2 - w / 2, h / 2], "quat": [0, 0, 0, 1]})
        parts.append({"size": [sx, w, h], "pos": [0, -sy / 2 + w / 2, h / 2], "quat": [0, 0, 0, 1]})
        return parts
    r, h, n = float(p["radius"]), float(p["height"]), int(p["segments"])
    flare = float(p["flare"])  # wall tilt outwards (rad)
    rb = r - h * math.tan(flare) if flare else r  # floor radius
    side = 2 * r * math.tan(math.pi / n) * 1.08
    floor = 2 * rb * math.cos(math.pi / 4)
    parts.append({"size": [floor * 1.2, floor * 1.2, w], "pos": [0, 0, w / 2], "quat": [0, 0, 0, 1]})
    wall_len = h / math.cos(flare)
    for i in range(n):
        a = 2 * math.pi * i / n
        rm = (rb + r) / 2
        yaw = quat_from_axis_angle([0, 0, 1], a)
        tilt = quat_from_axis_angle([0, 1, 0], flare)
        parts.append({"size": [w, side, wall_len], "pos": [rm * math.cos(a), rm * math.sin(a), h / 2],
                      "quat": quat_mul(yaw, tilt)})
    return parts


def _octagon_ring(apothem: float, half: float, z0: float, z1: float) -> list[Part]:
    """Boxes filling a square of half size ``half`` minus a centred octagonal opening, from z0 to z1."""
    h, zc, a = z1 - z0, (z0 + z1) / 2, apothem
    one = [0.0, 0.0, 0.0, 1.0]
    parts: list[Part] = [{"size": [2 * half, half - a, h], "pos": [0, (half + a) / 2, zc], "quat": one},
                         {"size": [2 * half, half - a, h], "pos": [0, -(half + a) / 2, zc], "quat": one},
                         {"size": [half - a, 2 * a, h], "pos": [(half + a) / 2, 0, zc], "quat": one},
                         {"size": [half - a, 2 * a, h], "pos": [-(half + a) / 2, 0, zc], "quat": one}]
    # the square's corners inside the opening: one box per diagonal side of the octagon
    th = (math.sqrt(2) - 1) * a + 0.001
    side = 2 * a * math.tan(math.pi / 8) + 2 * th
    for k in range(4):
        yaw = math.pi / 4 + k * math.pi / 2
        rc = a + th / 2
        parts.append({"size": [th, side, h], "pos": [rc * math.cos(yaw), rc * math.sin(yaw), zc],
                      "quat": quat_from_axis_angle([0, 0, 1], yaw)})
    return parts


def socket_parts(shape: Shape) -> list[Part]:
    """The boxes of a socket in its frame (the block's centre): a base, an octagonal hole, a 45-degree chamfer.

    From the bottom: a solid block up to the hole's bottom; walls round an octagonal hole (apothem ``hole``) up
    to the chamfer; eight slabs tilted 45 degrees whose upper faces form the chamfer, from the hole's apothem to
    ``hole + chamfer`` at the top; a top ring round it. A peg whose lower face lands on the chamfer slides into
    the hole; one that lands on the flat top (more than about ``hole + chamfer - radius`` off the axis) stays
    there. The synthetic reality builds its SPU from exactly these boxes."""
    sx, sy, H = (float(v) for v in shape["size"])
    half = min(sx, sy) / 2
    a, d, e = float(shape["hole"]), float(shape["depth"]), float(shape["chamfer"])
    z0 = -H / 2
    zb = z0 + H - d  # the hole's bottom
    parts: list[Part] = [{"size": [sx, sy, H - d], "pos": [0, 0, (z0 + zb) / 2], "quat": [0, 0, 0, 1]}]
    parts += _octagon_ring(a, half, zb, z0 + H - e)
    parts += _octagon_ring(a + e, half, z0 + H - e, z0 + H)
    t = e  # slab thickness: enough to fill the wedge under the slope
    b = a + e
    width = 2 * b * math.tan(math.pi / 8) + 0.001
    for k in range(8):
        yaw = k * math.pi / 4
        mid_r, mid_z = a + e / 2, z0 + H - e / 2
        n_r, n_z = -1 / math.sqrt(2), 1 / math.sqrt(2)  # slope normal: up and towards the axis
        cr, cz = mid_r - n_r * t / 2, mid_z - n_z * t / 2
        q = quat_mul(quat_from_axis_angle([0, 0, 1], yaw), quat_from_axis_angle([0, 1, 0], -math.pi / 4))
        parts.append({"size": [e * math.sqrt(2), width, t], "pos": [cr * math.cos(yaw), cr * math.sin(yaw), cz],
                      "quat": q})
    return parts


def inside_container(shape: Shape, pose: Pose, point: Vector, margin: float = 0.0) -> bool:
    """Is the world ``point`` within the open interior (floor to rim) of the container at ``pose``? ``margin``
    (m) widens the interior (negative: narrows it)."""
    p = container_params(shape)
    x, y, z = to_local(pose, point)
    w = float(p["wall"])
    if p["style"] in ("bin", "box"):
        sx, sy, h = map(float, p["size"])
        return bool(abs(x) <= sx / 2 - w + margin and abs(y) <= sy / 2 - w + margin and -margin <= z <= h + margin)
    h = float(p["height"])
    return bool(math.hypot(x, y) <= wall_radius(p, z) - w + margin and -margin <= z <= h + margin)


def wall_radius(p: Mapping[str, Any], z: Any) -> Any:
    """A round container's wall radius at height ``z`` (its frame; a number or an array): the rim's ``radius`` at the
    top, narrower below by the wall's ``flare`` (a bowl's is 2.5 cm narrower at its floor)."""
    r, h, flare = float(p["radius"]), float(p["height"]), float(p.get("flare") or 0.0)
    return r - (h - np.clip(z, 0.0, h)) * math.tan(flare) if flare else r


def bounding_radius(shape: Shape) -> float:
    """A radius (m) around the shape's origin that roughly bounds it (a container's is its half-diagonal or
    ``hypot(radius, height)``); 0.1 for a URDF or an unknown type."""
    t = shape.get("type")
    if t == "sphere":
        return float(shape["radius"])
    if t == "box":
        return float(np.linalg.norm(shape["size"])) / 2
    if t == "cylinder":
        return math.hypot(float(shape["radius"]), float(shape["length"]) / 2)
    if t == "container":
        p = container_params(shape)
        if "size" in p and p["style"] in ("bin", "box"):
            return float(np.linalg.norm(p["size"])) / 2
        return math.hypot(float(p["radius"]), float(p["height"]))
    return 0.1


FINITE_LIMIT = 1e9
"""The largest size :func:`finite_number` takes by default (a huge value is a unit or encoding error)."""


def finite_number(v: object, *, positive: bool = False, limit: float = FINITE_LIMIT) -> TypeGuard[float]:
    """A YAML/JSON number (not a boolean) below ``limit`` in size, > 0 if ``positive``: excludes NaN,
    infinities and huge integers without converting them."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        return False  # (a numpy number too: a robot's list(np.array(q, np.float32)) is numbers)
    return bool((0 < v if positive else -limit < v) and v < limit)


def finite_numbers(values: Sequence[object]) -> bool:
    """Whether every value is a :func:`finite_number`: at C speed for floats (a joint state's values are checked
    for every message), one by one for anything else."""
    if set(map(type, values)) <= _FLOATS:
        try:  # (the sum of finite numbers below the limit in size is finite; one NaN or infinity makes it not)
            return not values or (math.isfinite(math.fsum(values))  # type: ignore[arg-type]
                                  and -FINITE_LIMIT < min(values) and max(values) < FINITE_LIMIT)  # type: ignore
        except (OverflowError, ValueError):  # (fsum of huge ones overflows; of inf and -inf it refuses)
            return False
    return all(finite_number(v) for v in values)


_FLOATS = frozenset({float})


def valid_pose(pose: object) -> TypeGuard[list[float]]:
    """``[x, y, z]`` or ``[x, y, z, qx, qy, qz, qw]`` of finite numbers, the quaternion not of length 0 (it is
    normalised where it is used; one of length 0 is no rotation at all, and turns every value it touches NaN)."""
    return (isinstance(pose, list) and len(pose) in (3, 7) and all(finite_number(v) for v in pose)
            and (len(pose) == 3 or sum(float(v) ** 2 for v in pose[3:]) > 1e-12))


def full_pose(pose: Sequence[Any], rotation: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> list[float]:
    """A :func:`valid_pose` as seven floats: ``rotation`` given to a position alone, the quaternion scaled to unit
    length (physics normalises the one it is given; the conductor's predicates must read the same turn: ``inside``
    read a bin written ``[0, 0, 1, 1]`` as another shape than the physics built)."""
    q = [float(v) for v in (pose[3:7] if len(pose) == 7 else rotation)]
    n = math.sqrt(sum(v * v for v in q))
    if abs(n - 1.0) > 1e-4:  # (one of unit length, or written to 5 decimals, is kept as written to the last bit)
        q = [v / n for v in q]
    return [float(v) for v in pose[:3]] + q


def pose_problem(pose: object, what: str = "pose") -> str:
    """What is wrong with a pose that is not :func:`valid_pose`."""
    if isinstance(pose, list) and len(pose) == 7 and all(finite_number(v) for v in pose):
        return f"{what}'s quaternion {pose[3:]} is all zero: no rotation at all (the identity is [0, 0, 0, 1])"
    return f"{what} must be [x, y, z] or [x, y, z, qx, qy, qz, qw] (numbers)"


def validate_shape(shape: object) -> str | None:
    """Return a problem description, or None if the shape spec is valid."""
    if not isinstance(shape, dict):
        return "shape must be a map with a 'type'"
    t = shape.get("type")
    if not isinstance(t, str) or t not in SHAPE_TYPES:
        return f"shape.type must be one of {', '.join(SHAPE_TYPES)}, got {t!r}"
    unknown = [str(k) for k in shape if k != "type" and k not in SHAPE_KEYS[t]]
    if unknown:
        return f"unknown key {unknown[0]!r} in a {t} shape (allowed: type, {', '.join(SHAPE_KEYS[t])})"
    return _shape_values(t, shape)


def _shape_values(t: str, shape: dict[Any, Any]) -> str | None:
    """The problem with the values of a ``t`` shape whose keys are right, or None."""
    if t == "sphere" and not finite_number(shape.get("radius"), positive=True):
        return "sphere needs a positive 'radius'"
    if t == "box":
        s = shape.get("size")
        if not (isinstance(s, list) and len(s) == 3 and all(finite_number(v, positive=True) for v in s)):
            return "box needs 'size: [x, y, z]' with positive numbers"
    if t == "cylinder" and not all(finite_number(shape.get(k), positive=True) for k in ("radius", "length")):
        return "cylinder needs positive 'radius' and 'length'"
    if t == "container":
        return _container_values(shape)
    if t == "socket":
        s = shape.get("size")
        if not (isinstance(s, list) and len(s) == 3 and all(finite_number(v, positive=True) for v in s)):
            return "socket needs 'size: [x, y, z]' with positive numbers"
        if not all(finite_number(shape.get(k), positive=True) for k in ("hole", "depth", "chamfer")):
            return "socket needs positive 'hole' (apothem), 'depth' and 'chamfer' (m)"
        if shape["hole"] + shape["chamfer"] >= min(s[0], s[1]) / 2 or shape["depth"] >= s[2]:
            return "socket: the hole (hole + chamfer, depth) must fit inside the block"
    if t == "urdf" and not isinstance(shape.get("file"), str):
        return "urdf needs a 'file'"
    return None


def _container_values(shape: dict[Any, Any]) -> str | None:
    """The problem with a container's values (its style's defaults filled in), or None: the walls must fit inside
    it and a round one needs three panels at least, or the physics cannot build it and nothing is ever inside."""
    style = shape.get("style", "bin")
    if not isinstance(style, str) or style not in CONTAINER_DEFAULTS:
        return f"container style must be one of {', '.join(CONTAINER_DEFAULTS)}"
    p = container_params(shape)
    w = p["wall"]
    if not finite_number(w, positive=True):
        return f"container 'wall' must be a positive number (m), got {w!r}"
    if style in ("bin", "box"):
        s = p["size"]
        if not (isinstance(s, list) and len(s) == 3 and all(finite_number(v, positive=True) for v in s)):
            return f"a {style} container needs 'size: [x, y, z]' with positive numbers (m), got {s!r}"
        if 2 * w >= min(s[0], s[1]) or w >= s[2]:
            return f"container 'wall' {w} does not fit its size {s}: no room inside"
        return None
    for k in ("radius", "height"):
        if not finite_number(p[k], positive=True):
            return f"a {style} container needs a positive '{k}' (m), got {p[k]!r}"
    n, flare = p["segments"], p["flare"]
    if not finite_number(n) or n != int(n) or not 3 <= n <= 256:
        return f"container 'segments' must be a whole number from 3 to 256, got {n!r}"
    if not finite_number(flare) or not 0 <= flare < math.pi / 2:
        return f"container 'flare' must be an angle from 0 to below pi/2 (rad), got {flare!r}"
    floor = p["radius"] - p["height"] * math.tan(flare)
    if floor <= w or w >= p["height"]:
        return (f"container 'wall' {w} does not fit: the floor's radius is {floor:.4g} m "
                f"(radius - height * tan(flare)) and the height {p['height']}")
    return None
