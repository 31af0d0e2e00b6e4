"""Key expressions of the twin (docs/design.md, *Keys*).

Every key lives under ``twin/<ensemble>/``; :class:`Keys` builds them for one ensemble so that
no other module assembles key strings by hand.
"""
from __future__ import annotations

import re
from collections.abc import Iterable

__all__ = ["ROOT", "CONDUCTOR", "LISTENER", "RESERVED_IDENTITIES", "check_name", "Keys"]

ROOT = "twin"
"""The first chunk of every key of the twin."""
CONDUCTOR = "_conductor"
"""The conductor's name in keys: its liveliness token ``alive/_conductor`` and events ``event/_conductor/<name>``."""
LISTENER = "_listener"
"""A twin that interprets this ensemble's robot without being its conductor (a live run of ``twin serve``, whose
conductor is on a pool's ensemble): its liveliness token ``alive/_listener``, there while the run lasts."""
RESERVED_IDENTITIES = frozenset(("conductor", "router", "robot", "viewer"))
"""The certificate names of a deployment's own parts (:mod:`protocol.security`): no model may be named so (it
would share their certificate and access rights)."""
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")


def check_name(kind: str, name: str) -> str:
    """Return ``name`` if it can be one chunk of a key expression; ValueError (naming ``kind``) if not."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(
            f"invalid {kind} name {name!r}: use letters, digits, '_', '-', '.' (no '/', '*', '$', spaces)"
        )
    return name


class Keys:
    """Key-expression builders for one ensemble, every key under ``twin/<ensemble>/``.

    A ``*`` or ``**`` argument makes a selector for subscriptions. Raises ValueError for an ensemble name
    that cannot be a key chunk (:func:`check_name`); the other arguments are not checked.
    """

    __slots__ = ("ensemble", "prefix")

    def __init__(self, ensemble: str = "default") -> None:
        self.ensemble = check_name("ensemble", ensemble)
        self.prefix = f"{ROOT}/{ensemble}"

    # -- conductor
    def alive(self, agent: str = "*") -> str:
        """An agent's liveliness token (the conductor's is ``alive/_conductor``)."""
        return f"{self.prefix}/alive/{agent}"

    @property
    def alive_all(self) -> str:
        """Every liveliness token."""
        return f"{self.prefix}/alive/*"

    def conductor(self, op: str) -> str:
        """The conductor's queryable ``op`` (``register``, ``status``, ``start``, ``stop``)."""
        return f"{self.prefix}/conductor/{op}"

    @property
    def register(self) -> str:
        """Where the conductor takes registrations: ``conductor/register/*`` (see :meth:`register_as`)."""
        return self.conductor("register/*")

    def register_as(self, model_id: str) -> str:
        """Where model ``model_id`` registers: ``conductor/register/<id>``. The key names the model, so that under
        mutual TLS the access control lets a certificate register only the model it names; the conductor refuses
        a registration whose key and name differ."""
        return self.conductor(f"register/{model_id}")

    # -- models
    def model(self, model_id: str, op: str) -> str:
        """A model's queryable ``op`` (``params``, ``health``, ``init``, ``start``, ``stop``, ``release``,
        ``acquire``; :meth:`eval` and :meth:`call` build the evaluators' and services')."""
        return f"{self.prefix}/model/{model_id}/{op}"

    def model_all(self, model_id: str) -> str:
        """Every queryable of a model (``model/<id>/**``)."""
        return f"{self.prefix}/model/{model_id}/**"

    def eval(self, model_id: str, name: str) -> str:
        """A model's evaluator ``name``."""
        return f"{self.prefix}/model/{model_id}/eval/{name}"

    def call(self, model_id: str, name: str) -> str:
        """A model's service ``name``."""
        return f"{self.prefix}/model/{model_id}/call/{name}"

    # -- publications
    @property
    def clock(self) -> str:
        """The conductor's ticks for clock-driven models."""
        return f"{self.prefix}/clock"

    @property
    def step_all(self) -> str:
        """The conductor's step broadcast to every service-stepped model (one message per tick)."""
        return f"{self.prefix}/step"

    def step_to(self, model_ids: Iterable[str]) -> str:
        """A step message addressed to these models only (their ids as chunks, sorted): each hears it on
        :meth:`step_for`, the others do not wake for it."""
        return f"{self.prefix}/step/{'/'.join(sorted(model_ids))}"

    def step_for(self, model_id: str) -> str:
        """What a model subscribes to beside :attr:`step_all`: the step messages addressed to it and others."""
        return f"{self.prefix}/step/**/{model_id}/**"

    def done(self, model_id: str = "*") -> str:
        """A service-stepped model's step result (the conductor waits for these)."""
        return f"{self.prefix}/done/{model_id}"

    def state(self, model_id: str = "*") -> str:
        """A model's owned values after each step."""
        return f"{self.prefix}/state/{model_id}"

    def out(self, model_id: str = "*", name: str = "*") -> str:
        """A model's output ``name``."""
        return f"{self.prefix}/out/{model_id}/{name}"

    def event(self, model_id: str = "*", name: str = "*") -> str:
        """A model's (or the conductor's, ``_conductor``) event ``name``."""
        return f"{self.prefix}/event/{model_id}/{name}"

    @property
    def ownership(self) -> str:
        """The responsibility map, published on every change."""
        return f"{self.prefix}/ownership"

    def telemetry(self, stream: str = "**") -> str:
        """The robot's telemetry ``stream`` (``joint_states``, ``action``)."""
        return f"{self.prefix}/telemetry/{stream}"

    @property
    def everything(self) -> str:
        """Every key of the ensemble."""
        return f"{self.prefix}/**"

    def parse(self, key: str) -> tuple[str, list[str]]:
        """Split a key of this ensemble into (kind, rest), e.g. ('state', ['physics']); ValueError for a key of
        another ensemble."""
        key = str(key)
        if not key.startswith(self.prefix + "/"):
            raise ValueError(f"{key}: not a key of ensemble {self.ensemble!r}")
        parts = key[len(self.prefix) + 1 :].split("/")
        return parts[0], parts[1:]
