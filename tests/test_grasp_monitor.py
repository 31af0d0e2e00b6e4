"""The grasp monitor over the real protocol: the grasp_monitor agent as a subprocess, a Conductor
replaying finger telemetry written here (rosbag2 MCAP) through tests/scenes/grasp_monitor.yaml.

Two kinds of data:
- *recorded-style*: a pybullet Panda of the test's own (1 kHz, fingers under position control with a
  40 N limit, as a real gripper's grasp command) closes on nothing and opens, then closes on a tennis
  ball on a stand, opens, closes again and lifts it; sampled at 250 Hz with sensor noise;
- *crafted*: one value per monitor step (15 Hz) to pin the hysteresis down sample by sample.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agents.models.grasp_monitor import GraspMonitor
from agents.robot.index import BodyIndex
from conductor.core import Conductor, RunOptions
from conductor.runlog import read_run_log
from conductor.scene import load_scene
from conductor.sources.recording import load_recording
from conductor.sources.replay import ReplaySource
from protocol import codec
from protocol.keys import Keys
from protocol.robot import resolve_robot
from recordings.rosbag import RecordingWriter

from .conftest import spawn_agents
from .test_physics import PandaIK, smooth

PANDA = resolve_robot({"use": "panda"})
JOINTS, READY = PANDA.joints, PANDA.ready

HERE = Path(__file__).parent
CLOSE = {"hand": "hand", "command": "close"}
OPEN = {"hand": "hand", "command": "open"}


def run(router, procs, tmp_path, rec_path, ask_hand_free: bool = False):
    """Replay a recording to the monitor; returns (summary, events [(t, name, data)], grasped
    [(t, bool)], hand_free() asked after the run or None)."""
    session, endpoint = router
    scene = load_scene(HERE / "scenes" / "grasp_monitor.yaml")
    spawn_agents(procs, scene, endpoint)
    keys = Keys("default")
    c = Conductor(scene, session, keys, ReplaySource(load_recording(rec_path)),
                  RunOptions(run_log=str(tmp_path / "run.mcap"), register_timeout=60))
    try:
        summary = c.run()
        free = None
        if ask_hand_free:
            replies = list(session.get(keys.model("monitor", "eval/hand_free"),
                                       payload=codec.encode("eval", args=["hand"], tick=c.clock.tick,
                                                            t=c.clock.t), timeout=5.0))
            free = codec.decode("eval", replies[0].ok.payload, "value_reply").value
    finally:
        c.close()
    events, grasped = [], []
    for key, _, msg in read_run_log(summary["run_log"]):
        if not isinstance(msg, dict) or msg.get("model") != "monitor":
            continue
        if "/event/" in key:
            events.append((msg["t"], msg["name"], msg["data"]))
        elif key.endswith("/out/monitor/grasped"):
            grasped.append((msg["t"], msg["value"]))
    return summary, sorted(events, key=lambda e: e[0]), sorted(grasped), free


# ------------------------------------------------------------------- recorded-style data
def gripper_run(with_ball: bool, seconds: float, close_at, open_at, lift=None, force: float = 40.0):
    """A pybullet Panda (1 kHz) with its fingertip centre at a ball's place; the fingers close at each
    time in ``close_at`` and open at each in ``open_at``; ``lift = (t0, t1, dz)`` raises the hand.
    Returns rows (t, q1, q2, v1, v2, e1, e2) at 250 Hz."""
    import pybullet as p

    ik = PandaIK()
    c = p.connect(p.DIRECT)
    try:
        p.setTimeStep(1e-3, physicsClientId=c)
        p.setGravity(0, 0, -9.81, physicsClientId=c)
        p.setPhysicsEngineParameter(numSolverIterations=100, physicsClientId=c)
        p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=c), physicsClientId=c)
        robot = p.loadURDF(PANDA.urdf_file, useFixedBase=True, flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=c)
        idx = BodyIndex(robot, c)
        joints = [idx.joint[n] for n in JOINTS]
        ball = np.array([0.5, 0.0, 0.133])
        q0 = ik(ball, READY)
        q1 = ik(ball + [0, 0, lift[2]], q0) if lift else q0
        for j, v in zip(joints, q0 + [0.04, 0.04]):
            p.resetJointState(robot, j, v, physicsClientId=c)
        if with_ball:
            stand = p.createMultiBody(0, p.createCollisionShape(p.GEOM_CYLINDER, radius=0.025, height=0.1,
                                                                physicsClientId=c),
                                      basePosition=[0.5, 0.0, 0.05], physicsClientId=c)
            b = p.createMultiBody(0.057, p.createCollisionShape(p.GEOM_SPHERE, radius=0.033, physicsClientId=c),
                                  basePosition=ball.tolist(), physicsClientId=c)
            for body in (stand, b):
                p.changeDynamics(body, -1, lateralFriction=0.8, physicsClientId=c)
        switches = sorted([(t, 0.0) for t in close_at] + [(t, 0.04) for t in open_at])
        rows = []
        target = 0.04
        for k in range(int(round(seconds * 1000)) + 1):
            t = k * 1e-3
            while switches and switches[0][0] <= t:
                target = switches.pop(0)[1]
            q = list(smooth(q0, q1, (t - lift[0]) / (lift[1] - lift[0]))) if lift else q0
            p.setJointMotorControlArray(robot, joints, p.POSITION_CONTROL, targetPositions=q + [target] * 2,
                                        forces=[87.0] * 4 + [12.0] * 3 + [force] * 2,
                                        positionGains=[0.1] * 7 + [0.05] * 2, velocityGains=[1.0] * 9,
                                        physicsClientId=c)
            p.stepSimulation(physicsClientId=c)
            if k % 4 == 0:
                s = p.getJointStates(robot, joints[7:], physicsClientId=c)
                rows.append((t, s[0][0], s[1][0], s[0][1], s[1][1], s[0][3], s[1][3]))
        return np.array(rows)
    finally:
        p.disconnect(physicsClientId=c)
        ik.close()


def noisy_recording(path, rows, actions, seed: int = 3):
    """Joint states from gripper rows with sensor noise (finger 3e-5 m, effort 0.4 N, velocity 2e-3 m/s)."""
    rng = np.random.default_rng(seed)
    with RecordingWriter(path) as w:
        pending = sorted(actions, key=lambda a: a[0])
        for t, q1, q2, v1, v2, e1, e2 in rows:
            while pending and pending[0][0] <= t + 1e-9:
                ta, op, phase, params = pending.pop(0)
                w.action(t, op, phase, **params)
            pos = list(READY[:7]) + [q1 + rng.normal(0, 3e-5), q2 + rng.normal(0, 3e-5)]
            vel = [0.0] * 7 + [v1 + rng.normal(0, 2e-3), v2 + rng.normal(0, 2e-3)]
            eff = list(rng.normal(0, 0.2, 7)) + [e1 + rng.normal(0, 0.4), e2 + rng.normal(0, 0.4)]
            w.joint_state(t, JOINTS, pos, vel, eff)
    return path


@pytest.fixture(scope="module")
def realistic(tmp_path_factory):
    """Closing on nothing then opening (0-2 s); closing on a ball (2.3 s), opening (3.5 s), closing
    again (4.3 s) and lifting it 15 cm (4.9-5.6 s) until the end (5.8 s)."""
    empty = gripper_run(False, 2.0, close_at=[0.3], open_at=[1.2])
    held = gripper_run(True, 3.8, close_at=[0.3, 2.3], open_at=[1.5], lift=(2.9, 3.6, 0.15))
    held[:, 0] += 2.0 + 4e-3
    rows = np.vstack([empty, held])
    actions = [(0.3, "move_hand", "start", CLOSE), (0.7, "move_hand", "end", CLOSE),
               (1.2, "move_hand", "start", OPEN), (1.6, "move_hand", "end", OPEN),
               (2.3, "move_hand", "start", CLOSE), (2.7, "move_hand", "end", CLOSE),
               (3.5, "move_hand", "start", OPEN), (3.9, "move_hand", "end", OPEN),
               (4.3, "move_hand", "start", CLOSE), (4.7, "move_hand", "end", CLOSE)]
    path = noisy_recording(tmp_path_factory.mktemp("gm") / "gripper.mcap", rows, actions)
    return path, rows


def test_gripper_data_matches_the_documented_figures(realistic):
    """The simulated gripper produces what the module docstring says: on the ball both efforts sit
    at -F with the fingers still and apart; closed on nothing the efforts vanish at 0 mm; the
    closing transient saturates only while the fingers run fast."""
    _, rows = realistic
    t, q1, q2, v1, v2, e1, e2 = rows.T
    held = (t > 2.7) & (t < 3.5)
    assert np.allclose(e1[held], -40.0, atol=0.5) and np.allclose(e2[held], -40.0, atol=0.5)
    assert 0.030 < q1[held].min() and q2[held].max() < 0.0345 and np.abs(v1[held] + v2[held]).max() < 0.01
    empty = (t > 0.7) & (t < 1.2)
    assert np.abs(np.r_[e1[empty], e2[empty]]).max() < 0.5 and max(q1[empty].max(), q2[empty].max()) < 5e-4
    transient = (t < 0.7) & (np.abs(e1) > 5.0)
    assert transient.any() and np.abs(v1[transient] + v2[transient]).min() > 0.05
    lifted = (t > 4.9) & (t < 5.8)
    assert np.allclose(e1[lifted], -40.0, atol=0.5) and np.allclose(e2[lifted], -40.0, atol=0.5)


def test_grasp_decisions_on_recorded_style_data(router, procs, tmp_path, realistic):
    """Closing on nothing never reads as a grasp (despite the closing transient); closing on the
    ball does within a few monitor steps, opening ends it, a second grasp survives the lift, and
    hand_free() answers over the protocol at the end."""
    path, _ = realistic
    s, events, grasped, free = run(router, procs, tmp_path, path, ask_hand_free=True)
    assert s["errors"] == [], s["errors"]
    seq = [(round(t, 3), name) for t, name, _ in events]
    print("\ngrasp monitor on pybullet gripper data:", seq)
    assert [n for _, n in seq] == ["grasp_started", "grasp_lost", "grasp_started"]
    (t_on, _), (t_off, _), (t_on2, _) = seq
    # the fingers reach the ball ~0.1 s after the command and settle; 2 samples at 15 Hz
    assert 2.35 < t_on < 2.75 and 3.5 < t_off < 3.75 and 4.35 < t_on2 < 4.75
    assert not any(v for t, v in grasped if t < 2.3)
    assert all(v for t, v in grasped if t > t_on2)
    assert events[0][2]["hand"] == "hand" and all(f > 30.0 for f in events[0][2]["forces"])
    assert free is False


# --------------------------------------------------------------------------- hysteresis
STEP = 1.0 / 15.0  # the monitor's default rate


def crafted_recording(path, seq, seed: int = 5):
    """``seq``: per monitor step (force N, finger position m, finger velocity m/s); telemetry at
    120 Hz, each sample carrying the value of the monitor step nearest to it, with noise."""
    rng = np.random.default_rng(seed)
    with RecordingWriter(path) as w:
        n = len(seq) * 8
        for i in range(n):
            t = i / 120.0
            f, q, v = seq[min(len(seq) - 1, int(math.floor(t / STEP + 0.5)))]
            pos = list(READY[:7]) + [q + rng.normal(0, 3e-5), q + rng.normal(0, 3e-5)]
            vel = [0.0] * 7 + [v, v]
            eff = [0.0] * 7 + [-f + rng.normal(0, 0.3), -f + rng.normal(0, 0.3)]
            w.joint_state(t, JOINTS, pos, vel, eff)
    return path


def hysteresis_sequence():
    held, open_, closed = 0.032, 0.04, 0.0005
    seq = [(0.0, open_, 0.0)] * 3            # 0-2   open hand
    seq += [(8.0, held, 0.0)]                # 3     one pressing sample: a spike, no grasp
    seq += [(0.0, held, 0.0)] * 2            # 4-5
    seq += [(8.0, held, 0.0)] * 3            # 6-8   grasp confirmed at the 2nd pressing sample (7)
    seq += [(4.0, held, 0.0)] * 5            # 9-13  between the thresholds: keeps the grasp
    seq += [(1.0, held, 0.0)]                # 14    one released sample: keeps it
    seq += [(4.0, held, 0.0)] * 2            # 15-16
    seq += [(1.0, held, 0.0)] * 3            # 17-19 lost at the 2nd released sample (18)
    seq += [(8.0, held, -0.1)] * 3           # 20-22 pressing hard but the fingers run: no grasp
    seq += [(8.0, closed, 0.0)] * 3          # 23-25 pressing, but fully closed: no grasp
    seq += [(0.0, open_, 0.0)] * 3           # 26-28
    return seq


def test_hysteresis_over_the_protocol(router, procs, tmp_path):
    """Single spikes and single dropouts do not toggle the decision; forces between the on and off
    thresholds keep it; fast or fully closed fingers never read as a grasp."""
    path = crafted_recording(tmp_path / "crafted.mcap", hysteresis_sequence())
    s, events, grasped, _ = run(router, procs, tmp_path, path)
    assert s["errors"] == [], s["errors"]
    steps = [(int(round(t / STEP)), name) for t, name, _ in events]
    assert steps == [(7, "grasp_started"), (18, "grasp_lost")], steps
    on = [int(round(t / STEP)) for t, v in grasped if v]
    assert on == list(range(7, 18))


# ---------------------------------------------------------------------------- in-process
def make_monitor(**params) -> GraspMonitor:
    m = GraspMonitor()
    prm = {k: p.default for k, p in GraspMonitor.params.items()}
    prm.update(params)
    m.init(prm, {"entities": {}})
    return m


def feed(m: GraspMonitor, k: int, q: float, effort: float, actions=(), with_efforts=True):
    m._outputs, m._events = {}, []
    js = {"stamp": k * STEP, "name": list(JOINTS), "position": list(READY[:7]) + [q, q],
          "velocity": [], "effort": ([0.0] * 7 + [effort, effort]) if with_efforts else [0.0] * 9}
    m.step(k, k * STEP, STEP, {"joints": js, "actions": list(actions)}, {})
    return m._outputs["grasped"], [e["name"] for e in m._events]


def test_effortless_stream_decides_from_commands_and_positions():
    """With no efforts in the stream, a close command whose fingers stop apart is a grasp (once the width has held
    for ``steady_window``); fingers running to the end stop are not, nor fingers closing slowly on nothing (20 mm/s
    a finger, under ``max_speed`` sample by sample: that was a grasp until they met); an open command ends it
    (velocities from finite differences)."""
    m = make_monitor()
    cmd_close = {"operation": "move_hand", "phase": "start", "params": CLOSE}
    cmd_open = {"operation": "move_hand", "phase": "start", "params": OPEN}
    widths = [0.04, 0.04, 0.036, 0.033, 0.032, 0.032, 0.032, 0.032, 0.032, 0.036, 0.04, 0.04]
    got = []
    for k, q in enumerate(widths):
        acts = [cmd_close] if k == 1 else [cmd_open] if k == 8 else []
        got.append(feed(m, k, q, 0.0, acts, with_efforts=False))
    assert m.efforts_seen is False
    assert [g for g, _ in got] == [False] * 6 + [True] * 3 + [False] * 3
    assert got[6][1] == ["grasp_started"] and got[9][1] == ["grasp_lost"]
    m = make_monitor()
    for k, q in enumerate([0.04, 0.03, 0.015, 0.002, 0.0, 0.0, 0.0, 0.0]):  # closing on nothing
        g, ev = feed(m, k, q, 0.0, [cmd_close] if k == 0 else [], with_efforts=False)
        assert g is False and ev == []
    m = make_monitor()
    for k in range(40):  # closing slowly on nothing: 20 mm/s a finger, 40 mm/s of width (max_speed: 50)
        g, ev = feed(m, k, max(0.0, 0.04 - 0.02 * k * STEP), 0.0, [cmd_close] if k == 0 else [], with_efforts=False)
        assert g is False and ev == [], k


def test_parameters_are_checked_and_hands_are_separate():
    """Thresholds must leave a hysteresis band; hand_free names its hand; two hands decide apart."""
    with pytest.raises(ValueError):
        make_monitor(effort_on=2.0, effort_off=3.0)
    with pytest.raises(ValueError):
        make_monitor(hands={"left": ["a"]})
    m = make_monitor(hands={"left": ["l1", "l2"], "right": ["r1", "r2"]}, effort_sign=0.0)
    for k in range(3):
        m._outputs, m._events = {}, []
        m.step(k, k * STEP, STEP, {"joints": {"stamp": k * STEP, "name": ["l1", "l2", "r1", "r2"],
                                              "position": [0.02, 0.02, 0.02, 0.02], "velocity": [],
                                              "effort": [12.0, 12.0, 0.1, 0.1]}, "actions": []}, {})
    assert m.hand_free("left") is False and m.hand_free("right") is True
    assert m._outputs["grasped_by_hand"] == {"left": True, "right": False}
    assert m._outputs["grasped"] is True  # no hand named "hand": the first one
    with pytest.raises(KeyError):
        m.hand_free("hand")
