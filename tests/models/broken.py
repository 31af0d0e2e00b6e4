"""Models that break their contract on purpose: :func:`agents.testing.check_model` must catch each one."""
from __future__ import annotations

import os
import time
from typing import Any

from agents import Model, StepWarning

from .simple import Heartbeat as _Heartbeat
from .simple import Holder as _SimpleHolder


class _Holder(Model):
    """Owns poses and holds them where the scene put them (the base of the broken models below)."""

    kind = "holder"
    attributes = ("pose",)

    def init(self, params: dict[str, Any], scene: dict[str, Any]) -> None:
        self.poses = {n: list(e["pose"]) for n, e in scene["entities"].items()}

    def read(self, entity: str, attribute: str) -> Any:
        return self.poses[entity]

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict[str, Any]) -> None:
        self.poses[entity] = list(value)


class Dice(_Holder):
    """Not deterministic: its output is a fresh random number every step."""

    kind = "dice"
    outputs = ("roll",)

    def step(self, tick: int, t: float, dt: float, telemetry: dict[str, Any], inputs: dict[str, Any]) -> None:
        self.output("roll", os.urandom(4).hex())


class Leaky(_Holder):
    """Hands over a different pose than the one it holds: 1 mm higher at every release."""

    kind = "leaky"

    def release(self, entity: str, attribute: str) -> tuple[Any, dict[str, Any]]:
        x, y, z, *q = self.poses[entity]
        return [x, y, z + 0.001, *q], {}


class Chatty(_Holder):
    """Publishes an output it never declared."""

    kind = "chatty"

    def step(self, tick: int, t: float, dt: float, telemetry: dict[str, Any], inputs: dict[str, Any]) -> None:
        self.output("secret", tick)


class Blank(_Holder):
    """Its read gives None for the pose it owns from tick 2 on (a run leaves it out; the checker says so)."""

    kind = "blank"

    def read(self, entity: str, attribute: str) -> Any:
        return None if self.tick >= 2 else self.poses[entity]


class Clumsy(_Holder):
    """Its step fails from tick 3 on."""

    kind = "clumsy"

    def step(self, tick: int, t: float, dt: float, telemetry: dict[str, Any], inputs: dict[str, Any]) -> None:
        if tick >= 3:
            raise RuntimeError("dropped it")


class Sleepy(_Holder):
    """Never finishes its ``init`` within the checker's wait (the query to it times out)."""

    kind = "sleepy"

    def init(self, params: dict[str, Any], scene: dict[str, Any]) -> None:
        time.sleep(60.0)
        super().init(params, scene)


class ChattyHolder(_SimpleHolder):
    """A holder for tests/core_scene.yaml that, in a real run, publishes an output and raises an event it never
    declared, and warns (``StepWarning``) on every tenth step."""

    kind = "chatty_holder"

    def step(self, tick: int, t: float, dt: float, telemetry: dict[str, Any], inputs: dict[str, Any]) -> None:
        super().step(tick, t, dt, telemetry, inputs)
        self.output("secret", tick)
        if tick == 4:
            self.emit("gossip", about="ball")
        if tick % 10 == 0:
            raise StepWarning(f"nothing to hold at tick {tick}")


class StallingBeat(_Heartbeat):
    """A free-running heartbeat that hangs for 4 s at its sixth step, its liveliness token alive all along."""

    kind = "stalling_beat"

    def step(self, tick: int, t: float, dt: float, telemetry: dict[str, Any], inputs: dict[str, Any]) -> None:
        super().step(tick, t, dt, telemetry, inputs)
        if self.beats == 6:
            time.sleep(4.0)
