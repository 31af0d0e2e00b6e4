"""The realities by name: ``pybullet`` (the default) or ``mujoco`` (another engine than the twin's)."""
from __future__ import annotations

from .common import REALITIES
from .mujoco_reality import MujocoReality
from .reality import Reality, World


def make_world(reality: str, contact: dict[str, float]) -> World:
    """The reality called ``reality`` (``pybullet`` or ``mujoco``) with the drawn ``contact`` settings."""
    if reality == "pybullet":
        return Reality(contact)
    if reality == "mujoco":
        return MujocoReality(contact)
    raise ValueError(f"reality must be one of {', '.join(REALITIES)}, got {reality!r}")
