"""One entry point for every scenario."""
from __future__ import annotations

from pathlib import Path

from .ball_drop import synth_ball_drop
from .common import SCENARIOS, Progress, SynthResult
from .insertion import synth_insertion


def synthesize(scenario: str, seed: int, out: str | Path, container: str = "bin", outcome: str = "success",
               localization_error: float = 0.002, time_scale: float = 1.0,
               progress: Progress | None = None, reality: str = "pybullet") -> SynthResult:
    """Generate one recording of ``scenario`` (``ball_drop`` or ``insertion``) in ``reality``
    (``pybullet`` or ``mujoco``)."""
    if not 0.25 <= time_scale <= 4.0:
        raise ValueError(f"time scale must be within [0.25, 4], got {time_scale}")
    if scenario == "ball_drop":
        return synth_ball_drop(seed, out, container, outcome, time_scale, progress, reality)
    if scenario == "insertion":
        return synth_insertion(seed, out, localization_error, time_scale, progress, reality)
    raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
