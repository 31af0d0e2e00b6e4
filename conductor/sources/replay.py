"""Replay: a recording fed tick by tick, as fast as the models allow (or paced by the conductor)."""
from __future__ import annotations

from bisect import bisect_right

from .recording import Recording


class ReplaySource:
    """Feeds a recording tick by tick, as fast as the models allow (or paced by the conductor)."""

    live = False

    def __init__(self, rec: Recording, publish=None):
        self.rec = rec
        self._stamps = [s for s, _, _ in rec.items]
        self._i = 0
        self.publish = publish  # callable(kind, msg) to put telemetry on the network

    @property
    def duration(self) -> float:
        return self.rec.duration

    def due(self, t: float) -> list[tuple[str, dict]]:
        j = bisect_right(self._stamps, t + 1e-9)
        out = [(k, m) for _, k, m in self.rec.items[self._i:j]]
        self._i = j
        return out

    def exhausted(self, t: float) -> bool:
        return self._i >= len(self._stamps) and t >= self.rec.duration

    def lag_stats(self) -> dict:
        return {}
