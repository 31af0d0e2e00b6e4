"""Joint and link indices of a robot body loaded in a pybullet client, by name.

Example::

    import pybullet as p
    from agents.robot.index import BodyIndex

    cid = p.connect(p.DIRECT)
    body = p.loadURDF(robot.urdf_file, useFixedBase=True, physicsClientId=cid)   # robot: protocol.robot.Robot
    idx = BodyIndex(body, cid)
    idx.joint[robot.gripper.joints[0]]   # pybullet joint index
    idx.link[robot.gripper.hand]         # pybullet link index (-1 is the base link)
"""
from __future__ import annotations


class BodyIndex:
    """Joint and link indices of a loaded robot body, by name.

    ``joint``: movable joints' names -> pybullet joint index; ``link``: every link's name -> link
    index (the base link is -1); ``lower`` / ``upper`` / ``max_force``: each movable joint's URDF limits.
    """

    def __init__(self, body: int, client: int):
        import pybullet as p

        self.body = body
        self.joint: dict[str, int] = {}
        self.link: dict[str, int] = {}
        self.lower: dict[str, float] = {}
        self.upper: dict[str, float] = {}
        self.max_force: dict[str, float] = {}
        base = p.getBodyInfo(body, physicsClientId=client)[0].decode()
        self.link[base] = -1
        for j in range(p.getNumJoints(body, physicsClientId=client)):
            info = p.getJointInfo(body, j, physicsClientId=client)
            name = info[1].decode()
            self.link[info[12].decode()] = j
            if info[2] != p.JOINT_FIXED:
                self.joint[name] = j
                self.lower[name], self.upper[name] = float(info[8]), float(info[9])
                self.max_force[name] = float(info[10])

    @property
    def num_links(self) -> int:
        """Links including the base (pybullet link indices -1 .. num_links - 2)."""
        return len(self.link)
