"""The MuJoCo reality: the same scripted world as :class:`recordings.synth.reality.Reality`, another engine.

The world is built with :mod:`agents.engines.mujoco_world` (a builder, not a model of the
ensemble) and stepped at 1 kHz with elliptic friction cones, the Newton solver and implicit
damping. The random draws of a recording (friction, restitution, masses, sizes, positions) are the
same as in pybullet; what each means in MuJoCo's contact model, and the settings pybullet does
not have, are chosen here from physics:

- Joint servos: a position servo per arm joint with gravity compensation (as the Panda's own
  controller has), critically damped at a 10 Hz bandwidth for each joint's inertia at HOME:
  kp = I w^2, kv = 2 I w. The trajectory's velocity is fed forward (``ctrl = q + kv/kp qd``
  makes MuJoCo's kp (ctrl - q) - kv qd the PD law kp (q_ref - q) + kv (qd_ref - qd)).
  pybullet's position gain has no meaning here and is ignored.
- Fingers: a gripper that moves its fingers at a set speed and squeezes with a set force. A stiff
  servo per finger, force-limited to the grip force: kp = 10 kN/m reaches 40 N (the largest grip
  force drawn) 4 mm short of the target, so the 12 mm DIP and the 66 mm ball are both squeezed
  with the grip force itself; kv = 100 N s/m damps the 0.1 kg finger (critical: 63). The servo's
  setpoint moves towards the commanded opening at 0.1 m/s per finger, a gripper's top speed, so
  the fingers do not slam into what they grasp.
- Contacts: each surface's contacts are spring-dampers whose damping ratio gives that body's
  drawn restitution (MuJoCo averages the two surfaces' settings where pybullet multiplies their
  restitutions) and whose natural frequency is at most 500 rad/s, so that a bounce lasts several
  1 ms steps (timeconst = 1 / (0.95 w zeta)). The finger pads are critically damped and as stiff
  as the step allows (timeconst 2 ms; the URDF pads' 3e4 N/m on a 57 g ball would be 1.4 ms) and
  decide every contact they take part in (priority); their torsional friction is that of a 5 mm
  contact patch (2/3 mu a). Friction between two surfaces is the larger of the two (MuJoCo's rule;
  pybullet multiplies them).
- impratio 10 (elliptic cones): friction constraints ten times harder than the soft normal ones,
  so a held ball does not creep in the fingers -- the grip holds or slides as Coulomb's law says.

Joint efforts are ``qfrc_actuator``: what the servos or the torque controller apply, the arm's
gravity support included (MuJoCo counts the compensation as actuator force, limited by the joint's
torque limit), squeezing fingers negative -- what a Panda's joint torque sensors report.
"""
from __future__ import annotations

import math

import mujoco
import numpy as np

from agents.engines.mujoco_world import (
    MujocoWorld,
    Surface,
    add_entity,
    add_table,
    arm_inertia,
    damping_ratio_for_restitution,
    robot_spec,
    set_options,
)
from protocol.errors import SynthError
from protocol.robot import resolve_robot

from .arm import synth_arm
from .common import SIM_RATE, _rot
from .reality import Material, World

SERVO_BANDWIDTH_HZ = 10.0
_W = 2 * math.pi * SERVO_BANDWIDTH_HZ
ROBOT = resolve_robot({"use": "panda"})
ARM_KP = arm_inertia(ROBOT) * _W ** 2
ARM_KV = 2 * arm_inertia(ROBOT) * _W
FINGER_KP = 10000.0  # N/m: 40 N at 4 mm from the target
FINGER_KV = 100.0  # N s/m
FINGER_SPEED = 0.1  # m/s per finger: how fast the gripper moves its servos' setpoint
JOINT_DAMPING = 0.02  # as the pybullet reality
CONTACT_OMEGA = 500.0  # rad/s: the fastest contact oscillation the 1 kHz step follows (w dt = 0.5)
PAD_PATCH = 0.005  # m: radius of a finger pad's contact patch
PAD_TIMECONST = 2.0 / SIM_RATE
IMPRATIO = 10.0
SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)
PAD_SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)


def _surface(friction: float, restitution: float | None, *, rolling: float | None = None,
             spinning: float | None = None, condim: int = 3) -> Surface:
    """A surface whose contacts bounce back ``restitution`` of the speed (0.05 when None)."""
    zeta = damping_ratio_for_restitution(0.05 if restitution is None else restitution)
    tc = max(2.0 / SIM_RATE, 1.0 / (SOLIMP[1] * CONTACT_OMEGA * zeta))
    return Surface(friction=float(friction), torsional=1e-4 if spinning is None else float(spinning),
                   rolling=1e-4 if rolling is None else float(rolling), timeconst=tc, dampratio=zeta,
                   solimp=SOLIMP, condim=condim)


class MujocoReality(World):
    """The MuJoCo reality (see the module docstring). Bodies are named ``body0``, ``body1``, ...

    Bodies may be added at any time: the world is compiled when first stepped or asked, and
    recompiled (keeping the state) when a body is added later.
    """

    name = "mujoco"

    def __init__(self, contact: dict[str, float]):
        self.arm = synth_arm("panda")  # MuJoCo worlds are built for the Panda only (so far)
        self.dt = 1.0 / SIM_RATE
        self.t = 0.0
        self.steps = 0
        finger = Surface(friction=contact["finger_friction"], torsional=2 / 3 * contact["finger_friction"] * PAD_PATCH,
                         rolling=1e-4, timeconst=PAD_TIMECONST, dampratio=1.0, solimp=PAD_SOLIMP, condim=4,
                         priority=1)
        self.spec = robot_spec(ROBOT, arm_kp=ARM_KP, arm_kv=ARM_KV, finger_kp=FINGER_KP, finger_kv=FINGER_KV,
                               # the links' housings: some friction, little bounce
                               finger_force=20.0, arm_surface=_surface(0.5, 0.3), finger_surface=finger,
                               joint_damping=JOINT_DAMPING)
        set_options(self.spec, timestep=self.dt, impratio=IMPRATIO)
        add_table(self.spec, _surface(contact["table_friction"], contact["table_restitution"]))
        self._w: MujocoWorld | None = None
        self._dirty = True
        self._torque = False
        self._arm_init: tuple[np.ndarray, np.ndarray] | None = None
        self._finger_set = 0.0  # the finger servos' setpoint (m), moving at FINGER_SPEED
        self._bodies = 0

    # -- building
    @property
    def w(self) -> MujocoWorld:
        """The compiled world (compiled or recompiled here when bodies were added)."""
        if self._dirty:
            if self._w is None:
                self._w = MujocoWorld(self.spec, ROBOT)
                if self._arm_init is not None:
                    self._w.set_joints(*self._arm_init)
            else:
                self._w.rebuild()
                self._w.arm_torque_mode(self._torque)
            self._dirty = False
        assert self._w is not None
        return self._w

    def _body(self, shape: dict, pose, mass: float | None, surface: Surface, shell: bool = False,
              damping: float = 0.0) -> str:
        name = f"body{self._bodies}"
        self._bodies += 1
        add_entity(self.spec, name, shape, pose, mass=mass, surface=surface, shell=shell, damping=damping)
        self._dirty = True
        return name

    @staticmethod
    def _free_surface(m: Material | None, condim: int) -> Surface:
        if m is None:
            return _surface(0.5, None, condim=condim)
        return _surface(m.friction, m.restitution, rolling=m.rolling, spinning=m.spinning, condim=condim)

    def static_boxes(self, parts: list[dict], pose, friction: float, restitution: float) -> list[str]:
        return [self._body({"type": "boxes", "parts": parts}, pose, None, _surface(friction, restitution))]

    def cylinder(self, radius: float, length: float, pos, mass: float = 0.0, quat=(0, 0, 0, 1),
                 material: Material | None = None) -> str:
        shape = {"type": "cylinder", "radius": radius, "length": length}
        return self._body(shape, [*pos, *quat], mass or None, self._free_surface(material, 4))

    def sphere(self, radius: float, pos, mass: float, material: Material | None = None) -> str:
        # a tennis ball is a hollow rubber core: a shell's inertia, rolling friction (condim 6)
        damping = (material.damping or 0.0) * mass if material else 0.0
        return self._body({"type": "sphere", "radius": radius}, [*pos, 0, 0, 0, 1], mass,
                          self._free_surface(material, 6), shell=True, damping=damping)

    # -- the robot
    def reset_arm(self, q, fingers) -> None:
        self._arm_init = (np.asarray(q, float), np.asarray(fingers, float))
        self._finger_set = float(np.mean(fingers))
        if self._w is not None:
            self.w.set_joints(*self._arm_init)

    def set_finger_friction(self, friction: float) -> None:
        self.w.set_finger_friction(friction)

    def command_arm_position(self, q, qd, gain: float, limits) -> None:
        # the servos' torque limits are the URDF's effort limits (the same as ``limits``), set when built
        w = self.w
        if self._torque:
            self._torque = False
            w.arm_torque_mode(False)
        w.data.ctrl[w.arm_act] = np.asarray(q, float) + ARM_KV / ARM_KP * np.asarray(qd, float)

    def arm_torque_mode(self) -> None:
        self._torque = True
        self.w.arm_torque_mode(True)

    def command_arm_torque(self, tau) -> None:
        w = self.w
        w.data.ctrl[w.arm_act] = np.asarray(tau, float)

    def command_fingers(self, target: list[float], force: float) -> None:
        w = self.w
        step = FINGER_SPEED * self.dt
        self._finger_set += min(max(float(target[0]) - self._finger_set, -step), step)
        w.data.ctrl[w.finger_act] = self._finger_set
        w.set_finger_force(force)

    def joints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.w.joints()

    def hand(self) -> tuple[np.ndarray, np.ndarray]:
        p = self.w.body_pose(ROBOT.gripper.hand)
        return p[:3], p[3:]

    def tip_dynamics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        w = self.w
        pos, quat = self.hand()
        tip = pos + _rot(quat)[:, 2] * self.arm.tip
        J = w.jacobian(ROBOT.gripper.hand, tip)[:, w.arm_dof]
        return tip, quat, J, w.data.qfrc_bias[w.arm_dof].copy()

    # -- bodies and time
    def pose(self, body: str) -> np.ndarray:
        return self.w.body_pose(body)

    def speed(self, body: str) -> float:
        return float(np.linalg.norm(self.w.body_velocity(body)[0]))

    def step(self) -> None:
        w = self.w
        w.step()
        self.steps += 1
        self.t = self.steps * self.dt
        if self.steps % 100 == 0 and w.diverged():
            raise SynthError(f"the MuJoCo reality became unstable at t = {self.t:.3f} s (MuJoCo reset its state)")

    def describe(self) -> dict:
        return {"engine": f"mujoco {mujoco.__version__}", "timestep_s": self.dt, "cone": "elliptic",
                "solver": "newton", "integrator": "implicitfast", "impratio": IMPRATIO,
                "arm_kp": ARM_KP.tolist(), "arm_kv": ARM_KV.tolist(), "finger_kp": FINGER_KP, "finger_kv": FINGER_KV,
                "finger_speed_m_s": FINGER_SPEED,
                "contact_omega_rad_s": CONTACT_OMEGA, "pad_timeconst_s": PAD_TIMECONST, "pad_patch_m": PAD_PATCH,
                "solimp": list(SOLIMP), "pad_solimp": list(PAD_SOLIMP), "gravity_compensation": True}

    def close(self) -> None:
        self._w = None
