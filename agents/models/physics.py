"""The physics main model: a pybullet world with the scene's robot, the table and the scene's entities.

The main model of an ensemble owns every pose at the start of a run (paper §3.1) and takes back
whatever another model lets go of. This one keeps a pybullet ``DIRECT`` world stepped at a fixed
``time_step``; each ``step(dt)`` runs the substeps that keep the world's time on the clock's (at least one;
:class:`~agents.engines.bodies.Substeps`: two of 1/240 s at 120 Hz).

**World.** The table top is the plane z = 0 (named ``table``). The robot is the scene's
robot block (:class:`protocol.robot.Robot`: its URDF at its base, fixed; default the shipped Panda). Each
scene entity becomes one body built from its ``shape`` (:mod:`protocol.geometry`): ``sphere``,
``box``, ``cylinder`` (axis along the body's z), ``container`` (a static compound of the boxes of
:func:`~protocol.geometry.container_parts`), ``socket`` (the same of :func:`~protocol.geometry.socket_parts`:
the insertion scenario's SPU with its hole and chamfer), ``urdf`` (``shape.file``; its pose is its base link's
frame, not the centre of mass pybullet places). Containers and entities
tagged ``static`` (or with ``mass: 0``) are static; the rest is dynamic with the entity's ``mass``
or a default: a sphere is taken for a hollow ball with a tennis ball's areal density (0.057 kg at
r = 0.033 m, scaling with r²), boxes and cylinders are solid at ``density`` kg/m³. An entity's
``friction`` sets its lateral friction (else ``friction``). pybullet multiplies the two bodies'
coefficients in a contact, so the table and static bodies get friction and restitution 1.0 (unless
the entity sets ``friction``): a contact then has the moving body's own coefficients.

**Robot.** The robot follows the telemetry joint positions (``telemetry["joints"]``) under
``POSITION_CONTROL`` with the real force limits: 87/87/87/87/12/12/12 Nm for the arm, and
``finger_force`` (default 70 N, the Franka Hand's continuous grasp force; the URDF says 20 N) per
finger, so the fingers make real contacts and squeeze what they close on as hard as the robot
did. Telemetry velocities are used as target velocities when the stream has them. Until the first
joint state the robot holds ``initial_joints``; the first joint state is written with
``resetJointState`` (the robot starts where the recording starts, without a swing).

**Owned and followed poses.** ``read(entity, "pose")`` is the body's pose after the last step;
velocities are kept too. While another model owns an entity's pose (its value arrives as
``inputs[entity]["pose"]``) the body is carried along: every substep it is put on the straight
line (slerp for the orientation) from where it was to the owner's value, with the owner's
velocity (the poses it sent over the last ``velocity_window`` seconds, over their own times), so it
still pushes and collides with everything else; a body whose owner has sent
nothing yet stays where it was handed over. ``acquire`` continues from the handed-over pose with
``extra["velocity"]`` ([vx, vy, vz, wx, wy, wz]) if given, else with the velocity of the poses
the owner sent over the last ``velocity_window`` seconds (zero if it has sent nothing new for more
than twice its usual interval): a ball released from a swinging hand flies on. ``release``
returns ``(pose, {"velocity": [...]})``.

**Collision.** While another model owns an entity's ``collision`` its value says what physics
does with the body's contacts: ``true`` (or ``{"enabled": true}``) = collide as usual; ``false``
= no contacts with the entity's ``collision_partners`` (param: entity -> names; default every
other entity); ``{"enabled": false, "ignore": [names]}`` = no contacts with those names. Names are
entities, ``table``, ``robot`` (every robot link) or a robot link name. Contacts come back when
the value says so or physics acquires the collision again (``setCollisionFilterPair``, only on
changes). Physics' own value is ``true``.

**Grasp baselines** (``grasp_binding``): ``none`` = pure simulation, friction alone holds an
object; ``signal`` = when a ``move_hand`` action with ``command: close`` ends, the graspable
(tag ``graspable``) entity whose centre is nearest the fingertip centre, within
``bind_distance``, is fixed to the robot's hand link (a ``JOINT_FIXED`` constraint) until a ``release``
action or a ``move_hand`` ``open`` starts; ``force`` = no semantic signal: an object both fingers
press with a normal force above ``bind_force`` (summed over the contact points) is fixed to the
hand, and let go once either finger's force stays below ``unbind_force`` for ``unbind_substeps``
substeps (as Gazebo's grasp plugin does). Only entities whose pose physics owns are bound; a
bound entity whose pose is handed to another model is unbound first.

**Virtual entities.** An entity tagged ``virtual`` gets no body in this world (a fluid model's
particle set, whose pose is an N x 3 array, is one): physics only holds the last value handed to it.
An owner's pose that is not a 7-vector for a body is ignored with a warning.

**One-world fluid.** ``particles: {container, count, radius, mass, friction}`` fills a container
entity with ``count`` untracked spheres in this world, at this world's time step and solver
settings (Table 1's single-simulation baseline); they go out as the ``particles`` (N x 3) and
``spilled`` outputs every step.

Params: see :attr:`Physics.params`. Attributes: ``pose``, ``collision``. Reads: ``*.pose``,
``*.collision``. Outputs: ``links`` {link: pose} for the robot links in ``links`` (every step);
``bound`` (entities fixed to the hand; only when ``grasp_binding`` is not ``none``). Events:
``contact_begin`` / ``contact_end`` {a, b} when two named things start/stop touching (entities
by name, the table as ``table``, robot links by their link name (a finger link, for instance);
``a < b``; checked after every substep: contact points closer than ``contact_margin`` or
with a normal force; a bounce within one step raises both); ``grasp_bound`` /
``grasp_unbound`` {entity, mode}. Evaluators: ``closest(tag, link="hand")`` ->
{entity, distance} (the entity carrying ``tag`` whose centre is nearest the link frame's origin;
entity None if none has the tag), ``distance(a, b)`` (centre distance between entities and/or
robot links), ``velocity(entity)``, ``contacts(name)`` (names touching it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.geometry import STATIC_SHAPES, container_parts, is_static, socket_parts
from protocol.robot import resolve_robot, urdf_path

from ..engines.bodies import Followed, Substeps, default_mass
from ..engines.pybullet_robot import BulletRobot
from ..model import Model, Param, StepWarning, evaluator
from ..robot.kinematics import as_pose, base_link_frame, compose, invert, quat_matrix, quat_slerp
from .binding import GraspBindings

# the same particle lattice and rim as the fluid model's, so both start alike
from .fluid import fill_points, interior_mask, rim_top

BINDINGS = ("none", "signal", "force")


@dataclass
class Body:
    """One scene entity in the pybullet world."""

    name: str
    id: int
    dynamic: bool
    tags: tuple[str, ...]
    links: tuple[int, ...] = (-1,)
    pose: list[float] = field(default_factory=list)
    velocity: list[float] = field(default_factory=lambda: [0.0] * 6)
    inertial: np.ndarray | None = None  # its centre of mass in its frame, where a URDF puts it off the origin

    def to_frame(self, pos: Any, orn: Any, lin: Any = None, ang: Any = None) -> tuple[list[float], list[float]]:
        """The pose (and velocity) of the body's frame, from pybullet's, which are its centre of mass's."""
        if self.inertial is None:
            return [*pos, *orn], ([*lin, *ang] if lin is not None else [])
        pose = compose([*pos, *orn], invert(self.inertial))
        vel = []
        if lin is not None:
            vel = [*(np.asarray(lin) + np.cross(ang, pose[:3] - np.asarray(pos))), *ang]
        return [float(v) for v in pose], [float(v) for v in vel]

    def to_mass(self, pose: list[float], vel: list[float] | None = None) -> tuple[list[float], list[float]]:
        """What pybullet takes for a pose (and velocity) of the body's frame: its centre of mass's."""
        if self.inertial is None:
            return pose, vel or []
        com = compose(pose, self.inertial)
        out = []
        if vel:
            out = [*(np.asarray(vel[:3]) + np.cross(vel[3:6], com[:3] - np.asarray(pose[:3]))), *vel[3:6]]
        return [float(v) for v in com], [float(v) for v in out]


_Carried = tuple[Body, list[float], list[float], list[float]]
"""A body another model owns, carried through a step: (body, from pose, to pose, velocity)."""
_Pairs = set[tuple[str, str]]
"""Named pairs of things in contact (``a < b``)."""


def compound_body(p: Any, c: int, parts: list[dict[str, Any]], pose: np.ndarray) -> tuple[int, tuple[int, ...]]:
    """A static body of boxes ``{size, pos, quat}`` (in its frame) at ``pose``: pybullet keeps at most 16
    children per compound shape, so the first 16 are the base and each further 16 a fixed link."""
    cols = []
    for k in range(0, len(parts), 16):
        chunk = parts[k:k + 16]
        cols.append(p.createCollisionShapeArray(
            [p.GEOM_BOX] * len(chunk), halfExtents=[[float(v) / 2 for v in q["size"]] for q in chunk],
            collisionFramePositions=[[float(v) for v in q["pos"]] for q in chunk],
            collisionFrameOrientations=[[float(v) for v in q["quat"]] for q in chunk], physicsClientId=c))
    extra = cols[1:]
    bid = p.createMultiBody(0.0, cols[0], basePosition=pose[:3].tolist(), baseOrientation=pose[3:].tolist(),
                            linkMasses=[0.0] * len(extra), linkCollisionShapeIndices=extra,
                            linkVisualShapeIndices=[-1] * len(extra), linkPositions=[[0, 0, 0]] * len(extra),
                            linkOrientations=[[0, 0, 0, 1]] * len(extra),
                            linkInertialFramePositions=[[0, 0, 0]] * len(extra),
                            linkInertialFrameOrientations=[[0, 0, 0, 1]] * len(extra),
                            linkParentIndices=[0] * len(extra), linkJointTypes=[p.JOINT_FIXED] * len(extra),
                            linkJointAxis=[[0, 0, 1]] * len(extra), physicsClientId=c)
    return bid, tuple(range(-1, len(extra)))


class Physics(GraspBindings, Model):
    """pybullet world, main model (see the module docstring)."""

    kind = "physics"
    role = "simulation"
    params = {
        "time_step": Param(float, 1.0 / 240.0,
                           "fixed simulation time step (s), at most the step period; a step runs as many as "
                           "keep the world's time on the clock's", positive=True,
                           within_period=True),
        "gravity": Param(list, [0.0, 0.0, -9.81], "gravity vector (m/s^2)"),
        "solver_iterations": Param(int, 50, "pybullet numSolverIterations (fewer = faster, softer contacts)"),
        "links": Param(list, [], "robot links whose poses go out as the 'links' output (default: the robot's hand "
                                 "and fingers)"),
        "grasp_binding": Param(str, "none", "baseline grasp model: none | signal | force", choices=BINDINGS),
        "bind_distance": Param(float, 0.06, "signal binding: max distance (m) fingertip centre - object centre"),
        "bind_force": Param(float, 5.0, "force binding: normal force (N) each finger must exceed to bind"),
        "unbind_force": Param(float, 1.0, "force binding: a finger force (N) below this counts towards unbinding"),
        "unbind_substeps": Param(int, 5, "force binding: consecutive weak substeps that unbind"),
        "collision_partners": Param(dict, {}, "entity -> names it stops colliding with while another model "
                                              "owns its collision (default: every other entity)"),
        "friction": Param(float, 0.8, "lateral friction of entities that do not set 'friction'"),
        "finger_friction": Param(float, 1.0, "lateral friction of the finger pads"),
        "rolling_friction": Param(float, 2e-4, "rolling friction of dynamic entities"),
        "spinning_friction": Param(float, 1e-3, "spinning friction of dynamic entities"),
        "restitution": Param(dict, {"sphere": 0.6, "box": 0.1, "cylinder": 0.1, "urdf": 0.1},
                             "restitution of dynamic entities by shape type"),
        "density": Param(float, 500.0, "density (kg/m^3) of boxes and cylinders without a 'mass'"),
        "finger_force": Param(float, 0.0, "force limit of each gripper joint (N, or N m for a revolute drive; 0: "
                                          "the robot description's gripper force)"),
        "position_gain": Param(float, 0.3, "POSITION_CONTROL position gain of the arm joints at a 1/240 s time step "
                                                 "(scaled with time_step: the same tracking time constant)"),
        "finger_gain": Param(float, 0.1, "POSITION_CONTROL position gain of the finger joints at 1/240 s (scaled too)"),
        "velocity_gain": Param(float, 1.0, "POSITION_CONTROL velocity gain of every joint"),
        "initial_joints": Param(list, [], "joint positions held until the first telemetry (the arm's, then the "
                                          "gripper's; default: the robot description's ready posture)"),
        "velocity_window": Param(float, 0.05, "acquire without a handed-over velocity: estimate it over "
                                               "this many seconds of the owner's poses"),
        "particles": Param(dict, {}, "one-world fluid (Table 1's baseline): {container: NAME, count: N, radius: m, "
                                      "mass: kg, friction: mu} fills that container entity with N untracked "
                                      "particles in this world; outputs 'particles' and 'spilled' every step"),
        "contact_events": Param(bool, True, "raise contact_begin / contact_end"),
        "contact_margin": Param(float, 1e-3, "contact points closer than this (m) count as touching"),
    }
    attributes = ("pose", "collision")
    outputs = ("links", "bound", "particles", "spilled")  # the last two with the particles param
    events = ("contact_begin", "contact_end", "grasp_bound", "grasp_unbound")
    reads = ("*.pose", "*.collision")

    # ------------------------------------------------------------------ set-up
    def init(self, params: dict, scene: dict) -> None:
        import pybullet as p

        self.p = p
        self.prm = params
        if params["grasp_binding"] not in BINDINGS:
            raise ValueError(f"grasp_binding must be one of {', '.join(BINDINGS)}, got {params['grasp_binding']!r}")
        self.ts = float(params["time_step"])
        self.substeps = Substeps(self.ts, self.rate)
        self.cid = c = p.connect(p.DIRECT)
        p.setTimeStep(self.ts, physicsClientId=c)
        p.setGravity(*map(float, params["gravity"]), physicsClientId=c)
        # Bullet keeps the contact breaking threshold in a global of the process: set its default (0.02 m)
        # explicitly, so this world never depends on another pybullet world made in the same process
        p.setPhysicsEngineParameter(numSolverIterations=int(params["solver_iterations"]),
                                    contactBreakingThreshold=0.02, physicsClientId=c)
        self.bodies: dict[str, Body] = {}
        self.by_id: dict[int, Body] = {}
        self.names: dict[tuple[int, int], str] = {}  # (body id, link) -> name used in events
        # the table
        self.table = p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=c), physicsClientId=c)
        p.changeDynamics(self.table, -1, lateralFriction=1.0, restitution=1.0, physicsClientId=c)
        self.names[(self.table, -1)] = "table"
        self._load_robot(scene.get("robot") or {})
        self.virtual_values: dict[tuple[str, str], Any] = {}
        self.virtual_extra: dict[tuple[str, str], dict] = {}  # what came with them, handed on with them
        self.virtual = set()  # entities tagged 'virtual' have no body here (e.g. a fluid model's particle set)
        for name, ent in (scene.get("entities") or {}).items():
            if "virtual" in (ent.get("tags") or ()):
                self.virtual.add(name)
                continue
            self._add_entity(name, ent)
        self.dynamic = [b for b in self.bodies.values() if b.dynamic]
        self.particles: list[int] = []
        if params["particles"]:
            self._add_particles(dict(params["particles"]), scene.get("entities") or {})
        self.followed = Followed(float(params["velocity_window"]))  # the bodies other models own the pose of
        self.disabled: dict[str, set[tuple[int, int, int, int]]] = {}  # entity -> filtered link pairs
        self.collision_values: dict[str, Any] = {}
        self.bound: dict[str, int] = {}  # entity -> constraint id
        self.weak: dict[str, int] = {}
        self.contacts: set[tuple[str, str]] = set()
        for b in self.bodies.values():
            b.pose = self._body_pose(b)
        for name in self.bodies:
            if (name, "pose") not in self.owned:
                self.followed.follow(name, self.bodies[name].pose, 0.0)
        g = self.robot_spec.gripper
        links = list(params["links"]) or [g.hand, *g.fingers]
        self._out_links = [self.robot_links[n] for n in links if n in self.robot_links]
        self._out_names = [n for n in links if n in self.robot_links]
        unknown = [n for n in links if n not in self.robot_links]
        if unknown:
            raise ValueError(f"unknown robot links {unknown} (the robot has: {', '.join(self.robot_links)})")

    def _add_particles(self, spec: dict, entities: dict) -> None:
        """Fill a container entity with ``count`` spheres of this world (the single-simulation fluid
        that the paper's Table 1 compares a separate fluid model against). They take part in every
        collision check of this world, robot links included, at this world's time step and solver
        settings; they are not entities (nobody can own them) and are not contact-event names."""
        unknown = set(spec) - {"container", "count", "radius", "mass", "friction"}
        if unknown:
            raise ValueError(f"particles: unknown keys {sorted(unknown)} (container, count, radius, mass, friction)")
        name = spec.get("container")
        ent = entities.get(name)
        if ent is None or ent["shape"].get("type") != "container":
            raise ValueError(f"particles: container {name!r} is not a container entity of the scene")
        n, r = int(spec.get("count", 50)), float(spec.get("radius", 0.008))
        if n <= 0 or r <= 0:
            raise ValueError("particles: count and radius must be positive")
        p, c = self.p, self.cid
        self.particle_container = (ent["shape"], as_pose(ent.get("pose") or [0, 0, 0]))
        shape, pose = self.particle_container
        world = pose[:3] + fill_points(shape, n, r) @ quat_matrix(pose[3:]).T
        sphere = p.createCollisionShape(p.GEOM_SPHERE, radius=r, physicsClientId=c)
        self.particle_radius = r
        for pt in world:
            b = p.createMultiBody(float(spec.get("mass", 0.002)), sphere, basePosition=pt.tolist(), physicsClientId=c)
            p.changeDynamics(b, -1, lateralFriction=float(spec.get("friction", 0.05)), rollingFriction=0.0,
                             spinningFriction=0.0, restitution=0.0, linearDamping=0.05, angularDamping=0.05,
                             physicsClientId=c)
            self.particles.append(b)

    def _particle_outputs(self) -> None:
        get, c = self.p.getBasePositionAndOrientation, self.cid
        pts = np.array([get(b, physicsClientId=c)[0] for b in self.particles], dtype=float)
        shape, _ = self.particle_container
        cname = self.prm["particles"]["container"]
        body = self.bodies.get(cname)
        pose = as_pose(body.pose) if body is not None and body.pose is not None else self.particle_container[1]
        inside = interior_mask(shape, pose, pts, margin=self.particle_radius)
        below = pts[:, 2] < rim_top(shape, pose)
        self.output("particles", pts)
        self.output("spilled", int((~inside & below).sum()))

    def _load_robot(self, spec: dict) -> None:
        """The scene's robot, driven from the telemetry (:class:`agents.engines.pybullet_robot.BulletRobot`)."""
        g = float(self.prm["finger_gain"]), float(self.prm["position_gain"]), float(self.prm["velocity_gain"])
        self.arm = arm = BulletRobot(self.p, self.cid, resolve_robot(spec or None), time_step=self.ts,
                                     finger_force=float(self.prm["finger_force"]), gains=g,
                                     initial=[float(v) for v in self.prm["initial_joints"]])
        self.robot_spec, self.robot, self.robot_links = arm.spec, arm.body, dict(arm.index.link)
        self.fingers, self.hand, self.tip = arm.fingers, arm.hand, arm.tip
        for name, li in self.robot_links.items():
            self.names[(self.robot, li)] = name
        for li in self.fingers:
            self.p.changeDynamics(self.robot, li, lateralFriction=float(self.prm["finger_friction"]),
                                  physicsClientId=self.cid)

    def _tip_point(self) -> list[float]:
        """The point between the fingertips (the gripper's tip link and offset), in the world."""
        return self.arm.tip_point()

    def _add_entity(self, name: str, ent: dict) -> None:
        p, c = self.p, self.cid
        shape = ent["shape"]
        t = shape["type"]
        pose = as_pose(ent.get("pose") or [0, 0, 0])
        tags = tuple(ent.get("tags") or ())
        mass = ent.get("mass")
        static = is_static(shape, tags, mass)
        if t == "urdf":
            bid = p.loadURDF(urdf_path(shape["file"]), pose[:3].tolist(), pose[3:].tolist(),
                             useFixedBase=static, flags=p.URDF_IGNORE_VISUAL_SHAPES, physicsClientId=c)
            links = tuple(range(-1, p.getNumJoints(bid, physicsClientId=c)))
        else:
            if t == "sphere":
                col = p.createCollisionShape(p.GEOM_SPHERE, radius=float(shape["radius"]), physicsClientId=c)
            elif t == "box":
                col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[float(v) / 2 for v in shape["size"]],
                                             physicsClientId=c)
            elif t == "cylinder":
                col = p.createCollisionShape(p.GEOM_CYLINDER, radius=float(shape["radius"]),
                                             height=float(shape["length"]), physicsClientId=c)
            elif t in STATIC_SHAPES:
                bid, links = compound_body(p, c, container_parts(shape) if t == "container" else socket_parts(shape),
                                           pose)
            else:
                raise ValueError(f"entity {name!r}: unknown shape type {t!r}")
            if t not in STATIC_SHAPES:
                m = 0.0 if static else float(mass if mass is not None
                                             else default_mass(shape, float(self.prm["density"])))
                bid = p.createMultiBody(m, col, basePosition=pose[:3].tolist(), baseOrientation=pose[3:].tolist(),
                                        physicsClientId=c)
                links = (-1,)
        fr = ent.get("friction")
        for li in links:
            if static:
                p.changeDynamics(bid, li, lateralFriction=float(fr if fr is not None else 1.0), restitution=1.0,
                                 physicsClientId=c)
            else:
                rest = float((self.prm["restitution"] or {}).get(t, 0.1))
                p.changeDynamics(bid, li, lateralFriction=float(fr if fr is not None else self.prm["friction"]),
                                 rollingFriction=float(self.prm["rolling_friction"]),
                                 spinningFriction=float(self.prm["spinning_friction"]), restitution=rest,
                                 physicsClientId=c)
        b = Body(name, bid, not static, tags, links)
        info = p.getDynamicsInfo(bid, -1, physicsClientId=c)
        inertial = np.array([*info[3], *info[4]], float)
        if not np.allclose(inertial, [0, 0, 0, 0, 0, 0, 1], atol=1e-9):
            b.inertial = inertial
        self.bodies[name] = b
        self.by_id[bid] = b
        for li in links:
            self.names[(bid, li)] = name

    # --------------------------------------------------------------- helpers
    def _base_pose(self, bid: int) -> list[float]:
        pos, orn = self.p.getBasePositionAndOrientation(bid, physicsClientId=self.cid)
        return [*pos, *orn]

    def _body_pose(self, b: Body) -> list[float]:
        """An entity's pose: its frame's (pybullet places a body by its centre of mass)."""
        return b.to_frame(*self.p.getBasePositionAndOrientation(b.id, physicsClientId=self.cid))[0]

    def _place(self, b: Body, pose: list[float], vel: list[float] | None = None) -> None:
        """Put an entity's frame at ``pose`` (with velocity ``vel``, a dynamic body's)."""
        at, v = b.to_mass(pose, vel if b.dynamic else None)
        self.p.resetBasePositionAndOrientation(b.id, at[:3], at[3:], physicsClientId=self.cid)
        if v:
            self.p.resetBaseVelocity(b.id, v[:3], v[3:], physicsClientId=self.cid)

    def _link_pose(self, li: int) -> list[float]:
        if li < 0:  # the base link's frame (pybullet reports where its centre of mass is)
            return [float(v) for v in base_link_frame(self.p, self.robot, self.cid)]
        s = self.p.getLinkState(self.robot, li, computeForwardKinematics=1, physicsClientId=self.cid)
        return [*s[4], *s[5]]

    def _links_out(self) -> dict[str, list[float]]:
        """The ``links`` output: each named link's frame. pybullet's batched ``getLinkStates`` takes only
        links >= 0 (the base link, -1, ends the process), so the base link's frame comes from ``_link_pose``."""
        moving = [li for li in self._out_links if li >= 0]
        states = dict(zip(moving, self.p.getLinkStates(self.robot, moving, computeForwardKinematics=1,
                                                       physicsClientId=self.cid), strict=True)) if moving else {}
        return {nm: [*states[li][4], *states[li][5]] if li >= 0 else self._link_pose(li)
                for nm, li in zip(self._out_names, self._out_links, strict=True)}

    def _where(self, name: str) -> list[float]:
        """Current pose of an entity or a robot link (KeyError if neither); ``hand`` is the robot's hand link
        and ``tip`` the point between its fingertips, whatever the robot calls them."""
        if name == "hand" and name not in self.bodies:
            name = self.robot_spec.gripper.hand
        elif name == "tip" and name not in self.bodies:
            return [*self._tip_point(), *self._link_pose(self.tip)[3:]]
        if name in self.bodies:
            return self._body_pose(self.bodies[name])
        if name in self.robot_links:
            return self._link_pose(self.robot_links[name])
        raise KeyError(f"no entity or robot link named {name!r}")

    # ------------------------------------------------------------------ step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        n = self.substeps.take(dt)
        self.arm.drive(telemetry.get("joints"))
        mode = self.prm["grasp_binding"]
        if mode == "signal":
            for a in telemetry.get("actions") or ():
                self._signal(a)
        carried, bad = self._follow(t, n, inputs)
        if inputs:
            self._update_collisions(inputs)
        touched, now = self._substeps(n, carried, mode)
        self._place_carried(carried)
        self._read_dynamic()
        if self._out_links:
            self.output("links", self._links_out())
        if mode != "none":
            self.output("bound", sorted(self.bound))
        if self.particles:
            self._particle_outputs()
        if self.prm["contact_events"]:
            self._contact_events(touched, now)
        if bad:
            raise StepWarning(f"pose of {', '.join(bad)} from its owner is not [x, y, z, qx, qy, qz, qw]: the body "
                              "stays where it was (tag the entity 'virtual' if it has no body in this world)")

    def _follow(self, t: float, n: int, inputs: dict) -> tuple[list[_Carried], list[str]]:
        """The bodies other owners carry this step (their new values are the targets), and the entities
        whose owner sent a value that is not a pose (once each)."""
        bad: list[str] = []
        # a carried body's velocity is its owner's motion (the distinct poses it sent, over their own times): over
        # this step's time, an owner at half this model's rate gave 0 and 2x the speed on alternate steps
        carried = [(self.bodies[name], self.bodies[name].pose, target, v)
                   for name, target, v in self.followed.this_step(inputs, t, self.t, bad)]
        return carried, bad

    def _substeps(self, n: int, carried: list[_Carried], mode: str) -> tuple[_Pairs, _Pairs]:
        """Run ``n`` substeps, moving carried bodies along their line (slerp for the orientation); returns
        the pairs that touched in any substep and those touching after the last one."""
        p, c = self.p, self.cid
        reset, setvel, stepsim = p.resetBasePositionAndOrientation, p.resetBaseVelocity, p.stepSimulation
        events = self.prm["contact_events"]
        touched: set[tuple[str, str]] = set()
        now = self.contacts
        for k in range(n):
            for b, a, z, v in carried:
                s = k / n
                if a == z:
                    pose = z
                else:
                    pose = [*(a[i] + s * (z[i] - a[i]) for i in range(3)), *quat_slerp(a[3:], z[3:], s)]
                if b.inertial is not None:
                    self._place(b, pose, v)
                    continue
                reset(b.id, pose[:3], pose[3:], physicsClientId=c)
                if b.dynamic:
                    setvel(b.id, v[:3], v[3:], physicsClientId=c)
            stepsim(physicsClientId=c)
            if mode == "force":
                self._force_binding()
            if events:
                now = self._touching()
                touched |= now
        return touched, now

    def _place_carried(self, carried: list[_Carried]) -> None:
        """Carried bodies end the step exactly at their targets, with the velocity of their motion."""
        for b, _, z, v in carried:
            self._place(b, z, v)
            b.pose, b.velocity = list(z), list(v)

    def _read_dynamic(self) -> None:
        """Poses and velocities of the dynamic bodies this world moves (not the carried ones)."""
        getpose, getvel, c = self.p.getBasePositionAndOrientation, self.p.getBaseVelocity, self.cid
        for b in self.dynamic:
            if b.name in self.followed:
                continue
            pos, orn = getpose(b.id, physicsClientId=c)
            lin, ang = getvel(b.id, physicsClientId=c)
            if b.inertial is not None:
                b.pose, b.velocity = b.to_frame(pos, orn, lin, ang)
                continue
            b.pose = [*pos, *orn]
            b.velocity = [*lin, *ang]

    def _contact_events(self, touched: set, now: set) -> None:
        """Begin: pairs touching in any substep that were not touching before; end: pairs that
        touched before or during the step and do not at its last substep (a bounce inside one
        step raises both)."""
        before = self.contacts
        for a, b in sorted(touched - before):
            self.emit("contact_begin", a=a, b=b)
        for a, b in sorted((before | touched) - now):
            self.emit("contact_end", a=a, b=b)
        self.contacts = now

    def _touching(self) -> set[tuple[str, str]]:
        """Named pairs in contact after the last substep."""
        names, margin = self.names, self.prm["contact_margin"]
        now = set()
        robot = self.robot
        for cp in self.p.getContactPoints(physicsClientId=self.cid):
            # a point counts when it is (nearly) touching or pushed: a fast body bounces off a
            # speculative contact that never comes closer than a few mm at a step's end
            if (cp[8] > margin and cp[9] <= 0.0) or (cp[1] == robot and cp[2] == robot):
                continue
            a, b = names.get((cp[1], cp[3])), names.get((cp[2], cp[4]))
            if a is None or b is None or a == b:
                continue
            now.add((a, b) if a < b else (b, a))
        return now

    # ------------------------------------------------------------- collision
    def _partner_links(self, name: str, partners) -> set[tuple[int, int, int, int]]:
        b = self.bodies[name]
        out = set()
        for other in partners:
            if other == name:
                continue
            if other in self.bodies:
                o = self.bodies[other]
                if not (b.dynamic or o.dynamic):
                    continue  # two static bodies never touch anyway
                out |= {(b.id, o.id, la, lb) for la in b.links for lb in o.links}
            elif other == "table":
                out |= {(b.id, self.table, la, -1) for la in b.links}
            elif other in ("robot", self.robot_spec.name):
                out |= {(b.id, self.robot, la, lb) for la in b.links for lb in self.robot_links.values()}
            elif other in self.robot_links:
                out |= {(b.id, self.robot, la, self.robot_links[other]) for la in b.links}
        return out

    def _wanted_filters(self, name: str, value: Any) -> set[tuple[int, int, int, int]]:
        if value is None or value is True:
            return set()
        if isinstance(value, dict):
            if value.get("enabled", True):
                return set()
            partners = value.get("ignore")
        elif value is False:
            partners = None
        else:
            return set()
        if not partners:
            partners = self.prm["collision_partners"].get(name) or [n for n in self.bodies if n != name]
        return self._partner_links(name, partners)

    def _set_filters(self, name: str, wanted: set) -> None:
        have = self.disabled.get(name, set())
        if wanted == have:
            return
        f = self.p.setCollisionFilterPair
        for a, b, la, lb in have - wanted:
            f(a, b, la, lb, 1, physicsClientId=self.cid)
        for a, b, la, lb in wanted - have:
            f(a, b, la, lb, 0, physicsClientId=self.cid)
        self.disabled[name] = wanted

    def _update_collisions(self, inputs: dict) -> None:
        for name, attrs in inputs.items():
            if "collision" not in attrs or name not in self.bodies or (name, "collision") in self.owned:
                continue
            value = attrs["collision"]
            if self.collision_values.get(name, True) == value and name in self.collision_values:
                continue
            self.collision_values[name] = value
            self._set_filters(name, self._wanted_filters(name, value))

    # ------------------------------------------------------------- handover
    def read(self, entity: str, attribute: str) -> Any:
        if entity in self.virtual:  # held, not simulated: the last value handed over
            return self.virtual_values.get((entity, attribute))
        if attribute == "pose":
            return self.bodies[entity].pose
        if attribute == "collision":
            if entity not in self.bodies:
                raise KeyError(f"physics has no entity {entity!r}")
            return True
        raise KeyError(f"physics has no attribute {attribute!r}")

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict) -> None:
        if entity in self.virtual:
            self.virtual_values[(entity, attribute)] = value
            self.virtual_extra[(entity, attribute)] = dict(extra or {})  # (a fluid's particle velocities: kept)
            return
        b = self.bodies.get(entity)
        if b is None:
            raise KeyError(f"physics has no entity {entity!r}")
        if attribute == "collision":
            self.collision_values.pop(entity, None)
            self._set_filters(entity, set())
            return
        if attribute != "pose":
            raise KeyError(f"physics cannot own {attribute!r}")
        carried = self.followed.stop(entity, self.t)
        pose = list(as_pose(value)) if value is not None else list(b.pose)
        vel = (extra or {}).get("velocity")
        v = [float(x) for x in vel] + [0.0] * (6 - len(vel)) if vel is not None and len(vel) >= 3 else carried
        self._place(b, pose, v)
        b.pose, b.velocity = pose, (v if b.dynamic else [0.0] * 6)

    def release(self, entity: str, attribute: str) -> tuple[Any, dict]:
        if entity in self.virtual:
            return (self.virtual_values.pop((entity, attribute), None),
                    self.virtual_extra.pop((entity, attribute), {}))
        b = self.bodies.get(entity)
        if b is None:
            raise KeyError(f"physics has no entity {entity!r}")
        if attribute == "collision":
            return True, {}
        if entity in self.bound:
            self._unbind(entity)
        self.followed.follow(entity, b.pose, self.t)
        return list(b.pose), {"velocity": list(b.velocity)}

    # ------------------------------------------------------------- evaluators
    @evaluator("closest", names={"tag": "tag", "link": "body"})
    def closest(self, tag: str, link: str = "hand") -> dict:
        """The entity carrying ``tag`` whose centre is nearest ``link``'s frame origin (``hand``: the robot's
        hand link, ``tip``: between its fingertips)."""
        ref = self._where(link)[:3]
        best, dist = None, None
        for b in self.bodies.values():
            if tag in b.tags and b.name != link:
                d = math.dist(self._body_pose(b)[:3], ref)
                if dist is None or d < dist:
                    best, dist = b.name, d
        return {"entity": best, "distance": dist}

    @evaluator("distance", names={"a": "body", "b": "body"})
    def distance(self, a: str, b: str) -> float:
        """Centre distance (m) between two entities or robot links."""
        return math.dist(self._where(a)[:3], self._where(b)[:3])

    @evaluator("velocity", names={"entity": "entity"})
    def velocity(self, entity: str) -> list[float]:
        """[vx, vy, vz, wx, wy, wz] of an entity's body now."""
        b = self.bodies[entity]
        lin, ang = self.p.getBaseVelocity(b.id, physicsClientId=self.cid)
        pos, orn = self.p.getBasePositionAndOrientation(b.id, physicsClientId=self.cid)
        return b.to_frame(pos, orn, lin, ang)[1]

    @evaluator("contacts")
    def touching(self, name: str) -> list[str]:
        """Names touching ``name`` after the last step."""
        return sorted({b if a == name else a for a, b in self.contacts if name in (a, b)})

    def close(self) -> None:
        if getattr(self, "cid", -1) >= 0:  # connected (close may be called twice, or before init)
            try:
                self.p.disconnect(physicsClientId=self.cid)
            except Exception:
                pass
            self.cid = -1
