"""The run log's writer thread alone: it must not depend on how soon the thread that creates the log runs again.

On a loaded machine the creating thread can lose the CPU for longer than the writer's first wait; a writer that
then read state the constructor had not set yet failed, and the run stopped as failed before its agents were in
(seen once in CI with two CPU burners beside it)."""
from __future__ import annotations

import threading
import time

from conductor.runlog import writer
from conductor.runlog.reader import read_run_log
from protocol import codec


def test_a_slow_constructor_does_not_break_the_writer(tmp_path, monkeypatch):
    start = threading.Thread.start

    def start_then_stall(self):  # the creating thread descheduled right after the writer started
        start(self)
        time.sleep(10 * writer.WAKE_S)

    monkeypatch.setattr(threading.Thread, "start", start_then_stall)
    log = writer.RunLog(tmp_path / "run.mcap", {}, dt=0.01, prefix="twin/t")
    monkeypatch.setattr(threading.Thread, "start", start)
    log.record("twin/t/ownership", codec.encode("ownership", version=1, tick=3, t=0.03, change=None, owners={}))
    time.sleep(3 * writer.WAKE_S)
    log.close()
    assert log.error is None
    got = [(k, m["tick"]) for k, _, m in read_run_log(tmp_path / "run.mcap")]
    assert got == [("twin/t/ownership", 3)]
