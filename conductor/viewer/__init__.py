"""The Rerun stream of the twin: where every object is, which model is responsible for it, and why
that changed.

Two ways in, one logging code (:class:`TwinLogger`):

- live: :class:`ViewerSink` subscribes to the ensemble's own Zenoh traffic (``state/*``,
  ``out/*/*``, ``event/*/*`` including the conductor's ``event/_conductor/*``, ``ownership``,
  ``clock``, ``done/*``, ``telemetry/**``) into ring channels that never block the transport, and a
  worker thread turns it into Rerun data, so the conductor's tick loop never waits on the viewer;
- afterwards: :func:`log_run` turns a run log (``twin view RUNLOG``) into an ``.rrd``.

What the recording holds (entity paths):

- ``world/<entity>`` the pose (``Transform3D``), ``world/<entity>/shape`` the entity's real shape
  coloured by the model that owns its pose; ``world/panda`` the robot from its URDF, its joints
  moving with the telemetry; ``world/particles/<model>`` particles; ``world/estimates/...`` the
  in-hand estimate's 3σ sphere; ``world/legend`` one labelled dot per model in its colour;
- ``ownership/<entity>/<attribute>`` a state lane per responsibility (``StateChange``): which
  model owned it when;
- ``log/handovers``, ``log/triggers``, ``log/events/<model>``, ``log/actions``, ``log/outputs``,
  ``log/conductor`` the text log; ``legend`` a text document listing model → colour;
- ``health/rtf``, ``health/step_rate/<model>``, ``health/step_ms/<model>``, ``estimate/<model>/<entity>``
  (σ in mm), ``outputs/<model>/<name>`` numeric outputs, as time series.

Two timelines: ``tick`` (sequence) and ``sim_time`` (duration, the messages' ``t``). Poses, joints,
particles and plots are decimated to ``pose_hz`` of simulated time for the viewer (the run log keeps
everything); ownership changes, handovers, triggers and events are always logged. Viewer problems
are warnings: they never stop a run.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .colours import FIXED_COLOURS, Colours

if TYPE_CHECKING:  # the rest loads rerun: only when first used (the run log's Foxglove views need the colours)
    from .logger import TwinLogger
    from .replay import log_run, scene_for_run_log
    from .sink import ViewerSink, start_sink
    from .stream import MODES, Stream, ViewerError, close_stream, open_stream, parse_mode

_LAZY = {"TwinLogger": "logger", "log_run": "replay", "scene_for_run_log": "replay", "ViewerSink": "sink",
         "start_sink": "sink", "MODES": "stream", "Stream": "stream", "ViewerError": "stream",
         "close_stream": "stream", "open_stream": "stream", "parse_mode": "stream"}

__all__ = ["FIXED_COLOURS", "MODES", "Colours", "Stream", "TwinLogger", "ViewerError", "ViewerSink", "close_stream",
           "log_run", "open_stream", "parse_mode", "scene_for_run_log", "start_sink"]


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{mod}", __name__), name)
