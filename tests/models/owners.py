"""Small owners for the physics model's tests: a thrower that hands over a velocity, and a model
that owns collisions with fixed values.
"""
from __future__ import annotations

from agents import Model, Param


class Thrower(Model):
    """Moves the poses it owns in a straight line at ``velocity`` (m/s, no gravity) from ``start``
    (s) on; ``release`` hands over the pose with ``{"velocity": [vx, vy, vz, 0, 0, 0]}``."""

    kind = "thrower"
    role = "simulation"
    params = {"velocity": Param(list, [0.0, 0.0, 0.0], "linear velocity (m/s)"),
              "start": Param(float, 0.0, "time (s) the motion starts")}
    attributes = ("pose",)

    def init(self, params, scene):
        self.v = [float(x) for x in params["velocity"]]
        self.start_t = float(params["start"])
        self.poses = {n: list(map(float, e["pose"])) for n, e in scene["entities"].items()}

    def step(self, tick, t, dt, telemetry, inputs):
        if t <= self.start_t:
            return
        h = min(dt, t - self.start_t)
        for ent, attr in self.owned:
            if attr == "pose":
                p = self.poses[ent]
                self.poses[ent] = [p[0] + self.v[0] * h, p[1] + self.v[1] * h, p[2] + self.v[2] * h, *p[3:]]

    def read(self, entity, attribute):
        return self.poses[entity]

    def acquire(self, entity, attribute, value, extra):
        self.poses[entity] = list(value)

    def release(self, entity, attribute):
        moving = self.t > self.start_t
        return self.poses[entity], {"velocity": (self.v if moving else [0.0, 0.0, 0.0]) + [0.0, 0.0, 0.0]}


class CollisionOwner(Model):
    """Owns ``collision`` attributes with fixed values: ``values`` maps an entity to its value
    (``false``, ``true`` or ``{"enabled": ..., "ignore": [...]}``), others get ``default``."""

    kind = "collision_owner"
    role = "simulation"
    params = {"values": Param(dict, {}, "entity -> collision value"),
              "default": Param(object, False, "value of entities not in 'values'")}
    attributes = ("collision",)

    def init(self, params, scene):
        self.values = dict(params["values"])
        self.default = params["default"]

    def read(self, entity, attribute):
        return self.values.get(entity, self.default)

    def release(self, entity, attribute):
        return self.read(entity, attribute), {}
