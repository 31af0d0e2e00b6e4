"""MuJoCo worlds of a robot arm on a table, built with ``mujoco.MjSpec``.

Building is a few calls on one spec, then :class:`MujocoWorld` compiles it and answers queries::

    robot = resolve_robot({"use": "panda"})          # protocol.robot: the scene's robot block
    spec = robot_spec(robot, arm_kp=[...], arm_kv=[...], finger_kp=2000, finger_kv=30, finger_force=20)
    set_options(spec, timestep=0.001)
    add_table(spec, Surface(friction=0.6))
    add_entity(spec, "ball", {"type": "sphere", "radius": 0.033}, [0.5, 0, 0.2, 0, 0, 0, 1], mass=0.057)
    world = MujocoWorld(spec, robot)
    world.step()

Conventions: poses are ``[x, y, z, qx, qy, qz, qw]`` as everywhere in the twin (MuJoCo stores
quaternions scalar first; the conversion happens here and nowhere else). Lengths in metres.

What a URDF of ``pybullet_data`` needs to load in MuJoCo (verified with MuJoCo 4.0 on the Panda):

- MuJoCo does not resolve ``package://`` mesh paths: the prefix is stripped and ``meshdir`` set to
  the URDF's folder, with ``strippath="false"`` because visual and collision meshes may share a file
  name. Visual meshes are dropped unless ``visual=True`` (they then stay in geom group 1 without
  contacts; only collision meshes touch anything).
- ``fusestatic="false"`` keeps links welded to their parent (a hand, a tip link) as bodies of their own,
  so their frames and Jacobians can be asked for by name.
- The URDF has no actuators. :func:`robot_spec` adds a position actuator per arm joint and one per
  gripper joint (a gripper with two finger joints, like the Panda's, gets two actuators with the same
  force limit, which report what each finger presses with). The URDF's ``<mimic>`` joints become joint
  equalities (MuJoCo's URDF import), which keep the fingers symmetric as a rack or linkage does.
- Gravity compensation: the arm's links get ``gravcomp`` and the joints ``actgravcomp``, so the
  compensation is an actuator force limited by the joint's torque limit and counted in
  ``qfrc_actuator`` -- what a real joint controller does and what its torque sensors report.
- The robot does not collide with itself (as pybullet loads a URDF by default): its geoms have
  ``contype`` 2 and ``conaffinity`` 1; everything else has 1 and 3.

Contacts are MuJoCo's soft contacts: each geom has a :class:`Surface` (friction triple, solref,
solimp, condim, priority). When two geoms touch, MuJoCo uses the higher-priority geom's surface, or
else the larger friction, the larger condim and the mean of solref/solimp. Friction cones are
elliptic (:func:`set_options`).
"""
from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from protocol.geometry import container_parts, socket_parts
from protocol.robot import Robot

log = logging.getLogger(__name__)
# MuJoCo's own warnings ("Nan, Inf or huge value in QVEL ...") go to the log: MuJoCo wrote them to MUJOCO_LOG.TXT
# in whatever folder the process was started in, and to its stdout
mujoco.set_mju_user_warning(lambda msg: log.warning("MuJoCo: %s", str(msg).strip()))

ROBOT_CONTYPE, ROBOT_CONAFFINITY = 2, 1  # robot geoms touch the world, never each other
WORLD_CONTYPE, WORLD_CONAFFINITY = 1, 3


def wxyz(q) -> list[float]:
    """A twin quaternion [x, y, z, w] as MuJoCo's [w, x, y, z]."""
    return [float(q[3]), float(q[0]), float(q[1]), float(q[2])]


def xyzw(q) -> np.ndarray:
    """A MuJoCo quaternion [w, x, y, z] as the twin's [x, y, z, w]."""
    return np.array([q[1], q[2], q[3], q[0]], float)


def damping_ratio_for_restitution(e: float) -> float:
    """Damping ratio of a linear spring-damper contact whose bounce keeps ``e`` of the speed.

    A damped oscillator's half period ends with the speed scaled by exp(-zeta pi / sqrt(1 - zeta^2));
    solved for zeta. MuJoCo's contact is such a spring-damper (solref), softened by solimp, so
    the measured restitution comes close but not exactly.
    """
    e = min(max(float(e), 1e-3), 0.999)
    ln = math.log(e)
    return -ln / math.sqrt(math.pi ** 2 + ln ** 2)


@dataclass(frozen=True)
class Surface:
    """How a geom touches others (MuJoCo's per-geom contact parameters).

    ``friction`` is the sliding (Coulomb) coefficient; ``torsional`` and ``rolling`` are lengths (m):
    the resisting torque per newton of normal force about the normal and for rolling (used when the
    contact's ``condim`` is 4 or 6). ``timeconst``/``dampratio`` are solref (a contact behaves as a
    spring-damper of that time constant; MuJoCo keeps it at least two time steps), ``solimp`` its
    impedance (how much of the constraint force the solver applies as the geoms interpenetrate).
    """

    friction: float = 1.0
    torsional: float = 0.005
    rolling: float = 0.0001
    timeconst: float = 0.02
    dampratio: float = 1.0
    solimp: tuple[float, ...] = (0.9, 0.95, 0.001, 0.5, 2.0)
    condim: int = 3
    priority: int = 0

    def apply(self, geom) -> None:
        geom.friction = [float(self.friction), float(self.torsional), float(self.rolling)]
        geom.solref = [float(self.timeconst), float(self.dampratio)]
        geom.solimp = [float(v) for v in self.solimp]
        geom.condim = int(self.condim)
        geom.priority = int(self.priority)


def actuator(joint: str) -> str:
    """The name of the position actuator :func:`robot_spec` adds on ``joint``."""
    return f"act_{joint}"


def _urdf_xml(urdf: Path, visual: bool) -> str:
    text = urdf.read_text().replace("package://", "")
    block = (f'<mujoco><compiler meshdir="{urdf.parent}" strippath="false" '
             f'discardvisual="{"false" if visual else "true"}" fusestatic="false" '
             f'balanceinertia="true"/></mujoco>')
    text, n = re.subn(r"(<robot\b[^>]*>)", lambda m: m.group(1) + block, text, count=1)
    if n != 1:
        raise ValueError(f"{urdf}: no <robot> element")
    return text


def arm_inertia(robot: Robot) -> np.ndarray:
    """Diagonal of the arm's joint-space inertia (kg m^2): the description's ``arm_inertia``, else mj_fullM of
    the URDF's links at the robot's ready posture. The servo gains of a joint with bandwidth w are then
    kp = I w^2, kv = 2 I w (critically damped)."""
    if robot.arm_inertia:
        return np.array(robot.arm_inertia, float)
    spec = mujoco.MjSpec.from_string(_urdf_xml(Path(robot.urdf_file), False))
    m = spec.compile()
    d = mujoco.MjData(m)
    for name, v in robot.ready_positions().items():
        d.qpos[m.jnt_qposadr[m.joint(name).id]] = v
    mujoco.mj_forward(m, d)
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    return np.array([full[m.jnt_dofadr[m.joint(j).id], m.jnt_dofadr[m.joint(j).id]] for j in robot.arm])


def robot_spec(robot: Robot, *, arm_kp, arm_kv, finger_kp: float, finger_kv: float,
               finger_force: float, arm_surface: Surface | None = None, finger_surface: Surface | None = None,
               joint_damping: float = 0.0, gravcomp: bool = True, visual: bool = False) -> mujoco.MjSpec:
    """A spec holding the robot (fixed base at the origin) with position actuators on its arm and gripper joints.

    ``arm_kp``/``arm_kv``: a gain per arm joint (N m/rad, N m s/rad; or one for all); the arm's
    force limits are the URDF's effort limits. Gripper joints: gain ``finger_kp``, damping ``finger_kv``,
    force limited to ``finger_force`` (N, or N m for a revolute drive; changeable after compiling with
    :meth:`MujocoWorld.set_finger_force`). The URDF's ``<mimic>`` joints follow their drive through joint
    equalities (MuJoCo's URDF import). Actuators are named :func:`actuator` of each joint.
    """
    spec = mujoco.MjSpec.from_string(_urdf_xml(Path(robot.urdf_file), visual))
    n = len(robot.arm)
    arm_kp = np.broadcast_to(np.asarray(arm_kp, float), (n,))
    arm_kv = np.broadcast_to(np.asarray(arm_kv, float), (n,))
    arm_surface, finger_surface = arm_surface or Surface(), finger_surface or Surface()
    fingers = set(robot.gripper.fingers)
    for body in spec.bodies:
        if body.name == "world":
            continue
        # the URDF gives every link's inertia: fixed-base links only need gravity compensation
        body.gravcomp = 1.0 if gravcomp else 0.0
        for geom in body.geoms:
            if geom.contype == 0 and geom.conaffinity == 0:
                continue  # a visual mesh
            geom.contype, geom.conaffinity = ROBOT_CONTYPE, ROBOT_CONAFFINITY
            if body.name in fingers:
                finger_surface.apply(geom)
            else:
                arm_surface.apply(geom)
    for joint in spec.joints:
        joint.damping = [float(joint_damping), 0.0, 0.0]  # linear damping (MuJoCo 4: a polynomial)
        joint.actgravcomp = bool(gravcomp)
    for k, name in enumerate(robot.arm):
        act = spec.add_actuator(name=actuator(name), target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=float(arm_kp[k]), kv=float(arm_kv[k]))
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        # the robot block's torque limits (the URDF's efforts unless it gives its own), as pybullet's motors have
        spec.joint(name).actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
        spec.joint(name).actfrcrange = [-float(robot.arm_force[k]), float(robot.arm_force[k])]
    for name in robot.gripper.joints:
        act = spec.add_actuator(name=actuator(name), target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=float(finger_kp), kv=float(finger_kv))
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-float(finger_force), float(finger_force)]
        # the actuator's own limit applies, not the URDF's effort (a Franka Hand grasps with up to 70 N, its
        # URDF says 20 N)
        spec.joint(name).actfrclimited = mujoco.mjtLimited.mjLIMITED_FALSE
    return spec


def set_options(spec: mujoco.MjSpec, *, timestep: float = 0.001, impratio: float = 1.0, iterations: int = 100,
                tolerance: float = 1e-10, gravity=(0.0, 0.0, -9.81)) -> None:
    """Physics options: elliptic friction cones, Newton solver, implicit-in-velocity integration.

    ``implicitfast`` integrates actuator damping (kv) and joint damping implicitly, so stiff joint
    servos stay stable at a 1 kHz step. ``impratio`` > 1 makes friction stiffer than the normal
    force (less creep of a held object under elliptic cones).
    """
    o = spec.option
    o.timestep = float(timestep)
    o.gravity = [float(g) for g in gravity]
    o.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    o.solver = mujoco.mjtSolver.mjSOL_NEWTON
    o.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    o.impratio = float(impratio)
    o.iterations = int(iterations)
    o.tolerance = float(tolerance)


def add_table(spec: mujoco.MjSpec, surface: Surface | None = None, name: str = "table") -> None:
    """An infinite table plane at z = 0."""
    g = spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05])
    g.contype, g.conaffinity = WORLD_CONTYPE, WORLD_CONAFFINITY
    (surface or Surface()).apply(g)


def _shape_geoms(shape: dict) -> list[tuple[int, list[float], list[float], list[float]]]:
    """(geom type, MuJoCo size, position, quaternion [x, y, z, w]) of a twin shape, in its frame."""
    t = shape.get("type")
    one = [0.0, 0.0, 0.0, 1.0]
    if t == "sphere":
        return [(mujoco.mjtGeom.mjGEOM_SPHERE, [float(shape["radius"]), 0, 0], [0, 0, 0], one)]
    if t == "box":
        return [(mujoco.mjtGeom.mjGEOM_BOX, [float(s) / 2 for s in shape["size"]], [0, 0, 0], one)]
    if t == "cylinder":
        return [(mujoco.mjtGeom.mjGEOM_CYLINDER, [float(shape["radius"]), float(shape["length"]) / 2, 0], [0, 0, 0],
                 one)]
    if t in ("container", "socket", "boxes"):
        parts = container_parts(shape) if t == "container" else socket_parts(shape) if t == "socket" else shape["parts"]
        return [(mujoco.mjtGeom.mjGEOM_BOX, [float(s) / 2 for s in p["size"]], [float(v) for v in p["pos"]],
                 [float(v) for v in p["quat"]]) for p in parts]
    raise ValueError(f"shape type {t!r} cannot be built in MuJoCo (sphere, box, cylinder, container, socket, boxes)")


def add_entity(spec: mujoco.MjSpec, name: str, shape: dict, pose, *, mass: float | None = None,
               surface: Surface | None = None, shell: bool = False, damping: float = 0.0) -> None:
    """A body ``name`` of ``shape`` at ``pose``: free (a free joint) when ``mass`` > 0, else static.

    Shapes as in :mod:`protocol.geometry`: sphere, box, cylinder (along its z axis), container
    (its boxes from :func:`protocol.geometry.container_parts`), socket (from :func:`~protocol.geometry.socket_parts`)
    and ``{type: boxes, parts: [{size,
    pos, quat}]}`` (any static compound of boxes in the body's frame). A free body's inertia comes
    from its geoms (``shell``: a thin shell's instead of a solid's, e.g. a hollow ball); ``damping``
    is a small velocity damping of its free joint (air drag, N s/m and N m s/rad).
    """
    if any(b.name == name for b in spec.bodies):
        raise ValueError(f"entity {name!r}: the world has a body of that name already (the robot's links, 'world'): "
                         "rename the entity")
    body = spec.worldbody.add_body(name=name, pos=[float(v) for v in pose[:3]], quat=wxyz(pose[3:7]))
    free = mass is not None and mass > 0
    geoms = _shape_geoms(shape)
    if free:
        j = body.add_freejoint(name=f"{name}_free")
        j.damping = [float(damping), 0.0, 0.0]
    for gtype, size, pos, quat in geoms:
        # (unnamed: contacts are told apart by their bodies; a name such as 'bin_0' or 'table' could be taken)
        g = body.add_geom(type=gtype, size=size, pos=pos, quat=wxyz(quat))
        g.contype, g.conaffinity = WORLD_CONTYPE, WORLD_CONAFFINITY
        (surface or Surface()).apply(g)
        if free:
            assert mass is not None, "a free body needs a mass"
            g.mass = float(mass) / len(geoms)
            if shell:
                g.typeinertia = mujoco.mjtGeomInertia.mjINERTIA_SHELL


_UNSTABLE = ("mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC")
"""MuJoCo's warnings of a state it reset (a position, velocity or acceleration that is not a number, or too large)."""


class MujocoWorld:
    """A compiled spec and its data: stepping and the queries a robot world needs.

    Stepping is split (``mj_step2`` then ``mj_step1``) so that after :meth:`step` every derived
    quantity (body poses, Jacobians, bias forces) belongs to the current state; :meth:`forward`
    must follow any direct change of ``qpos``/``qvel``.
    """

    def __init__(self, spec: mujoco.MjSpec, robot: Robot | None = None):
        self.spec = spec
        self.robot = robot
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._index()
        self.forward()

    def rebuild(self) -> None:
        """Compile the spec again after adding to it, keeping the state of what was there.

        Changes made to the compiled model by hand (gains, force limits, friction) are lost: make
        them in the spec too, or again after rebuilding.
        """
        self.model, self.data = self.spec.recompile(self.model, self.data)
        self.__dict__.pop("_servo", None)  # (arm_torque_mode's saved servo: sized for the model before)
        self._index()
        self.forward()

    def _index(self) -> None:
        m = self.model
        arm = self.robot.arm if self.robot else ()
        grip = self.robot.gripper.joints if self.robot else ()
        self.arm_qpos = np.array([m.jnt_qposadr[m.joint(j).id] for j in arm], int)
        self.arm_dof = np.array([m.jnt_dofadr[m.joint(j).id] for j in arm], int)
        self.finger_qpos = np.array([m.jnt_qposadr[m.joint(j).id] for j in grip], int)
        self.finger_dof = np.array([m.jnt_dofadr[m.joint(j).id] for j in grip], int)
        self.arm_act = np.array([m.actuator(actuator(j)).id for j in arm], int)
        self.finger_act = np.array([m.actuator(actuator(j)).id for j in grip], int)
        # the URDF's mimic joints: (qpos and dof addresses, the leader's index among the gripper joints, multiplier,
        # offset)
        mimic = self.robot.gripper.mimic if self.robot else {}
        self.mimic_qpos = [(int(m.jnt_qposadr[m.joint(f).id]), int(m.jnt_dofadr[m.joint(f).id]),
                            list(grip).index(leader), float(mult), float(off))
                           for f, (leader, mult, off) in mimic.items() if leader in grip and f not in grip]
        fingers = {m.body(b).id for b in (self.robot.gripper.fingers if self.robot else ())}
        self.finger_geoms = np.array([g for g in range(m.ngeom) if m.geom_bodyid[g] in fingers
                                      and m.geom_contype[g] == ROBOT_CONTYPE], int)
        self._jacp = np.zeros((3, m.nv))
        self._jacr = np.zeros((3, m.nv))

    # -- time
    def forward(self) -> None:
        """Recompute everything derived from the state (after setting qpos/qvel by hand)."""
        mujoco.mj_forward(self.model, self.data)

    def step(self) -> None:
        """One time step with the current controls; derived quantities then match the new state."""
        mujoco.mj_step2(self.model, self.data)
        mujoco.mj_step1(self.model, self.data)

    def diverged(self) -> str | None:
        """Whether the simulation became unstable since this was last asked: the warning MuJoCo gave (it then resets
        the whole state, every body to where the model put it and the arm to zero, and only warns), or None."""
        w = self.data.warning
        bad = [name for name in _UNSTABLE if w[getattr(mujoco.mjtWarning, name)].number]
        for name in _UNSTABLE:
            w[getattr(mujoco.mjtWarning, name)].number = 0
        return ", ".join(bad) or None

    # -- robot
    def set_joints(self, arm_q, fingers) -> None:
        """Put the arm and fingers at these positions, at rest (and the controls there too); the URDF's mimic
        joints where their leader puts them (their equalities hold from the start, stepped or not)."""
        d = self.data
        d.qpos[self.arm_qpos] = np.asarray(arm_q, float)
        d.qpos[self.finger_qpos] = np.asarray(fingers, float)
        for adr, dof, leader, mult, off in self.mimic_qpos:
            d.qpos[adr] = mult * float(d.qpos[self.finger_qpos[leader]]) + off
            d.qvel[dof] = 0.0
        d.qvel[self.arm_dof] = 0.0
        d.qvel[self.finger_dof] = 0.0
        d.ctrl[self.arm_act] = np.asarray(arm_q, float)
        d.ctrl[self.finger_act] = np.asarray(fingers, float)
        self.forward()

    def set_finger_force(self, force: float) -> None:
        """Limit each finger actuator to ``force`` newtons."""
        self.model.actuator_forcerange[self.finger_act] = [-float(force), float(force)]

    def set_finger_friction(self, friction: float) -> None:
        """The finger pads' sliding friction coefficient (in the spec too: it survives :meth:`rebuild`)."""
        self.model.geom_friction[self.finger_geoms, 0] = float(friction)
        for body in self.spec.bodies:
            if self.robot is not None and body.name in self.robot.gripper.fingers:
                for g in body.geoms:
                    if g.contype == ROBOT_CONTYPE:
                        g.friction = [float(friction), float(g.friction[1]), float(g.friction[2])]

    def arm_torque_mode(self, on: bool) -> None:
        """Turn the arm's position servos into torque motors (``ctrl`` = joint torque) or back.

        In torque mode the controller owns gravity too: the links' gravity compensation is off.
        """
        m, a = self.model, self.arm_act
        if not hasattr(self, "_servo"):
            self._servo = (m.actuator_gainprm[a].copy(), m.actuator_biasprm[a].copy(), m.body_gravcomp.copy())
        gain, bias, gravcomp = self._servo
        if on:
            m.actuator_gainprm[a] = 0.0
            m.actuator_gainprm[a, 0] = 1.0
            m.actuator_biasprm[a] = 0.0
            m.body_gravcomp[:] = 0.0
        else:
            m.actuator_gainprm[a], m.actuator_biasprm[a], m.body_gravcomp[:] = gain, bias, gravcomp

    def joints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and actuator forces (incl. gravity compensation) of the arm's joints, then the
        gripper's."""
        d = self.data
        idx_q = np.concatenate([self.arm_qpos, self.finger_qpos])
        idx_v = np.concatenate([self.arm_dof, self.finger_dof])
        return d.qpos[idx_q].copy(), d.qvel[idx_v].copy(), d.qfrc_actuator[idx_v].copy()

    def jacobian(self, body: str, point) -> np.ndarray:
        """6 x nv Jacobian (linear over angular, world frame) of the world ``point`` fixed to ``body``."""
        mujoco.mj_jac(self.model, self.data, self._jacp, self._jacr, np.asarray(point, float),
                      self.model.body(body).id)
        return np.vstack([self._jacp, self._jacr])

    # -- bodies
    def body_pose(self, name: str) -> np.ndarray:
        """[x, y, z, qx, qy, qz, qw] of a body's frame."""
        b = self.data.body(name)
        return np.concatenate([b.xpos, xyzw(b.xquat)])

    def body_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Linear velocity of the body's centre of mass and angular velocity, in the world frame (MuJoCo's
        ``mjOBJ_BODY``). An entity's sphere, box or cylinder has its centre of mass at its frame's origin, so this
        is also the velocity a free joint's ``qvel`` holds; a robot link's frame may move otherwise."""
        v = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_BODY, self.model.body(name).id, v, 0)
        return v[3:], v[:3]
