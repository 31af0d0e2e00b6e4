"""Key expressions of the twin (docs/design.md, *Keys*).

Every key lives under ``twin/<ensemble>/``; :class:`Keys` builds them for one ensemble so that
no other module assembles key strings by hand.
"""
from __future__ import annotations

import re

ROOT = "twin"
CONDUCTOR = "_conductor"
"""The conductor's name in keys: its liveliness token ``alive/_conductor`` and events ``event/_conductor/<name>``."""
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")


def check_name(kind: str, name: str) -> str:
    """Validate a name used as one chunk of a key expression."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(
            f"invalid {kind} name {name!r}: use letters, digits, '_', '-', '.' (no '/', '*', '$', spaces)"
        )
    return name


class Keys:
    """Key-expression builders for one ensemble."""

    __slots__ = ("ensemble", "prefix")

    def __init__(self, ensemble: str = "default"):
        self.ensemble = check_name("ensemble", ensemble)
        self.prefix = f"{ROOT}/{ensemble}"

    # -- conductor
    def alive(self, agent: str = "*") -> str:
        return f"{self.prefix}/alive/{agent}"

    @property
    def alive_all(self) -> str:
        return f"{self.prefix}/alive/*"

    def conductor(self, op: str) -> str:
        return f"{self.prefix}/conductor/{op}"

    @property
    def register(self) -> str:
        return self.conductor("register")

    # -- models
    def model(self, model_id: str, op: str) -> str:
        return f"{self.prefix}/model/{model_id}/{op}"

    def model_all(self, model_id: str) -> str:
        return f"{self.prefix}/model/{model_id}/**"

    def eval(self, model_id: str, name: str) -> str:
        return f"{self.prefix}/model/{model_id}/eval/{name}"

    def call(self, model_id: str, name: str) -> str:
        return f"{self.prefix}/model/{model_id}/call/{name}"

    # -- publications
    @property
    def clock(self) -> str:
        return f"{self.prefix}/clock"

    @property
    def step_all(self) -> str:
        """The conductor's step broadcast to every service-stepped model (one message per tick)."""
        return f"{self.prefix}/step"

    def done(self, model_id: str = "*") -> str:
        """A service-stepped model's step result (the conductor waits for these)."""
        return f"{self.prefix}/done/{model_id}"

    def state(self, model_id: str = "*") -> str:
        return f"{self.prefix}/state/{model_id}"

    def out(self, model_id: str = "*", name: str = "*") -> str:
        return f"{self.prefix}/out/{model_id}/{name}"

    def event(self, model_id: str = "*", name: str = "*") -> str:
        return f"{self.prefix}/event/{model_id}/{name}"

    @property
    def ownership(self) -> str:
        return f"{self.prefix}/ownership"

    def telemetry(self, stream: str = "**") -> str:
        return f"{self.prefix}/telemetry/{stream}"

    @property
    def everything(self) -> str:
        return f"{self.prefix}/**"

    def parse(self, key: str) -> tuple[str, list[str]]:
        """Split a key of this ensemble into (kind, rest), e.g. ('state', ['physics'])."""
        key = str(key)
        if not key.startswith(self.prefix + "/"):
            raise ValueError(f"{key}: not a key of ensemble {self.ensemble!r}")
        parts = key[len(self.prefix) + 1 :].split("/")
        return parts[0], parts[1:]
