"""One entry point for every scenario."""
from __future__ import annotations

from pathlib import Path

from .arm import ROBOTS
from .ball_drop import synth_ball_drop
from .common import SCENARIOS, Progress, SynthResult
from .insertion import synth_insertion


def synthesize(scenario: str, seed: int, out: str | Path, container: str = "bin", outcome: str = "success",
               localization_error: float = 0.002, time_scale: float = 1.0,
               progress: Progress | None = None, reality: str = "pybullet", robot: str = "panda") -> SynthResult:
    """Generate one recording of ``scenario`` (``ball_drop`` or ``insertion``) in ``reality``
    (``pybullet`` or ``mujoco``), played by ``robot`` (``panda``, or ``xarm6`` for ball_drop in pybullet)."""
    if not 0.25 <= time_scale <= 4.0:
        raise ValueError(f"time scale must be within [0.25, 4], got {time_scale}")
    if robot not in ROBOTS:
        raise ValueError(f"robot must be one of {', '.join(ROBOTS)}, got {robot!r}")
    if robot != "panda" and (scenario != "ball_drop" or reality != "pybullet"):
        raise ValueError(f"the {robot} plays ball_drop in the pybullet reality only (so far)")
    if scenario == "ball_drop":
        return synth_ball_drop(seed, out, container, outcome, time_scale, progress, reality, robot)
    if scenario == "insertion":
        return synth_insertion(seed, out, localization_error, time_scale, progress, reality)
    raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
