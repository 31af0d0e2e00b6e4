"""A model that records which thread runs each of its hooks (the runtime runs them all on the main thread), and the
times a handover is asked at."""
from __future__ import annotations

import threading
from typing import Any

from agents import Model, Param, evaluator


class ThreadProbe(Model):
    """Owns poses and counts its steps; ``threads()`` names every thread a hook ran on."""

    kind = "thread_probe"
    attributes = ("pose",)
    outputs = ("steps",)
    events = ("released",)

    def __init__(self) -> None:
        super().__init__()
        self.threads: set[str] = set()
        self.handovers: list[list[Any]] = []  # [hook, its last step's t, now]

    def _note(self) -> None:
        self.threads.add(threading.current_thread().name)

    def init(self, params: dict[str, Any], scene: dict[str, Any]) -> None:
        self._note()
        self.steps = 0
        self.poses = {n: list(e["pose"]) for n, e in scene["entities"].items()}

    def start(self) -> None:
        self._note()

    def step(self, tick: int, t: float, dt: float, telemetry: dict[str, Any], inputs: dict[str, Any]) -> None:
        self._note()
        self.steps += 1
        self.output("steps", self.steps)

    def read(self, entity: str, attribute: str) -> Any:
        self._note()
        return self.poses[entity]

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict[str, Any]) -> None:
        self._note()
        self.handovers.append(["acquire", self.t, self.now])
        self.poses[entity] = list(value)

    def release(self, entity: str, attribute: str) -> tuple[Any, dict[str, Any]]:
        self._note()
        self.handovers.append(["release", self.t, self.now])
        self.emit("released", entity=entity)  # (raised outside step: it goes out with the next one)
        return self.poses[entity], {}

    @evaluator("threads")
    def thread_names(self) -> list[str]:
        self._note()
        return sorted(self.threads)

    @evaluator("handovers")
    def handover_times(self) -> list[list[Any]]:
        return self.handovers

    @evaluator("steps")
    def step_count(self) -> int:
        return self.steps


class Connected(ThreadProbe):
    """Connects in ``init`` and disconnects in ``close``, as a pybullet model does (closing when not connected
    raises); with ``fail`` its init fails before it connects (a bad argument)."""

    kind = "connected_probe"
    params = {"fail": Param(bool, False, "init fails before it connects")}

    def init(self, params: dict[str, Any], scene: dict[str, Any]) -> None:
        if params["fail"]:
            raise ValueError("fail: a bad argument")
        super().init(params, scene)
        self.connected = True

    def close(self) -> None:
        if not getattr(self, "connected", False):
            raise RuntimeError("Not connected to physics server.")
        self.connected = False
