"""Small synthetic recordings for framework tests and the fallback demo (written with the rosbag2 writer)."""
from __future__ import annotations

from .rosbag import RecordingWriter


def core_recording(path, seconds: float = 3.0, rate: float = 100.0, grip=(0.8, 2.0), action_at: float = 0.7):
    """Joint 'finger' closes (0.2) during ``grip``; a move_hand end annotation at ``action_at``."""
    with RecordingWriter(path) as w:
        n = int(seconds * rate)
        for i in range(n):
            t = i / rate
            f = 0.2 if grip[0] < t < grip[1] else 1.0
            w.joint_state(t, ["j1", "finger"], [0.1, f], [0.0, 0.0], [0.0, 0.0])
            if abs(t - action_at) < 0.5 / rate:
                w.action(t, "move_hand", "end", hand="right")
        w.metadata("twin.ground_truth", {"in_container": "true"})
    return path
