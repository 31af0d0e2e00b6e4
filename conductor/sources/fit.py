"""Does the robot's telemetry fit the scene's robot? Checked before the first tick, and renamed on the way.

A recording names its joints as its robot's driver did; the scene's robot block says which URDF joints
those are (``joints:``, identity by default). :func:`check_fit` compares the two sets once the map is
applied: no recorded joint is a joint of the robot -> a one-line error naming both sets and the map to
write; some arm or gripper joints missing -> a warning that the run reports (its status is then
``degraded``: the robot moves, but not all of it). :func:`rename` applies the map to one joint state.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

from protocol.errors import InputError, RunAborted, TwinError
from protocol.robot import Robot

log = logging.getLogger("twin.source")


def _few(names: Iterable[str], n: int = 8) -> str:
    names = list(names)
    return ", ".join(names[:n]) + (f", ... ({len(names)} in all)" if len(names) > n else "")


def check_fit(robot: Robot, recorded: Iterable[str], where: str) -> list[str]:
    """Warnings (empty when every arm and gripper joint is reported); InputError when none is. ``recorded`` in
    the bag's order (the suggested map pairs them with the robot's joints in order)."""
    recorded = list(dict.fromkeys(recorded))
    matched, missing = robot.fit(recorded)
    if not recorded:
        raise InputError(f"{where}: it has no joint states with joint names, so nothing moves the scene's robot "
                        f"{robot.name}")
    if not matched:
        raise InputError(f"{where}: none of its joint names ({_few(recorded)}) is a joint of the scene's robot "
                        f"{robot.name} ({_few(robot.joints, 12)}): map them in the scene's robot block, e.g. "
                        f"{suggested_map(robot, recorded)}")
    if missing:
        return [f"{where}: the robot's joints {_few(missing)} are not in the telemetry (recorded: "
                f"{_few(recorded)}); they stay where they started: map them in the scene's robot block "
                "(joints: {recorded_name: urdf_name})"]
    return []


GRIPPER_WORDS = ("finger", "grip", "drive", "jaw", "claw", "hand")
"""Parts of a recorded joint's name that say it moves the gripper (the xArm's ``drive_joint``, ``finger_joint``)."""


def suggested_map(robot: Robot, recorded: list[str]) -> str:
    """A joint map to start from: the recording's arm joints paired with the robot's arm joints in order, the
    ones whose names say gripper (:data:`GRIPPER_WORDS`) with its gripper joints (never a gripper joint with an
    arm joint); joints one side has more of are left out, and a note says so when the arms differ."""
    grip = [n for n in recorded if any(w in n.lower() for w in GRIPPER_WORDS)]
    arm = [n for n in recorded if n not in grip]
    pairs = [*zip(arm, robot.arm, strict=False), *zip(grip, robot.gripper.joints, strict=False)]
    text = "joints: {" + ", ".join(f"{a}: {b}" for a, b in pairs) + "}"
    if len(arm) != len(robot.arm):
        text += (f" (the recording has {len(arm)} arm joint{'s' if len(arm) != 1 else ''}, the robot "
                 f"{len(robot.arm)}: check the pairs)")
    return text


def rename(robot: Robot, msg: dict[str, Any]) -> dict[str, Any]:
    """A joint state with its names as the URDF's (the same dict when the robot has no joint map)."""
    if not robot.joint_map:
        return msg
    return {**msg, "name": robot.rename(list(msg["name"]))}


def recorded_joints(items: Iterable[tuple[float, str, dict[str, Any]]]) -> list[str]:
    """Every joint name a recording's joint states carry, in the order they first come."""
    out: dict[str, None] = {}
    for _, kind, m in items:
        if kind == "joint_state":
            out.update(dict.fromkeys(m["name"]))
    return list(out)


LIVE_FIT_S = 1.0
"""Seconds of a live robot's joint states whose joint names are checked against the scene's robot together: an
arm's and a gripper's driver publishing apart each name only theirs, and the first message alone would be half
the robot."""


class JointFit:
    """The scene's robot between a source and the models: every joint state renamed by the robot's joint
    map, the source's joints checked against the robot once (a replay before the first tick, a live source
    over its first :data:`LIVE_FIT_S` seconds of joint states, or at its end if that came first). ``report``
    takes the warnings (the run's degraded reasons)."""

    def __init__(self, robot: Robot | None, source: Any, report: Any) -> None:
        self.robot = robot
        self.rec = getattr(source, "rec", None)
        self.report = report
        self.pending = robot is not None and source is not None and self.rec is None
        self._heard: dict[str, None] = {}  # a live source's joint names so far, in the order they came
        self._first: float | None = None  # the stamp of its first joint state

    def before_run(self) -> None:
        """A replay's joints against the robot (RunAborted when none of them is the robot's)."""
        if self.robot is not None and self.rec is not None:
            try:
                self._report(check_fit(self.robot, self.rec.joints_in_order, self.rec.path))
            except TwinError as e:
                raise RunAborted(str(e)) from None

    def _report(self, warnings: list[str]) -> None:
        for w in warnings:
            log.warning("%s", w)
        self.report(warnings)

    def take(self, msg: dict[str, Any]) -> dict[str, Any]:
        """One joint state, renamed (and, the first live one, checked: reported, never fatal)."""
        if self.robot is None:
            return msg
        if self.pending:
            self._heard.update(dict.fromkeys(msg["name"]))
            self._first = msg["stamp"] if self._first is None else self._first
            if msg["stamp"] - self._first >= LIVE_FIT_S:
                self.finish()
        return rename(self.robot, msg)

    def finish(self) -> None:
        """The run has ended (the conductor's summary): check a live source's joints if :meth:`take` has not yet
        (a run shorter than :data:`LIVE_FIT_S`)."""
        if self.pending and self.robot is not None and self._heard:
            self.pending = False
            try:
                warnings = check_fit(self.robot, self._heard, "the live telemetry")
            except TwinError as e:
                warnings = [str(e)]
            self._report(warnings)
