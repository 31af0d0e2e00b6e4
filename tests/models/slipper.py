"""A model that declares ``slip`` an owner event (raised only about what it owns) and can be told to break that."""
from __future__ import annotations

from agents import Model, Param


class Slipper(Model):
    """Holds poses it is handed; raises ``slip`` about what it owns at tick ``slip_at`` (``lie``: even when it owns
    nothing, which its declaration says it never does)."""

    kind = "slipper"
    attributes = ("pose",)
    events = ("slip",)
    owner_events = ("slip",)
    params = {"slip_at": Param(int, -1, "tick at which it raises 'slip' (-1: never)"),
              "lie": Param(bool, False, "raise it at slip_at even while owning nothing")}

    def init(self, params, scene):
        self.p = params
        self.poses = {n: list(e["pose"]) for n, e in scene["entities"].items()}

    def step(self, tick, t, dt, telemetry, inputs):
        if tick == self.p["slip_at"] and (self.owned or self.p["lie"]):
            self.emit("slip", entity="ball")

    def read(self, entity, attribute):
        return self.poses[entity]

    def acquire(self, entity, attribute, value, extra):
        self.poses[entity] = list(value)

    def release(self, entity, attribute):
        return self.poses[entity], {}
