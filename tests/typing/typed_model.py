"""A small, fully typed model: ``mypy --strict`` must accept it (tests/typing/test_typing.py runs it).

It is the author API as a type checker sees it: the declarations, the hooks with their annotations, the
helpers, an evaluator and a service, and the entry point.
"""
from __future__ import annotations

from typing import Any

from agents import Model, Param, StepWarning, evaluator, run_agent, service
from agents.model import Inputs, Telemetry


class Thermometer(Model):
    """Owns the temperature of the entities it is given; they cool down towards the room's."""

    kind = "thermometer"
    role = "simulation"
    step_modes = ("service", "clock")
    params = {"room": Param(float, 20.0, "room temperature (°C)"),
              "rate": Param(float, 0.1, "share of the difference lost per second (1/s)"),
              "label": Param(str, None, "a name for the log")}
    attributes = ("temperature",)
    outputs = ("mean",)
    events = ("cold",)
    reads = ("*.heat",)

    def init(self, params: dict[str, Any], scene: dict[str, Any]) -> None:
        self.room: float = params["room"]
        self.k: float = params["rate"]
        self.temperature: dict[str, float] = {name: self.room for name in scene["entities"]}

    def step(self, tick: int, t: float, dt: float, telemetry: Telemetry, inputs: Inputs) -> None:
        for entity, _ in self.owned:
            heat = float(inputs.get(entity, {}).get("heat", 0.0))
            now = self.temperature[entity]
            self.temperature[entity] = now + dt * (heat - self.k * (now - self.room))
            if self.temperature[entity] < 0.0:
                self.emit("cold", entity=entity)
        if not self.owned:
            raise StepWarning("owns nothing to measure")
        self.output("mean", sum(self.temperature.values()) / len(self.temperature))

    def read(self, entity: str, attribute: str) -> float:
        return self.temperature[entity]

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict[str, Any]) -> None:
        self.temperature[entity] = float(value) if value is not None else self.room

    def release(self, entity: str, attribute: str) -> tuple[float, dict[str, Any]]:
        return self.temperature[entity], {"room": self.room}

    @evaluator("warmest")
    def warmest(self) -> str | None:
        """The entity with the highest temperature (None if there is none)."""
        return max(self.temperature, key=self.temperature.__getitem__, default=None)

    @service()
    def reset(self, to: float = 20.0) -> bool:
        """Set every temperature to ``to``."""
        self.temperature = dict.fromkeys(self.temperature, to)
        return True


def use() -> tuple[float, str | None, dict[str, str]]:
    """What the runtime does with it, as a type checker sees it."""
    m = Thermometer()
    m.owned = {("kettle", "temperature")}
    m.init({"room": 20.0, "rate": 0.1, "label": None}, {"entities": {"kettle": {}, "mug": {}}})
    m.step(0, 0.0, 0.01, {"joints": None, "actions": []}, {"kettle": {"heat": 100.0}})
    value, extra = m.release("kettle", "temperature")
    m.acquire("kettle", "temperature", value, extra)
    return m.read("kettle", "temperature"), m.warmest(), Thermometer.evaluators()


def main() -> int:
    """Run it as an agent: ``python -m tests.typing.typed_model``."""
    return run_agent(Thermometer(), "thermo")

if __name__ == "__main__":
    raise SystemExit(main())
