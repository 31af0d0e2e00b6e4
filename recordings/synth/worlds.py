"""The realities by name: ``pybullet`` (the default) or ``mujoco`` (another engine than the twin's)."""
from __future__ import annotations

from .arm import SynthArm
from .common import REALITIES
from .mujoco_reality import MujocoReality
from .reality import Reality, World


def make_world(reality: str, contact: dict[str, float], arm: SynthArm | None = None) -> World:
    """The reality called ``reality`` (``pybullet`` or ``mujoco``) with the drawn ``contact`` settings, playing
    ``arm`` (default the Panda; the MuJoCo reality plays the Panda only)."""
    if reality == "pybullet":
        return Reality(contact, arm)
    if reality == "mujoco":
        return MujocoReality(contact)
    raise ValueError(f"reality must be one of {', '.join(REALITIES)}, got {reality!r}")
