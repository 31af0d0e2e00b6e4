"""Synthetic robot recordings: a separate *reality* that plays the real robot.

``twin record synth`` runs a scripted robot task (a Franka Panda, or a UFactory xArm 6) in a simulated world
of its own and records what a real robot would log: ``/joint_states`` of every joint of the robot at 250 Hz
(with sensor noise and timing jitter) and ``/action`` annotations (``move_arm``, ``move_hand``, ``release``, phases
``start``/``end``), as MCAP in rosbag2 layout (:class:`recordings.rosbag.RecordingWriter`). It then
measures what really happened and stores it as the recording's ground truth.

Two realities implement one interface (:class:`recordings.synth.reality.World`: bodies, the
Panda's joint commands and sensors, stepping at 1 kHz):

- ``pybullet`` (the default): its own DIRECT world with more solver iterations, cone friction,
  rolling and spinning friction, restitution and the URDF's soft finger pads -- the same engine as
  the ensemble's physics model, with other settings;
- ``mujoco`` (``--reality mujoco``): another engine (:mod:`recordings.synth.mujoco_reality`, built
  with :mod:`agents.engines.mujoco_world`), with soft contacts, elliptic friction cones, joint
  servos with gravity compensation, so that the twin is not judged by the engine it runs itself.

Both draw the same randomized world from the seed (friction, masses, sizes, positions). Nothing here
imports the ensemble's models; the MuJoCo world builder is shared with model agents, its settings are not.

Two scenarios, each computed with pybullet IK on ``panda_hand`` (hand pointing down) by a separate
kinematic planner client (the robot's own software, in either reality), played as smooth (quintic)
joint trajectories under position control with the Panda's torque limits:

- ``ball_drop``: pick a tennis ball from a stand and drop it into a container (``bin``, ``box``,
  ``bowl``, ``cup``). Outcomes: ``success``; ``released_early`` (the hand opens on the way, well
  before the container); ``missed`` (it opens beside the container); ``empty_grasp`` (the fingers
  close on nothing -- the ball is not where the robot believes, or the hand stops too high -- and
  the robot carries on with its script); ``slipped`` (the grip holds, then the gripper's force
  fails during the carry and the ball slides out while the robot still commands the grasp until its
  release at the container); ``knocked`` (the ball is not where the robot believes: a fingertip
  comes down on it and the closing fingers push it off its stand; the robot carries on). Ground
  truth ``in_container``: the ball's settled position inside the container's interior
  (:func:`protocol.geometry.inside_container`), whatever the outcome asked for.
- ``insertion``: the DIP (plug) starts grasped; the SPU (socket: a static body with a chamfered
  square hole) stands on the table. The robot moves the DIP above where it *believes* the SPU is
  (true pose + ``localization_error`` in a random horizontal direction, 0 to 10 cm) and inserts it
  downwards under a Cartesian impedance controller (torque control with gravity compensation):
  small errors are guided in by the chamfer, larger ones stop on the rim or the SPU's top (the arm
  stops about 20 mm higher), errors beyond the SPU's side let the DIP go down beside it. Ground
  truth ``connected``: the DIP ends within 3 mm of the hole's axis and inserted to within 4 mm of
  the hole's bottom (``depth_error_m`` says how high it stopped).

Every random choice (positions, friction, masses, noise levels, jitter, durations, heights, faults)
comes from ``numpy.random.default_rng(seed)`` streams; the same arguments give the same file.
Metadata: ``twin.ground_truth``, ``twin.scene`` (what the robot perceived) and ``twin.generation``
(every parameter; ``reality`` and ``engine`` when the reality is not pybullet).
"""
from __future__ import annotations

from importlib import import_module
from typing import Any

from protocol.errors import SynthError

from .common import CONTAINERS, JOINT_NAMES, OUTCOMES, REALITIES, SCENARIOS, SynthResult

# the generators (and the engines they import: pybullet, MuJoCo) load when first used, not with the choices
# above: every ``twin`` command's parser names those choices
_LAZY = {"synth_ball_drop": ".ball_drop", "synthesize": ".generate", "SPU_CONNECTION_OFFSET": ".insertion",
         "SPU_SIZE": ".insertion", "spu_parts": ".insertion", "synth_insertion": ".insertion"}


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


__all__ = ["CONTAINERS", "JOINT_NAMES", "OUTCOMES", "REALITIES", "SCENARIOS", "SPU_CONNECTION_OFFSET", "SPU_SIZE",
           "SynthError", "SynthResult", "spu_parts", "synth_ball_drop", "synth_insertion", "synthesize"]
