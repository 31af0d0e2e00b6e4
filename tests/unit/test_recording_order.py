"""A recording is replayed in log-time order whatever order its file holds the messages in (the reader takes
them in the file's order and sorts them once, stably: equal log times keep the file's order), and a file
written out of order is said to be; its joint values are checked as they were (NaN, infinities, huge values
and non-numbers left out and counted)."""
from __future__ import annotations

import logging
import random

from conductor.sources.recording import load_recording
from recordings.rosbag import RecordingWriter


def test_messages_written_out_of_order_are_replayed_in_time_order(tmp_path, caplog):
    times = [i / 100 for i in range(300)]
    shuffled = times[:]
    random.Random(7).shuffle(shuffled)
    path = tmp_path / "shuffled.mcap"
    with RecordingWriter(path) as w:
        for t in shuffled:
            w.joint_state(t, ["j1", "finger"], [t, 1.0], [], [])
        w.action(1.5, "move_hand", "start", command="close")  # at the same time as a joint state: after it
    with caplog.at_level(logging.WARNING):
        rec = load_recording(path)
    stamps = [m["stamp"] for _, kind, m in rec.items if kind == "joint_state"]
    assert stamps == sorted(stamps) and len(stamps) == 300
    assert [m["position"][0] for _, kind, m in rec.items if kind == "joint_state"] == times
    kinds = [kind for t, kind, _ in rec.items if abs(t - 1.5) < 1e-6]
    assert kinds == ["joint_state", "action"]  # equal log times: the file's order
    assert "recorded out of time order" in caplog.text


def test_joint_values_that_are_not_finite_numbers_are_left_out(tmp_path):
    path = tmp_path / "bad.mcap"
    bad = [float("nan"), float("inf"), -float("inf"), 1e9, -2e9, 1e308]
    with RecordingWriter(path) as w:
        for i, v in enumerate(bad):
            w.joint_state(i * 0.01, ["j1", "finger"], [0.5, v], [], [])
        for i in range(len(bad), 20):
            w.joint_state(i * 0.01, ["j1", "finger"], [0.5, 999999999.0], [0.0, -0.0], [0.0, 5e-324])
    rec = load_recording(path)
    assert sum(kind == "joint_state" for _, kind, _ in rec.items) == 20 - len(bad)
    assert rec.skipped == {"joint states with NaN, infinite or non-numeric values": len(bad)}
