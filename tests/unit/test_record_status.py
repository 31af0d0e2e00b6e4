"""A run's status and its reasons: cut short (stopped, interrupted) it is truncated or interrupted, and what went
wrong before the cut is still listed after the cut's reason; a failure is said alone."""
from __future__ import annotations

from conductor.record import RunRecord
from conductor.scene import load_scene


def test_a_cut_short_run_keeps_what_went_wrong_before():
    rec = RunRecord(load_scene("scenes/ball_drop.yaml"))
    rec.degraded.append("the main model physics was unreachable at tick 9 (its token vanished) and came back")
    assert rec.status({"in(container, ball)": True}, 0, []) == ("degraded", [rec.degraded[0]])
    rec.stopped = "stopped at max_ticks 60"
    status, reasons = rec.status({"in(container, ball)": True}, 2, ["3 joint states left out"])
    assert status == "truncated" and reasons == ["stopped at max_ticks 60", rec.degraded[0],
                                                 "2 malformed messages were dropped", "input: 3 joint states left out"]
    rec.interrupted = "SIGTERM"
    assert rec.status({"in(container, ball)": None}, 0, [])[1] == [
        "SIGTERM", rec.degraded[0], "the predicate 'in(container, ball)' could not be evaluated"]
    rec.failure = "the main model 'physics' died at tick 12"
    assert rec.status({}, 5, []) == ("failed", ["the main model 'physics' died at tick 12"])
