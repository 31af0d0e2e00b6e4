"""The source's telemetry, tick by tick, for the tick loop (:class:`Feeder`).

Each tick takes what the source has up to its time: joint states (renamed to the scene's robot,
:class:`~.fit.JointFit`) become the latest joints of the step broadcast, actions are queued for every model that
wants telemetry until it is next stepped. A joint state that names only some joints (an arm's driver and a
gripper's publishing apart on one topic) is merged by name into the last one
(:class:`~protocol.joints.LatestJoints`): the step broadcast carries the latest value of every joint heard, never
only the last message's. A replay also republishes both on ``telemetry/*`` for the run log and anyone watching.

A replay's telemetry does not depend on what the models answer, so while the models step one window the loop
fetches (and republishes) the next window's ticks ahead (:meth:`Feeder.ahead`): that work then overlaps the
models' instead of lying between two windows. What a tick *enters* (:meth:`Feeder.enter`) is the same either way.
Where a model steps on the bus's telemetry (clock-driven or free-running: ``defer``), a tick's telemetry goes out
only when the tick is entered, just before its clock tick, so that it steps each tick on that tick's telemetry,
never on a later tick's.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from protocol import codec
from protocol.joints import LatestJoints
from protocol.keys import Keys

Joints = dict[str, Any]
Action = dict[str, Any]
Fetched = tuple[Joints | None, list[Action], list[tuple[str, bytes]]]
"""One tick of the source: its last joint state (None: none), its actions, and a replay's telemetry still to
publish."""


class Feeder:
    """Telemetry from ``source`` into the tick loop. ``publish(key, payload)`` puts a replay's telemetry on the
    bus (when a tick is entered if ``defer``, else when it is fetched); ``telemetry_models()`` are the models that
    get actions; ``fit`` renames joint states (``fit.take``)."""

    def __init__(self, source: Any, fit: Any, keys: Keys, publish: Callable[[str, bytes], None],
                 telemetry_models: Callable[[], Iterable[str]], models: Iterable[str], *, defer: bool = True) -> None:
        self.defer = defer
        self.source = source
        self.fit = fit
        self.keys = keys
        self.publish = publish
        self.telemetry_models = telemetry_models
        self.latest: Joints | None = None  # the joints of the step broadcast
        self.pending: dict[str, list[Action]] = {m: [] for m in models}  # actions not yet given to each model
        self._ahead: dict[int, Fetched] = {}
        self._joints = LatestJoints()  # every joint heard, at its latest value
        self._next = 0  # the first tick not yet fetched

    def enter(self, tick: int, dt: float) -> list[Action]:
        """Tick ``tick`` begins: its joints become the latest, its actions are queued for the models that want
        telemetry; returns its actions."""
        got = self._ahead.pop(tick, None)
        if got is None:
            got = self._fetch(tick, dt)
        joints, actions, telemetry = got
        for key, payload in telemetry:
            self.publish(key, payload)
        if joints is not None:
            self.latest = joints
        if actions:
            wanting = list(self.telemetry_models())
            for a in actions:
                for n in wanting:
                    self.pending[n].append(a)
        return actions

    def take_actions(self, name: str) -> list[Action]:
        """The actions queued for ``name`` since it was last stepped."""
        acts, self.pending[name] = self.pending[name], []
        return acts

    def exhausted(self, tick: int, dt: float) -> bool:
        """Whether the source has nothing more for ``tick`` on (what was fetched ahead but not entered counts)."""
        if self.source is None or any(j >= tick and (joints is not None or actions)
                                      for j, (joints, actions, _) in self._ahead.items()):
            return False
        return bool(self.source.exhausted(tick * dt))

    def ahead(self, first: int, last: int, dt: float) -> None:
        """Fetch ticks ``first``..``last`` now (a replay only: a live source's telemetry arrives in its own time)."""
        if self.source is None or self.source.live:
            return
        for tick in range(max(first, self._next), last + 1):
            self._ahead[tick] = self._fetch(tick, dt)

    def _fetch(self, tick: int, dt: float) -> Fetched:
        """What the source has up to ``tick``'s time (:data:`Fetched`)."""
        self._next = tick + 1
        joints: Joints | None = None
        actions: list[Action] = []
        telemetry: list[tuple[str, bytes]] = []
        if self.source is None:
            return joints, actions, telemetry
        replay = not self.source.live
        for kind, msg in self.source.due(tick * dt):
            msg = self.fit.take(msg) if kind == "joint_state" else msg
            if replay:  # validated when the recording was read: no checks on the hot path
                out = (self.keys.telemetry("joint_states" if kind == "joint_state" else "action"),
                       codec.encode_unchecked(kind, dict(msg)))
                if self.defer:
                    telemetry.append(out)
                else:
                    self.publish(*out)
            if kind == "joint_state":
                joints = self._joints.take(msg)
            else:
                actions.append(msg)
        return joints, actions, telemetry
