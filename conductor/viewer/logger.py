"""The one logging code of the viewer: turns the ensemble's messages into Rerun entities and timelines."""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr

from protocol import codec
from protocol.robot import description, shipped

from .style import CONDUCTOR, GREY, Colours, resolve_urdf, shape_archetype

log = logging.getLogger("twin.viewer")


# --------------------------------------------------------------------------- the logger
@dataclass
class _Series:
    ticks: list = field(default_factory=list)
    times: list = field(default_factory=list)
    values: list = field(default_factory=list)


def _short(v: Any, limit: int = 80) -> str:
    if isinstance(v, float):
        s = f"{v:.4g}"
    elif isinstance(v, dict):
        s = "{" + ", ".join(f"{k}: {_short(x, 30)}" for k, x in v.items()) + "}"
    elif isinstance(v, (list, tuple)) and len(v) <= 8:
        s = "[" + ", ".join(_short(x, 20) for x in v) + "]"
    elif isinstance(v, np.ndarray):
        s = f"array{list(v.shape)}"
    elif v is None:
        s = "null"
    elif isinstance(v, bool):
        s = "true" if v else "false"
    else:
        s = str(v)
    return s if len(s) <= limit else s[: limit - 1] + "…"


class TwinLogger:
    """Turns the ensemble's messages into Rerun data. Not thread-safe: one thread feeds it.

    ``feed(key, msg, wall_ns)`` takes one decoded message with its full key
    (``twin/<ensemble>/...``) and the wall time it was seen; ``flush()`` sends what is batched;
    ``finish()`` ends the recording's content (call ``flush`` and close the stream yourself).
    ``scene`` (a :class:`conductor.scene.Scene`) gives shapes, the robot and the model list; without
    it the logger draws what the messages tell (poses as labelled markers, the Panda if the joint
    names are the Panda's).
    """

    def __init__(self, rec, scene=None, *, pose_hz: float = 60.0, particle_hz: float = 30.0,
                 health_period_s: float = 0.5):
        self.rec = rec
        self.scene = scene
        self.pose_dt = 1.0 / pose_hz if pose_hz > 0 else 0.0
        self.particle_dt = 1.0 / particle_hz if particle_hz > 0 else 0.0
        self.health_period_ns = int(health_period_s * 1e9)
        models = list(scene.models) if scene is not None else []
        self.colours = Colours(models)
        self.kinds = {n: m.kind for n, m in scene.models.items()} if scene is not None else {}
        self.shapes: dict[str, dict | None] = {}
        self.owner: dict[tuple[str, str], str] = {}
        self.version = -1
        self.tick = 0
        self.t = 0.0
        self._series: dict[str, _Series] = {}
        self._last_t: dict[str, float] = {}
        self._poses: dict[str, _Series] = {}
        self._latest_pose: dict[str, tuple[int, float, list, bool]] = {}
        self._force_pose: set[str] = set()
        self._joint_cols: dict[str, _Series] = {}
        self._joints: dict[str, Any] = {}  # name -> rr.urdf.UrdfJoint (moving joints)
        self._robot_loaded = False
        self._robot_failed = False
        self._last_outputs: dict[tuple[str, str], Any] = {}
        self._keys: dict[str, _Key] = {}
        self._styled: set[str] = set()
        self._step_s: dict[str, list[float]] = {}  # model -> [sum of sampled step times, samples]
        self._health_prev: tuple[int, float, dict, dict] | None = None
        self._wall_ns: int | None = None
        self._legend_models: list[str] = []
        self._estimates_shown: set[str] = set()
        self.counts = {"messages": 0, "bad": 0, "handovers": 0, "poses": 0}
        self.final_rtf: float | None = None

    # ---------------------------------------------------------------- set-up
    def begin(self) -> None:
        """Log what is known before the first message: table, legend, entities, ownership at t = 0."""
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world/table", rr.Boxes3D(centers=[[0.35, 0.0, -0.01]], half_sizes=[[0.75, 0.75, 0.01]],
                                          colors=[(205, 200, 190, 140)], fill_mode=rr.components.FillMode.Solid),
                static=True)
        if self.scene is None:
            self._legend()
            return
        self._at(0, 0.0)
        for name, ent in self.scene.entities.items():
            self.shapes[name] = ent.shape
        for (e, a), m in sorted(self.scene.initial_owners().items()):
            self.owner[(e, a)] = m
            self._track_config(e, a)
            rec.log(f"ownership/{e}/{a}", rr.StateChange(state=m))
        for name, ent in self.scene.entities.items():
            self._draw_entity(name, 0, 0.0)
            self._queue_pose(name, 0, 0.0, ent.pose, force=True)
        if self.scene.raw.get("robot") and self.scene.robot is not None:
            self._load_robot(self.scene.robot.urdf_file, self.scene.robot.base)
        self._legend()

    def _at(self, tick: int, t: float) -> None:
        self.rec.set_time("tick", sequence=int(tick))
        self.rec.set_time("sim_time", duration=float(t))

    def _legend(self) -> None:
        """The model → colour legend: a text document and labelled dots beside the table."""
        names = [n for n in self.colours.assigned if n != CONDUCTOR]
        if names == self._legend_models:
            return
        self._legend_models = list(names)
        rows = ["Colour of an object in the 3D view = the model that owns its **pose** now; the "
                "*Responsibility* lanes show every attribute's owner over time.", "",
                "| model | colour |", "|---|---|"]
        for n in names:
            cname, rgb = self.colours.get(n)
            kind = self.kinds.get(n, n)
            label = f"**{n}**" + (f" ({kind.rsplit(':', 1)[-1]})" if kind != n else "")
            rows.append(f"| {label} | {cname} `#{rgb[0]:02x}{rgb[1]:02x}{rgb[2]:02x}` |")
        self.rec.log("legend", rr.TextDocument("\n".join(rows), media_type=rr.MediaType.MARKDOWN), static=True)
        if names:
            pts = [[-0.3, -0.55 + 0.12 * i, 0.0] for i in range(len(names))]
            self.rec.log("world/legend", rr.Points3D(pts, radii=[0.02] * len(names),
                                                     colors=[self.colours.rgb(n) for n in names],
                                                     labels=names, show_labels=True), static=True)
        # each ownership lane and step-rate series uses the same colours
        for (e, a) in list(self.owner):
            self._track_config(e, a)
        for n in names:
            if n in self._styled:
                self._series_style(f"health/step_rate/{n}", n, self.colours.rgb(n))
                self._series_style(f"health/step_ms/{n}", n, self.colours.rgb(n))

    def _model_seen(self, name: str) -> None:
        if name and name != CONDUCTOR and name not in self.colours.assigned:
            self.colours.get(name)
            self._legend()

    def _track_config(self, e: str, a: str) -> None:
        names = [n for n in self.colours.assigned if n != CONDUCTOR]
        self.rec.log(f"ownership/{e}/{a}", rr.StateConfiguration(
            values=names, colors=[self.colours.rgb(n) for n in names]), static=True)

    def _series_style(self, path: str, name: str, rgb) -> None:
        self.rec.log(path, rr.SeriesLines(colors=[rgb], names=[name]), static=True)

    def _load_robot(self, spec: str, base) -> None:
        """Log the robot's URDF (visual meshes) once, attached to the world at ``base``."""
        self._robot_loaded = True
        path = resolve_urdf(spec)
        if path is None:
            log.warning("viewer: robot URDF %r not found; the robot is not drawn", spec)
            self._robot_failed = True
            return
        # the Panda's meshes are package://meshes/...: the package root is the URDF's folder
        pkg = str(path.parent)
        paths = os.environ.get("ROS_PACKAGE_PATH", "")
        if pkg not in paths.split(os.pathsep):
            os.environ["ROS_PACKAGE_PATH"] = pkg + (os.pathsep + paths if paths else "")
        try:
            tree = rr.urdf.UrdfTree.from_file_path(str(path), entity_path_prefix="world")
            root = tree.root_link().name
            stream = tree.stream().drop(content=f"/world/{tree.name}/collision_geometries/**")
            self.rec.send_chunks(stream)
        except Exception as e:  # a broken URDF costs the robot, not the run
            log.warning("viewer: cannot draw robot %s: %s", path, e)
            self._robot_failed = True
            return
        b = [float(v) for v in (base or [0, 0, 0, 0, 0, 0, 1])]
        b = b + [0.0, 0.0, 0.0, 1.0] if len(b) == 3 else b
        self.rec.log("world/robot_base", rr.Transform3D(translation=b[:3], quaternion=rr.Quaternion(xyzw=b[3:7]),
                                                        parent_frame="tf#/world", child_frame=root), static=True)
        self._joints = {j.name: j for j in tree.joints() if j.joint_type in ("revolute", "prismatic", "continuous")}

    # ----------------------------------------------------------------- input
    def _key(self, key: str) -> _Key:
        k = self._keys.get(key)
        if k is None:
            parts = key.split("/")
            kind = parts[2] if len(parts) > 2 else ""
            model = parts[3] if kind in ("state", "out", "done", "event") and len(parts) > 3 else ""
            # what the viewer shows of every message: ownership, events, actions; the rest is sampled
            always = kind in ("ownership", "event") or (kind == "telemetry" and parts[-1] != "joint_states")
            # decoded per simulated second: poses, joints, outputs at pose_hz; the clock (only
            # for the time) at 10 Hz; one done/ reply in 16 (only its step time is shown)
            dt = 0.1 if kind == "clock" else self.pose_dt
            k = self._keys[key] = _Key(kind, model, always, dt, 16 if kind == "done" else 1)
            if model and kind in ("state", "out", "done") and model not in self._styled:
                self._styled.add(model)
                self._model_seen(model)
                rgb = self.colours.rgb(model)
                self._series_style(f"health/step_rate/{model}", model, rgb)
                self._series_style(f"health/step_ms/{model}", model, rgb)
        return k

    def offer(self, key: str, payload: bytes, wall_ns: int) -> None:
        """Take one raw message: counted always, decoded and shown only as often as the viewer needs
        it (about ``pose_hz`` per simulated second for the high-rate keys; ownership, events and
        actions every time)."""
        k = self._key(key)
        k.count += 1
        if k.kind == "done":
            # one step, unless the answer covers a batch of ticks (only then is it decoded to count them)
            k.steps += _batch_len(payload) if b"more" in payload else 1
        if k.kind not in _SHOWN:
            return  # e.g. the step broadcast: large, and nothing in it the viewer draws
        if not k.always:
            k.skip -= 1
            if k.skip > 0:
                return
            k.skip = k.n
        try:
            msg = codec.unpack(payload)
        except Exception:
            self.counts["messages"] += 1
            self.counts["bad"] += 1
            return
        self._feed(key, k, msg, wall_ns)

    def offer_decoded(self, key: str, msg: dict[str, Any], wall_ns: int) -> None:
        """Take one message already decoded (a result a step answer carried), sampled as :meth:`offer` samples."""
        k = self._key(key)
        k.count += 1
        if not k.always:
            k.skip -= 1
            if k.skip > 0:
                return
            k.skip = k.n
        self._feed(key, k, msg, wall_ns)

    def feed(self, key: str, msg: Any, wall_ns: int) -> None:
        """Take one decoded message of the ensemble (never raises: a bad message is counted)."""
        k = self._key(key)
        k.count += 1
        if k.kind == "done":
            k.steps += _batch_len(msg)
        self._feed(key, k, msg, wall_ns)

    def _feed(self, key: str, k: _Key, msg: Any, wall_ns: int) -> None:
        self.counts["messages"] += 1
        if not isinstance(msg, dict):
            self.counts["bad"] += 1
            return
        kind = k.kind
        t = msg.get("t", msg.get("stamp"))
        if isinstance(t, (int, float)) and not k.always:
            k.observe(t)
        try:
            if kind == "state":
                self._on_state(msg)
            elif kind == "out":
                self._on_out(msg)
            elif kind == "event":
                self._on_event(msg)
            elif kind == "ownership":
                self._on_ownership(msg)
            elif kind == "clock":
                self._advance(msg["tick"], msg["t"])
            elif kind == "done":
                st = msg.get("step_s")
                if isinstance(st, (int, float)):
                    acc = self._step_s.setdefault(k.model, [0.0, 0])
                    acc[0] += float(st)
                    acc[1] += 1
            elif kind == "telemetry":
                if msg.get("type") == "joint_state":
                    self._on_joints(msg)
                elif msg.get("type") == "action":
                    self._on_action(msg)
            else:
                return
        except Exception as e:  # the viewer never takes the run down with it
            self.counts["bad"] += 1
            if self.counts["bad"] <= 5:
                log.warning("viewer: cannot show %s: %s: %s", key, type(e).__name__, e)
        self._health(wall_ns)

    def _advance(self, tick, t) -> None:
        if isinstance(t, (int, float)) and t >= self.t:
            self.t = float(t)
            self.tick = int(tick)

    def _on_state(self, msg: dict) -> None:
        model, tick, t = msg["model"], msg["tick"], msg["t"]
        self._advance(tick, t)
        self._model_seen(model)
        for e, attrs in msg["values"].items():
            if not isinstance(attrs, dict):
                continue
            for a, v in attrs.items():
                if a == "pose":
                    if e not in self.shapes:
                        self._new_entity(e, tick, t)
                    self._queue_pose(e, tick, t, v)
                elif isinstance(v, (int, float)):
                    self._scalar(f"attributes/{e}/{a}", tick, t, float(v))

    def _new_entity(self, e: str, tick: int, t: float) -> None:
        self.shapes[e] = None
        self._draw_entity(e, tick, t)

    def _queue_pose(self, e: str, tick: int, t: float, pose, force: bool = False) -> None:
        if not isinstance(pose, (list, tuple, np.ndarray)) or len(pose) < 3:
            return
        p = [float(v) for v in pose[:7]]
        if len(p) < 7:
            p = p[:3] + [0.0, 0.0, 0.0, 1.0]
        due = force or e in self._force_pose or t >= self._last_t.get("pose:" + e, -math.inf) + self.pose_dt - 1e-9
        self._latest_pose[e] = (tick, t, p, due)
        if not due:
            return
        self._force_pose.discard(e)
        self._last_t["pose:" + e] = t
        s = self._poses.setdefault(e, _Series())
        s.ticks.append(tick)
        s.times.append(t)
        s.values.append(p)
        self.counts["poses"] += 1

    def _draw_entity(self, e: str, tick: int, t: float) -> None:
        """(Re)draw an entity's shape in the colour of its pose's owner, from (tick, t) on."""
        owner = self.owner.get((e, "pose")) or next((m for (x, _), m in self.owner.items() if x == e), "")
        label = f"{e} ({owner})" if owner else e
        arche = shape_archetype(self.shapes.get(e), self.colours.rgb(owner) if owner else GREY[1], label)
        self._at(tick, t)
        self.rec.log(f"world/{e}/shape", arche)

    def _on_out(self, msg: dict) -> None:
        model, name, tick, t, value = msg["model"], msg["name"], msg["tick"], msg["t"], msg["value"]
        self._advance(tick, t)
        self._model_seen(model)
        if name == "particles":
            self._particles(model, tick, t, value)
            return
        if name == "estimate" and isinstance(value, dict):
            self._estimate(model, tick, t, value)
            return
        k = (model, name)
        if isinstance(value, (bool, str)) or value is None:
            old = self._last_outputs.get(k, _UNSET)
            if old != value:
                self._last_outputs[k] = value
                self._text("log/outputs", tick, t, f"{model}.{name} = {_short(value)}", "INFO",
                           self.colours.rgb(model))
            if isinstance(value, bool):
                self._scalar(f"outputs/{model}/{name}", tick, t, float(value), force=old != value)
        elif isinstance(value, (int, float)):
            self._scalar(f"outputs/{model}/{name}", tick, t, float(value))

    def _particles(self, model: str, tick: int, t: float, value) -> None:
        key = "particles:" + model
        if t < self._last_t.get(key, -math.inf) + self.particle_dt - 1e-9:
            return
        arr = np.asarray(value, dtype=np.float32)
        if arr.ndim != 2 or arr.shape[1] != 3:
            return
        self._last_t[key] = t
        self._at(tick, t)
        self.rec.log(f"world/particles/{model}", rr.Points3D(arr, radii=0.005, colors=[self.colours.rgb(model)]))

    def _estimate(self, model: str, tick: int, t: float, value: dict) -> None:
        key = "estimate:" + model
        due = t >= self._last_t.get(key, -math.inf) + self.pose_dt - 1e-9
        if not due:
            return
        self._last_t[key] = t
        rgb = self.colours.rgb(model)
        for ent, est in value.items():
            if not isinstance(est, dict):
                continue
            sigma = est.get("sigma")
            path = f"estimate/{model}/{ent}"
            if isinstance(sigma, (int, float)):
                if path not in self._estimates_shown:
                    self._series_style(path, f"{ent} σ (mm)", rgb)
                self._scalar(path, tick, t, 1e3 * float(sigma), force=True)
            pose = est.get("pose")
            wpath = f"world/estimates/{model}/{ent}"
            self._at(tick, t)
            if est.get("lost"):
                if wpath in self._estimates_shown:
                    self.rec.log(wpath, rr.Clear(recursive=False))
                    self._estimates_shown.discard(wpath)
                continue
            # the 3σ sphere shows while the estimating model is responsible for the pose
            if (isinstance(sigma, (int, float)) and isinstance(pose, (list, tuple)) and len(pose) >= 3
                    and self.owner.get((ent, "pose")) == model):
                r = max(3.0 * float(sigma), 1e-4)
                self.rec.log(wpath, rr.Ellipsoids3D(centers=[[float(v) for v in pose[:3]]], half_sizes=[[r, r, r]],
                                                    colors=[rgb + (160,)],
                                                    fill_mode=rr.components.FillMode.MajorWireframe))
                self._estimates_shown.add(wpath)
            self._estimates_shown.add(path)
        # entities the estimate no longer lists (released): take their sphere away
        for wpath in [p for p in self._estimates_shown if p.startswith(f"world/estimates/{model}/")]:
            if wpath.rsplit("/", 1)[-1] not in value:
                self._at(tick, t)
                self.rec.log(wpath, rr.Clear(recursive=False))
                self._estimates_shown.discard(wpath)

    def _on_event(self, msg: dict) -> None:
        model, name, tick, t, data = msg["model"], msg["name"], msg["tick"], msg["t"], msg.get("data") or {}
        self._advance(tick, t)
        if model != CONDUCTOR:
            self._model_seen(model)
            self._text(f"log/events/{model}", tick, t, f"{model}.{name} {_short(data, 200)}", "INFO",
                       self.colours.rgb(model))
            return
        if name == "handover":
            self.counts["handovers"] += 1
            src, dst = data.get("from", "?"), data.get("to", "?")
            self._model_seen(src)
            self._model_seen(dst)
            vars_ = data.get("variables") or {}
            why = data.get("trigger", "?")
            if vars_:
                why += "; " + ", ".join(f"{k} = {_short(v, 40)}" for k, v in vars_.items())
            self._text("log/handovers", data.get("tick", tick), data.get("t", t),
                       f"handover {data.get('entity')}.{data.get('attribute')}: {src} → {dst}  (trigger {why})",
                       "WARN", self.colours.rgb(dst))
        elif name == "trigger":
            vars_ = data.get("variables") or {}
            vs = ", ".join(f"{k} = {_short(v, 40)}" for k, v in vars_.items())
            if data.get("fired"):
                self._text("log/triggers", tick, t, f"trigger {data.get('trigger')} fired (on {data.get('on')})"
                           + (f": {vs}" if vs else ""), "INFO")
            else:
                self._text("log/triggers", tick, t, f"trigger {data.get('trigger')} not fired: "
                           f"{data.get('reason', '')}" + (f" ({vs})" if vs else ""), "DEBUG")
        elif name == "trigger_error":
            self._text("log/triggers", tick, t, f"trigger {data.get('trigger')} failed: {data.get('problem')}", "ERROR")
        elif name == "agent_lost":
            self._text("log/conductor", tick, t, f"agent lost: {data.get('model')} (its responsibilities fall back "
                       "to the main model)", "ERROR")
        elif name == "rejoin":
            self._text("log/conductor", tick, t, f"agent rejoined: {data.get('model')}", "INFO")
        elif name == "run_start":
            for m in data.get("models") or []:
                self._model_seen(m)
            self._text("log/conductor", tick, t, f"run start: scene {data.get('scene')}, models "
                       f"{', '.join(data.get('models') or [])}", "INFO")
        elif name == "run_end":
            rtf = data.get("rtf")
            self.final_rtf = rtf if isinstance(rtf, (int, float)) else None
            sem = ", ".join(f"{k} = {_short(v)}" for k, v in (data.get("semantic_state") or {}).items())
            self._text("log/conductor", tick, t, f"run end: {data.get('ticks')} ticks, real-time factor {rtf}"
                       + (f"; {sem}" if sem else ""), "INFO")
        else:
            self._text("log/conductor", tick, t, f"{name} {_short(data, 200)}", "INFO")

    def _on_ownership(self, msg: dict) -> None:
        version, tick, t = msg["version"], msg["tick"], msg["t"]
        if version <= self.version:
            return
        self.version = version
        for e, attrs in (msg.get("owners") or {}).items():
            for a, m in attrs.items():
                self._model_seen(m)
                if self.owner.get((e, a)) == m:
                    continue
                new_track = (e, a) not in self.owner
                self.owner[(e, a)] = m
                if new_track:
                    self._track_config(e, a)
                self._at(tick, t)
                self.rec.log(f"ownership/{e}/{a}", rr.StateChange(state=m))
                if e not in self.shapes:
                    self.shapes[e] = None
                if a == "pose" or new_track:
                    self._draw_entity(e, tick, t)
                if a == "pose":
                    for wpath in [p for p in self._estimates_shown if p.startswith("world/estimates/")
                                  and p.endswith(f"/{e}") and p.split("/")[2] != m]:
                        self.rec.log(wpath, rr.Clear(recursive=False))
                        self._estimates_shown.discard(wpath)
                if a == "pose" and not new_track:
                    # show where it was handed over, and the first pose of the new owner
                    last = self._latest_pose.get(e)
                    if last is not None and not last[3]:
                        self._queue_pose(e, last[0], last[1], last[2], force=True)
                    self._force_pose.add(e)

    def _on_joints(self, msg: dict) -> None:
        names, pos = msg.get("name") or [], msg.get("position") or []
        if not self._robot_loaded and (self.scene is None or not self.scene.raw.get("robot")):
            # no scene: a shipped robot whose arm joints the telemetry names
            for name in shipped():
                d = description(name)
                if d["arm"][0] in names:
                    self._load_robot(d["urdf"], None)
                    break
        if not self._joints:
            return
        stamp = msg.get("stamp")
        # replay stamps are simulated seconds; a live robot's are wall clock: use the twin's time then
        t = float(stamp) if isinstance(stamp, (int, float)) and -1e-6 <= stamp <= self.t + 1.0 else self.t
        if t < self._last_t.get("joints", -math.inf) + self.pose_dt - 1e-9:
            return
        self._last_t["joints"] = t
        tick = self.tick
        for n, q in zip(names, pos):
            if n in self._joints:
                s = self._joint_cols.setdefault(n, _Series())
                s.ticks.append(tick)
                s.times.append(t)
                s.values.append(float(q))

    def _on_action(self, msg: dict) -> None:
        stamp = msg.get("stamp")
        t = float(stamp) if isinstance(stamp, (int, float)) and -1e-6 <= stamp <= self.t + 1.0 else self.t
        params = msg.get("params") or {}
        self._text("log/actions", self.tick, t, f"action {msg.get('operation')} {msg.get('phase')}"
                   + (f" {_short(params, 120)}" if params else ""), "INFO")

    def _text(self, path: str, tick: int, t: float, text: str, level: str, rgb=None) -> None:
        self._at(tick, t)
        self.rec.log(path, rr.TextLog(text, level=level, color=rgb))

    def _scalar(self, path: str, tick: int, t: float, value: float, force: bool = False) -> None:
        if not force and t < self._last_t.get(path, -math.inf) + self.pose_dt - 1e-9:
            return
        self._last_t[path] = t
        s = self._series.setdefault(path, _Series())
        s.ticks.append(tick)
        s.times.append(t)
        s.values.append(value)

    def _steps(self) -> dict[str, int]:
        """Steps per model so far: the steps its done/ answers cover (service-stepped), else the message count of
        its busiest state/ or out/ key (one message per step)."""
        done: dict[str, int] = {}
        other: dict[str, int] = {}
        for k in self._keys.values():
            if not k.model:
                continue
            if k.kind == "done":
                done[k.model] = done.get(k.model, 0) + k.steps
            elif k.kind in ("state", "out"):
                other[k.model] = max(other.get(k.model, 0), k.count)
        other.update(done)
        return other

    def _health(self, wall_ns: int, final: bool = False) -> None:
        """Real-time factor and step rates over the last ``health_period`` of wall time (and over
        what is left at the end)."""
        self._wall_ns = wall_ns
        prev = self._health_prev
        if prev is not None:
            dw = (wall_ns - prev[0]) * 1e-9
            if self.t <= prev[1] or dw <= 0 or (dw * 1e9 < self.health_period_ns and not (final and dw > 0.02)):
                return
        steps = self._steps()
        step_s = {m: tuple(v) for m, v in self._step_s.items()}
        if prev is None:
            self._health_prev = (wall_ns, self.t, steps, step_s)
            return
        tick, t = self.tick, self.t
        if "health/rtf" not in self._series:
            self._series_style("health/rtf", "real-time factor", (60, 60, 60))
        self._scalar("health/rtf", tick, t, (t - prev[1]) / dw, force=True)
        for m, n in steps.items():
            self._scalar(f"health/step_rate/{m}", tick, t, (n - prev[2].get(m, 0)) / dw, force=True)
            s0, c0 = prev[3].get(m, (0.0, 0))
            s1, c1 = step_s.get(m, (0.0, 0))
            if c1 > c0:
                self._scalar(f"health/step_ms/{m}", tick, t, 1e3 * (s1 - s0) / (c1 - c0), force=True)
        self._health_prev = (wall_ns, t, steps, step_s)

    # ---------------------------------------------------------------- output
    def flush(self) -> None:
        """Send the batched poses, joint angles and series as columns (cheap per row)."""
        rec = self.rec
        for e, s in self._poses.items():
            if s.ticks:
                v = np.asarray(s.values, dtype=np.float64)
                rec.send_columns(f"world/{e}", _index(s), rr.Transform3D.columns(translation=v[:, :3], quaternion=v[:,
                                                                                                                    3:7]))
                s.ticks, s.times, s.values = [], [], []
        for n, s in self._joint_cols.items():
            if s.ticks:
                cols = self._joints[n].compute_transform_columns(s.values, clamp=False)
                rec.send_columns(f"world/robot_joints/{n}", _index(s), cols)
                s.ticks, s.times, s.values = [], [], []
        for path, s in self._series.items():
            if s.ticks:
                rec.send_columns(path, _index(s), rr.Scalars.columns(scalars=np.asarray(s.values, dtype=np.float64)))
                s.ticks, s.times, s.values = [], [], []

    def finish(self) -> None:
        """Last poses of every entity (so the end of the timeline shows where things came to rest)
        and the last health window."""
        if self._wall_ns is not None:
            self._health(self._wall_ns, final=True)
        for e, (tick, t, p, logged) in list(self._latest_pose.items()):
            if not logged:
                self._queue_pose(e, tick, t, p, force=True)
        self.flush()


# message kinds (the key's third part) the viewer draws something from
_SHOWN = frozenset(("state", "out", "event", "ownership", "clock", "done", "telemetry"))


def _batch_len(msg) -> int:
    """Ticks a done/ answer (decoded, or its raw payload) covers: 1, plus its ``more``."""
    try:
        more = (codec.unpack(msg) if isinstance(msg, bytes) else msg).get("more")
    except Exception:
        return 1
    return 1 + len(more) if isinstance(more, list) else 1


class _Key:
    """Per key: how many messages came, and every how many one is decoded (``n``, from the key's
    rate in simulated time, so that at most one per ``dt`` of simulated time is decoded)."""

    __slots__ = ("kind", "model", "always", "dt", "min_n", "count", "steps", "n", "skip", "c0", "t0")

    def __init__(self, kind: str, model: str, always: bool, dt: float, min_n: int = 1):
        self.kind, self.model, self.always, self.dt, self.min_n = kind, model, always, dt, min_n
        self.count = 0
        self.steps = 0  # done/ keys: steps answered (a batched answer covers several ticks)
        self.n = min_n
        self.skip = 1
        self.c0 = 0
        self.t0: float | None = None

    def observe(self, t: float) -> None:
        if self.t0 is None or t < self.t0:
            self.c0, self.t0 = self.count, t
        elif t - self.t0 >= 0.25:
            rate = (self.count - self.c0) / (t - self.t0)
            self.n = max(self.min_n, math.ceil(rate * self.dt - 1e-3))
            self.c0, self.t0 = self.count, t


class _Unset:
    pass


_UNSET = _Unset()


def _index(s: _Series):
    return [rr.TimeColumn("tick", sequence=np.asarray(s.ticks, dtype=np.int64)),
            rr.TimeColumn("sim_time", duration=np.asarray(s.times, dtype=np.float64))]
