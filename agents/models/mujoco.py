"""A MuJoCo world as a model of the ensemble: the pybullet physics model's contract, another engine.

The world is built once, at ``init``, with the twin's one MuJoCo builder (:mod:`agents.engines.mujoco_world`,
the same the MuJoCo reality of ``twin record synth`` uses): the scene's robot (its URDF, ``package://``
paths resolved, collision meshes only, position servos added with ``MjSpec``, the finger mimic as a joint
equality), the table (the plane z = 0) and the scene's entities (``entities``: by default every one not tagged
``virtual``): sphere, box, cylinder, container and socket shapes; containers, sockets, ``static`` entities and
those with ``mass: 0`` are fixed bodies, the rest free bodies with the entity's ``mass`` (or the pybullet
model's default: a tennis ball's areal density for spheres, ``density`` for boxes and cylinders). Contacts
are MuJoCo's soft contacts with elliptic friction cones; ``impratio`` makes friction stiffer than the normal
force, so a held object does not creep. A free body's surface (its restitution as a damping ratio, its friction)
decides its contacts with the table, fixed bodies and the arm, and the finger pads' decide theirs (geom
priority): MuJoCo otherwise averages two surfaces' damping and takes the larger friction, where the pybullet
model gives the table and fixed bodies 1.0 for pybullet to multiply by the body's own (a fixed entity's own
``friction`` then counts against the arm alone, where pybullet would multiply it in).

**Robot.** The arm follows the telemetry's joint positions with position servos of ``arm_bandwidth`` Hz
(critically damped for each joint's inertia, the velocity fed forward) and gravity compensation; the first
joint state is set directly (no swing). The fingers follow the telemetry too, but a parallel gripper is
force-controlled: its finger positions are what the object let it reach, not a command. So while a finger
presses (its squeezing force, ``effort_sign`` × the force its joint's effort makes by the gripper's geometry as
grasp_monitor and in_hand read it -- a Panda finger joint is the finger's travel, the xArm's drive joint turns a
linkage --, above ``press_effort`` N), its servo aims ``squeeze`` metres of finger travel past the reported
position with the *measured* effort as its limit: the simulated fingers
press on the simulated object as hard as the real ones pressed on the real one, whatever the small difference
in size between the two, and when the real squeeze fades (a gripper that weakens) the simulated one fades
with it. Without efforts in the stream the fingers follow the positions with ``finger_force``.

**Owned and followed attributes** (the contract of ``physics``). While another model owns an entity's pose
(its value arrives in ``inputs``), the body is carried on the straight line (slerp) from where it was to the
owner's value over the step's substeps, with the owner's velocity (its last poses over its own times, as physics
does); ``acquire`` continues from the handed-over pose with ``extra["velocity"]`` (else the velocity of the
owner's last poses); ``release`` returns ``(pose, {"velocity": [...]})``. While another model owns an entity's
``collision``, its value says what the body stops touching (``false``: every other entity or
``collision_partners``; ``{"enabled": false, "ignore": [names]}``: those names; names are entities, ``table``,
``robot`` or a robot link); MuJoCo keeps such pairs as compiled exclusions, so a change recompiles the world (a
few milliseconds, state kept: the bodies' motion, the fingers' force limits, where fixed bodies were put).

**Selectively active** (the paper's advice for specialised models): with ``idle: kinematic`` a model that owns
no pose simulates nothing: each step it puts the robot at the telemetry's joint positions and the carried
bodies at their owners' poses, and reports contacts; when it acquires a pose it simulates from that state on.
A hand model that only holds the ball while the grasp lasts then costs little the rest of the time.

Each step runs the substeps of ``time_step`` that keep its world's time on the clock's
(:class:`~agents.engines.bodies.Substeps`: 8 or 9 of 1 ms at 120 Hz). Outputs: ``links`` {link: pose} for the
robot links in ``links``. Events: ``contact_begin`` / ``contact_end`` {a, b} (entities by name, ``table``, robot
links by name; ``a < b``; after every substep; a contact counts when closer than ``contact_margin``). Evaluators:
``closest(tag, link="hand")`` (``hand``: the robot's hand link, ``tip``: its fingertip centre),
``distance(a, b)``, ``velocity(entity)``, ``contacts(name)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from protocol.geometry import is_static
from protocol.joints import joint_state_key
from protocol.robot import resolve_robot

from ..engines.bodies import Followed, Substeps, default_mass
from ..engines.mujoco_world import (
    MujocoWorld,
    Surface,
    add_entity,
    add_table,
    arm_inertia,
    damping_ratio_for_restitution,
    robot_spec,
    set_options,
    wxyz,
    xyzw,
)
from ..model import Model, Param, StepWarning, evaluator
from ..robot.kinematics import GripperGeometry, as_pose, compose, quat_slerp

CONTACT_OMEGA = 500.0
"""rad/s: the fastest a free body's contact oscillates (at the default 1 ms step, w dt = 0.5)."""


@dataclass
class _Body:
    """One scene entity in the MuJoCo world."""

    name: str
    id: int
    free: bool
    tags: tuple[str, ...]
    qpos: int = -1  # address of its free joint's 7 coordinates (-1: a fixed body)
    dof: int = -1
    pose: list[float] = field(default_factory=list)
    velocity: list[float] = field(default_factory=lambda: [0.0] * 6)


class MuJoCo(Model):
    """A MuJoCo world with the robot, the table and the scene's entities (see the module docstring)."""

    kind = "mujoco"
    role = "simulation"
    params = {
        "time_step": Param(float, 0.001, "MuJoCo time step (s), at most the step period; a step runs as many as keep "
                           "the world's time on the clock's",
                           positive=True, within_period=True),
        "gravity": Param(list, [0.0, 0.0, -9.81], "gravity vector (m/s^2)"),
        "entities": Param(list, None, "the entities built in this world (default: every one not tagged virtual)"),
        "robot": Param(bool, True, "build the scene's robot and drive it from the telemetry"),
        "arm_bandwidth": Param(float, 10.0, "bandwidth (Hz) of the arm's joint servos (critically damped)"),
        "finger_force": Param(float, 0.0, "force limit (N) of each finger when the telemetry has no efforts (0: the "
                                          "robot description's gripper force)"),
        "finger_kp": Param(float, 10000.0, "finger servo stiffness (N/m)"),
        "finger_kv": Param(float, 100.0, "finger servo damping (N s/m)"),
        "press_effort": Param(float, 2.0, "squeezing effort (N) above which a finger presses on something"),
        "squeeze": Param(float, 0.005, "how far (m) past the reported position a pressing finger aims"),
        "effort_sign": Param(float, -1.0, "sign of a squeezing finger effort in the telemetry (0: |effort|)"),
        "friction": Param(float, 0.8, "sliding friction of entities that do not set 'friction'"),
        "rolling_friction": Param(float, 2e-4, "rolling friction (m: resisting torque per newton of normal force) of "
                                               "free spheres and cylinders, as the physics model's"),
        "spinning_friction": Param(float, 1e-3, "spinning friction (m) of free spheres and cylinders"),
        "finger_friction": Param(float, 1.0, "sliding friction of the finger pads"),
        "restitution": Param(dict, {"sphere": 0.6, "box": 0.1, "cylinder": 0.1},
                             "restitution of free entities by shape type (a contact's damping ratio)"),
        "density": Param(float, 500.0, "density (kg/m^3) of boxes and cylinders without a 'mass'"),
        "impratio": Param(float, 10.0, "friction-to-normal constraint stiffness ratio (elliptic cones)"),
        "links": Param(list, [], "robot links whose poses go out as the 'links' output (default: the robot's "
                                 "hand and fingers)"),
        "initial_joints": Param(list, [], "joint positions until the first telemetry (the arm's, then the "
                                          "gripper's; default: the robot description's ready posture)"),
        "velocity_window": Param(float, 0.05, "acquire without a handed-over velocity: estimate it over this "
                                               "many seconds of the owner's poses"),
        "collision_partners": Param(dict, {}, "entity -> names it stops touching while another model owns its "
                                              "collision (default: every other entity)"),
        "idle": Param(str, "simulate", "while it owns no pose: 'simulate' as always, or 'kinematic': put the robot and "
                                       "the carried bodies where the telemetry and their owners say, no dynamics"),
        "contact_events": Param(bool, True, "raise contact_begin / contact_end"),
        "contact_margin": Param(float, 1e-3, "geoms closer than this (m) count as touching"),
    }
    attributes = ("pose", "collision")
    outputs = ("links",)
    events = ("contact_begin", "contact_end")
    reads = ("*.pose", "*.collision")

    # ------------------------------------------------------------------ set-up
    def init(self, params: dict, scene: dict) -> None:
        self.prm = params
        self.ts = float(params["time_step"])
        self.substeps = Substeps(self.ts, self.rate)
        entities = scene.get("entities") or {}
        chosen = params["entities"]
        if chosen is None:
            chosen = [n for n, e in entities.items() if "virtual" not in (e.get("tags") or ())]
        unknown = [n for n in chosen if n not in entities]
        if unknown:
            raise ValueError(f"entities: {unknown} are not entities of the scene ({', '.join(entities)})")
        self.tags = {n: tuple(entities[n].get("tags") or ()) for n in chosen}
        self.robot = resolve_robot(scene.get("robot") or None)
        self.finger_force = float(params["finger_force"]) or float(self.robot.gripper.force)
        self.gripper = GripperGeometry.of(self.robot) if params["robot"] else None
        self.spec = self._robot_spec(self.robot) if params["robot"] else mujoco.MjSpec()
        set_options(self.spec, timestep=self.ts, impratio=float(params["impratio"]),
                    gravity=[float(g) for g in params["gravity"]])
        add_table(self.spec, Surface(friction=1.0))
        self.shapes: dict[str, dict] = {}
        for name in chosen:
            self._add_entity(name, entities[name])
        self.world = MujocoWorld(self.spec, self.robot if params["robot"] else None)
        self._index()
        self.excluded: dict[str, set[tuple[str, str]]] = {}  # entity -> body pairs kept apart
        self._apart: frozenset[tuple[str, ...]] = frozenset()  # the same pairs, each sorted (never touching)
        self.collision_values: dict[str, Any] = {}
        self.followed = Followed(float(params["velocity_window"]))  # the bodies other models own the pose of
        for b in self.bodies.values():
            b.pose = self._pose(b)
            if (b.name, "pose") not in self.owned:
                self.followed.follow(b.name, b.pose, 0.0)
        self.contacts: set[tuple[str, str]] = set()
        self._touch_geoms: dict[tuple[str, str], tuple[int, int]] = {}  # the geoms of each pair last touching
        self.telemetry_seen = False
        self._efforts_seen = False  # (a gripper effort not zero heard in this run: the stream carries efforts)
        self._last_key: Any = None  # the joint state last driven by
        self._names: list | None = None
        self._arm_i: list[int] | None = None
        self._finger_i: list[int] | None = None
        if params["idle"] not in ("simulate", "kinematic"):
            raise ValueError(f"idle must be simulate or kinematic, got {params['idle']!r}")
        if params["robot"]:
            init = self.robot.posture(params["initial_joints"])
            n = len(self.robot.arm)
            self.world.set_joints(init[:n], init[n:])

    def _robot_spec(self, robot: Any) -> mujoco.MjSpec:
        p = self.prm
        w = 2 * math.pi * float(p["arm_bandwidth"])
        inertia = arm_inertia(robot)
        self.arm_kp, self.arm_kv = inertia * w * w, 2 * inertia * w
        pads = Surface(friction=float(p["finger_friction"]), torsional=2 / 3 * float(p["finger_friction"]) * 0.005,
                       timeconst=max(2 * self.ts, 0.002), dampratio=1.0, solimp=(0.95, 0.99, 0.001, 0.5, 2.0),
                       condim=4, priority=2)  # above the free bodies' 1: the pads decide
        spec = robot_spec(robot, arm_kp=self.arm_kp, arm_kv=self.arm_kv,
                          finger_kp=float(p["finger_kp"]), finger_kv=float(p["finger_kv"]),
                          finger_force=self.finger_force, finger_surface=pads,
                          joint_damping=0.02)
        base = as_pose(robot.base)
        for root in spec.worldbody.bodies:  # the URDF's root link(s), moved to the robot's base
            root.pos, root.quat = [float(v) for v in base[:3]], wxyz(base[3:])
        return spec

    def _add_entity(self, name: str, ent: dict) -> None:
        shape, tags, mass = ent["shape"], tuple(ent.get("tags") or ()), ent.get("mass")
        t = shape["type"]
        if t == "urdf":
            raise ValueError(f"entity {name!r}: a urdf shape cannot be built in the mujoco model")
        static = is_static(shape, tags, mass)
        fr = ent.get("friction")
        if static:
            surface = Surface(friction=float(fr if fr is not None else 1.0))
            add_entity(self.spec, name, shape, as_pose(ent.get("pose") or [0, 0, 0]), surface=surface)
        else:
            e = float((self.prm["restitution"] or {}).get(t, 0.1))
            zeta = damping_ratio_for_restitution(e)
            # a contact oscillates at 1 / (timeconst zeta): 0.95 x 500 rad/s, or slower when the time step could not
            # follow that (w dt under 0.5; past 2 the integration gains energy: a ball bounced higher at 1/240 s)
            omega = min(CONTACT_OMEGA, 0.5 / self.ts)
            # a rolling ball or cylinder slows, and one spinning on its end (condim 6), as in the physics model
            surface = Surface(friction=float(fr if fr is not None else self.prm["friction"]),
                              torsional=float(self.prm["spinning_friction"]),
                              rolling=float(self.prm["rolling_friction"]),
                              timeconst=max(2 * self.ts, 1.0 / (0.95 * omega * zeta)), dampratio=zeta, priority=1,
                              condim=6 if t in ("sphere", "cylinder") else 3)
            m = float(mass if mass is not None else default_mass(shape, float(self.prm["density"])))
            add_entity(self.spec, name, shape, as_pose(ent.get("pose") or [0, 0, 0]), mass=m, surface=surface,
                       shell=t == "sphere")
        self.shapes[name] = shape

    def _index(self) -> None:
        """Bodies, joints and names of the compiled world (again after each recompilation)."""
        m = self.world.model
        self.bodies: dict[str, _Body] = {}
        old = getattr(self, "_old_bodies", {})
        for name in self.shapes:
            bid = m.body(name).id
            jnt = m.body_jntadr[bid]
            b = _Body(name, bid, jnt >= 0, self.tags[name], int(m.jnt_qposadr[jnt]) if jnt >= 0 else -1,
                      int(m.jnt_dofadr[jnt]) if jnt >= 0 else -1)
            prev = old.get(name)
            if prev is not None:
                b.pose, b.velocity = prev.pose, prev.velocity
            self.bodies[name] = b
        # geom -> the name used in contact events: the entity, the table, or the robot link
        self.geom_names: list[str | None] = []
        entity_of = {b.id: n for n, b in self.bodies.items()}
        for g in range(m.ngeom):
            body = int(m.geom_bodyid[g])
            if body == 0:
                self.geom_names.append("table" if m.geom(g).name == "table" else None)
            elif body in entity_of:
                self.geom_names.append(entity_of[body])
            else:
                self.geom_names.append(m.body(body).name)
        self.robot_links = {m.body(i).name: i for i in range(1, m.nbody) if i not in entity_of}
        links = list(self.prm["links"]) or [self.robot.gripper.hand, *self.robot.gripper.fingers]
        unknown = [n for n in links if n not in self.robot_links]
        if unknown and self.prm["robot"]:
            raise ValueError(f"unknown robot links {unknown} (the robot has: {', '.join(self.robot_links)})")
        self._out_links = [n for n in links if n in self.robot_links]

    # --------------------------------------------------------------- bodies
    def _pose(self, b: _Body) -> list[float]:
        d = self.world.data
        return [*map(float, d.xpos[b.id]), *map(float, xyzw(d.xquat[b.id]))]

    def _velocity(self, b: _Body) -> list[float]:
        if not b.free:
            return [0.0] * 6
        lin, ang = self.world.body_velocity(b.name)
        return [*map(float, lin), *map(float, ang)]

    def _put(self, b: _Body, pose: list[float], velocity: list[float] | None) -> None:
        """Place a body (a free one with a velocity; a fixed one by moving its frame in the model)."""
        m, d = self.world.model, self.world.data
        if b.free:
            d.qpos[b.qpos:b.qpos + 3] = pose[:3]
            d.qpos[b.qpos + 3:b.qpos + 7] = wxyz(pose[3:7])
            v = velocity or [0.0] * 6
            d.qvel[b.dof:b.dof + 3] = v[:3]
            # a free joint's angular velocity is in the body frame
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, np.asarray(wxyz(pose[3:7])))
            d.qvel[b.dof + 3:b.dof + 6] = rot.reshape(3, 3).T @ np.asarray(v[3:6], float)
        else:
            m.body_pos[b.id] = pose[:3]
            m.body_quat[b.id] = wxyz(pose[3:7])

    # ---------------------------------------------------------------- robot
    def _drive(self, js: dict | None) -> None:
        """Servo targets from the latest joint state (only when a new one arrived)."""
        if js is None or not self.prm["robot"]:
            return
        key = joint_state_key(js)
        if key == self._last_key and self.telemetry_seen:
            return
        self._last_key = key
        names = js["name"]
        if names != self._names:
            self._names = list(names)
            pos = {n: i for i, n in enumerate(names)}
            arm, grip = self.robot.arm, self.robot.gripper.joints
            self._arm_i = [pos[n] for n in arm] if all(n in pos for n in arm) else None
            self._finger_i = [pos[n] for n in grip] if all(n in pos for n in grip) else None
        if self._arm_i is None:
            return
        q = np.array([float(js["position"][i]) for i in self._arm_i])
        vel = js.get("velocity") or []
        qd = np.array([float(vel[i]) for i in self._arm_i]) if len(vel) == len(names) else np.zeros(len(q))
        w = self.world
        fingers = [float(js["position"][i]) for i in self._finger_i] if self._finger_i is not None else None
        if not self.telemetry_seen or self._idle():
            w.set_joints(q, fingers if fingers is not None else w.joints()[0][len(q):])
            self.telemetry_seen = True
        w.data.ctrl[w.arm_act] = q + self.arm_kv / self.arm_kp * qd
        if fingers is not None:
            self._drive_fingers(fingers, js.get("effort") or [], len(names))

    def _drive_fingers(self, fingers: list[float], effort: list, n: int) -> None:
        """Each gripper joint's servo: at the reported position, or, while the fingers it drives press (their
        force from the joint's effort by the gripper's geometry), ``squeeze`` metres of finger travel past it
        with the measured effort as its limit; else at the reported position, closing with no more than the
        measured effort (a squeeze that faded as a ball slipped out was the gripper's full force here, and the
        simulated fingers held on to the ball) and opening with the gripper's force. Efforts that were all zero
        so far are none (a real robot's often are). A Panda finger joint is its finger's opening in metres; the
        xArm's drive joint turns (radians) one way to close both fingers through a linkage."""
        p, w, g, geo = self.prm, self.world, self.robot.gripper, self.gripper
        sign = float(p["effort_sign"])
        limits = w.model.actuator_forcerange
        assert self._finger_i is not None and geo is not None, "called with the fingers' positions only"
        q = dict(zip(g.joints, fingers, strict=True))
        if len(effort) == n and not self._efforts_seen:
            self._efforts_seen = any(float(effort[i]) != 0.0 for i in self._finger_i)
        forces = geo.forces(q, {j: float(effort[i]) for j, i in zip(g.joints, self._finger_i, strict=True)}) \
            if len(effort) == n and self._efforts_seen else None
        for k, joint in enumerate(g.joints):
            act = w.finger_act[k]
            driven = [i for i in (0, 1) if g.driver(i) == joint]
            press = 0.0
            if forces is not None and driven:
                f = sum(forces[i] for i in driven) / len(driven)
                press = sign * f if sign else abs(f)
            share = sum(geo.slope(i, q[joint]) for i in driven)  # the fingers' opening per joint unit, summed
            if press > float(p["press_effort"]) and abs(share) > 1e-9:
                w.data.ctrl[act] = q[joint] - float(p["squeeze"]) * len(driven) / share
                tau = abs(float(effort[self._finger_i[k]]))  # the joint's measured effort (N, or N m): press x share
                limits[act] = [-tau, tau]
            else:
                w.data.ctrl[act] = q[joint]
                full = self.finger_force
                tau = abs(float(effort[self._finger_i[k]])) if forces is not None else full
                # closing is towards a smaller opening: a negative force where the opening grows with the joint
                limits[act] = [-tau, full] if share > 1e-9 else [-full, tau] if share < -1e-9 else [-full, full]

    # ------------------------------------------------------------------ step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        idle = self._idle()
        n = 0 if idle else self.substeps.take(dt)
        if idle:
            self.substeps.idle()
        self._drive(telemetry.get("joints"))
        bad: list[str] = []
        # a carried body's velocity is its owner's motion over the owner's own times (over this step's, an owner
        # at half this model's rate gave 0 and twice the speed on alternate steps)
        carried = [(self.bodies[name], list(self.bodies[name].pose), target, v)
                   for name, target, v in self.followed.this_step(inputs, t, self.t, bad)]
        if inputs:
            self._update_collisions(inputs)
        touched: set[tuple[str, str]] = set()
        now = self.contacts
        m, d = self.world.model, self.world.data
        events = self.prm["contact_events"]
        if n == 0:  # nothing of its own to simulate (idle, a step of no time): the carried bodies go to their targets
            for b, _, z, v in carried:
                self._put(b, z, v)
            mujoco.mj_forward(m, d)
            if events:
                now = touched = self._touching()
        saved = d.qpos.copy(), d.ctrl.copy()  # (MuJoCo resets both when it finds the state unstable)
        for k in range(n):
            s = (k + 1) / n
            for b, a, z, v in carried:
                pose = z if a == z else [*(a[i] + s * (z[i] - a[i]) for i in range(3)), *quat_slerp(a[3:], z[3:], s)]
                self._put(b, pose, v)
            mujoco.mj_step(m, d)
            if events:
                now = self._touching()
                touched |= now
        unstable = self.world.diverged()
        if unstable:
            self._recover(*saved)
            raise StepWarning(f"MuJoCo's simulation became unstable ({unstable}) and reset its state: the bodies and "
                              f"the robot are put back where they were before this step, at rest")
        mujoco.mj_forward(m, d)
        for b, _, z, v in carried:
            b.pose, b.velocity = list(z), list(v)
        for b in self.bodies.values():
            if b.name not in self.followed:
                b.pose, b.velocity = self._pose(b), self._velocity(b)
        if self._out_links:
            self.output("links", {nm: [*map(float, d.xpos[self.robot_links[nm]]),
                                       *map(float, xyzw(d.xquat[self.robot_links[nm]]))] for nm in self._out_links})
        if events:
            before = self.contacts
            for one, other in sorted(touched - before):
                self.emit("contact_begin", a=one, b=other)
            for one, other in sorted((before | touched) - now):
                self.emit("contact_end", a=one, b=other)
            self.contacts = now
        if bad:
            raise StepWarning(f"pose of {', '.join(bad)} from its owner is not [x, y, z, qx, qy, qz, qw]: the body "
                              "stays where it was")

    def _recover(self, qpos: np.ndarray, ctrl: np.ndarray) -> None:
        """After MuJoCo reset the whole state (every body where the model was built, the arm at zero): everything
        where it was before the step (``qpos``), at rest, the servos' targets as they were (``ctrl``)."""
        d = self.world.data
        d.qpos[:], d.ctrl[:] = qpos, ctrl
        d.qvel[:] = 0.0
        for b in self.bodies.values():
            b.velocity = [0.0] * 6
        mujoco.mj_forward(self.world.model, d)

    def _idle(self) -> bool:
        return self.prm["idle"] == "kinematic" and not any(a == "pose" for _, a in self.owned)

    def _touching(self) -> set[tuple[str, str]]:
        """Named pairs closer than ``contact_margin`` after the last substep. MuJoCo lists only the geoms that
        overlap, so a pair it no longer lists counts until its geoms are ``contact_margin`` apart: a ball at rest
        on the table, hopping by micrometres, began and ended its contact 20 times a second."""
        c, names = self.world.data.contact, self.geom_names
        margin = float(self.prm["contact_margin"])
        # the contact list's fields as arrays: indexing its items builds a Python object per contact, which cost
        # three quarters of a step with the robot's dozens of contacts
        close = ~(c.dist > margin)
        now: dict[tuple[str, str], tuple[int, int]] = {}
        for g1, g2 in zip(c.geom1[close].tolist(), c.geom2[close].tolist()):
            a, b = names[g1], names[g2]
            if a is None or b is None or a == b:
                continue
            now[(a, b) if a < b else (b, a)] = (g1, g2)
        m, d = self.world.model, self.world.data
        for pair, (g1, g2) in self._touch_geoms.items():
            if pair in now:
                continue
            bodies = tuple(sorted((m.body(int(m.geom_bodyid[g1])).name, m.body(int(m.geom_bodyid[g2])).name)))
            if bodies not in self._apart and mujoco.mj_geomDistance(m, d, g1, g2, margin, None) < margin:
                now[pair] = (g1, g2)
        self._touch_geoms = now
        return set(now)

    # ------------------------------------------------------------- collision
    def _bodies_of(self, name: str) -> list[str]:
        """MuJoCo body names standing for a name of a collision value."""
        if name in self.bodies:
            return [name]
        if name == "table":
            return ["world"]
        if name in ("robot", self.robot.name):
            return list(self.robot_links)
        if name in self.robot_links:
            return [name]
        return []

    def _wanted(self, name: str, value: Any) -> set[tuple[str, str]]:
        if value is None or value is True or (isinstance(value, dict) and value.get("enabled", True)):
            return set()
        partners = value.get("ignore") if isinstance(value, dict) else None
        if value is not False and not isinstance(value, dict):
            return set()
        if not partners:
            partners = self.prm["collision_partners"].get(name) or [n for n in self.bodies if n != name]
        return {(name, other) for p in partners if p != name for other in self._bodies_of(p)}

    def _set_exclusions(self, name: str, wanted: set[tuple[str, str]]) -> None:
        if wanted == self.excluded.get(name, set()):
            return
        self.excluded[name] = wanted
        self._apart = frozenset(tuple(sorted(p)) for pairs in self.excluded.values() for p in pairs)
        for ex in list(self.spec.excludes):
            self.spec.delete(ex)
        for pairs in self.excluded.values():
            for a, b in sorted(pairs):
                self.spec.add_exclude(bodyname1=a, bodyname2=b)
        # what this model set in the compiled model by hand, which compiling the spec again resets: the fingers'
        # force limits (the squeeze measured from the efforts, set again only when new telemetry comes) and the
        # frames of fixed bodies it placed
        forcerange, ctrl = self.world.model.actuator_forcerange.copy(), self.world.data.ctrl.copy()
        self._old_bodies = self.bodies
        self.world.rebuild()
        self._index()
        self._old_bodies = {}  # (kept, a warm agent's next run began with this run's velocities)
        m = self.world.model
        if m.nu == len(ctrl):  # (an exclusion adds no actuator)
            m.actuator_forcerange[:] = forcerange
            self.world.data.ctrl[:] = ctrl
        for body in self.bodies.values():
            if not body.free:
                self._put(body, body.pose, None)
        mujoco.mj_forward(m, self.world.data)

    def _update_collisions(self, inputs: dict) -> None:
        for name, attrs in inputs.items():
            if "collision" not in attrs or name not in self.bodies or (name, "collision") in self.owned:
                continue
            value = attrs["collision"]
            if name in self.collision_values and self.collision_values[name] == value:
                continue
            self.collision_values[name] = value
            self._set_exclusions(name, self._wanted(name, value))

    # ------------------------------------------------------------- handover
    def read(self, entity: str, attribute: str) -> Any:
        b = self.bodies.get(entity)
        if b is None:
            raise KeyError(f"the mujoco model has no entity {entity!r}")
        if attribute == "pose":
            return list(b.pose)
        if attribute == "collision":
            return True
        raise KeyError(f"the mujoco model has no attribute {attribute!r}")

    def acquire(self, entity: str, attribute: str, value: Any, extra: dict) -> None:
        b = self.bodies.get(entity)
        if b is None:
            raise KeyError(f"the mujoco model has no entity {entity!r}")
        if attribute == "collision":
            self.collision_values.pop(entity, None)
            self._set_exclusions(entity, set())
            return
        if attribute != "pose":
            raise KeyError(f"the mujoco model cannot own {attribute!r}")
        carried = self.followed.stop(entity, self.t)
        pose = list(as_pose(value)) if value is not None else list(b.pose)
        vel = (extra or {}).get("velocity")
        v = [float(x) for x in vel] + [0.0] * (6 - len(vel)) if vel is not None and len(vel) >= 3 else carried
        self._put(b, pose, v if b.free else None)
        mujoco.mj_forward(self.world.model, self.world.data)
        b.pose, b.velocity = pose, (v if b.free else [0.0] * 6)

    def release(self, entity: str, attribute: str) -> tuple[Any, dict]:
        b = self.bodies.get(entity)
        if b is None:
            raise KeyError(f"the mujoco model has no entity {entity!r}")
        if attribute == "collision":
            return True, {}
        self.followed.follow(entity, b.pose, self.t)
        return list(b.pose), {"velocity": list(b.velocity)}

    # ------------------------------------------------------------- evaluators
    def _where(self, name: str) -> list[float]:
        """Pose of an entity or a robot link; ``hand`` / ``tip`` name the robot's hand and fingertip centre."""
        d = self.world.data
        g = self.robot.gripper
        if name == "hand" and name not in self.bodies:
            name = g.hand
        elif name == "tip" and name not in self.bodies and g.tip in self.robot_links:
            return [float(v) for v in compose(self._where(g.tip), [*g.tip_offset, 0, 0, 0, 1])]
        if name in self.bodies:
            return list(self.bodies[name].pose)
        if name in self.robot_links:
            i = self.robot_links[name]
            return [*map(float, d.xpos[i]), *map(float, xyzw(d.xquat[i]))]
        raise KeyError(f"no entity or robot link named {name!r}")

    @evaluator("closest", names={"tag": "tag", "link": "body"})
    def closest(self, tag: str, link: str = "hand") -> dict:
        """The entity carrying ``tag`` whose centre is nearest ``link``'s frame origin."""
        ref = self._where(link)[:3]
        best, dist = None, None
        for name in self.bodies:
            if tag in self.tags.get(name, ()) and name != link:
                dd = math.dist(self.bodies[name].pose[:3], ref)
                if dist is None or dd < dist:
                    best, dist = name, dd
        return {"entity": best, "distance": dist}

    @evaluator("distance", names={"a": "body", "b": "body"})
    def distance(self, a: str, b: str) -> float:
        """Centre distance (m) between two entities or robot links."""
        return math.dist(self._where(a)[:3], self._where(b)[:3])

    @evaluator("velocity", names={"entity": "entity"})
    def velocity(self, entity: str) -> list[float]:
        """[vx, vy, vz, wx, wy, wz] of an entity's body now."""
        return self._velocity(self.bodies[entity])

    @evaluator("contacts")
    def touching(self, name: str) -> list[str]:
        """Names touching ``name`` after the last step."""
        return sorted({b if a == name else a for a, b in self.contacts if name in (a, b)})
