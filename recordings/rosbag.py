"""Writing robot recordings: MCAP in rosbag2 layout (``/joint_states``, ``/action``)."""
from __future__ import annotations

import json
import os
from pathlib import Path

from protocol.ros2 import JOINT_STATE_DEF, STRING_DEF


class RecordingWriter:
    """Write joint states and action annotations; ``t`` is seconds since the start (plus ``t0``).
    ``namespace`` (e.g. ``/panda``) puts them on ``/panda/joint_states`` and ``/panda/action``.

    The recording is written beside ``path`` (``.NAME.partial``) and takes its name only when closed whole: a
    writing stopped by an exception or Ctrl-C (the ``with`` block left so) leaves no recording that reads as
    whole but is not, and a recording already at ``path`` stays as it was."""

    def __init__(self, path: str | Path, t0: float = 1_700_000_000.0, namespace: str = ""):
        from mcap_ros2.writer import Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._target = Path(os.path.realpath(self.path))  # (through a symbolic link, not over it)
        self._partial = self._target.with_name(f".{self._target.name}.partial")
        self._f = open(self._partial, "wb")
        self._w = Writer(self._f)
        self._js = self._w.register_msgdef("sensor_msgs/msg/JointState", JOINT_STATE_DEF)
        self._str = self._w.register_msgdef("std_msgs/msg/String", STRING_DEF)
        self.t0 = t0
        self._seq = 0
        self.joint_topic, self.action_topic = f"{namespace}/joint_states", f"{namespace}/action"

    def _ns(self, t: float) -> int:
        # (t0 + t) in one double rounds to the 238 ns a double has at 1.7e9 s: a stamp can come up to 128 ns after
        # its tick's time. Kept so that the shipped recordings stay byte for byte what this writer makes
        # (tests/test_synth.py); the replay takes a message up to 1 us late as its tick's (sources/replay.py)
        return int(round((self.t0 + t) * 1e9))

    def joint_state(self, t: float, names, position, velocity, effort) -> None:
        ns = self._ns(t)
        msg = {"header": {"stamp": {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}, "frame_id": ""},
               "name": list(names), "position": [float(x) for x in position],
               "velocity": [float(x) for x in velocity], "effort": [float(x) for x in effort]}
        self._w.write_message(self.joint_topic, self._js, msg, log_time=ns, publish_time=ns, sequence=self._seq)
        self._seq += 1

    def action(self, t: float, operation: str, phase: str = "start", **params) -> None:
        self.raw_action(t, json.dumps({"operation": operation, "phase": phase, "params": params}))

    def raw_action(self, t: float, data: str) -> None:
        """An action annotation with ``data`` written as given (for tests of malformed input)."""
        ns = self._ns(t)
        self._w.write_message(self.action_topic, self._str, {"data": data}, log_time=ns, publish_time=ns,
                              sequence=self._seq)
        self._seq += 1

    def metadata(self, name: str, data: dict) -> None:
        self._w.add_metadata(name, {str(k): (v if isinstance(v, str) else json.dumps(v)) for k, v in data.items()})

    def close(self) -> None:
        """End the recording (its summary and footer) and give it its name."""
        try:
            self._w.finish()
            self._f.close()
        except BaseException:
            self.abandon()
            raise
        os.replace(self._partial, self._target)

    def abandon(self) -> None:
        """Drop what was written (nothing takes ``path``)."""
        self._f.close()
        self._partial.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, kind, *exc):
        if kind is None:
            self.close()
        else:
            self.abandon()
