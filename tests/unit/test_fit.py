"""The joint map a recording that does not fit the scene's robot is told to write (conductor.sources.fit)."""
from types import SimpleNamespace

import pytest

from conductor.sources.fit import check_fit, suggested_map
from protocol.errors import TwinError
from protocol.robot import resolve_robot

XARM = ["joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "drive_joint"]


def test_a_gripper_joint_is_never_paired_with_an_arm_joint():
    panda = resolve_robot({"use": "panda"})
    text = suggested_map(panda, XARM)
    assert "drive_joint: panda_finger_joint1" in text
    assert "panda_joint7" not in text  # the xArm has six arm joints: the Panda's seventh has no partner
    assert "joint6: panda_joint6" in text and "6 arm joints, the robot 7: check the pairs" in text


def test_same_shapes_pair_in_order_without_a_note():
    panda = resolve_robot({"use": "panda"})
    names = [f"arm_{i}" for i in range(1, 8)] + ["grip_l", "grip_r"]
    text = suggested_map(panda, names)
    assert text == ("joints: {arm_1: panda_joint1, arm_2: panda_joint2, arm_3: panda_joint3, arm_4: panda_joint4, "
                    "arm_5: panda_joint5, arm_6: panda_joint6, arm_7: panda_joint7, grip_l: panda_finger_joint1, "
                    "grip_r: panda_finger_joint2}")


def test_the_error_names_the_map_and_a_recording_without_joint_states_says_so():
    panda = resolve_robot({"use": "panda"})
    with pytest.raises(TwinError, match=r"rec.mcap: none of its joint names \(joint1, .*drive_joint: panda_finger"):
        check_fit(panda, XARM, "rec.mcap")
    with pytest.raises(TwinError, match=r"rec.mcap: it has no usable joint states with joint names, so") as e:
        check_fit(panda, [], "rec.mcap")
    assert "()" not in str(e.value)
    # every joint state left out: the error says why (it blamed the names of joint states it had dropped for NaN)
    with pytest.raises(TwinError, match=r"no usable joint states with joint names \(left out: 2557 joint states "
                                        r"with NaN, infinite or non-numeric values\), so nothing moves"):
        check_fit(panda, [], "rec.mcap", SimpleNamespace(skipped={"joint states with NaN, infinite or non-numeric "
                                                                  "values": 2557}))


def test_a_trigger_for_a_related_action_is_no_misspelling():
    """A trigger for ``open_gripper`` on a bag that only closes the gripper is a note (a task that never opens it),
    not a misspelling that makes every replay degraded; ``relase`` for ``release`` is one. An action another trigger
    waits for under its own name is never the misspelt one."""
    from conductor.sources.fit import unheard_actions

    def trig(name: str, action: str) -> SimpleNamespace:
        return SimpleNamespace(name=name, on={"action": action})

    rec = SimpleNamespace(path="bag.mcap", items=[(0.0, "action", {"operation": op}) for op in
                                                  ("close_gripper", "movej", "grasp", "release")])
    said = dict(unheard_actions([trig("open", "open_gripper"), trig("linear", "movel"), trig("drop", "ungrasp"),
                                 trig("let_go", "relase")], rec))
    assert [close for close in said.values()] == [False, False, False, True], said
    assert any("waits for action 'relase', which the bag never has (did you mean 'release'?)" in line for line in said)
    said = dict(unheard_actions([trig("let_go", "relase"), trig("go", "release")], rec))
    assert list(said.values()) == [False], said  # (release has a trigger of its own)
    assert "(did you mean 'release'? another trigger waits for that one too)" in next(iter(said)), said


def test_a_replay_keeps_its_notes_on_unheard_actions_and_warns_of_a_bag_without_any():
    """A trigger waiting for an action the bag never has, when that is no misspelling, was said by twin check only:
    the run's summary keeps it as a note now. A bag with no action at all while triggers wait for some (its action
    topic is another) is a warning naming the String topics it did not read: it ended complete, its triggers dead."""
    from conductor.sources.fit import JointFit, unheard_actions

    triggers = [SimpleNamespace(name=n, on={"action": a}) for n, a in (("grasp", "move_hand"), ("let_go", "move_hnd"))]
    rec = SimpleNamespace(path="bag", items=[(0.0, "action", {"operation": "move_hand"})])
    warnings: list[str] = []
    notes: list[str] = []
    JointFit(None, SimpleNamespace(rec=rec), warnings.extend, triggers=triggers, note=notes.extend).before_run()
    assert warnings == [] and notes == ["bag: trigger let_go waits for action 'move_hnd', which the bag never has "
                                        "(did you mean 'move_hand'? another trigger waits for that one too): it will "
                                        "never fire"], notes
    silent = SimpleNamespace(path="bag", items=[(0.0, "joint_state", {})], topics={"/action": ["/action"]},
                             other_action_topics=["/task/annotations"])
    assert unheard_actions(triggers, silent) == [
        ("bag: it has no action at all on /action, and triggers grasp, let_go wait for actions: they will never fire "
         "(the bag's String topics it did not read: /task/annotations; --remap /action:=/task/annotations reads one)",
         True)]
    assert unheard_actions([SimpleNamespace(name="t", on={"topic": "m.x"})], silent) == []


def test_a_live_gripper_that_speaks_late_is_a_note_one_that_never_does_a_warning():
    """A gripper's driver that starts 1.5 s after the arm's: the live name check ran once, over the first second, and
    said the finger joints 'are not in the telemetry; they stay where they started', the run degraded for joints that
    came and moved the twin's fingers. They are judged on every name heard now, late ones said in a note; fingers
    that never come are still a warning."""
    from conductor.sources.fit import JointFit
    from protocol.robot import resolve_robot

    robot = resolve_robot({"urdf": "franka_panda/panda.urdf"})

    def run(gripper_from: int | None) -> tuple[list[str], list[str]]:
        said: list[str] = []
        noted: list[str] = []
        fit = JointFit(robot, object(), said.extend, note=noted.extend)  # (a source with no recording: live)
        for i in range(300):
            t = 1000.0 + i * 0.01
            fit.take({"stamp": t, "name": list(robot.arm), "position": [0.0] * 7, "velocity": [], "effort": []})
            if gripper_from is not None and i >= gripper_from and i % 10 == 0:
                fit.take({"stamp": t, "name": list(robot.gripper.joints), "position": [0.04, 0.04], "velocity": [],
                          "effort": []})
        fit.finish()
        return said, noted

    said, noted = run(150)
    assert said == [] and noted == [
        "the live telemetry: the robot's joints panda_finger_joint1, panda_finger_joint2 came only after its first 1 "
        "s of joint states (a driver that started late?): they stood where they started until then"], noted
    said, noted = run(None)
    assert len(said) == 1 and "panda_finger_joint1, panda_finger_joint2 are not in the telemetry" in said[0], said
    assert noted == []
    assert run(0) == ([], [])


def test_the_suggested_map_pairs_joints_by_what_their_names_say():
    """The map paired the recording's arm joints with the URDF's in the order they first came: a driver that
    publishes fr3_joint2..7 before fr3_joint1 was told to map every joint to its neighbour, and with that map
    twin check said it fits (a review's finding). Names now pair by name, by what is left after a common prefix,
    or by their trailing numbers when every name has one; what only the order pairs is said."""
    panda = resolve_robot({"use": "panda"})
    text = suggested_map(panda, [f"fr3_joint{i}" for i in (2, 3, 4, 5, 6, 7, 1)] + ["fr3_finger_joint1"])
    assert all(f"fr3_joint{i}: panda_joint{i}" in text for i in range(1, 8)) and "order" not in text, text
    text = suggested_map(panda, [f"j{i}" for i in (7, 1, 2, 3, 4, 5, 6)])
    assert all(f"j{i}: panda_joint{i}" in text for i in range(1, 8)), text
    ur = ["shoulder_pan", "shoulder_lift", "elbow", "w1", "w2", "w3", "w4"]  # (names that do not say: order)
    text = suggested_map(panda, ur)
    assert "shoulder_pan: panda_joint1" in text and "w1: panda_joint4" in text, text
    assert "shoulder_pan, shoulder_lift, elbow, w1, w2, w3, w4 paired by order alone: check them" in text, text


def test_a_joint_map_that_gives_two_joints_one_name_is_refused():
    """A map {a: X} where the recording also reports X: every joint state would name X twice (a review's point)."""
    robot = resolve_robot({"use": "panda", "joints": {"j1": "panda_joint1"}})
    names = ["j1", "panda_joint1", *[f"panda_joint{i}" for i in range(2, 8)]]
    with pytest.raises(TwinError, match="j1 and panda_joint1 would both be panda_joint1"):
        check_fit(robot, names, "bag.mcap")
