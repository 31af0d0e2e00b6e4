"""The physics main model over the real protocol: a real router, the physics agent (and small owner
models) as subprocesses, a Conductor replaying rosbag2 MCAP recordings written here.

    recording ──joint states, actions──▶ conductor ──step(inputs: others' poses/collisions)──▶ physics
    mover / thrower / ghost ──state──▶ conductor ──triggers on `release`──▶ handover to physics

Scenes: tests/scenes/physics_handover.yaml, physics_collision.yaml, physics_grasp.yaml. Scripted
Panda motions are computed with pybullet IK in a DIRECT client of the test's own.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agents.robot.index import BodyIndex
from conductor.core import Conductor, RunOptions
from conductor.runlog import read_run_log
from conductor.scene import load_scene
from conductor.sources.recording import load_recording
from conductor.sources.replay import ReplaySource
from protocol.keys import Keys
from protocol.robot import resolve_robot
from recordings.rosbag import RecordingWriter

from .conftest import spawn_agents

PANDA = resolve_robot({"use": "panda"})
JOINTS, READY, TIP_LINK = PANDA.joints, PANDA.ready, PANDA.gripper.tip

HERE = Path(__file__).parent
HAND_DOWN = [1.0, 0.0, 0.0, 0.0]  # panda_hand's z axis pointing at the table, fingers closing along world y


# ------------------------------------------------------------------------------------ helpers
def write_recording(path, seconds: float, rate: float, joints, actions=(), effort=None):
    """Joint states at ``rate``: ``joints(t) -> 9 positions`` (velocities by central differences),
    finger efforts ``effort(t)`` (N, squeezing negative); ``actions``: (t, operation, phase, params)."""
    n = int(round(seconds * rate)) + 1
    h = 1.0 / rate
    qs = [np.asarray(joints(i * h), float) for i in range(n)]
    with RecordingWriter(path) as w:
        pending = sorted(actions, key=lambda a: a[0])
        for i in range(n):
            t = i * h
            vel = (qs[min(i + 1, n - 1)] - qs[max(i - 1, 0)]) / (2 * h)
            e = effort(t) if effort else 0.0
            w.joint_state(t, JOINTS, qs[i], vel, [0.0] * 7 + [e, e])
            while pending and pending[0][0] <= t + 0.5 * h:
                ta, op, phase, params = pending.pop(0)
                w.action(t, op, phase, **params)
    return path


def still_recording(path, seconds: float, actions=()):
    """The Panda standing still in its ready posture, with annotations."""
    return write_recording(path, seconds, 100.0, lambda t: READY, actions)


def run(router, procs, tmp_path, scene_file: str, rec_path, physics_args: dict | None = None):
    """Run a scene over a recording; returns (summary, states, events, outs).

    states: entity -> [(t, pose)] as physics published them; events: [(t, model, name, data)];
    outs: [(t, model, name, value)]."""
    session, endpoint = router
    scene = load_scene(HERE / "scenes" / scene_file)
    if physics_args:
        scene.models["physics"].args.update(physics_args)
    spawn_agents(procs, scene, endpoint)
    c = Conductor(scene, session, Keys("default"), ReplaySource(load_recording(rec_path)),
                  RunOptions(run_log=str(tmp_path / "run.mcap"), register_timeout=60))
    try:
        summary = c.run()
    finally:
        c.close()
    states: dict[str, list] = {}
    events, outs = [], []
    for key, _, msg in read_run_log(summary["run_log"]):
        if not isinstance(msg, dict):
            continue
        if key.endswith("/state/physics"):
            for ent, attrs in msg["values"].items():
                if "pose" in attrs:
                    states.setdefault(ent, []).append((msg["t"], np.asarray(attrs["pose"], float)))
        elif "/event/" in key and msg.get("model") is not None:
            events.append((msg["t"], msg["model"], msg["name"], msg["data"]))
        elif "/out/" in key and msg.get("model") is not None:
            outs.append((msg["t"], msg["model"], msg["name"], msg["value"]))
    for rows in states.values():
        rows.sort(key=lambda r: r[0])
    return summary, states, sorted(events, key=lambda e: e[0]), sorted(outs, key=lambda o: o[0])


def track(states, entity, t0=-1.0, t1=1e9):
    """(times, positions) of an entity's published poses with t0 <= t <= t1."""
    rows = [(t, p[:3]) for t, p in states.get(entity, []) if t0 <= t <= t1]
    return np.array([r[0] for r in rows]), np.array([r[1] for r in rows])


class PandaIK:
    """Joint targets for a hand-down fingertip position (pybullet IK in a DIRECT client of its own)."""

    def __init__(self):
        import pybullet as p

        self.p = p
        self.c = p.connect(p.DIRECT)
        self.robot = p.loadURDF(PANDA.urdf_file, useFixedBase=True, physicsClientId=self.c)
        self.idx = BodyIndex(self.robot, self.c)
        self.j = [self.idx.joint[n] for n in JOINTS]
        self.lo = [self.idx.lower[n] for n in JOINTS]
        self.hi = [self.idx.upper[n] for n in JOINTS]
        self.tip_link = self.idx.link[TIP_LINK]

    def _set(self, q):
        for j, v in zip(self.j, q):
            self.p.resetJointState(self.robot, j, float(v), physicsClientId=self.c)

    def tip(self, q) -> np.ndarray:
        self._set(q)
        return np.array(self.p.getLinkState(self.robot, self.tip_link, computeForwardKinematics=1,
                                            physicsClientId=self.c)[4])

    def __call__(self, tip, seed) -> list[float]:
        self._set(list(seed[:7]) + [0.04, 0.04])
        for _ in range(4):
            q = self.p.calculateInverseKinematics(
                self.robot, self.tip_link, [float(v) for v in tip], HAND_DOWN, lowerLimits=self.lo,
                upperLimits=self.hi, jointRanges=[b - a for a, b in zip(self.lo, self.hi)], restPoses=list(READY),
                maxNumIterations=100, residualThreshold=1e-6, physicsClientId=self.c)
            self._set(list(q[:7]) + [0.04, 0.04])
        return list(q[:7])

    def close(self):
        self.p.disconnect(physicsClientId=self.c)


def smooth(a, b, s: float) -> np.ndarray:
    s = min(1.0, max(0.0, s))
    return np.asarray(a, float) + (3 * s * s - 2 * s * s * s) * (np.asarray(b, float) - np.asarray(a, float))


# --------------------------------------------------------------------------- handover
def test_physics_follows_owners_and_continues_handed_over_motion(router, procs, tmp_path):
    """Bodies owned elsewhere are carried along and still collide (the pusher shoves the puck);
    on acquire a ball carried sideways at 1 m/s keeps that velocity (estimated from the poses
    physics saw) and falls, and a dart flies on with the velocity in the handover's extra."""
    rec = still_recording(tmp_path / "still.mcap", 1.6, [(0.8, "release", "start", {"hand": "hand"})])
    s, states, events, _ = run(router, procs, tmp_path, "physics_handover.yaml", rec)
    assert s["errors"] == [] and s["invariant_violations"] == 0 and s["unauthorized_writes"] == 0, s["errors"]
    hs = {(h["entity"], h["from"], h["to"]): h["t"] for h in s["handovers"]}
    assert set(hs) == {("ball", "mover", "physics"), ("dart", "thrower", "physics")}
    th = hs[("ball", "mover", "physics")]
    assert 0.79 <= th <= 0.82

    # the puck (physics) is pushed by the pusher (mover) only once it arrives: contact at x = 0.56
    # (pusher centre at 0.4 + 0.4 (t - 0.2) / 0.8): t ~ 0.52 s
    t, puck = track(states, "puck")
    before = puck[t < 0.45]
    assert np.allclose(before[:, :2], [0.62, -0.45], atol=1e-3)
    assert puck[-1, 0] > 0.80, puck[-1]          # shoved along x ahead of the pusher (which stops at 0.8)
    assert abs(puck[-1, 1] + 0.45) < 0.03
    hits = [e for e in events if e[2] == "contact_begin" and {e[3]["a"], e[3]["b"]} == {"puck", "pusher"}]
    assert hits and 0.45 < hits[0][0] < 0.6, hits

    # the ball: published by physics only from the handover on
    t, ball = track(states, "ball")
    assert t.size and t[0] >= th - 1e-9
    fly = t <= th + 0.25                          # before it lands (0.40 m: 0.27 s of free fall)
    tt = t[fly] - th
    vy = np.polyfit(tt, ball[fly, 1], 1)[0]
    az = 2 * np.polyfit(tt, ball[fly, 2], 2)[0]
    print(f"\nball after handover: vy {vy:.3f} m/s (mover: 1.0), az {az:.2f} m/s^2; "
          f"dart: {states['dart'][-1][1][:3].round(3)}")
    assert abs(vy - 1.0) < 0.1, vy
    assert abs(az + 9.81) < 0.5, az
    assert abs(ball[fly, 0] - 0.6).max() < 5e-3   # no velocity along x was handed over
    # it hits the table after the free fall of 0.40 - 0.033 m (0.27 s), y ~ 0.0 + 0.27 m, and bounces
    landing = [e[0] for e in events if e[2] == "contact_begin" and {e[3]["a"], e[3]["b"]} == {"ball", "table"}]
    assert landing and abs(landing[0] - th - math.sqrt(2 * 0.367 / 9.81)) < 0.03, (landing, th)
    assert ball[t >= landing[0]][0, 1] == pytest.approx(ball[0, 1] + (landing[0] - th), abs=0.03)

    # the dart: handed over with {"velocity": [0, 0.5, 0.6, 0, 0, 0]}: it keeps rising for ~0.06 s
    t, dart = track(states, "dart")
    fly = t <= th + 0.2
    tt = t[fly] - th
    vy, vz0 = np.polyfit(tt, dart[fly, 1], 1)[0], np.polyfit(tt, dart[fly, 2], 2)[1]
    assert abs(vy - 0.5) < 0.05 and abs(vz0 - 0.6) < 0.08, (vy, vz0)
    assert dart[fly, 2].max() > dart[0, 2] + 0.01   # it rose after the handover


# -------------------------------------------------------------------------- collision
def test_collision_ownership_switches_contacts_off_and_on(router, procs, tmp_path):
    """While `ghost` owns a ball's collision physics ignores its contacts with the partners the value
    names (default: every other entity); handed back, contacts return: ball_a falls through its
    shelf, ball_b (collision back at 0.1 s) lands on its shelf, ball_c ignores only the table."""
    rec = still_recording(tmp_path / "still.mcap", 1.2, [(0.1, "release", "start", {"hand": "hand"})])
    s, states, events, _ = run(router, procs, tmp_path, "physics_collision.yaml", rec)
    assert s["errors"] == [] and s["invariant_violations"] == 0, s["errors"]
    assert [(h["entity"], h["attribute"], h["from"], h["to"]) for h in s["handovers"]] == \
        [("ball_b", "collision", "ghost", "physics")]
    final = {e: states[e][-1][1] for e in ("ball_a", "ball_b", "ball_c")}
    assert final["ball_a"][2] == pytest.approx(0.033, abs=3e-3)   # through the shelf, onto the table
    assert final["ball_b"][2] == pytest.approx(0.233, abs=3e-3)   # on the shelf (top at 0.2)
    assert final["ball_c"][2] < -1.0                              # through the table
    np.testing.assert_allclose(final["ball_a"][:2], [0.6, 0.35], atol=2e-3)
    touched = {frozenset((e[3]["a"], e[3]["b"])) for e in events if e[2] == "contact_begin"}
    assert frozenset(("ball_b", "shelf_b")) in touched
    assert frozenset(("ball_a", "shelf_a")) not in touched and frozenset(("ball_a", "table")) in touched
    assert not any("ball_c" in pair for pair in touched)


# ------------------------------------------------------------------------------ grasping
BALL = np.array([0.45, -0.2, 0.133])
BALL2 = np.array([0.45, 0.2, 0.133])
SQUEEZE = 0.031  # recorded finger position while holding the tennis ball (r = 33 mm, pads squeezed)


def grasp_recording(path):
    """Pick `ball` from its stand, lift it, carry it 15 cm along x, open; then close with the
    fingertip centre 5 cm beside `ball2` (the fingers close on nothing), lift, carry, open."""
    ik = PandaIK()
    above = BALL + [0, 0, 0.2]
    aside = BALL + [0.15, 0, 0.2]
    off = BALL2 + [0.05, 0, 0.0]
    path_keys = [(0.0, above), (0.3, above), (1.3, BALL), (1.9, BALL), (2.7, above), (3.3, aside), (3.8, aside),
                 (4.8, off + [0, 0, 0.2]), (5.6, off), (6.1, off), (6.8, off + [0, 0, 0.2]), (7.4, off + [0.15, 0,
                                                                                                          0.2]),
                 (8.6, off + [0.15, 0, 0.2])]

    def tip(t):
        for (t0, a), (t1, b) in zip(path_keys, path_keys[1:]):
            if t <= t1:
                return smooth(a, b, (t - t0) / (t1 - t0))
        return path_keys[-1][1]

    def fingers(t):
        if t < 1.4:
            return 0.04
        if t < 3.4:
            return float(smooth([0.04], [SQUEEZE], (t - 1.4) / 0.3)[0])
        if t < 5.7:
            return float(smooth([SQUEEZE], [0.04], (t - 3.4) / 0.3)[0])
        if t < 7.5:
            return float(smooth([0.04], [0.0], (t - 5.7) / 0.3)[0])
        return float(smooth([0.0], [0.04], (t - 7.5) / 0.3)[0])

    seed = list(READY)
    cache = {}

    def joints(t):
        nonlocal seed
        key = round(t, 6)
        if key not in cache:
            q = ik(tip(t), seed)
            seed = q
            f = fingers(t)
            cache[key] = q + [f, f]
        return cache[key]

    def effort(t):
        return -30.0 if 1.65 < t < 3.45 else 0.0

    close = {"hand": "hand", "command": "close"}
    opened = {"hand": "hand", "command": "open"}
    actions = [(1.4, "move_hand", "start", close), (1.75, "move_hand", "end", close),
               (3.4, "release", "start", {"hand": "hand"}), (3.7, "release", "end", {"hand": "hand"}),
               (5.7, "move_hand", "start", close), (6.05, "move_hand", "end", close),
               (7.5, "move_hand", "start", opened), (7.8, "move_hand", "end", opened)]
    try:
        write_recording(path, 8.6, 100.0, joints, actions, effort)
        # the script really reaches its targets: fingertip centre at the ball when closing
        assert np.linalg.norm(ik.tip(joints(1.6)) - BALL) < 2e-3
        assert np.linalg.norm(ik.tip(joints(5.9)) - off) < 2e-3
    finally:
        ik.close()
    return path


@pytest.fixture(scope="module")
def grasp_rec(tmp_path_factory):
    return grasp_recording(tmp_path_factory.mktemp("grasp") / "grasp.mcap")


def hand_distance(states, outs, entity, t0, t1):
    """Distance (m) between an entity and panda_hand over [t0, t1], from the published poses."""
    links = {round(t, 6): v["panda_hand"] for t, m, n, v in outs if m == "physics" and n == "links"}
    d = [np.linalg.norm(p[:3] - np.asarray(links[round(t, 6)][:3])) for t, p in states[entity]
         if t0 <= t <= t1 and round(t, 6) in links]
    return np.array(d)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["none", "signal", "force"])
def test_grasp_baselines_on_a_scripted_pick(router, procs, tmp_path, grasp_rec, mode):
    """The three grasp baselines on the same pick-and-drop recording.

    The fingers track the recorded positions with 70 N each and the ball's friction is 0.8, so even
    `none` holds the 57 g ball by friction alone (2 x 0.8 x ~45 N measured squeeze >> 0.56 N): in
    every mode `ball` is lifted, carried and dropped on opening. They differ where physics matters:
    `signal` binds at the close annotation whatever the fingers touch, so it also lifts `ball2`,
    which the fingers missed by 5 cm; `force` binds only when both fingers press (before the
    annotation ends) and, like `none`, leaves `ball2` on its stand."""
    s, states, events, outs = run(router, procs, tmp_path, "physics_grasp.yaml", grasp_rec, {"grasp_binding": mode})
    assert s["errors"] == [] and s["handovers"] == [], s["errors"]
    bind = [(round(t, 3), n, d["entity"]) for t, m, n, d in events if n in ("grasp_bound", "grasp_unbound")]

    t, ball = track(states, "ball")
    lifted = ball[(t > 2.8) & (t < 3.4)]
    assert lifted[:, 2].min() > 0.30, lifted[:, 2].min()              # carried 20 cm up
    assert abs(lifted[-1, 0] - 0.6) < 0.01                             # and 15 cm along x
    assert ball[-1, 2] == pytest.approx(0.033, abs=3e-3)               # dropped onto the table
    assert ball[-1, 0] > 0.52                                          # not back onto its stand
    d = hand_distance(states, outs, "ball", 2.0, 3.35)
    print(f"\n{mode}: ball-hand distance while carried {d.min() * 1e3:.1f}..{d.max() * 1e3:.1f} mm; binding {bind}")
    assert d.max() - d.min() < 5e-3                                    # held firmly

    t2, ball2 = track(states, "ball2")
    if mode == "signal":
        assert [b[1:] for b in bind] == [("grasp_bound", "ball"), ("grasp_unbound", "ball"),
                                         ("grasp_bound", "ball2"), ("grasp_unbound", "ball2")]
        assert [b[0] for b in bind] == pytest.approx([1.75, 3.4, 6.05, 7.5], abs=0.02)
        assert ball2[(t2 > 6.8) & (t2 < 7.5), 2].min() > 0.3            # lifted without a touch
        assert ball2[-1, 2] == pytest.approx(0.033, abs=3e-3)           # dropped off its stand
    else:
        np.testing.assert_allclose(ball2[-1], [0.45, 0.2, 0.133], atol=3e-3)  # never touched
        if mode == "force":
            assert [b[1:] for b in bind] == [("grasp_bound", "ball"), ("grasp_unbound", "ball")]
            assert 1.5 < bind[0][0] < 1.75          # both fingers press before the close annotation ends
            assert 3.4 < bind[1][0] < 3.7           # let go while the fingers open
        else:
            assert bind == []


# ---------------------------------------------------------------------------- in-process
def make_physics(entities: dict, owned=None, **params):
    from agents.models.physics import Physics

    m = Physics()
    m.owned = set(owned) if owned is not None else {(n, "pose") for n in entities}
    m.init({k: p.default for k, p in Physics.params.items()} | params, {"entities": entities, "robot": {}})
    return m


def step(m, k: int, dt: float, inputs=None):
    m._outputs, m._events = {}, []
    m.tick, m.t = k, k * dt
    m.step(k, k * dt, dt, {"joints": None, "actions": []}, inputs or {})
    return m._outputs, m._events


def test_world_masses_and_evaluators():
    """Bodies get the documented masses (a tennis ball by default, solid boxes at 500 kg/m³,
    static stands and containers); closest/distance answer from the current world; bad
    parameters are refused."""
    ents = {"ball": {"shape": {"type": "sphere", "radius": 0.033}, "pose": [0.45, 0.1, 0.45], "tags": ["graspable"]},
            "big": {"shape": {"type": "sphere", "radius": 0.066}, "pose": [0.5, -0.3, 0.5], "tags": ["graspable"]},
            "brick": {"shape": {"type": "box", "size": [0.1, 0.1, 0.1]}, "pose": [0.7, 0.0, 0.05]},
            "stand": {"shape": {"type": "cylinder", "radius": 0.02, "length": 0.1}, "pose": [0.3, 0.3, 0.05],
                      "tags": ["static"]},
            "bin": {"shape": {"type": "container", "style": "bin"}, "pose": [0.6, 0.5, 0.0]}}
    m = make_physics(ents)
    try:
        mass = {n: m.p.getDynamicsInfo(b.id, -1, physicsClientId=m.cid)[0] for n, b in m.bodies.items()}
        assert mass["ball"] == pytest.approx(0.057) and mass["big"] == pytest.approx(4 * 0.057)
        assert mass["brick"] == pytest.approx(0.5) and mass["stand"] == 0.0 and mass["bin"] == 0.0
        near = m.closest("graspable", "panda_hand")
        hand = m._where("panda_hand")
        assert near["entity"] == "ball" and near["distance"] == pytest.approx(math.dist(hand[:3], [0.45, 0.1, 0.45]),
                                                                              abs=1e-6)
        assert m.closest("nothing") == {"entity": None, "distance": None}
        assert m.distance("ball", "stand") == pytest.approx(math.dist([0.45, 0.1, 0.45], [0.3, 0.3, 0.05]), abs=1e-6)
        for k in range(120):  # one second: the ball falls onto the table, the brick stays
            out, _ = step(m, k, 1 / 120)
        assert m.read("ball", "pose")[2] == pytest.approx(0.033, abs=2e-3)
        assert "table" in m.touching("ball") and m.touching("stand") == []
        assert set(out["links"]) == {"panda_hand", "panda_leftfinger", "panda_rightfinger"}
    finally:
        m.close()
    with pytest.raises(ValueError):
        make_physics({}, grasp_binding="glue")
    with pytest.raises(ValueError):
        make_physics({}, links=["panda_nose"])


def test_the_links_output_may_name_the_robot_base_link():
    """``links`` names the base link beside a moving one: its frame is the URDF's (not pybullet's centre of
    mass), as ``_where`` gives it. pybullet's batched link query ended the process on the base link (-1)."""
    m = make_physics({}, links=["panda_link0", "panda_hand"])
    try:
        out, _ = step(m, 0, 1 / 120)
        assert set(out["links"]) == {"panda_link0", "panda_hand"}
        assert out["links"]["panda_link0"] == pytest.approx(m._where("panda_link0"), abs=1e-9)
        assert out["links"]["panda_link0"][:3] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
        assert out["links"]["panda_hand"] == pytest.approx(m._where("panda_hand"), abs=1e-9)
    finally:
        m.close()


def test_every_pybullet_robot_gives_the_base_links_urdf_frame_not_its_centre_of_mass():
    """panda_link0's inertial origin is 5 cm above its frame: the robot's kinematics, the engine's robot and the
    physics model all say the frame is where the robot block puts the base."""
    import pybullet as p

    from agents.engines.pybullet_robot import BulletRobot
    from agents.robot.kinematics import RobotKinematics
    from protocol.robot import resolve_robot

    robot = resolve_robot({"use": "panda", "base": [0.2, 0.0, 0.1]})
    kin = RobotKinematics(robot)
    cid = p.connect(p.DIRECT)
    try:
        assert kin.link_pose(None, "panda_link0")[:3] == pytest.approx([0.2, 0.0, 0.1], abs=1e-6)
        arm = BulletRobot(p, cid, robot, time_step=1 / 240, finger_force=0.0, gains=(0.1, 0.1, 1.0), initial=[])
        assert arm.link_pose(-1)[:3] == pytest.approx([0.2, 0.0, 0.1], abs=1e-6)
    finally:
        p.disconnect(cid)
        kin.close()


def test_a_new_joint_state_under_the_stamp_already_seen_is_still_driven():
    """An arm's joint state, then the merged state after its gripper's message with the same header stamp: the
    fingers close (the second was taken for the first, its stamp being the same, and the close was lost)."""
    import pybullet as p

    from agents.engines.pybullet_robot import BulletRobot
    from protocol.robot import resolve_robot

    robot = resolve_robot({"use": "panda"})
    cid = p.connect(p.DIRECT)
    try:
        arm = BulletRobot(p, cid, robot, time_step=1 / 240, finger_force=20.0, gains=(0.1, 0.1, 1.0),
                          initial=list(robot.ready))
        names = [*robot.arm, *robot.gripper.joints]
        opened = {"stamp": 1.0, "name": names, "position": [*robot.ready[:7], 0.04, 0.04]}
        closed = {**opened, "position": [*robot.ready[:7], 0.0, 0.0]}
        for js in (opened, closed):
            arm.drive(js)
            for _ in range(240):
                p.stepSimulation(physicsClientId=cid)
        fingers = [p.getJointState(arm.body, arm.index.joint[n], physicsClientId=cid)[0] for n in robot.gripper.joints]
        assert max(fingers) < 0.005, fingers
        arm.drive(dict(closed))  # the same state again (decoded anew each tick): nothing new to drive
        assert arm._last_key == (1.0, tuple(names), tuple(closed["position"]))
    finally:
        p.disconnect(cid)


def test_acquire_estimates_velocity_from_the_owners_poses():
    """Without a velocity in the handover, physics continues with the velocity of the poses the
    owner sent (a 60 Hz owner seen by a 120 Hz physics), and with zero once the owner stopped."""
    ball = {"shape": {"type": "sphere", "radius": 0.03}, "pose": [0.5, 0.0, 0.5]}
    for still in (0.0, 0.5):
        m = make_physics({"ball": ball}, owned=set())
        dt = 1 / 120
        try:
            k = 0
            x = 0.5
            for k in range(int((0.4 + still) / dt)):
                t = k * dt
                if k % 2 == 0 and t <= 0.4:       # the owner steps at 60 Hz: 0.8 m/s along x
                    x = 0.5 + 0.8 * t
                step(m, k, dt, {"ball": {"pose": [x, 0.0, 0.5, 0, 0, 0, 1]}})
            m.acquire("ball", "pose", [x, 0.0, 0.5, 0, 0, 0, 1], {})
            m.owned.add(("ball", "pose"))
            v = m.bodies["ball"].velocity
            if still:
                assert v == [0.0] * 6
            else:
                np.testing.assert_allclose(v[:3], [0.8, 0.0, 0.0], atol=1e-6)
            step(m, k + 1, dt)
            assert m.read("ball", "pose")[0] > x if not still else abs(m.read("ball", "pose")[0] - x) < 1e-9
        finally:
            m.close()


@pytest.mark.parametrize("engine", ["physics", "mujoco"])
def test_a_body_carried_by_a_slower_owner_moves_at_its_owners_speed(engine):
    """in_hand sends the ball's pose at 60 Hz, physics steps at 120 Hz: the carried body's velocity (what its
    contacts and the velocity() evaluator see) was taken over this model's step, 0 and twice the speed on
    alternate steps. It is now the owner's motion over the owner's own times: 0.5 m/s every step. The same in the
    MuJoCo model (both use agents.engines.bodies.owner_velocity)."""
    ball = {"shape": {"type": "sphere", "radius": 0.033}, "pose": [0.45, 0, 0.5, 0, 0, 0, 1], "mass": 0.057}
    if engine == "physics":
        m = make_physics({"ball": ball}, owned=set(), time_step=1 / 240)
    else:
        pytest.importorskip("mujoco")
        from agents.models.mujoco import MuJoCo

        m = MuJoCo()
        m.owned = set()
        m.init({k: p.default for k, p in MuJoCo.params.items()} | {"robot": False},
               {"entities": {"ball": ball}, "robot": {}})
    try:
        speeds = []
        for k in range(1, 12):
            t_owner = k // 2 * 2 / 120  # the owner's value changes every other tick
            step(m, k, 1 / 120, {"ball": {"pose": [0.45 + 0.5 * t_owner, 0, 0.5, 0, 0, 0, 1]}})
            speeds.append(m.bodies["ball"].velocity[0])
        assert speeds[3:] == pytest.approx([0.5] * 8, abs=1e-6), speeds
    finally:
        m.close()


def test_one_world_particles_and_virtual_entities():
    """particles: fills a container of this world (they settle, none spilled, outputs every step); an
    entity tagged virtual gets no body and keeps the value handed to it; a tipped cup spills."""
    cup = {"shape": {"type": "container", "style": "cup"}, "pose": [0.4, 0.0, 0.0], "tags": ["static"]}
    water = {"shape": {"type": "sphere", "radius": 0.008}, "pose": [0.4, 0.0, 0.0], "tags": ["virtual"]}
    m = make_physics({"cup": cup, "water": water}, owned={("cup", "pose")},
                     particles={"container": "cup", "count": 30, "radius": 0.008})
    try:
        assert "water" not in m.bodies and len(m.particles) == 30
        for k in range(60):
            out, _ = step(m, k, 1 / 120, {"water": {"pose": np.zeros((5, 3))}})
        assert out["particles"].shape == (30, 3) and out["spilled"] == 0
        assert np.all(out["particles"][:, 2] < 0.1)   # resting inside the cup, below its rim
        m.acquire("water", "pose", [[1.0, 2.0, 3.0]], {"velocity": [[0.1, 0.0, 0.0]]})
        assert m.read("water", "pose") == [[1.0, 2.0, 3.0]]
        # what came with it goes back with it (a fluid's particle velocities through a fallback round trip)
        assert m.release("water", "pose") == ([[1.0, 2.0, 3.0]], {"velocity": [[0.1, 0.0, 0.0]]})
    finally:
        m.close()
    tipped = dict(cup, pose=[0.4, 0.0, 0.15, 0.7071068, 0, 0, 0.7071068])  # on its side, in the air
    m = make_physics({"cup": tipped}, owned={("cup", "pose")}, particles={"container": "cup", "count": 30})
    try:
        for k in range(120):
            out, _ = step(m, k, 1 / 120)
        assert out["spilled"] > 15
    finally:
        m.close()
    with pytest.raises(ValueError):
        make_physics({"cup": cup}, particles={"container": "nothing", "count": 5})


def test_the_mujoco_model_keeps_its_hand_set_state_when_a_collision_change_recompiles_it():
    """A collision value another model sends recompiles the MuJoCo world, which reset what the model had set in the
    compiled model by hand: the fingers' force limits measured from the efforts (set again only when new telemetry
    came: until then a squeezing hand held with the default force) and the frames of fixed bodies it placed (a
    static stand handed to it at a new place went back to where the scene put it; one another model owns is put
    again every substep)."""
    pytest.importorskip("mujoco")
    from agents.models.mujoco import MuJoCo
    from protocol.robot import resolve_robot

    robot = resolve_robot(None)
    m = MuJoCo()
    m.owned = {("ball", "pose")}
    ents = {"ball": {"shape": {"type": "sphere", "radius": 0.03}, "pose": [0.6, 0.3, 0.2, 0, 0, 0, 1]},
            "stand": {"shape": {"type": "box", "size": [0.05, 0.05, 0.1]}, "pose": [0.6, -0.3, 0.05, 0, 0, 0, 1],
                      "tags": ["static"]}}
    m.init({k: p.default for k, p in MuJoCo.params.items()}, {"entities": ents, "robot": robot.as_dict()})
    names = [*robot.arm, *robot.gripper.joints]
    js = {"name": names, "position": list(robot.ready[:7]) + [0.02, 0.02], "velocity": [0.0] * 9,
          "effort": [0.0] * 7 + [-30.0, -30.0], "stamp": 1.0}  # squeezing with 30 N
    moved = [0.7, -0.2, 0.05, 0, 0, 0, 1]
    try:
        m.t = 1 / 120
        m.acquire("stand", "pose", moved, {})  # (handed over where another model had put it)
        m.owned.add(("stand", "pose"))
        m.step(1, m.t, 1 / 120, {"joints": js, "actions": []}, {})
        fingers = m.world.finger_act
        assert m.world.model.actuator_forcerange[fingers].tolist() == [[-30.0, 30.0]] * 2
        np.testing.assert_allclose(m.world.model.body_pos[m.bodies["stand"].id], moved[:3])
        m.t = 2 / 120  # the same joint state (no new telemetry), and physics says the ball stops colliding
        m.step(2, m.t, 1 / 120, {"joints": js, "actions": []}, {"ball": {"collision": False}})
        assert m.excluded["ball"], "the collision change should have recompiled the world"
        assert m.world.model.actuator_forcerange[fingers].tolist() == [[-30.0, 30.0]] * 2
        np.testing.assert_allclose(m.world.model.body_pos[m.bodies["stand"].id], moved[:3])
        np.testing.assert_allclose(m.read("stand", "pose")[:3], moved[:3], atol=1e-9)
        for k in range(3, 13):  # the ball falls
            m.t = k / 120
            m.step(k, m.t, 1 / 120, {"joints": js, "actions": []}, {})
        assert m.bodies["ball"].velocity[2] < -0.05
        # the next run on this warm agent: its ball is at rest where the scene puts it (the recompile's bodies
        # lent the last run's velocities to the new run's)
        m.close()
        m.owned = {("ball", "pose")}
        m.init({k: p.default for k, p in MuJoCo.params.items()}, {"entities": ents, "robot": robot.as_dict()})
        _, extra = m.release("ball", "pose")
        assert extra["velocity"] == [0.0] * 6, extra
    finally:
        m.close()


def test_a_first_joint_state_naming_the_gripper_alone_waits_for_the_arm():
    """A driver that publishes the arm's and the gripper's joint states apart: the first one the twin gets may name
    the fingers alone (the merge begins with the second). Physics took it as the robot's first telemetry, set the
    fingers only and then drove the arm from its ready posture, swinging it across the table (35 cm at the hand);
    in_hand, holding the DIP from the start, seeded it against the hand of an arm at all-zero joints (29 cm off,
    then 69 cm for the rest of the run). Both now wait for a joint state that names the arm."""
    from agents.models.in_hand import InHand
    from agents.robot.kinematics import RobotKinematics, compose
    from protocol.joints import LatestJoints
    from protocol.robot import resolve_robot

    robot = resolve_robot({"use": "panda"})
    arm, grip = list(robot.arm), list(robot.gripper.joints)
    q_arm = [0.3, 0.1, -0.2, -2.2, 0.1, 2.4, 0.5]  # not the ready posture
    merged = LatestJoints()
    feed = [merged.take({"stamp": 0.0, "name": grip, "position": [0.006, 0.006], "velocity": [], "effort": []}),
            merged.take({"stamp": 0.004, "name": arm, "position": q_arm, "velocity": [], "effort": []})]
    assert feed[0]["name"] == grip and feed[1]["name"] == grip + arm
    fk = RobotKinematics(robot)
    hand = fk.link_pose(dict(zip(arm + grip, q_arm + [0.006, 0.006], strict=True)))
    fk.close()

    m = make_physics({})
    try:
        link = m.robot_links[robot.gripper.hand]
        for k in range(6):
            m.tick, m.t = k, k / 120
            js = feed[min(k, 1)] if k < 2 else {**feed[1], "stamp": 0.004 * k}
            m.step(k, m.t, 1 / 120, {"joints": js, "actions": []}, {})
            if k >= 1:
                assert np.linalg.norm(np.array(m._link_pose(link)[:3]) - hand[:3]) < 0.01, k
    finally:
        m.close()

    dip = compose(hand, [0, 0, 0.1, 0, 0, 0, 1])
    ih = InHand()
    ih.owned = {("dip", "pose")}
    ih.init({k: p.default for k, p in InHand.params.items()},
            {"entities": {"dip": {"shape": {"type": "cylinder", "radius": 0.006, "length": 0.05},
                                  "pose": [float(v) for v in dip]}}, "robot": {}})
    try:
        for k in range(3):
            ih.step(k, k / 60, 1 / 60, {"joints": feed[min(k, 1)], "actions": []}, {})
            np.testing.assert_allclose(ih.read("dip", "pose")[:3], dip[:3], atol=1e-3)
    finally:
        ih.close()


def test_a_urdf_entity_s_pose_is_its_frame_not_its_centre_of_mass():
    """pybullet places a body by its centre of mass, which a URDF may put off the link's origin (the duck's is
    2 cm along its y axis). An entity's pose is its frame's, as the scene gives it and the other models send it:
    the duck read where it was put (it was 2 cm off), placed where it was handed, and its frame's velocity is
    its centre's plus the spin's share. The robot's base link too (the Panda's centre is 5 cm above it)."""
    q = [0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)]  # a quarter turn about z: the offset along -x
    duck = {"shape": {"type": "urdf", "file": "duck_vhacd.urdf"}, "pose": [0.5, 0.2, 0.3, *q], "tags": ["static"]}
    m = make_physics({"duck": duck})
    try:
        np.testing.assert_allclose(m.read("duck", "pose"), [0.5, 0.2, 0.3, *q], atol=1e-9)
        com = m.p.getBasePositionAndOrientation(m.bodies["duck"].id, physicsClientId=m.cid)[0]
        np.testing.assert_allclose(com, [0.48, 0.2, 0.3], atol=1e-9)  # pybullet's own
        m.acquire("duck", "pose", [0.1, -0.2, 0.4, 0, 0, 0, 1], {})
        np.testing.assert_allclose(m._where("duck"), [0.1, -0.2, 0.4, 0, 0, 0, 1], atol=1e-9)
        np.testing.assert_allclose(m._where("panda_link0")[:3], [0, 0, 0], atol=1e-9)
    finally:
        m.close()
    m = make_physics({"duck": {**duck, "tags": []}})
    try:
        m.acquire("duck", "pose", [0.5, 0.2, 0.3, 0, 0, 0, 1], {"velocity": [0.1, 0, 0, 0, 0, 2.0]})
        v = m.velocity("duck")  # the frame's, as handed
        np.testing.assert_allclose(v, [0.1, 0, 0, 0, 0, 2.0], atol=1e-9)
        lin = m.p.getBaseVelocity(m.bodies["duck"].id, physicsClientId=m.cid)[0]  # the centre's, 2 cm along +y
        np.testing.assert_allclose(lin, [0.1 - 2.0 * 0.02, 0, 0], atol=1e-9)
        step(m, 1, 1 / 120)
        p = m.read("duck", "pose")
        assert p[2] < 0.3 and abs(p[0] - 0.5) < 0.01, p
    finally:
        m.close()


@pytest.mark.parametrize("engine", ["physics", "mujoco"])
def test_a_step_of_no_time_moves_nothing(engine):
    """Steps of dt = 0 ran a substep each: 120 of them let a ball fall from 0.5 m to 0.2 m in pybullet (0.43 m in
    MuJoCo) while no time passed. Now nothing moves until time does."""
    ball = {"shape": {"type": "sphere", "radius": 0.033}, "pose": [0.45, 0, 0.5, 0, 0, 0, 1], "mass": 0.057}
    if engine == "physics":
        m = make_physics({"ball": ball}, owned={("ball", "pose")}, time_step=1 / 240)
    else:
        pytest.importorskip("mujoco")
        from agents.models.mujoco import MuJoCo

        m = MuJoCo()
        m.owned = {("ball", "pose")}
        m.init({k: p.default for k, p in MuJoCo.params.items()} | {"robot": False},
               {"entities": {"ball": ball}, "robot": {}})
    try:
        for k in range(1, 121):
            step(m, k, 0.0)
        assert m.read("ball", "pose")[2] == pytest.approx(0.5, abs=1e-9)
        step(m, 121, 1 / 120)
        assert m.read("ball", "pose")[2] < 0.5  # (and it falls once time passes)
    finally:
        m.close()


def _engine(engine: str, entities: dict, owned: set):
    if engine == "physics":
        return make_physics(entities, owned=owned, time_step=1 / 240)
    pytest.importorskip("mujoco")
    from agents.models.mujoco import MuJoCo

    m = MuJoCo()
    m.owned = set(owned)
    m.init({k: p.default for k, p in MuJoCo.params.items()} | {"robot": False}, {"entities": entities, "robot": {}})
    return m


@pytest.mark.parametrize("engine", ["physics", "mujoco"])
def test_a_free_body_s_own_surface_decides_its_contacts_with_the_table(engine):
    """The scene's restitution and friction of a free body are what it does on the table, in both engines.
    pybullet multiplies two surfaces' coefficients and gives the table 1.0. MuJoCo averaged the ball's contact
    damping with the table's critically damped one, and took the larger friction: a tennis ball (restitution 0.6)
    bounced back 0.23 of its speed and every body slid with the table's friction 1.0. The free body's surface now
    has the priority (the finger pads' is above it)."""
    dt = 1 / 120
    ball = {"shape": {"type": "sphere", "radius": 0.033}, "pose": [0.45, 0, 0.5, 0, 0, 0, 1], "mass": 0.057}
    m = _engine(engine, {"ball": ball}, {("ball", "pose")})
    try:
        z = []
        for k in range(1, 181):
            step(m, k, dt)
            z.append(m.read("ball", "pose")[2] - 0.033)
        first = next(k for k in range(1, len(z)) if z[k] > z[k - 1])  # rising: it has bounced
        e = math.sqrt(max(z[first:first + 60]) / (0.5 - 0.033))  # the apex against the drop height
        assert 0.5 < e < 0.75, e  # pybullet 0.60, MuJoCo 0.60-0.69 by where in a 1 ms step it touches
    finally:
        m.close()
    # a 10 cm box of friction 0.3 let go at 1 m/s slides v^2 / (2 mu g) = 0.17 m
    box = {"shape": {"type": "box", "size": [0.1, 0.1, 0.1]}, "pose": [0.4, 0, 0.05, 0, 0, 0, 1], "mass": 0.5,
           "friction": 0.3}
    m = _engine(engine, {"box": box}, set())
    try:
        x, k = 0.4, 0
        for k in range(1, 13):  # carried by another owner at 1 m/s
            x = 0.4 + k * dt
            step(m, k, dt, {"box": {"pose": [x, 0, 0.05, 0, 0, 0, 1]}})
        m.acquire("box", "pose", [x, 0, 0.05, 0, 0, 0, 1], {})
        m.owned.add(("box", "pose"))
        for j in range(k + 1, k + 121):
            step(m, j, dt)
        slid = m.read("box", "pose")[0] - x
        assert slid == pytest.approx(1 / (2 * 0.3 * 9.81), rel=0.25), slid
    finally:
        m.close()


def test_the_mujoco_model_reads_an_xarm_drive_joint_s_torque_as_its_fingers_force():
    """The MuJoCo model took a gripper joint's effort for a finger's force with the Panda's signs: the xArm's drive
    joint closes by turning positive, so its squeezing torque (positive) was no squeeze and an opening push was one,
    aimed 5 mm-as-radians the opening way. It now reads the force through the gripper's geometry, as grasp_monitor
    and in_hand do: a 3 N m squeeze is ~30 N on each finger, aimed 5 mm of finger travel closed (0.1 rad) with the
    3 N m measured as the drive's limit; an opening push leaves the drive at the reported position (closing with
    no more than the measured effort, opening with the gripper's force)."""
    pytest.importorskip("mujoco")
    from agents.models.mujoco import MuJoCo
    from protocol.robot import resolve_robot

    robot = resolve_robot({"use": "xarm6"})
    m = MuJoCo()
    m.owned = set()
    m.init({k: p.default for k, p in MuJoCo.params.items()}, {"entities": {}, "robot": robot.as_dict()})
    names = [*robot.arm, *robot.gripper.joints]
    try:
        w = m.world
        drive = w.finger_act[0]
        for k, (tau, closing) in enumerate(((3.0, True), (-3.0, False))):
            js = {"name": names, "position": list(robot.ready[:6]) + [0.4], "velocity": [0.0] * 7,
                  "effort": [0.0] * 6 + [tau], "stamp": float(k + 1)}
            m.t = (k + 1) / 120
            m.step(k + 1, m.t, 1 / 120, {"joints": js, "actions": []}, {})
            if closing:
                assert w.data.ctrl[drive] == pytest.approx(0.4 + 0.005 * 2 / 0.1, abs=0.03)  # slope ~0.05 m/rad
                assert w.model.actuator_forcerange[drive].tolist() == [-3.0, 3.0]
            else:
                assert w.data.ctrl[drive] == pytest.approx(0.4)
                assert w.model.actuator_forcerange[drive].tolist() == [-m.finger_force, 3.0]  # (closing: positive)
    finally:
        m.close()


@pytest.mark.parametrize("engine", ["physics", "mujoco"])
def test_both_engines_hold_still_what_the_scene_checker_calls_static(engine):
    """Which entities the world holds still was decided three times (the physics model, the MuJoCo model, the
    check of ``uncertain:`` mass ranges); it is one function now, :func:`protocol.geometry.is_static`. Each entity
    here starts 0.4 m up: the static ones are still there after half a second, the others fell."""
    from protocol.geometry import is_static

    ball = {"shape": {"type": "sphere", "radius": 0.03}, "mass": 0.05}
    entities = {
        "free": ball | {"pose": [0.0, 0.0, 0.4]},
        "massless": ball | {"pose": [0.2, 0.0, 0.4], "mass": 0},
        "tagged": ball | {"pose": [0.4, 0.0, 0.4], "tags": ["static"]},
        "bin": {"shape": {"type": "container", "style": "bin"}, "pose": [0.0, 0.5, 0.4], "mass": 1.0},
    }
    m = _engine(engine, entities, {(n, "pose") for n in entities})
    try:
        for k in range(1, 61):
            step(m, k, 1 / 120)
        for name, ent in entities.items():
            held = is_static(ent["shape"], ent.get("tags") or (), ent.get("mass"))
            assert held == (name != "free")
            z = m.read(name, "pose")[2]
            assert (z == pytest.approx(0.4, abs=1e-6)) == held, (name, z)
    finally:
        m.close()


@pytest.mark.parametrize("kind", ["physics", "mujoco"])
def test_initial_joints_of_the_wrong_length_is_refused_naming_the_joints(kind):
    """Three values for a seven-joint arm: both engines refuse them alike, naming what they take (pybullet put
    the other joints at zero without a word; MuJoCo ended in a numpy broadcast error). The arm's seven alone
    leave the gripper open in both."""
    from agents.models.mujoco import MuJoCo
    from agents.models.physics import Physics

    cls = Physics if kind == "physics" else MuJoCo
    params = {k: p.default for k, p in cls.params.items()}
    with pytest.raises(ValueError, match=r"initial_joints: 3 values; panda takes 7 .* or 9 "):
        cls().init(params | {"initial_joints": [0.3, -0.5, 0.2]}, {"entities": {}, "robot": {"use": "panda"}})
    m = cls()
    arm = [0.1, -0.4, 0.0, -2.2, 0.0, 1.9, 0.7]
    m.init(params | {"initial_joints": arm}, {"entities": {}, "robot": {"use": "panda"}})
    try:
        if kind == "physics":
            import pybullet as p

            q = [p.getJointState(m.robot, m.arm.index.joint[n], physicsClientId=m.cid)[0]
                 for n in m.robot_spec.joints]
        else:
            q = list(m.world.joints()[0])
        assert q == pytest.approx([*arm, 0.04, 0.04], abs=1e-6)
    finally:
        m.close()
