"""What every synthetic scenario shares: the robot's constants, the random draws, errors and results."""
from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol.geometry import (
    CONTAINER_DEFAULTS,
    quat_from_axis_angle,
    quat_mul,
    quat_to_matrix,
)

JOINT_NAMES = tuple(f"panda_joint{i}" for i in range(1, 8)) + ("panda_finger_joint1", "panda_finger_joint2")


SCENARIOS = ("ball_drop", "insertion")


REALITIES = ("pybullet", "mujoco")  # the first is the default: its recordings name no reality


CONTAINERS = tuple(CONTAINER_DEFAULTS)


OUTCOMES = ("success", "released_early", "missed", "empty_grasp", "slipped", "knocked")


GENERATOR = "twin.synth/1"


SIM_RATE = 1000.0  # reality steps per second


TELEMETRY_RATE = 250.0  # joint states per second


SOLVER_ITERATIONS = 150


ARM = (0, 1, 2, 3, 4, 5, 6)  # pybullet joint indices of panda_joint1..7


FINGERS = (9, 10)


HAND = 8  # panda_hand link


TIP = 0.105  # fingertip centre along panda_hand's z axis


TORQUE_LIMITS = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])


FINGER_OPEN = 0.04


HAND_DOWN = (1.0, 0.0, 0.0, 0.0)  # panda_hand z axis pointing at the table


HOME = np.array([0.0, -0.55, 0.0, -2.35, 0.0, 1.80, 0.785])


Progress = Callable[[str], None]



@dataclass
class SynthResult:
    """What one generation produced: the file, the measured ground truth and some figures."""

    path: Path
    ground_truth: dict[str, str]
    generation: dict[str, Any]
    duration: float  # recorded seconds
    joint_states: int
    actions: int
    sim_steps: int
    wall_s: float
    size_bytes: int = 0
    measured: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------ math
def _yaw_quat(yaw: float) -> list[float]:
    return quat_from_axis_angle([0, 0, 1], yaw)


def hand_down(yaw: float) -> list[float]:
    """Orientation of panda_hand pointing down, turned by ``yaw`` about the world z axis."""
    return [float(v) for v in quat_mul(_yaw_quat(yaw), list(HAND_DOWN))]


def _rot(q) -> np.ndarray:
    return quat_to_matrix(q)


def _quintic(tau: float) -> tuple[float, float]:
    """Minimum-jerk time scaling s(tau) and ds/dtau on [0, 1]."""
    tau = min(max(tau, 0.0), 1.0)
    return (10 * tau**3 - 15 * tau**4 + 6 * tau**5, 30 * tau**2 - 60 * tau**3 + 30 * tau**4)


def _quat_error(q_target, q) -> np.ndarray:
    """Rotation vector taking orientation ``q`` to ``q_target`` (world frame)."""
    x1, y1, z1, w1 = q_target
    x2, y2, z2, w2 = -q[0], -q[1], -q[2], q[3]  # conjugate of q
    e = np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                  w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                  w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                  w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])
    if e[3] < 0:
        e = -e
    s = np.linalg.norm(e[:3])
    if s < 1e-12:
        return np.zeros(3)
    return e[:3] / s * 2 * math.atan2(s, e[3])


def _r(v, nd: int = 5):
    """Round floats (also inside lists/dicts) for compact, stable metadata."""
    if isinstance(v, dict):
        return {k: _r(x, nd) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_r(x, nd) for x in v]
    if isinstance(v, (float, np.floating)):
        return round(float(v), nd)
    if isinstance(v, np.integer):
        return int(v)
    return v


# ------------------------------------------------------------------------------------ generation
def _noise_levels(rng: np.random.Generator) -> dict[str, float]:
    return {"position_rad": float(rng.uniform(5e-5, 2e-4)), "finger_position_m": float(rng.uniform(1e-5, 5e-5)),
            "effort_nm": float(rng.uniform(0.05, 0.3)), "finger_effort_n": float(rng.uniform(0.1, 0.5)),
            "jitter_s": float(rng.uniform(5e-5, 3e-4)), "perception_m": float(rng.uniform(0.001, 0.003)),
            "perception_yaw_rad": float(rng.uniform(0.005, 0.02))}


def _contact(rng: np.random.Generator) -> dict[str, float]:
    return {"finger_friction": float(rng.uniform(0.9, 1.3)), "finger_spinning": float(rng.uniform(0.02, 0.1)),
            "finger_stiffness": float(rng.uniform(2.5e4, 4e4)), "finger_damping": float(rng.uniform(600, 1200)),
            "table_friction": float(rng.uniform(0.45, 0.8)), "table_restitution": float(rng.uniform(0.55, 0.7))}


def _scale_durations(rng: np.random.Generator, base: dict[str, float], time_scale: float) -> dict[str, float]:
    return {k: float(v * time_scale * rng.uniform(0.85, 1.15)) for k, v in base.items()}


def _perceive(rng: np.random.Generator, pose, sigma: float, yaw_sigma: float = 0.0) -> list[float]:
    pose = list(map(float, pose))
    out = [pose[0] + rng.normal(0, sigma), pose[1] + rng.normal(0, sigma), pose[2] + rng.normal(0, sigma / 2)]
    q = pose[3:7] if len(pose) >= 7 else [0.0, 0.0, 0.0, 1.0]
    if yaw_sigma:
        q = quat_mul(_yaw_quat(rng.normal(0, yaw_sigma)), q)
    return out + [float(v) for v in q]


def _metadata_generation(gen: dict) -> dict[str, str]:
    out = {k: (v if isinstance(v, str) else json.dumps(_r(v, 7), sort_keys=True)) for k, v in gen.items()}
    out["json"] = json.dumps(_r(gen, 7), sort_keys=True)
    return out


def _command(gen: dict) -> str:
    cmd = f"twin record synth --scenario {gen['scenario']} --seed {gen['seed']}"
    if gen.get("reality", REALITIES[0]) != REALITIES[0]:
        cmd += f" --reality {gen['reality']}"
    if gen.get("robot", "panda") != "panda":
        cmd += f" --robot {gen['robot']}"
    if gen["scenario"] == "ball_drop":
        cmd += f" --container {gen['container']} --outcome {gen['outcome']}"
    else:
        cmd += f" --localization-error {gen['localization_error']}"
    if gen.get("time_scale", 1.0) != 1.0:
        cmd += f" --time-scale {gen['time_scale']}"
    return cmd + " --out FILE.mcap"
