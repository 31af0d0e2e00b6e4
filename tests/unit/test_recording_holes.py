"""Holes in a recording's telemetry are said, so a replay that misses part of the robot's motion is not
``complete``: joint states that stop for longer than a live run would call a gap, actions on another clock, and
joint states that name a joint twice (which of the values is the joint's?)."""
from __future__ import annotations

import pytest

from conductor.sources.recording import Recording, _joint_state
from protocol import codec
from protocol.errors import ProtocolError


def joint(t: float) -> tuple[float, str, dict]:
    return t, "joint_state", {"stamp": t, "name": ["j1"], "position": [0.0], "velocity": [], "effort": []}


def action(t: float) -> tuple[float, str, dict]:
    return t, "action", {"stamp": t, "operation": "grip", "phase": "end", "params": {}}


def test_a_clean_recording_has_no_holes():
    rec = Recording("clean.mcap", [action(0.0)] + [joint(i * 0.01) for i in range(300)] + [action(2.99)])
    assert rec.holes == [] and rec.warnings() == []


def test_joint_states_that_stop_are_said_with_the_longest_gap():
    stamps = [i * 0.01 for i in range(100)] + [2.5 + i * 0.01 for i in range(100)] + [4.0, 5.0]
    rec = Recording("gaps.mcap", [joint(t) for t in stamps])
    (hole,) = rec.holes
    assert "its joint states stop 3 times for more than 0.5 s (the longest 1.51 s from t=0.99 s)" in hole, hole
    assert rec.warnings() == [f"gaps.mcap: {hole}"]


def step(t: float, op: str, phase: str) -> tuple[float, str, dict]:
    return t, "action", {"stamp": t, "operation": op, "phase": phase, "params": {}}


def test_a_recording_cut_in_the_middle_of_the_task_says_so():
    """A bag that starts or stops in the middle of the robot's task ended complete with the wrong answer, where a
    live run says the same thing (began late, went quiet during an action): a replay says it too (degraded)."""
    joints = [joint(i * 0.01) for i in range(300)]
    whole = [step(0.0, "move_arm", "start"), step(1.0, "move_arm", "end"), step(1.0, "release", "start"),
             step(2.0, "release", "end")]
    assert Recording("whole.mcap", joints + whole).unfinished == []
    (late,) = Recording("late.mcap", joints + whole[1:]).unfinished
    assert late.startswith("it begins in the middle of the robot's task: its action move_arm ends at t=1.00 s, but "
                           "its start is not in the recording"), late
    early = Recording("early.mcap", joints + whole[:3])
    (cut,) = early.unfinished
    assert cut.startswith("it ends in the middle of the robot's task: its action release (begun at t=1.00 s) never "
                          "ends"), cut
    assert early.warnings() == [f"early.mcap: {cut}"]
    # a robot that annotates only its actions' ends (or only their starts) has nothing to pair them with
    assert Recording("ends.mcap", joints + [action(1.0), action(2.0)]).unfinished == []
    assert Recording("starts.mcap", joints + [step(1.0, "grip", "start")]).unfinished == []


def test_actions_far_outside_the_joint_states_are_said():
    rec = Recording("shifted.mcap", [joint(i * 0.01) for i in range(300)] + [action(30.0), action(31.0)])
    (hole,) = rec.holes
    assert hole.startswith("2 of its actions (the first at t=30.00 s) come more than 0.5 s outside its joint "
                           "states (t=0.00 to 2.99 s)"), hole


def test_a_joint_named_twice_is_left_out_of_a_recording_and_refused_on_the_wire():
    class Ros:
        name = ["j1", "j2", "j1"]
        position = [0.1, 0.2, 0.3]
        velocity: list = []
        effort: list = []

    msg, why = _joint_state(Ros(), 0)
    assert msg is None and why == "joint states that name a joint twice"
    with pytest.raises(ProtocolError, match="names a joint twice"):
        codec.encode("joint_state", stamp=0.0, name=["j1", "j1"], position=[0.0, 1.0], velocity=[], effort=[])


def test_joint_states_without_efforts_are_noted():
    """A real robot's joint states often carry no efforts: the grasp monitor then decides from positions and hand
    commands (a slip replayed so gave the wrong answer, COMPLETE, with no word of it). Said as a note: the input
    has no defect, but the answer rests on less."""
    from conductor.sources.recording import NO_EFFORTS

    bare = Recording("bare.mcap", [joint(i * 0.01) for i in range(10)])
    assert f"bare.mcap: {NO_EFFORTS}" in bare.notes() and bare.warnings() == []
    forced = [(t, k, {**m, "effort": [0.0 if i < 5 else -20.0]}) for i, (t, k, m) in
              enumerate(joint(i * 0.01) for i in range(10))]
    assert not any(NO_EFFORTS in n for n in Recording("forces.mcap", forced).notes())


def test_a_slow_robot_s_joint_states_are_no_gap_but_a_note():
    """A robot that publishes its joint states twice a second spaces them 0.5 s apart by design: each spacing a
    hair over 0.5 s used to be a gap, and the run degraded. A gap is now also five of the stream's usual spacings;
    the slow rate is a note (the robot moves in steps), and a real gap at that rate is still said."""
    import random

    jitter = random.Random(7)
    stamps = [i * 0.5 + jitter.uniform(0.0, 0.02) for i in range(40)]
    slow = Recording("slow.mcap", [action(0.0)] + [joint(t) for t in stamps] + [action(stamps[-1] + 0.6)])
    assert slow.holes == [] and slow.warnings() == []
    (note,) = [n for n in slow.notes() if "come every" in n]
    assert note.startswith("slow.mcap: its joint states come every 0.50 s (2 a second)"), note
    dropped = Recording("slow_gap.mcap", [joint(t) for t in stamps[:20] + [s + 6.0 for s in stamps[20:]]])
    (hole,) = dropped.holes
    assert "stop 1 time for more than 2.5" in hole and "the longest 6.5" in hole, hole
    fast = Recording("fast.mcap", [joint(i * 0.01) for i in range(300)])
    assert not any("come every" in n for n in fast.notes())


def test_a_live_robot_s_slow_joint_states_are_no_gap_but_a_note():
    """The same rule live: the usual spacing is that of the last joint states taken."""
    from conductor.sources.live import LiveSource

    source = object.__new__(LiveSource)
    source._init_state(idle_timeout=1.0, wait_first=1.0)
    t0 = 1000.0
    for i in range(20):
        assert source._admit("joint_state", joint(t0 + i * 0.5 + (0.01 if i % 2 else 0.0))[2])
    assert source.gaps == [] and not any("stopped" in w for w in source.warnings())
    assert any(n.startswith("the robot's joint states come every 0.5") for n in source.notes()), source.notes()
    fast = object.__new__(LiveSource)
    fast._init_state(idle_timeout=1.0, wait_first=1.0)
    for i in range(20):
        fast._admit("joint_state", joint(t0 + i * 0.01)[2])
    fast._admit("joint_state", joint(t0 + 0.19 + 0.6)[2])  # (0.6 s ahead of the last: not yet "far ahead")
    assert len(fast.gaps) == 1 and fast.notes() == [], (fast.gaps, fast.notes())


def test_a_frozen_header_stamp_counts_only_while_the_robot_acts():
    """Joint states that keep one header stamp for 2 s: said when the robot's actions go on meanwhile (the twin's arm
    stands while the real one works), not when nothing happens then (an idle gripper's driver republishing)."""
    joints = [joint(i * 0.01) for i in range(400)]
    acting = Recording("acting.mcap", joints + [step(1.5, "move_arm", "start"), step(3.5, "move_arm", "end")],
                       frozen=[(1.0, 2.0)])
    (hole,) = acting.holes
    assert hole.startswith("its joint states repeat one header stamp 1 time for more than 0.5 s (the longest 2.00 s "
                           "from t=1.00 s) while they go on being recorded and the robot's actions go on"), hole
    idle = Recording("idle.mcap", joints + [step(0.5, "move_arm", "start"), step(0.9, "move_arm", "end")],
                     frozen=[(1.0, 2.0)])
    assert idle.holes == []


@pytest.mark.parametrize("acting", [True, False])
def test_a_live_driver_that_freezes_and_thaws_loses_nothing_after_it(monkeypatch, acting):
    """A live driver republishes its last joint state for 1.5 s, then goes on. Every joint state after it was left
    out as "stamped far ahead" (each repeat moved the arrival its stamp was measured against), to the end of the
    run. Now nothing is left out and the freeze is no gap; it is said when the robot acted meanwhile, as for a
    recording."""
    from conductor.sources import live

    now = [500.0]
    monkeypatch.setattr(live.time, "monotonic", lambda: now[0])
    source = object.__new__(live.LiveSource)
    source._init_state(idle_timeout=1.0, wait_first=1.0)
    t0 = 1000.0
    stamps = [t0 + i * 0.01 for i in range(50)] + [t0 + 0.49] * 150 + [t0 + 2.0 + i * 0.01 for i in range(50)]
    for i, stamp in enumerate(stamps):
        if acting and i == 30:
            assert source._admit("action", {"stamp": stamp, "operation": "move_arm", "phase": "start"})
        assert source._admit("joint_state", joint(stamp)[2]), i
        now[0] += 0.01
    assert source._admit("action", {"stamp": stamps[-1], "operation": "move_arm", "phase": "end"})
    assert source.left_out == {} and source.gaps == []
    said = [w for w in source.warnings() if "repeated one stamp" in w]
    if acting:
        assert said == ["the robot's joint states repeated one stamp 1 time for more than 0.5 s (the longest 1.50 s "
                        "from t=0.49 s) while they went on coming and the robot acted: a driver republishing its "
                        "last message? The twin's robot stood still there"], said
    else:
        assert said == [] and source.warnings() == []


def test_a_live_robot_s_clock_that_steps_forward_loses_nothing_after_it(monkeypatch):
    """The robot's clock steps 30 s forward (an NTP step) and stays there: every message after it was left out as
    stamped far ahead, to the end of the run. Five joint states in step with one another make it a clock step:
    they and everything after are taken 30 s earlier, by when they came, and it is said. One bad stamp, or a second
    robot's stream interleaved with the first, are still left out."""
    from conductor.sources import live

    now = [500.0]
    monkeypatch.setattr(live.time, "monotonic", lambda: now[0])

    def source():
        s = object.__new__(live.LiveSource)
        s._init_state(idle_timeout=1.0, wait_first=1.0)
        return s

    t0 = 1000.0
    stepped = source()
    for i in range(100):
        stamp = t0 + i * 0.01 + (30.0 if i >= 50 else 0.0)
        if i in (20, 70):
            stepped._admit("action", {"stamp": stamp, "operation": "move_arm", "phase": "start" if i == 20 else "end"})
        stepped._admit("joint_state", joint(stamp)[2])
        now[0] += 0.01
    assert stepped.left_out == {} and stepped.gaps == []
    taken = stepped.due(10.0)
    assert len(taken) == 102 and [k for k, _ in taken].count("action") == 2
    stamps = [m["stamp"] for k, m in taken if k == "joint_state"]
    assert stamps == sorted(stamps) and max(b - a for a, b in zip(stamps, stamps[1:])) < 0.02, stamps[45:56]
    (said,) = [w for w in stepped.warnings() if "clock stepped" in w]
    assert said.startswith("the robot's clock stepped forward 1 time (first by 30.00 s after t=0.49 s)"), said

    bad = source()  # three stamped an hour ahead among good ones: left out, nothing re-based
    for i in range(60):
        bad._admit("joint_state", joint(t0 + i * 0.01 + (3600.0 if 20 <= i < 23 else 0.0))[2])
        now[0] += 0.01
    assert bad.steps == [] and sum(bad.left_out.values()) == 3  # (held until the good one after them came)
    assert bad.warnings()[0] == "3 telemetry messages left out: stamped far ahead of when it came (a clock that " \
                                "jumped forward)"

    two = source()  # a second robot 10 s ahead on the same stream: never five in a row
    for i in range(60):
        two._admit("joint_state", joint(t0 + i * 0.01)[2])
        two._admit("joint_state", joint(t0 + 10.0 + i * 0.01)[2])
        now[0] += 0.01
    assert two.steps == [] and two.left_out[next(iter(two.left_out))] == 59


def test_a_live_robot_whose_clock_steps_back_or_that_says_little_is_not_taken_for_quiet(monkeypatch):
    """The robot's clock steps back 10 s: its messages are left out until their stamps pass the old ones, but they
    still come, and the run ended as if the robot had gone quiet. An action stamped on another clock than the joint
    states (a ROS 2 action by the sender's wall clock, joint states on sim time) was queued and held back every
    message after it; it is left out. A joint state with no positions (velocities alone, as ROS allows) reached
    physics, which indexed its positions; it is left out."""
    from conductor.sources import live

    now = [500.0]
    monkeypatch.setattr(live.time, "monotonic", lambda: now[0])
    s = object.__new__(live.LiveSource)
    s._init_state(idle_timeout=3.0, wait_first=1.0)
    t0 = 1000.0
    for i in range(1000):  # 2 s, then the clock steps back 10 s for the remaining 8 s
        assert not s.exhausted(0.0), i
        s._admit("joint_state", joint(t0 + i * 0.01 - (10.0 if i >= 200 else 0.0))[2])
        now[0] += 0.01
    assert sum(s.left_out.values()) == 800 and not s.exhausted(0.0)

    other = object.__new__(live.LiveSource)
    other._init_state(idle_timeout=3.0, wait_first=1.0)
    for i in range(100):
        if i == 10:
            other._admit("action", {"stamp": 1.7e9, "operation": "grip", "phase": "start"})
        if i == 20:
            other._admit("joint_state", {**joint(12.0 + i * 0.01)[2], "position": [], "velocity": [0.1]})
        other._admit("joint_state", joint(12.0 + i * 0.01)[2])
        now[0] += 0.01
    assert len(other.due(10.0)) == 100 and not other._q
    assert other.left_out == {live.AHEAD_WHY: 1, "joint states without positions (velocities or efforts alone: the "
                                                  "twin moves its robot by the positions)": 1}, other.left_out


def test_ros2_publications_lost_on_the_way_are_a_warning():
    """Gaps in the publishers' sequence numbers were counted in the lag figures only: a lost grasp annotation left
    the run complete."""
    from conductor.sources.ros2 import Ros2Source

    s = object.__new__(Ros2Source)
    s._init_state(idle_timeout=3.0, wait_first=1.0)
    s.last_seq, s.dropped, s._before, s.domain = {}, 0, None, 0
    assert s.warnings() == []
    s.dropped = 42
    assert s.warnings() == ["42 of the robot's ROS 2 publications never came (gaps in their publishers' sequence "
                            "numbers): lost on the way"]


def test_live_joint_states_that_stop_while_the_robot_acts_on_are_said():
    """The arm's driver dies and the task node goes on: no two joint states far apart make a gap, so the run ended
    complete with the twin's arm held still through the robot's last actions. Said now; actions within the joint
    states' time are not."""
    from conductor.sources.live import LiveSource

    source = object.__new__(LiveSource)
    source._init_state(idle_timeout=1.0, wait_first=1.0)
    t0 = 1000.0
    for i in range(100):
        assert source._admit("joint_state", joint(t0 + i * 0.01)[2])
    assert source._admit("action", {"stamp": t0 + 0.5, "operation": "move_arm", "phase": "start"})
    assert not any("stopped" in w for w in source.warnings())
    for k, phase in enumerate(("end", "start", "end")):
        assert source._admit("action", {"stamp": t0 + 1.5 + k, "operation": "move_arm", "phase": phase})
    assert [w for w in source.warnings() if "stopped" in w] == [
        "the robot's joint states stopped at t=0.99 s while its actions went on to t=3.50 s: the twin held the last "
        "joints meanwhile, its arm still"]


def test_live_messages_a_little_out_of_step_do_not_hold_back_those_behind_them():
    """Two publishers on one topic, the gripper's clock 0.3 s ahead of the arm's (taken: BEHIND_S is 0.5 s): each
    gripper message, not yet due, held back every arm joint state queued behind it, and the arm's came ten at a
    time. Each message is now taken at its own tick, in arrival order; none is lost."""
    from conductor.sources.live import LiveSource

    source = object.__new__(LiveSource)
    source._init_state(idle_timeout=1.0, wait_first=1.0)
    t0 = 1000.0
    for i in range(100):
        assert source._admit("joint_state", {**joint(t0 + i * 0.01)[2], "name": ["arm"]})
        if i % 10 == 0:
            assert source._admit("joint_state", {**joint(t0 + i * 0.01 + 0.3)[2], "name": ["grip"]})
    taken = [source.due(k * 0.01 + 1e-6) for k in range(131)]
    arm = [[m["stamp"] for kind, m in tick if m["name"] == ["arm"]] for tick in taken]
    assert all(len(one) == 1 for one in arm[:100]), [len(one) for one in arm[:100]]
    assert [one[0] for one in arm[:100]] == pytest.approx([t0 + k * 0.01 for k in range(100)])
    grip = [k for k, tick in enumerate(taken) for kind, m in tick if m["name"] == ["grip"]]
    assert grip == list(range(30, 130, 10)) and not source._q


def test_live_joint_states_with_nan_efforts_are_filled_as_a_ros2_robot_s_are():
    """A robot on the twin's own telemetry keys whose gripper driver sends NaN efforts: every joint state was left out
    as malformed (the twin's robot frozen), while a ROS 2 robot's and a replay's are taken with their efforts filled.
    A NaN position is still left out."""
    import math

    from conductor.sources.live import LiveSource

    source = object.__new__(LiveSource)
    source._init_state(idle_timeout=1.0, wait_first=1.0)
    key = "twin/e/telemetry/joint_states"

    def sent(effort, position=(0.1, 0.04)):
        return codec.encode_unchecked("joint_state", {"stamp": 1000.0, "name": ["j1", "finger"],
                                                      "position": list(position), "velocity": [],
                                                      "effort": list(effort)})

    source._before = {"name": ["j1", "finger"], "position": [0.1, 0.04], "velocity": [], "effort": [2.0, 5.0]}
    msg = source._filled(key, sent([1.0, math.nan]))
    assert msg is not None and msg["effort"] == [1.0, 5.0] and msg["position"] == [0.1, 0.04]
    assert dict(source.partial) == {"joint states with NaN or infinite efforts": 1}
    assert source._filled(key, sent([1.0, 2.0], position=(math.nan, 0.04))) is None
    assert source._filled(key, sent([1.0, math.nan], position=(0.1,))) is None  # (one position for two names)
    assert source._filled(key, codec.encode("action", stamp=1.0, operation="x", phase="end", params={})) is None
    assert source._filled(key, b"\x00not msgpack") is None


@pytest.mark.parametrize("rate", [0.5, 1.0, 1.5])
def test_a_live_robot_whose_clock_runs_slow_or_fast_is_said(monkeypatch, rate):
    """A simulator at half real time stamping by its sim time: the live twin, paced by the wall clock, moved its arm
    at half speed against physics at full speed, and said nothing (its lag read 1.8e12 ms: stamps of another clock
    taken for this host's). The rate is said now, and the lag counted from the first message; a robot on this
    host's clock is not."""
    from conductor.sources import live

    now = [500.0]
    monkeypatch.setattr(live.time, "monotonic", lambda: now[0])
    source = object.__new__(live.LiveSource)
    source._init_state(idle_timeout=1.0, wait_first=1.0)
    start = 50.0 if rate != 1.0 else live.time.time()  # (sim time: 50 s since the simulator began)
    for i in range(300):
        assert source._admit("joint_state", joint(start + rate * i * 0.01)[2])
        now[0] += 0.01
    said = [w for w in source.warnings() if "the robot's clock went" in w]
    if rate == 1.0:
        assert said == []
    else:
        assert said == [f"the robot's clock went {rate:.2f} s a second of this host's clock over 3.0 s (a simulator on "
                        "its sim time, slower or faster than real time?): the live twin follows the wall clock, so its "
                        f"arm moved {rate:.2f} times as fast as the robot's stamps say, against physics at full speed"]
        source.due(0.0)
        assert source.lag_stats()["max_ms"] < 60_000  # (not this host's clock less the simulator's)
