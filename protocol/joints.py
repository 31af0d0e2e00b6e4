"""Joint states that name only some joints (an arm's and a gripper's driver publishing apart on one topic): the
latest value of every joint heard, as one joint state (:class:`LatestJoints`). The conductor's feed and an agent
that takes telemetry from the bus both read a robot's joints through it, so that every model sees the whole robot
whatever the driver's habits."""
from __future__ import annotations

import math
from typing import Any

from .geometry import finite_number, finite_numbers

__all__ = ["LatestJoints", "fill_unknown", "joint_state_key", "unknown_fields"]

_FIELDS = ("position", "velocity", "effort")


class LatestJoints:
    """The latest value of every joint heard (:meth:`take` each joint state in turn): a joint state that names
    only some joints leaves the others at their last values, in a steady order (as first heard). A joint state
    carries a field for every joint or for none, so velocities and efforts go with the merged state only while the
    latest message naming each joint gave them: one joint without them leaves them out for all. Messages that name
    the joints the one before named (the usual case) pass as they are, with no merging."""

    def __init__(self) -> None:
        self.last: dict[str, Any] | None = None  # what take returned last
        self._unfolded: dict[str, Any] | None = None  # a message passed as it was, not yet in the values below
        self._order: list[str] = []
        self._values: dict[str, dict[str, Any]] = {f: {} for f in _FIELDS}

    def take(self, msg: dict[str, Any]) -> dict[str, Any]:
        """``msg`` merged into what came before: the robot's joints as they now are."""
        last = self.last
        if last is None or msg["name"] == last["name"]:
            self.last = self._unfolded = msg
            return msg
        for m in (self._unfolded, msg):
            if m is not None:
                self._fold(m)
        self._unfolded = None
        names = list(self._order)
        out: dict[str, Any] = {**msg, "name": names}
        for f in _FIELDS:
            vals = [self._values[f].get(n) for n in names]
            out[f] = vals if all(v is not None for v in vals) else []
        self.last = out
        return out

    def _fold(self, m: dict[str, Any]) -> None:
        known = self._values["position"]
        self._order += [n for n in m["name"] if n not in known]
        for f in _FIELDS:
            given = m.get(f) or ()
            self._values[f].update(zip(m["name"], given, strict=True) if given else
                                   ((n, None) for n in m["name"]))


def joint_state_key(js: dict[str, Any]) -> tuple[Any, ...]:
    """What tells one joint state from another for a model that acts only on a new one: its stamp, names and
    positions. The stamp alone does not: a merged state (an arm's message, then its gripper's with the same
    header stamp) carries new positions under the stamp already seen."""
    return (js.get("stamp"), tuple(js["name"]), tuple(js["position"]))


def unknown_fields(msg: dict[str, Any]) -> list[str]:
    """The fields of a joint state, of ``velocity`` and ``effort``, that hold a value that is not a finite number
    (a gripper driver's NaN effort; one beyond :data:`~protocol.geometry.FINITE_LIMIT` in size is none either), as
    ``velocities`` / ``efforts``."""
    return [word for f, word in (("velocity", "velocities"), ("effort", "efforts"))
            if not finite_numbers(msg.get(f) or ())]


def fill_unknown(msg: dict[str, Any], before: dict[str, Any] | None) -> None:
    """A joint state's velocities or efforts that are not finite numbers, each from the same joint in the joint state
    ``before`` on its topic (a grasp monitor reads a missing effort as a hand let go); a field it cannot fill so is
    left out (``[]``). The positions are not touched."""
    where = {n: i for i, n in enumerate(before["name"])} if before is not None else {}
    for f in ("velocity", "effort"):
        values = msg.get(f) or []
        if finite_numbers(values):
            continue
        known = before.get(f) or [] if before is not None else []
        filled = [v if finite_number(v) else
                  (known[where[n]] if n in where and where[n] < len(known) else math.nan)
                  for n, v in zip(msg["name"], values, strict=False)]
        msg[f] = filled if finite_numbers(filled) else []
