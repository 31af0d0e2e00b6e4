"""Replay: a recording fed tick by tick, as fast as the models allow (or paced by the conductor)."""
from __future__ import annotations

from bisect import bisect_right

from .recording import Recording

TOLERANCE = 1e-6
"""Seconds after a tick's time that a message still belongs to that tick (:meth:`ReplaySource.due`)."""


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
        """The messages stamped up to ``t``, and within 1 us after it: a writer that adds the start's epoch
        seconds to a tick's time in one double (ours did) stamps it up to 128 ns late, and the tick it was
        recorded for would get it one tick late."""
        j = bisect_right(self._stamps, t + TOLERANCE)
        out = [(k, m) for _, k, m in self.rec.items[self._i:j]]
        self._i = j
        return out

    def exhausted(self, t: float) -> bool:
        return self._i >= len(self._stamps) and t >= self.rec.duration

    def warnings(self) -> list[str]:
        """What the recording left out or lacks (the run is then degraded): its reader's."""
        return list(self.rec.warnings())

    def notes(self) -> list[str]:
        return list(self.rec.notes())

    def lag_stats(self) -> dict:
        return {}
