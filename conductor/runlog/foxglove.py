"""What the run log adds for Foxglove and Lichtblick, in their well-known schemas (protobuf, written with
``foxglove-sdk``'s message types), so that a run opens there without any plug-in:

- ``/twin/tf`` (``foxglove.FrameTransforms``): each entity's pose in frame ``world`` as the model that owns it
  reports it, at most ``pose_hz`` times per simulated second;
- ``/twin/scene`` (``foxglove.SceneUpdate``): each entity's shape in its own frame, coloured by the model that
  owns its pose and labelled with it, sent again on every change of ownership;
- ``/twin/log`` (``foxglove.Log``): every event, one line each (the conductor's ``handover`` events included).

- ``/twin/ownership`` (``twin.ownership`` JSON): the ownership messages again, the last once more at the run's end,
  for the ownership lanes (which otherwise stop at the last change).

The robot's ``/joint_states`` give the joint plots: see :func:`layout` and ``docs/foxglove/``.
"""
from __future__ import annotations

import json
from typing import Any

from protocol.geometry import container_parts, socket_parts

from ..viewer.colours import CONDUCTOR, Colours

TF, SCENE, LOG = "/twin/tf", "/twin/scene", "/twin/log"
WARN_EVENTS = frozenset({"agent_lost", "trigger_error", "network_lost", "rejoin"})


def _ts(ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


class Views:
    """Turns the twin's decoded messages into Foxglove messages: ``feed(rest, msg, log_ns)`` returns
    ``[(topic, message), ...]`` (``rest`` is the key after ``twin/<ensemble>/``)."""

    def __init__(self, entities: dict[str, Any] | None, models: list[str], pose_hz: float = 60.0) -> None:
        import foxglove.messages as fm

        self.fm = fm
        self.entities = dict(entities or {})
        self.colours = Colours(models)
        self.owner: dict[str, str] = {}  # entity -> the model owning its pose
        self.min_dt = 1.0 / pose_hz if pose_hz > 0 else 0.0
        self._last_t: dict[str, float] = {}  # model -> sim time of its last poses sent

    def feed(self, rest: str, msg: Any, log_ns: int) -> list[tuple[str, Any]]:
        if not isinstance(msg, dict):
            return []
        kind = rest.split("/", 1)[0]
        if kind == "state":
            return self._poses(msg, log_ns)
        if kind == "ownership":
            return self._ownership(msg, log_ns)
        if kind == "event":
            return self._event(msg, log_ns)
        return []

    # ------------------------------------------------------------------------------ poses
    def _poses(self, msg: dict[str, Any], ns: int) -> list[tuple[str, Any]]:
        model, t, values = msg.get("model"), msg.get("t"), msg.get("values")
        if not isinstance(values, dict) or not isinstance(t, (int, float)):
            return []
        last = self._last_t.get(str(model))
        if last is not None and t - last < self.min_dt - 1e-9:
            return []
        fm = self.fm
        out = []
        for entity, attrs in values.items():
            pose = attrs.get("pose") if isinstance(attrs, dict) else None
            if self.owner.get(entity, model) != model or pose is None or len(pose) != 7:
                continue
            x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
            out.append(fm.FrameTransform(timestamp=_ts(ns), parent_frame_id="world", child_frame_id=str(entity),
                                         translation=fm.Vector3(x=x, y=y, z=z),
                                         rotation=fm.Quaternion(x=qx, y=qy, z=qz, w=qw)))
        if not out:
            return []
        self._last_t[str(model)] = float(t)
        return [(TF, fm.FrameTransforms(transforms=out))]

    # ------------------------------------------------------------------------------ shapes
    def _ownership(self, msg: dict[str, Any], ns: int) -> list[tuple[str, Any]]:
        owners = msg.get("owners")
        if not isinstance(owners, dict):
            owners = {}
        self.owner = {e: str(a.get("pose")) for e, a in owners.items() if isinstance(a, dict) and a.get("pose")}
        return [(SCENE, self.fm.SceneUpdate(entities=[
            self._entity(e, ns) for e in sorted(set(self.entities) | set(self.owner))]))]

    def _entity(self, name: str, ns: int) -> Any:
        fm = self.fm
        owner = self.owner.get(name, "")
        r, g, b = self.colours.rgb(owner or CONDUCTOR)
        colour = fm.Color(r=r / 255, g=g / 255, b=b / 255, a=0.85)
        shape = (self.entities.get(name) or {}).get("shape") or {}
        kind = shape.get("type")
        cubes, spheres, cylinders = [], [], []
        try:
            if kind == "sphere":
                d = 2 * float(shape["radius"])
                spheres.append(fm.SpherePrimitive(pose=_pose(fm), size=fm.Vector3(x=d, y=d, z=d), color=colour))
            elif kind == "box":
                sx, sy, sz = (float(v) for v in shape["size"])
                cubes.append(fm.CubePrimitive(pose=_pose(fm), size=fm.Vector3(x=sx, y=sy, z=sz), color=colour))
            elif kind == "cylinder":
                d, h = 2 * float(shape["radius"]), float(shape["length"])
                cylinders.append(fm.CylinderPrimitive(pose=_pose(fm), size=fm.Vector3(x=d, y=d, z=h), bottom_scale=1.0,
                                                      top_scale=1.0, color=colour))
            elif kind in ("container", "socket"):
                for p in (container_parts(shape) if kind == "container" else socket_parts(shape)):
                    sx, sy, sz = (float(v) for v in p["size"])
                    cubes.append(fm.CubePrimitive(pose=_pose(fm, p["pos"], p["quat"]),
                                                  size=fm.Vector3(x=sx, y=sy, z=sz), color=colour))
        except (KeyError, TypeError, ValueError):  # a shape the scene checker would refuse: the label only
            cubes, spheres, cylinders = [], [], []
        text = fm.TextPrimitive(pose=_pose(fm, [0.0, 0.0, 0.08]), billboard=True, font_size=14.0, scale_invariant=True,
                                color=fm.Color(r=1.0, g=1.0, b=1.0, a=1.0), text=f"{name} ({owner or 'nobody'})")
        return fm.SceneEntity(timestamp=_ts(ns), frame_id=name, id=name, frame_locked=True,
                              metadata=[fm.KeyValuePair(key="owner", value=owner)],
                              cubes=cubes, spheres=spheres, cylinders=cylinders, texts=[text])

    # ------------------------------------------------------------------------------ text
    def _event(self, msg: dict[str, Any], ns: int) -> list[tuple[str, Any]]:
        name, model = str(msg.get("name")), str(msg.get("model"))
        try:
            data = json.dumps(msg.get("data"), default=str, sort_keys=True)
        except TypeError:  # (keys of two kinds, 1 and "b", cannot be sorted)
            data = json.dumps(msg.get("data"), default=str)
        return [(LOG, self._log(ns, model, f"{model}.{name} {data}", warn=name in WARN_EVENTS))]

    def _log(self, ns: int, name: str, text: str, warn: bool) -> Any:
        fm = self.fm
        return fm.Log(timestamp=_ts(ns), level=fm.LogLevel.Warning if warn else fm.LogLevel.Info, message=text,
                      name=name, file="", line=0)


def _pose(fm: Any, pos: Any = (0.0, 0.0, 0.0), quat: Any = (0.0, 0.0, 0.0, 1.0)) -> Any:
    return fm.Pose(position=fm.Vector3(x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
                   orientation=fm.Quaternion(x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3])))


# ------------------------------------------------------------------------------------------- layout
def layout(scene: Any, joint_names: list[str]) -> dict[str, Any]:
    """A Foxglove / Lichtblick layout (``Import layout`` in either) for a run of ``scene``: the 3D scene (entity
    shapes coloured by owner, following ``/twin/tf``), one ownership lane per responsibility (State Transitions on
    ``/twin/ownership``), the robot's joint positions (Plot on ``/joint_states``) and the handover/event log."""
    lanes = [{"value": f"/twin/ownership.owners.{e}.{a}", "timestampMethod": "receiveTime", "label": f"{e}.{a}"}
             for e, ent in sorted(scene.entities.items()) for a in sorted(ent.attributes)]
    joints = [{"value": f"/joint_states.position[{i}]", "enabled": True, "timestampMethod": "receiveTime",
               "label": name} for i, name in enumerate(joint_names)]
    points = [ent.pose[:3] for ent in scene.entities.values()] or [[0.4, 0.0, 0.1]]
    centre = [sum(p[i] for p in points) / len(points) for i in range(3)]
    spread = max(max(abs(p[i] - centre[i]) for p in points for i in range(3)), 0.05)
    config: dict[str, Any] = {
        "3D!twin": {  # looking at the scene's entities from a little above, far enough to see them all
            "followMode": "follow-none", "followTf": "world",
            "cameraState": {"distance": round(max(0.4, 6 * spread), 3), "perspective": True, "phi": 55,
                            "thetaOffset": 35, "target": [0, 0, 0], "targetOffset": [round(c, 3) for c in centre],
                            "targetOrientation": [0, 0, 0, 1],
                            "fovy": 45, "near": 0.01, "far": 500},
            "scene": {"enableStats": False, "transforms": {"showLabel": False, "axisScale": 0.4, "lineWidth": 1}},
            "topics": {SCENE: {"visible": True}},
            "layers": {"grid": {"layerId": "foxglove.Grid", "instanceId": "grid", "label": "Grid", "visible": True,
                                "frameId": "world", "size": 2, "divisions": 20, "lineWidth": 1,
                                "color": "#248eff66", "position": [0, 0, 0], "rotation": [0, 0, 0]}},
        },
        "StateTransitions!ownership": {"paths": lanes, "isSynced": True, "showPoints": True},
        "Plot!joints": {"title": "joint positions (rad, m)", "paths": joints, "isSynced": True,
                        "showLegend": True, "legendDisplay": "floating", "xAxisVal": "timestamp"},
        "RosOut!log": {"topicToRender": LOG, "searchTerms": [], "minLogLevel": 1},
    }
    return {
        "configById": config, "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1.0},
        "layout": {"direction": "row", "splitPercentage": 55, "first": "3D!twin",
                   "second": {"direction": "column", "splitPercentage": 40, "first": "StateTransitions!ownership",
                              "second": {"direction": "column", "splitPercentage": 60, "first": "Plot!joints",
                                         "second": "RosOut!log"}}},
    }
