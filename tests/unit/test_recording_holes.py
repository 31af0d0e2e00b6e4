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


def test_actions_before_a_merged_topic_was_heard_from_are_no_hole():
    """Joint states of two topics merged: those before every topic was heard from are held back (a note), so the
    first merged one comes late; an action before it is inside what the robot recorded, not on another clock."""
    items = [action(0.1)] + [joint(0.8 + i * 0.01) for i in range(100)]
    assert Recording("merged.mcap", items).holes  # (measured from the merged joint states alone)
    assert Recording("merged.mcap", items, joints_span=(0.0, 1.79)).holes == []
