"""Small test models for the framework's integration tests (not shipped as agents)."""
from __future__ import annotations

import time

from agents import Model, Param, evaluator, service


class BallSim(Model):
    """A point-mass simulation: owns poses, integrates gravity to a floor, follows others' poses."""

    kind = "ballsim"
    role = "simulation"
    params = {"gravity": Param(float, -9.81, "m/s^2"), "floor": Param(float, 0.0, "floor height (m)"),
              "label": Param(str, "", "free text echoed as an output")}
    attributes = ("pose",)
    outputs = ("label", "steps")
    events = ("landed",)
    reads = ()

    def init(self, params, scene):
        self.p = params
        self.poses = {n: list(e["pose"]) for n, e in scene["entities"].items()}
        self.vel = {n: 0.0 for n in self.poses}
        self.steps = 0
        self.init_params = params

    def step(self, tick, t, dt, telemetry, inputs):
        self.steps += 1
        for ent, attrs in inputs.items():
            if "pose" in attrs:
                self.poses[ent] = list(attrs["pose"])
        for ent, attr in self.owned:
            if attr != "pose":
                continue
            p = self.poses[ent]
            v = self.vel[ent] + self.p["gravity"] * dt
            z = p[2] + v * dt
            if z <= self.p["floor"] and p[2] > self.p["floor"]:
                self.emit("landed", entity=ent)
            if z <= self.p["floor"]:
                z, v = self.p["floor"], 0.0
            p[2] = z
            self.vel[ent] = v
        self.output("label", self.p["label"])
        self.output("steps", self.steps)

    def read(self, entity, attribute):
        return self.poses[entity]

    def acquire(self, entity, attribute, value, extra):
        self.poses[entity] = list(value)
        self.vel[entity] = float(extra.get("vz", 0.0))

    def release(self, entity, attribute):
        return self.poses[entity], {"vz": self.vel[entity]}

    @evaluator("height")
    def height(self, entity):
        return self.poses[entity][2]

    @evaluator("params")
    def get_params(self):
        return self.init_params

    @service("lowest")
    def lowest(self):
        """The entity lowest of those this simulation moves (a result a trigger binds with ``as``). (Of every pose it
        knew, a ball handed away after it landed tied with the bin on the floor, and won or lost by the timing of
        the handover: a test that flipped under load.)"""
        moved = [e for e, a in self.owned if a == "pose"] or list(self.poses)
        return min(moved, key=lambda n: self.poses[n][2])


class Holder(Model):
    """Holds whatever pose it acquires at a fixed height (stands in for an in-hand model)."""

    kind = "holder"
    role = "simulation"
    params = {"hold_z": Param(float, 1.0, "height at which it holds objects")}
    attributes = ("pose",)
    outputs = ("holding",)

    def init(self, params, scene):
        self.hold_z = params["hold_z"]
        self.poses = {}
        self.steps = 0

    def step(self, tick, t, dt, telemetry, inputs):
        self.steps += 1
        for ent, _ in self.owned:
            self.poses[ent][2] = self.hold_z
        self.output("holding", sorted(e for e, _ in self.owned))

    def read(self, entity, attribute):
        return self.poses[entity]

    def acquire(self, entity, attribute, value, extra):
        self.poses[entity] = list(value)

    def release(self, entity, attribute):
        return self.poses.pop(entity), {"vz": 0.0}

    @evaluator("closest")
    def closest(self, tag):
        ents = [n for n, e in self.scene["entities"].items() if tag in e["tags"]]
        return ents[0] if ents else None


class GripSwitch(Model):
    """An observer driven by the clock: publishes 'gripping' from the latest finger telemetry, and 'stamp', the
    time of the joint state it stepped on."""

    kind = "gripswitch"
    role = "observer"
    params = {"delay": Param(float, 0.0, "seconds each step takes (stands in for a slow model)")}
    outputs = ("gripping", "stamp")

    def init(self, params, scene):
        self.steps = 0
        self.delay = params["delay"]

    def step(self, tick, t, dt, telemetry, inputs):
        self.steps += 1
        if self.delay > 0:
            time.sleep(self.delay)
        js = telemetry.get("joints")
        if js is not None:
            pos = dict(zip(js["name"], js["position"]))
            self.output("gripping", pos.get("finger", 1.0) < 0.5)
            self.output("stamp", js["stamp"])

    @evaluator("ticks")
    def ticks(self):
        return self.steps


class Heartbeat(Model):
    """A free-running observer: counts its own steps and publishes them."""

    kind = "heartbeat"
    role = "observer"
    outputs = ("beats",)

    def init(self, params, scene):
        self.beats = 0

    def step(self, tick, t, dt, telemetry, inputs):
        self.beats += 1
        self.output("beats", self.beats)

    @service("reset")
    def reset(self):
        self.beats = 0
        return True


class Counter(Model):
    """A service-stepped observer that counts its steps; it can be slow (``delay`` s per step) and can
    publish an output nothing can encode on one tick (``bad_tick``), standing in for a model bug."""

    kind = "counter"
    role = "observer"
    wants_telemetry = False
    params = {"delay": Param(float, 0.0, "seconds each step takes"),
              "bad_tick": Param(int, -1, "tick whose output cannot be encoded (-1: none)"),
              "stall_tick": Param(int, -1, "tick at which it hangs for stall_s seconds (-1: never)"),
              "stall_s": Param(float, 0.0, "how long it hangs at stall_tick")}
    outputs = ("count",)

    def init(self, params, scene):
        self.count = 0
        self.delay, self.bad_tick = params["delay"], params["bad_tick"]
        self.stall_tick, self.stall_s = params["stall_tick"], params["stall_s"]

    def step(self, tick, t, dt, telemetry, inputs):
        self.count += 1
        if self.delay > 0:
            time.sleep(self.delay)
        if tick == self.stall_tick:
            time.sleep(self.stall_s)
        self.output("count", complex(self.count, 1) if tick == self.bad_tick else self.count)


class RewindCounter(Counter):
    """A :class:`Counter` that can go back to a checkpoint (``snapshot``/``restore``: tick.mark and rewind)."""

    kind = "rewind_counter"

    def snapshot(self):
        return self.count

    def restore(self, state):
        self.count = state
