"""agents/engines/mujoco_world.py: the Panda of pybullet_data loads in MuJoCo with actuators, the
finger equality and the table; it holds its pose under gravity, its fingers close and open on
command, and bodies built from the twin's shapes fall and come to rest where physics says."""
from __future__ import annotations

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from agents.engines.mujoco_world import (  # noqa: E402
    MujocoWorld,
    Surface,
    add_entity,
    add_table,
    damping_ratio_for_restitution,
    robot_spec,
    set_options,
)
from protocol.geometry import inside_container  # noqa: E402
from protocol.robot import resolve_robot  # noqa: E402

PANDA = resolve_robot({"use": "panda"})
ARM_JOINTS, FINGER_JOINTS = PANDA.arm, PANDA.gripper.joints

HOME = np.array([0.0, -0.55, 0.0, -2.35, 0.0, 1.80, 0.785])
INERTIA = np.array([1.69, 2.40, 1.83, 1.68, 0.82, 0.74, 0.60])
W = 2 * np.pi * 10


def _world(*entities, visual: bool = False) -> MujocoWorld:
    spec = robot_spec(PANDA, arm_kp=INERTIA * W ** 2, arm_kv=2 * INERTIA * W, finger_kp=3000, finger_kv=250,
                      finger_force=20, visual=visual)
    set_options(spec, timestep=0.001)
    add_table(spec, Surface(friction=0.6, timeconst=0.01, dampratio=damping_ratio_for_restitution(0.5)))
    for name, shape, pose, mass in entities:
        add_entity(spec, name, shape, pose, mass=mass,
                   surface=Surface(friction=0.6, timeconst=0.01, dampratio=damping_ratio_for_restitution(0.5),
                                   condim=6, rolling=3e-4))
    w = MujocoWorld(spec, PANDA)
    w.set_joints(HOME, [0.04, 0.04])
    return w


@pytest.mark.filterwarnings("ignore:obj_decoder")  # two visual meshes lack texture coordinates
def test_the_urdf_loads_with_actuators_equality_and_kinematics_of_pybullet():
    """9 joints, 9 actuators, the finger mimic as one joint equality, no visual mesh unless asked,
    and panda_hand where pybullet puts it."""
    w = _world()
    m = w.model
    assert [m.joint(j).name for j in range(m.njnt)] == list(ARM_JOINTS + FINGER_JOINTS)
    assert m.nu == 9 and m.neq == 1 and m.eq_type[0] == mujoco.mjtEq.mjEQ_JOINT
    assert all(m.geom_contype[g] != 0 for g in range(m.ngeom)), "visual meshes are dropped by default"
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    with_visual = _world(visual=True).model
    visual = [g for g in range(with_visual.ngeom) if with_visual.geom_contype[g] == 0]
    assert visual and all(with_visual.geom_conaffinity[g] == 0 for g in visual), "visual meshes never touch"

    import pybullet as p

    cid = p.connect(p.DIRECT)
    try:
        robot = p.loadURDF(PANDA.urdf_file, useFixedBase=True, physicsClientId=cid)
        for j, v in enumerate(HOME):
            p.resetJointState(robot, j, v, physicsClientId=cid)
        link = p.getLinkState(robot, 8, computeForwardKinematics=True, physicsClientId=cid)
    finally:
        p.disconnect(cid)
    hand = w.body_pose("panda_hand")
    assert np.allclose(hand[:3], link[4], atol=1e-6)
    assert abs(abs(float(np.dot(hand[3:], link[5]))) - 1.0) < 1e-6


def test_the_arm_holds_its_pose_and_reports_gravity_as_effort():
    """Gravity compensation is part of the servo: the arm stays put, efforts carry the gravity load."""
    w = _world()
    for _ in range(500):
        w.step()
    q, qd, effort = w.joints()
    assert np.max(np.abs(q[:7] - HOME)) < 1e-3
    assert np.max(np.abs(qd[:7])) < 1e-3
    assert np.allclose(effort[:7], w.data.qfrc_bias[w.arm_dof], atol=0.2)
    assert abs(effort[1]) > 5 and abs(effort[3]) > 5, "the shoulder and elbow hold the arm up"


def test_the_fingers_close_and_open_on_command():
    w = _world()
    w.data.ctrl[w.finger_act] = 0.0
    for _ in range(1000):
        w.step()
    q, _, _ = w.joints()
    assert q[7] + q[8] < 0.001 and abs(q[7] - q[8]) < 0.001, "closed, and kept symmetric by the equality"
    w.data.ctrl[w.finger_act] = 0.04
    for _ in range(1000):
        w.step()
    q, _, _ = w.joints()
    assert q[7] > 0.038 and q[8] > 0.038
    w.set_finger_force(5.0)
    assert np.allclose(w.model.actuator_forcerange[w.finger_act], [[-5, 5], [-5, 5]])


def test_a_dropped_ball_comes_to_rest_on_the_table_and_in_a_bin():
    """A ball dropped on the table bounces and settles on it; one dropped into a bin stays inside."""
    bin_pose = [0.0, -0.6, 0.0, 0.0, 0.0, 0.0, 1.0]
    w = _world(("ball", {"type": "sphere", "radius": 0.033}, [0.5, 0.3, 0.3, 0, 0, 0, 1], 0.057),
               ("ball2", {"type": "sphere", "radius": 0.033}, [0.02, -0.6, 0.3, 0, 0, 0, 1], 0.057),
               ("bin", {"type": "container", "style": "bin"}, bin_pose, None))
    peak_after_bounce, touched = 0.0, False
    for _ in range(3000):
        w.step()
        z = w.body_pose("ball")[2]
        touched = touched or z < 0.0335
        if touched and peak_after_bounce < 0.3:
            peak_after_bounce = max(peak_after_bounce, z)
    ball = w.body_pose("ball")
    assert abs(ball[2] - 0.033) < 0.001, ball
    assert np.linalg.norm(w.body_velocity("ball")[0]) < 0.005
    # restitution 0.5 from a 0.267 m fall: a bounce of about 0.25 * 0.267 = 0.067 m (peak near z = 0.1)
    assert 0.07 < peak_after_bounce < 0.14, f"bounced to {peak_after_bounce:.3f} m"
    assert inside_container({"type": "container", "style": "bin"}, bin_pose, w.body_pose("ball2")[:3])
    assert not w.diverged()


def test_set_joints_puts_the_urdf_mimic_joints_where_their_drive_puts_them():
    """The xArm's gripper is one drive joint and five mimic joints: set without a step (the MuJoCo model's
    kinematic idle never steps), each follower stands where its equality holds and the fingers' frames are
    pybullet's for the same drive (the right finger stayed open 45 mm away before)."""
    from agents.robot.kinematics import RobotKinematics

    xarm = resolve_robot({"use": "xarm6"})
    assert len(xarm.gripper.mimic) >= 2
    w = MujocoWorld(robot_spec(xarm, arm_kp=1000.0, arm_kv=50.0, finger_kp=100, finger_kv=5, finger_force=20), xarm)
    arm = [0.1, -0.3, -0.5, 0.2, 0.6, -0.1]
    w.set_joints(arm, [0.85])
    m = w.model
    for follower, (_leader, mult, off) in xarm.gripper.mimic.items():
        assert w.data.qpos[m.jnt_qposadr[m.joint(follower).id]] == pytest.approx(mult * 0.85 + off), follower
    kin = RobotKinematics(xarm)
    try:
        kin.set_joints(dict(zip(xarm.arm, arm, strict=True)) | {xarm.gripper.joints[0]: 0.85})
        for finger in xarm.gripper.fingers:
            assert np.allclose(w.body_pose(finger)[:3], kin.link_pose(None, finger)[:3], atol=1e-4), finger
    finally:
        kin.close()


def test_the_arm_torque_limits_are_the_robot_blocks():
    """A robot block's ``arm_force`` limits MuJoCo's arm joints as it limits pybullet's motors (MuJoCo kept the
    URDF's efforts); without one, the URDF's efforts."""
    weak = resolve_robot({"use": "panda", "arm_force": [20, 20, 20, 20, 5, 5, 5]})
    for robot, want in ((weak, [20, 20, 20, 20, 5, 5, 5]), (PANDA, [87, 87, 87, 87, 12, 12, 12])):
        m = MujocoWorld(robot_spec(robot, arm_kp=100.0, arm_kv=10.0, finger_kp=100, finger_kv=5, finger_force=20),
                        robot).model
        ids = [m.joint(j).id for j in robot.arm]
        assert np.allclose(m.jnt_actfrcrange[ids], [[-f, f] for f in want])
        assert all(m.jnt_actfrclimited[ids])
