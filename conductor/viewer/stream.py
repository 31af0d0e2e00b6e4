"""Where the Rerun data goes: a file, a spawned viewer, a served web viewer or a running one; the blueprint."""
from __future__ import annotations

import logging
import os
import socket
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import rerun.blueprint.components as rrbc
import rerun.blueprint.encodings as rrbe

from protocol.errors import ViewerError

log = logging.getLogger("twin.viewer")


MODES = ("none", "save", "spawn", "serve", "connect")


DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"



# --------------------------------------------------------------------------- layout
def blueprint(scene=None):
    """The viewer layout: the 3D scene and the responsibility lanes on the left; legend, the event
    log and the plots on the right; the ``sim_time`` timeline selected."""
    # frame the space the scene's objects and the robot's hand can be in (up to ~0.8 m above the table)
    pts = [[0.45, 0.0, 0.0], [0.45, 0.0, 0.8]]
    if scene is not None:
        for e in scene.entities.values():
            pts += [list(e.pose[:3]), [e.pose[0], e.pose[1], max(0.8, e.pose[2] + 0.3)]]
        base = (scene.raw.get("robot") or {}).get("base")
        if scene.raw.get("robot"):
            b = list(base[:3]) if base else [0.0, 0.0, 0.0]
            pts += [b, [b[0], b[1], b[2] + 0.9]]
    pts = np.asarray(pts, dtype=float)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = (lo + hi) / 2
    radius = max(0.45, float(np.linalg.norm(hi - lo)) / 2)
    direction = np.array([1.0, -0.85, 0.6])
    look = [float(v) for v in centre]
    eye = [float(v) for v in centre + 2.0 * radius * direction / np.linalg.norm(direction)]
    scene3d = rrb.Spatial3DView(origin="world", name="Scene (colour = owner of the pose)",
                                eye_controls=rrb.EyeControls3D(position=eye, look_target=look, eye_up=[0, 0, 1]),
                                line_grid=rrb.LineGrid3D(visible=False))
    lanes = rrb.StateTimelineView(origin="ownership", name="Responsibility: which model owns what, when")
    plots = rrb.Tabs(
        rrb.TimeSeriesView(origin="health/rtf", name="Real-time factor"),
        rrb.TimeSeriesView(origin="health/step_rate", name="Step rate (steps per wall s)"),
        rrb.TimeSeriesView(origin="estimate", name="In-hand σ (mm)"),
        rrb.TimeSeriesView(origin="health/step_ms", name="Step time (ms)"),
        rrb.TimeSeriesView(origin="outputs", name="Outputs"),
    )
    def columns(*shown: str):
        return rrb.TextLogColumns(
            timeline_columns=[rrbe.TimelineColumn("sim_time")],
            text_log_columns=[rrbc.TextLogColumn(k, visible=k in shown) for k in ("LogLevel", "EntityPath", "Body")])

    why = rrb.TextLogView(origin="log", contents=["$origin/handovers", "$origin/triggers", "$origin/conductor"],
                          name="Handovers and why (triggers, conductor)", columns=columns("LogLevel", "Body"),
                          rows=rrb.TextLogRows(filter_by_log_level=["INFO", "WARN", "ERROR"]))
    events = rrb.TextLogView(origin="log", contents=["$origin/events/**", "$origin/actions", "$origin/outputs"],
                             name="Model events, robot actions, outputs", columns=columns("EntityPath", "Body"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(scene3d, lanes, row_shares=[3.0, 1.3]),
            rrb.Vertical(why, events,
                         rrb.Horizontal(rrb.TextDocumentView(origin="legend", name="Legend"), plots,
                                        column_shares=[1.0, 1.5]),
                         row_shares=[1.3, 1.3, 1.2]),
            column_shares=[1.5, 1.0]),
        rrb.TimePanel(timeline="sim_time", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


# --------------------------------------------------------------------------- streams
@dataclass
class Stream:
    """An open Rerun recording and where it goes."""

    rec: Any
    mode: str
    path: Path | None = None
    url: str | None = None  # serve: the web viewer URL; connect/spawn: the viewer's gRPC URL
    grpc_url: str | None = None
    undelivered: str | None = None  # why no viewer took it: none answered at connect=URL, or the last flush failed

    def facts(self) -> dict[str, Any]:
        """Where it went, for a program (the summary's ``rerun_stream``): the mode, the ``.rrd`` file written
        (None: none), the web viewer's or the viewer's URL, and whether a viewer took it (None: none was asked)."""
        asked = self.mode in ("spawn", "connect") and self.grpc_url is not None
        return {"mode": self.mode, "rrd": str(self.path) if self.path is not None else None,
                "url": self.url if self.mode == "serve" else self.grpc_url,
                "delivered": (self.undelivered is None) if asked else None,
                **({"undelivered": self.undelivered} if asked and self.undelivered else {})}

    def hint(self) -> str:
        """How to look at it, in one line for a person."""
        lines = []
        if self.mode == "serve" and self.url:
            lines.append(f"Rerun web viewer: {self.url}")
        elif self.mode in ("spawn", "connect") and self.grpc_url and self.undelivered:
            lines.append(f"warning: the Rerun stream reached no viewer: {self.undelivered}")
        elif self.mode in ("spawn", "connect") and self.grpc_url:
            lines.append(f"Rerun stream sent to {self.grpc_url}")
        if self.path is not None:
            lines.append(f"Rerun recording: rerun {self.path}")
        return "\n".join(lines)


def parse_mode(mode: str | None) -> tuple[str, str | None]:
    """``none | save | spawn | serve | serve=WEBPORT | connect | connect=URL`` → (mode, argument)."""
    if not mode:
        return "none", None
    name, _, arg = str(mode).partition("=")
    name = name.strip().lower()
    if name not in MODES:
        raise ViewerError(f"unknown Rerun mode {mode!r}: use none, save, spawn, serve[=WEBPORT] or connect[=URL]")
    return name, (arg or None)


def no_display() -> str | None:
    """Why no Rerun viewer window can open here (None: it can, as far as can be told): on Linux, no display."""
    if sys.platform.startswith("linux") and not any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY",
                                                                                "WAYLAND_SOCKET")):
        return ("spawn: no display here (neither DISPLAY nor WAYLAND_DISPLAY is set) for a Rerun viewer window: "
                "serve the web viewer instead (twin view --serve, twin run --rerun serve), or open the .rrd")
    return None


def web_port_of(text: str) -> int:
    """``serve=WEBPORT``'s port, 1-65535 (ViewerError naming it otherwise)."""
    try:
        port = int(text)
    except ValueError:
        port = 0
    if not 1 <= port <= 65535:
        raise ViewerError(f"serve={text}: the web viewer's port must be a number from 1 to 65535")
    return port


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _nobody_at(url: str, timeout: float = 1.0) -> str | None:
    """Why nothing can take a stream at a viewer's gRPC ``url`` (``rerun+http://HOST:PORT/proxy``), or None
    when something accepts a connection there."""
    parts = urlsplit(url.removeprefix("rerun+"))
    try:
        host, port = parts.hostname or "127.0.0.1", parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError as e:
        return f"bad viewer address {url!r}: {e}"
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as e:
        return f"no Rerun viewer answers at {host}:{port} ({e.strerror or e})"


def open_stream(mode: str = "save", path: str | Path | None = None, url: str | None = None, *, scene=None,
                name: str = "twin", recording_id: str | None = None, web_port: int | None = None,
                grpc_port: int | None = None, spawn_port: int = 9876) -> Stream:
    """Open a recording for ``mode``; every mode also writes ``path`` when one is given."""
    mode, arg = parse_mode(mode)
    if mode == "none":
        raise ViewerError("mode 'none' has no stream")
    if mode == "serve" and arg:
        web_port = web_port_of(arg)
    if mode == "connect":
        url = arg or url or DEFAULT_CONNECT_URL
    # bigger, rarer chunks than Rerun's default (8 ms): less work per logged row, latency a viewer
    # does not notice
    rec = rr.RecordingStream("twin", recording_id=recording_id or f"{name}-{uuid.uuid4().hex[:12]}",
                             batcher_config=rr.ChunkBatcherConfig(flush_tick=0.25, flush_num_bytes=4 << 20))
    rec.set_log_time_enabled(False)  # the timelines are the twin's own: tick and sim_time
    rec.set_log_tick_enabled(False)
    sinks: list[Any] = []
    p = None
    if path is not None:
        p = Path(path)
        try:
            if p.is_dir():
                raise IsADirectoryError("a folder, not a file")
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ViewerError(f"cannot write the Rerun recording {p}: {e}") from None
        sinks.append(rr.FileSink(str(p)))
    stream = Stream(rec, mode, p)
    if mode == "save" and p is None:
        raise ViewerError("save mode needs a path for the .rrd")
    if mode == "serve":
        server = rr.GrpcServerSink("127.0.0.1", grpc_port or _free_port())
        sinks.append(server)
        stream.grpc_url = server.uri
        wp = web_port or _free_port()
        try:
            rr.serve_web_viewer(web_port=wp, open_browser=False, connect_to=server.uri)
        except Exception as e:
            raise ViewerError(f"cannot serve the Rerun web viewer on port {wp}: {e}") from None
        stream.url = f"http://127.0.0.1:{wp}/?url={quote(server.uri, safe='')}"
    elif mode == "spawn" and no_display():  # the file is still written (said at once, not after a 10 s flush)
        stream.undelivered = no_display()
        log.warning("viewer: %s: the stream goes to the file only", stream.undelivered)
    elif mode == "spawn":
        try:
            # (the recording is named: rr.spawn asks whether *it* is enabled, and a call without one asks the
            # global recording, which this module never makes, and so started nothing); the viewer beside this
            # interpreter's, found without the virtual environment being activated
            beside = Path(sys.executable).with_name("rerun")
            rr.spawn(port=spawn_port, connect=False, recording=rec,
                     executable_path=str(beside) if beside.is_file() else None)
        except Exception as e:
            raise ViewerError(f"cannot start a Rerun viewer: {e}") from None
        stream.grpc_url = f"rerun+http://127.0.0.1:{spawn_port}/proxy"
        sinks.append(rr.GrpcSink(stream.grpc_url))
    elif mode == "connect":
        url = url or DEFAULT_CONNECT_URL
        stream.grpc_url = url
        stream.undelivered = _nobody_at(url)
        if stream.undelivered is None:
            sinks.append(rr.GrpcSink(url))
        else:  # said now, not after a run and a 10 s flush; the file (when given) is still written
            log.warning("viewer: %s: the stream goes to the file only", stream.undelivered)
    try:
        rec.set_sinks(*sinks, default_blueprint=blueprint(scene))
    except RuntimeError as e:  # the file sink opens its file here: Failed to create file
        raise ViewerError(f"cannot write the Rerun recording {p}: {e}") from None
    rec.send_recording_name(name)
    return stream


def close_stream(stream: Stream) -> None:
    """Flush and close; a stream no viewer took is marked :attr:`Stream.undelivered` (its file is whole)."""
    try:
        stream.rec.flush(timeout_sec=10.0)
    except Exception as e:
        if stream.undelivered is None:
            stream.undelivered = f"{stream.grpc_url or stream.path}: {str(e) or type(e).__name__}"
        log.warning("viewer: flush failed: %s", e)
    try:
        stream.rec.disconnect()
    except Exception as e:
        log.warning("viewer: closing the Rerun stream failed: %s", e)
