"""The connector model of the insertion scenario (paper §4.4): is the DIP plugged into the SPU?

Snapping a probe into a tight socket is what a general physics engine does worst: contacts in a
hole with almost no clearance make it jitter, explode or jam. This model replaces that contact
with geometry. It knows the *ideal* pose of the DIP when connected (``connection_pose``) and two
cylinders around it, both on the connection axis (the z axis of the ideal pose) and centred on
the ideal position:

- the **outer** cylinder (``outer: {radius, length}``): once the DIP's origin is inside, physics
  must stop simulating DIP–SPU contacts; the model raises ``enter_outer`` so that a scene trigger
  hands ``dip.collision`` to it (physics then ignores the pair);
- the **inner** cylinder (``inner: {radius, length}``): the DIP is close enough to snap; the
  model raises ``enter_inner`` so that a trigger hands it ``dip.pose``. When it acquires the pose
  (and the handed-over pose is still inside the inner cylinder) it snaps it to the ideal pose,
  raises ``connected`` and from then on publishes ``connected = true``. Handed a pose that went on
  out of the cylinder, it holds it where it is and raises ``leave_inner`` (and ``leave_outer``, if
  it left that too) with its next step, so that the triggers give it back.

Leaving a cylinder raises ``leave_inner`` / ``leave_outer`` (triggers give the responsibilities
back: the pose to ``in_hand`` or the physics, the collision to the physics). A point is inside a
cylinder when, in the ideal frame, ``hypot(x, y) <= radius`` and ``|z| <= length / 2``; leaving
needs ``hysteresis`` metres more, so a DIP wobbling on the boundary does not flood the triggers.
If one step takes the DIP across both boundaries, both events are raised in the natural order
(``enter_outer`` before ``enter_inner``, ``leave_inner`` before ``leave_outer``).

**Deciding from evidence** (``decide: evidence``, the insertion scenes' choice). The socket is not
necessarily where the robot believed it was (its perception has an error the twin is never told), so a
fixed radius round the believed pose misjudges both ways: a DIP guided into a socket 8 mm off the belief
is outside a 4 mm cylinder, and a DIP that goes down *beside* a socket several centimetres off passes
through it. The twin's DIP follows the real arm (the in-hand model places it from the joint positions), so
what it did is known: where it came to rest. A socket's floor stops a DIP at the seat's depth; one that
lands on the rim or the top rests a hole's depth (20 mm) higher; one that misses the block goes lower
(the robot pushes past the seat). So the DIP counts as plugged once it has **come to rest** (it moved less
than ``rest_speed`` × ``rest_time`` over ``rest_time``) **with its end at the seat's depth** (from
``seat_below`` under to ``seat_above`` over the seat: the first is 3 σ of the twin's estimate of the DIP's
height, about 1 mm for a perceived DIP in the hand; the second the contact length of the connector) and
**within reach of a socket** round the believed axis (the socket's opening, hole apothem plus chamfer,
plus 3 σ of the perception's stated position uncertainty, ``position_sigma``). On ``acquire`` it keeps the
DIP where it went (the socket is there), on the seat.

*Once connected it stays connected*: while the model owns the DIP's pose it is the only one who
could tell that the DIP moved, so it keeps it at the ideal pose; the real robot's compliant
controller holds a snapped DIP in place too. A scene that wants to model pulling the DIP out
transfers the pose away (e.g. on a ``release``/``move_arm`` annotation); the model then drops
``connected`` and watches the DIP again. It asks for the pose again (``enter_inner``) only once the DIP has left
the inner cylinder (with ``decide: evidence``, the seat) and come back: a DIP left seated stays unconnected (asking
at once would take the pose straight back, and a pull-out could never be seen). ``max_angle`` (degrees, optional)
additionally requires the DIP's orientation to be within that angle of the ideal one for the inner cylinder.

This is the "ask for a responsibility by raising an event" pattern: a model never takes a
responsibility itself; it raises an event, and the scene decides (with its triggers) whether the
responsibility moves. See ``docs/models.md``.

Params: ``dip`` / ``spu`` (entity names), ``connection_pose`` (world ``[x, y, z(, q)]``; default:
``spu``'s pose ∘ ``connection_offset``), ``connection_offset`` (``[x, y, z(, qx, qy, qz, qw)]`` in
the SPU's frame), ``outer``, ``inner``, ``hysteresis``, ``max_angle``. Reads: ``dip.pose``,
``spu.pose`` (a scene whose entities have other names lists them in the model's ``reads:``).
Outputs (every step): ``connected`` (bool), ``distance_to_ideal`` (m), ``angle_to_ideal`` (deg),
``inside`` ({outer, inner}). Events: ``enter_outer``, ``enter_inner``, ``leave_inner``,
``leave_outer``, ``connected``, each with ``{entity, spu, distance}``. Owned values: the DIP's
``pose``; the DIP's ``collision`` as ``{"enabled": false, "ignore": [spu], "by": <model id>}``.
Evaluators: ``connected()``, ``distance_to_ideal()``.
"""
from __future__ import annotations

import math

import numpy as np

from ..model import Model, Param, StepWarning, evaluator
from ..robot.kinematics import as_pose, compose, invert, quat_angle


class SPU(Model):
    """Two cylinders around the ideal connection pose (see the module docstring)."""

    kind = "spu"
    role = "simulation"
    params = {
        "dip": Param(str, "dip", "the probe entity (its pose is read every step)"),
        "spu": Param(str, "spu", "the socket entity"),
        "connection_pose": Param(list, None, "ideal world pose of the DIP when connected; default: spu pose ∘ offset"),
        "connection_offset": Param(list, [0.0, 0.0, 0.0], "ideal DIP pose in the SPU's frame [x, y, z(, q)]"),
        "outer": Param(dict, {"radius": 0.04, "length": 0.12}, "outer cylinder (m): collisions go to this model"),
        "inner": Param(dict, {"radius": 0.008, "length": 0.02}, "inner cylinder (m): the pose snaps"),
        "hysteresis": Param(float, 0.002, "extra distance (m) needed to leave a cylinder"),
        "max_angle": Param(float, None, "max angle (deg) between DIP and ideal orientation to enter inner"),
        "decide": Param(str, "geometry", "how the DIP counts as plugged: 'geometry' (its origin enters the inner "
                                         "cylinder round the believed ideal pose) or 'evidence' (it came to rest at "
                                         "the seat's depth, where the socket can be: see the module docstring)"),
        "seat_above": Param(float, 0.004, "evidence: how far (m) above the seat a resting DIP still counts as "
                                          "seated (the contact length of the connector)"),
        "seat_below": Param(float, 0.003, "evidence: how far (m) below the seat it may seem to rest (3 sigma of "
                                          "the twin's DIP height: perception of the DIP in the hand, about 1 mm)"),
        "rest_speed": Param(float, 0.005, "evidence: the DIP is at rest below this speed (m/s)..."),
        "rest_time": Param(float, 0.25, "evidence: ... held for this long (s)"),
        "position_sigma": Param(float, None, "evidence: the perception's stated position uncertainty of the socket "
                                             "(m, 1 sigma; default: the socket entity's position_sigma, else 5 mm)"),
    }
    attributes = ("pose", "collision")
    outputs = ("connected", "distance_to_ideal", "angle_to_ideal", "inside")
    events = ("enter_outer", "enter_inner", "leave_inner", "leave_outer", "connected")
    reads = ("dip.pose", "spu.pose")

    def init(self, params: dict, scene: dict) -> None:
        self.p = params
        if params["decide"] not in ("geometry", "evidence"):
            raise ValueError(f"spu model: decide must be geometry or evidence, got {params['decide']!r}")
        ents = scene.get("entities", {})
        self.dip, self.spu = params["dip"], params["spu"]
        for role, name in (("dip", self.dip), ("spu", self.spu)):
            if name not in ents:
                raise KeyError(f"spu model: no entity {name!r} for param {role!r} (entities: {', '.join(ents)})")
        self.fixed_connection = params["connection_pose"] is not None
        self.offset = as_pose(params["connection_offset"])
        self.spu_pose = as_pose(ents[self.spu]["pose"])
        self.ideal = (as_pose(params["connection_pose"]) if self.fixed_connection
                      else compose(self.spu_pose, self.offset))
        self.cyl = {}
        for name in ("outer", "inner"):
            c = params[name]
            r, length = float(c.get("radius", 0)), float(c.get("length", 0))
            if r <= 0 or length <= 0:
                raise ValueError(f"spu model: {name} needs positive radius and length, got {c!r}")
            self.cyl[name] = (r, length)
        if self.cyl["inner"][0] > self.cyl["outer"][0] or self.cyl["inner"][1] > self.cyl["outer"][1]:
            raise ValueError("spu model: the inner cylinder must fit inside the outer one")
        self.dip_pose = as_pose(ents[self.dip]["pose"])
        self.inside = {"outer": False, "inner": False}
        self.connected = False
        self.collision_in: dict | None = None
        self.collision_value = {"enabled": False, "ignore": [self.spu], "by": self.id}
        self.distance = float(np.linalg.norm(self.dip_pose[:3] - self.ideal[:3]))
        self.angle = math.degrees(quat_angle(self.dip_pose[3:], self.ideal[3:]))
        self._warned = False
        self._announce: list[tuple[str, float]] = []  # events of a handover, raised with the next step
        # evidence: where a socket can be round the believed axis (its opening plus 3 sigma of the perception)
        shape = ents[self.spu].get("shape") or {}
        sigma = params["position_sigma"] if params["position_sigma"] is not None else \
            float(ents[self.spu].get("position_sigma", 0.005))
        opening = (float(shape["hole"]) + float(shape["chamfer"]) if shape.get("type") == "socket"
                   else self.cyl["inner"][0])
        self.capture = opening + 3.0 * sigma
        self._trail: list[tuple[float, np.ndarray]] = []  # (t, DIP position) over the last rest_time
        for ent, attr in self.owned:  # owned from the start: judge the scene pose
            if (ent, attr) == (self.dip, "pose"):
                self._take_pose(self.dip_pose)

    # ---------------------------------------------------------------- geometry
    def local(self, pose) -> np.ndarray:
        """The DIP's position in the ideal connection frame."""
        return compose(invert(self.ideal), as_pose(pose))[:3]

    def _in(self, name: str, pose, leaving: bool) -> bool:
        if name == "inner" and self.p["decide"] == "evidence":
            ok = self._seated(pose, leaving)
        else:
            r, length = self.cyl[name]
            h = self.p["hysteresis"] if leaving else 0.0
            x, y, z = self.local(pose)
            ok = math.hypot(x, y) <= r + h and abs(z) <= length / 2 + h
        if ok and name == "inner" and self.p["max_angle"] is not None:  # (either way: a crooked DIP is not in)
            ok = math.degrees(quat_angle(pose[3:], self.ideal[3:])) <= self.p["max_angle"] + (1.0 if leaving else 0.0)
        return ok

    def _seated(self, pose, leaving: bool) -> bool:
        """Evidence that the DIP is in the socket: it has come to rest with its end at the seat's depth
        (a socket's floor stops it there; on the rim or the top it rests a hole's depth higher, beside the
        socket it goes lower), within the reach of a socket round the believed axis."""
        h = self.p["hysteresis"] if leaving else 0.0
        x, y, z = self.local(pose)
        if math.hypot(x, y) > self.capture + h or not -self.p["seat_below"] - h <= z <= self.p["seat_above"] + h:
            return False
        return leaving or self._at_rest()

    def _at_rest(self) -> bool:
        trail = self._trail
        if not trail or trail[-1][0] - trail[0][0] < self.p["rest_time"] - 1e-9:
            return False
        ref = trail[-1][1]
        return max(float(np.linalg.norm(p - ref)) for _, p in trail) <= self.p["rest_speed"] * self.p["rest_time"]

    def _remember(self, t: float, pose) -> None:
        self._trail.append((t, np.asarray(pose[:3], float)))
        while len(self._trail) > 1 and t - self._trail[1][0] >= self.p["rest_time"]:
            self._trail.pop(0)

    # -------------------------------------------------------------------- step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        spu_in = inputs.get(self.spu, {}).get("pose")
        if spu_in is not None and not self.fixed_connection:
            self.spu_pose = as_pose(spu_in)
            if not self.connected:
                self.ideal = compose(self.spu_pose, self.offset)
        owns_pose = self.owns(self.dip, "pose")
        if not owns_pose:
            dip_in = inputs.get(self.dip, {}).get("pose")
            if dip_in is not None:
                self.dip_pose = as_pose(dip_in)
                self._remember(t, self.dip_pose)
                self._classify()
        for name, distance in self._announce:
            self.emit(name, entity=self.dip, spu=self.spu, distance=distance)
        self._announce = []
        self.distance = float(np.linalg.norm(self.dip_pose[:3] - self.ideal[:3]))
        self.angle = math.degrees(quat_angle(self.dip_pose[3:], self.ideal[3:]))
        self.output("connected", self.connected)
        self.output("distance_to_ideal", self.distance)
        self.output("angle_to_ideal", self.angle)
        self.output("inside", dict(self.inside))
        if not owns_pose and self.dip not in inputs and not self._warned:
            self._warned = True
            raise StepWarning(f"no pose of {self.dip!r} in the inputs: add 'reads: [{self.dip}.pose]' "
                              f"to this model's entry in the scene")

    def _classify(self) -> None:
        pose = self.dip_pose
        was_outer, was_inner = self.inside["outer"], self.inside["inner"]
        outer = self._in("outer", pose, leaving=was_outer)
        inner = self._in("inner", pose, leaving=was_inner) and outer
        data = {"entity": self.dip, "spu": self.spu}
        if outer and not was_outer:
            self.inside["outer"] = True
            self.emit("enter_outer", **data, distance=self._dist(pose))
        if inner and not was_inner:
            self.inside["inner"] = True
            self.emit("enter_inner", **data, distance=self._dist(pose))
        if was_inner and not inner:
            self.inside["inner"] = False
            self.emit("leave_inner", **data, distance=self._dist(pose))
        if was_outer and not outer:
            self.inside["outer"] = False
            self.emit("leave_outer", **data, distance=self._dist(pose))

    def _dist(self, pose) -> float:
        return float(np.linalg.norm(np.asarray(pose[:3]) - self.ideal[:3]))

    def _take_pose(self, pose) -> None:
        pose = as_pose(pose)
        if self._in("inner", pose, leaving=True) and self._in("outer", pose, leaving=True):
            if self.p["decide"] == "evidence":
                # the socket is where the DIP went: keep it there, on the seat
                x, y, _ = self.local(pose)
                self.dip_pose = np.concatenate([compose(self.ideal, as_pose([x, y, 0.0]))[:3], pose[3:]])
            else:
                self.dip_pose = self.ideal.copy()
            self.inside = {"outer": True, "inner": True}
            if not self.connected:
                self.connected = True
                # events raised outside step() are not published: announce it with the next step
                self._announce.append(("connected", self._dist(pose)))
        else:
            # handed a pose outside the inner cylinder (it went on after it entered): hold it, do not pretend a
            # connection, and say that it left, so that the scene's triggers give it back (owning the pose, this
            # model no longer reads it: it would hold the DIP there, whatever the arm did)
            self.log.warning("%s handed to %s outside the inner cylinder (%.4f m from ideal): not snapping",
                             self.dip, self.id, self._dist(pose))
            self.dip_pose = pose
            for name in ("inner", "outer"):
                if self.inside[name] and not (name == "outer" and self._in("outer", pose, leaving=True)):
                    self.inside[name] = False
                    self._announce.append((f"leave_{name}", self._dist(pose)))

    # --------------------------------------------------------------- ownership
    def read(self, entity: str, attribute: str):
        if entity == self.dip and attribute == "pose":
            return [float(v) for v in self.dip_pose]
        if entity == self.dip and attribute == "collision":
            return dict(self.collision_value)
        raise KeyError(f"spu model owns only {self.dip}.pose and {self.dip}.collision, not {entity}.{attribute}")

    def acquire(self, entity: str, attribute: str, value, extra: dict) -> None:
        if entity != self.dip:
            raise KeyError(f"spu model handles only {self.dip!r}, not {entity!r}")
        if attribute == "pose":
            self._take_pose(value if value is not None else self.dip_pose)
        else:
            self.collision_in = value
            self.collision_value = {"enabled": False, "ignore": [self.spu], "by": self.id}

    def release(self, entity: str, attribute: str):
        if attribute == "pose":
            pose = [float(v) for v in self.dip_pose]
            self.connected = False
            return pose, {"velocity": [0.0] * 6, "connected_to": self.spu if self.inside["inner"] else None}
        value = self.collision_in if isinstance(self.collision_in, dict) else {"enabled": True}
        self.collision_in = None
        return value, {}

    # --------------------------------------------------------------- evaluators
    @evaluator("connected")
    def is_connected(self) -> bool:
        return self.connected

    @evaluator("distance_to_ideal")
    def distance_to_ideal(self) -> float:
        return self.distance
