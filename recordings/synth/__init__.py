"""Synthetic robot recordings: a separate, higher-fidelity *reality* that plays the real robot.

``twin record synth`` runs a scripted Franka Panda task in a pybullet world of its own and records
what a real robot would log: ``/joint_states`` of the nine Panda joints at 250 Hz (with sensor noise
and timing jitter) and ``/action`` annotations (``move_arm``, ``move_hand``, ``release``, phases
``start``/``end``), as MCAP in rosbag2 layout (:class:`recordings.rosbag.RecordingWriter`). It then
measures what really happened and stores it as the recording's ground truth.

The reality is deliberately *not* the ensemble's physics model: it is its own pybullet DIRECT
world stepped at 1 kHz with more solver iterations, cone friction, rolling and spinning friction,
restitution, the URDF's soft finger pads, and randomized friction, masses and sizes. Nothing here
imports ``agents/``.

Two scenarios, each computed with pybullet IK on ``panda_hand`` (hand pointing down) by a separate
kinematic planner client, played as smooth (quintic) joint trajectories under position control with
the Panda's torque limits:

- ``ball_drop``: pick a tennis ball from a stand and drop it into a container (``bin``, ``box``,
  ``bowl``, ``cup``). Outcomes: ``success``; ``released_early`` (the hand opens on the way, well
  before the container); ``missed`` (it opens beside the container); ``empty_grasp`` (the fingers
  close on nothing -- the ball is not where the robot believes, or the hand stops too high -- and
  the robot carries on with its script). Ground truth ``in_container``: the ball's settled position
  inside the container's interior (:func:`protocol.geometry.inside_container`).
- ``insertion``: the DIP (plug) starts grasped; the SPU (socket: a static body with a chamfered
  square hole) stands on the table. The robot moves the DIP above where it *believes* the SPU is
  (true pose + ``localization_error`` in a random horizontal direction) and inserts it downwards
  under a Cartesian impedance controller (torque control with gravity compensation, so a
  misaligned DIP is stopped on the SPU's top or guided by the chamfer). Ground truth
  ``connected``: the DIP ends within 3 mm of the hole's axis and inserted to within 4 mm of the
  hole's bottom.

Every random choice (positions, friction, masses, noise levels, jitter, durations, heights) comes
from ``numpy.random.default_rng(seed)``; the same arguments give the same file. Metadata:
``twin.ground_truth``, ``twin.scene`` (what the robot perceived) and ``twin.generation`` (every
parameter).
"""
from __future__ import annotations

from protocol.errors import SynthError

from .ball_drop import synth_ball_drop
from .common import CONTAINERS, JOINT_NAMES, OUTCOMES, SCENARIOS, SynthResult
from .generate import synthesize
from .insertion import SPU_CONNECTION_OFFSET, SPU_SIZE, spu_parts, synth_insertion

__all__ = ["CONTAINERS", "JOINT_NAMES", "OUTCOMES", "SCENARIOS", "SPU_CONNECTION_OFFSET", "SPU_SIZE", "SynthError",
           "SynthResult", "spu_parts", "synth_ball_drop", "synth_insertion", "synthesize"]
