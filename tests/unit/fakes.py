"""Stand-ins for the wire in unit tests of the conductor's parts (the parts never see Zenoh themselves)."""
from __future__ import annotations

from typing import Any

from conductor.registry import AgentInfo, Registry
from protocol import codec
from protocol.errors import AgentError
from protocol.keys import Keys
from protocol.messages import Message


class FakeLink:
    """Answers queries from Python: ``values[(model, op)]`` is the answer's ``value`` (evaluators, services),
    ``refuse`` holds (model, op) pairs that answer with an error. Remembers every query, publication and event."""

    def __init__(self, values: dict[tuple[str, str], Any] | None = None) -> None:
        self.keys = Keys("unit")
        self.values = dict(values or {})
        self.refuse: set[tuple[str, str]] = set()
        self.asked: list[tuple[str, str, dict[str, Any]]] = []
        self.published: list[tuple[str, dict[str, Any]]] = []
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.held: dict[tuple[str, str, str], Any] = {}  # (model, entity, attribute) -> value it was given
        self.extra: dict[str, dict[str, Any]] = {}  # model -> the extra state its releases carry (default: by)

    def ask(self, model: str, op: str, payload: bytes, expect: str, timeout: float | None = None) -> Message:
        msg = codec.unpack(payload)
        self.asked.append((model, op, msg))
        if (model, op) in self.refuse:
            raise AgentError(model, f"model/{model}/{op}", None, "KeyError", "refused")
        if op == "release":
            value = self.held.pop((model, msg["entity"], msg["attribute"]), None)
            return Message({"type": "release_reply", "entity": msg["entity"], "attribute": msg["attribute"],
                            "value": value, "extra": self.extra.get(model, {"by": model})})
        if op == "acquire":
            self.held[(model, msg["entity"], msg["attribute"])] = msg["value"]
            return Message({"type": "ack", "ok": True})
        return Message({"type": "value_reply", "value": self.values.get((model, op))})

    def publish(self, key: str, payload: bytes) -> None:
        self.published.append((key, codec.unpack(payload)))

    def event(self, name: str, data: dict[str, Any], tick: int, t: float) -> None:
        self.events.append((name, data))


def ready_registry(models: dict[str, list[str]]) -> Registry:
    """A registry whose agents are all alive and ready, each declaring the given attributes."""
    reg = Registry(models)
    for name, attrs in models.items():
        reg.agents[name] = AgentInfo(name, {"kind": name, "attributes": attrs}, alive=True, ready=True)
    return reg
