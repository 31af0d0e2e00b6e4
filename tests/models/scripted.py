"""A scripted owner for model tests: moves entities along keyframes, holds everything else.

Params: ``script`` maps an entity to keyframes ``[[t, x, y, z, qx, qy, qz, qw], ...]`` (or
``[t, x, y, z]``); between keyframes the pose is interpolated (lerp + slerp), before the first
and after the last it holds. While it owns a scripted entity's pose it follows the script;
unscripted entities keep the value they were handed (or their scene pose). It can own ``pose``
and ``collision`` (default value ``{"enabled": true}``), and publishes ``acquired``: per entity,
the last value and extra it was handed, so tests can check what a model released.
"""
from __future__ import annotations

import numpy as np

from agents import Model, Param
from agents.robot.kinematics import as_pose, quat_slerp


def _interp(frames: list[list[float]], t: float) -> list[float]:
    ts = [f[0] for f in frames]
    if t <= ts[0]:
        return list(as_pose(frames[0][1:]))
    if t >= ts[-1]:
        return list(as_pose(frames[-1][1:]))
    i = int(np.searchsorted(ts, t, side="right")) - 1
    a, b = as_pose(frames[i][1:]), as_pose(frames[i + 1][1:])
    s = (t - ts[i]) / (ts[i + 1] - ts[i])
    return [*(a[:3] + s * (b[:3] - a[:3])), *quat_slerp(a[3:], b[3:], s)]


class Scripted(Model):
    kind = "scripted"
    role = "simulation"
    params = {"script": Param(dict, {}, "entity -> keyframes [[t, x, y, z(, qx, qy, qz, qw)], ...]")}
    attributes = ("pose", "collision")
    outputs = ("acquired",)

    def init(self, params, scene):
        self.script = {e: sorted(frames, key=lambda f: f[0]) for e, frames in params["script"].items()}
        self.values = {(n, "pose"): list(e["pose"]) for n, e in scene["entities"].items()}
        self.acquired = {}

    def step(self, tick, t, dt, telemetry, inputs):
        for ent, attr in self.owned:
            if attr == "pose" and ent in self.script:
                self.values[(ent, "pose")] = _interp(self.script[ent], t)
        if self.acquired:
            self.output("acquired", self.acquired)

    def read(self, entity, attribute):
        return self.values.get((entity, attribute), {"enabled": True} if attribute == "collision" else None)

    def acquire(self, entity, attribute, value, extra):
        if value is not None:
            self.values[(entity, attribute)] = value
        self.acquired = {**self.acquired, f"{entity}.{attribute}": {"value": value, "extra": dict(extra or {}),
                                                                    "t": self.t}}

    def release(self, entity, attribute):
        return self.read(entity, attribute), {}
