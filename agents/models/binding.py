"""The grasp models of the single-simulation baselines (the physics model's ``grasp_binding``).

A pure simulation holds a grasped object only by friction, which a coarse contact model loses. The usual
shortcuts fix the object to the hand with a constraint: ``signal`` binds the graspable nearest the fingertip
when the hand's close command ends and unbinds on ``release`` or an open command (the baseline "binding on
signals"); ``force`` binds an object both fingers press harder than ``bind_force`` and unbinds it after
``unbind_substeps`` substeps below ``unbind_force`` (the baseline "force binding"). They are the paper's
baselines, kept apart from the simulation they patch.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from ..engines.bodies import Followed


class GraspBindings:
    """Mixed into :class:`agents.models.physics.Physics`: it reads the physics' pybullet client (``p``,
    ``cid``), robot (``robot``, ``hand``, ``tip``, ``fingers``), bodies (``dynamic``, ``bodies``, ``by_id``),
    the bodies other models carry (``followed``), parameters (``prm``) and keeps ``bound`` (entity -> constraint) and
    ``weak`` (entity -> substeps below the unbind force)."""

    p: Any
    cid: int
    robot: int
    hand: int
    tip: int
    fingers: list[int]
    dynamic: list[Any]
    bodies: dict[str, Any]
    by_id: dict[int, Any]
    followed: Followed
    prm: dict[str, Any]
    bound: dict[str, int]
    weak: dict[str, int]

    if TYPE_CHECKING:  # provided by the class it is mixed into (declared here for the type checker only)
        def emit(self, name: str, **data: Any) -> None: ...
        def _link_pose(self, link: int) -> list[float]: ...
        def _tip_point(self) -> list[float]: ...
        def _base_pose(self, body: int) -> list[float]: ...

    def _graspables(self) -> Iterator[Any]:
        for b in self.dynamic:
            if "graspable" in b.tags and b.name not in self.followed and b.name not in self.bound:
                yield b

    def _bind(self, b: Any, mode: str) -> None:
        p, c = self.p, self.cid
        hs = p.getLinkState(self.robot, self.hand, computeForwardKinematics=1, physicsClientId=c)
        pos, orn = p.getBasePositionAndOrientation(b.id, physicsClientId=c)
        # the constraint frames are in the link's and the body's centre-of-mass frames
        inv_pos, inv_orn = p.invertTransform(hs[0], hs[1])
        rel_pos, rel_orn = p.multiplyTransforms(inv_pos, inv_orn, pos, orn)
        cid = p.createConstraint(self.robot, self.hand, b.id, -1, p.JOINT_FIXED, [0, 0, 0], rel_pos, [0, 0, 0],
                                 rel_orn, [0, 0, 0, 1], physicsClientId=c)
        p.changeConstraint(cid, maxForce=500.0, physicsClientId=c)
        self.bound[b.name] = cid
        self.weak[b.name] = 0
        self.emit("grasp_bound", entity=b.name, mode=mode)

    def _unbind(self, name: str) -> None:
        cid = self.bound.pop(name, None)
        self.weak.pop(name, None)
        if cid is not None:
            self.p.removeConstraint(cid, physicsClientId=self.cid)
            self.emit("grasp_unbound", entity=name, mode=self.prm["grasp_binding"])

    def _signal(self, action: dict[str, Any]) -> None:
        op, phase = action.get("operation"), action.get("phase")
        params = action.get("params") or {}
        if op == "move_hand" and params.get("command") == "close" and phase == "end":
            tip = self._tip_point()
            best, dist = None, float(self.prm["bind_distance"])
            for b in self._graspables():
                pos = self._base_pose(b.id)[:3]
                d = math.dist(pos, tip)
                if d <= dist:
                    best, dist = b, d
            if best is not None:
                self._bind(best, "signal")
        elif (op == "release" and phase == "start") or (
                op == "move_hand" and params.get("command") == "open" and phase == "start"):
            for name in list(self.bound):
                self._unbind(name)

    def _finger_forces(self) -> list[dict[int, float]]:
        """Per finger: body id -> summed normal force (N) of the finger's contact points."""
        out = []
        for li in self.fingers:
            f: dict[int, float] = {}
            for cp in self.p.getContactPoints(bodyA=self.robot, linkIndexA=li, physicsClientId=self.cid):
                f[cp[2]] = f.get(cp[2], 0.0) + cp[9]
            out.append(f)
        return out

    def _force_binding(self) -> None:
        if len(self.fingers) != 2:
            return
        left, right = self._finger_forces()
        lo, hi = float(self.prm["unbind_force"]), float(self.prm["bind_force"])
        for name in list(self.bound):
            bid = self.bodies[name].id
            if min(left.get(bid, 0.0), right.get(bid, 0.0)) < lo:
                self.weak[name] += 1
                if self.weak[name] >= int(self.prm["unbind_substeps"]):
                    self._unbind(name)
            else:
                self.weak[name] = 0
        for bid in set(left) & set(right):
            b = self.by_id.get(bid)
            if b is None or not b.dynamic or "graspable" not in b.tags or b.name in self.bound \
                    or b.name in self.followed:
                continue
            if left[bid] > hi and right[bid] > hi:
                self._bind(b, "force")
