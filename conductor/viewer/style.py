"""How the twin looks in Rerun: a colour per model (fixed for the built-in ones), shapes as archetypes, the
robot's URDF."""
from __future__ import annotations

from pathlib import Path

import pybullet_data
import rerun as rr

from protocol.geometry import container_parts, socket_parts

from .colours import CONDUCTOR, FIXED_COLOURS, GREY, PALETTE, Colours, model_colour

__all__ = ["CONDUCTOR", "FIXED_COLOURS", "GREY", "PALETTE", "Colours", "model_colour", "shape_archetype",
           "resolve_urdf"]

# --------------------------------------------------------------------------- shapes
def shape_archetype(shape: dict | None, rgb: tuple[int, int, int], label: str):
    """A Rerun archetype drawing one entity's shape in its own frame (see protocol/geometry.py)."""
    shape = shape or {}
    t = shape.get("type")
    solid = rr.components.FillMode.Solid
    if t == "sphere":
        r = float(shape["radius"])
        return rr.Ellipsoids3D(half_sizes=[[r, r, r]], colors=[rgb], fill_mode=solid, labels=[label])
    if t == "box":
        h = [float(v) / 2 for v in shape["size"]]
        return rr.Boxes3D(half_sizes=[h], colors=[rgb], fill_mode=solid, labels=[label])
    if t == "cylinder":  # along the body's z axis, centred on its origin, as in pybullet
        return rr.Cylinders3D(lengths=[float(shape["length"])], radii=[float(shape["radius"])], colors=[rgb],
                              fill_mode=solid, labels=[label])
    if t in ("container", "socket"):
        parts = container_parts(shape) if t == "container" else socket_parts(shape)
        labels = [label] + [""] * (len(parts) - 1)
        return rr.Boxes3D(half_sizes=[[s / 2 for s in p["size"]] for p in parts],
                          centers=[p["pos"] for p in parts],
                          quaternions=[rr.Quaternion(xyzw=p["quat"]) for p in parts],
                          colors=[rgb + (215,)] * len(parts), fill_mode=solid, labels=labels)
    # unknown shape (no scene, or a URDF entity): a labelled marker at its origin
    return rr.Points3D([[0.0, 0.0, 0.0]], radii=[0.02], colors=[rgb], labels=[label])


def resolve_urdf(spec: str) -> Path | None:
    """A robot URDF given as a path, or relative to pybullet_data (``franka_panda/panda.urdf``)."""
    p = Path(spec)
    if p.is_file():
        return p.resolve()
    try:
        q = Path(pybullet_data.getDataPath()) / spec
        if q.is_file():
            return q
    except ImportError:
        pass
    return None
