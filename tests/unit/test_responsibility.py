"""The responsibility map and handovers, alone: any sequence of transfers (accepted or refused) and fallbacks
keeps exactly one owner per attribute, and the handover records tell the map's history exactly."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conductor.handover import Handovers
from conductor.record import RunRecord
from conductor.responsibility import Responsibilities
from conductor.scene import parse_scene
from conductor.stepping import Clock
from protocol.errors import RunAborted

from .fakes import FakeLink, ready_registry

SCENE = """
name: owners
main: phys
models:
  phys: {kind: physics}
  hand: {kind: in_hand}
  conn: {kind: spu}
  obs: {kind: grasp_monitor}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0, 0, 0.1]}
  dip: {shape: {type: box, size: [0.01, 0.01, 0.05]}, pose: [0.2, 0, 0.1], attributes: {pose: phys, collision: phys}}
  cup: {shape: {type: sphere, radius: 0.05}, pose: [0.4, 0, 0.1], attributes: {pose: phys, temperature: conn}}
"""
MODELS = {"phys": ["pose", "collision"], "hand": ["pose"], "conn": ["pose", "collision", "temperature"], "obs": []}

ops = st.lists(st.one_of(
    st.tuples(st.just("transfer"), st.sampled_from(["ball", "dip", "cup", "nowhere"]),
              st.sampled_from(["pose", "collision", "temperature"]), st.sampled_from(sorted(MODELS) + ["ghost"]),
              st.booleans(), st.booleans(), st.booleans()),
    st.tuples(st.just("fallback"), st.sampled_from(["hand", "conn", "obs"])),
), max_size=40)


def _setup():
    scene = parse_scene(SCENE, "<unit>")
    link, registry, rmap, clock = FakeLink(), ready_registry(MODELS), Responsibilities(scene), Clock(0.01)
    return scene, link, registry, rmap, clock, Handovers(link, registry, rmap, RunRecord(scene), "phys", clock)


@settings(max_examples=300, deadline=None)
@given(ops=ops)
def test_any_sequence_of_handovers_keeps_one_owner_per_attribute(ops):
    """After every transfer (accepted, refused on release or on acquire, or impossible) and every fallback, each
    of the scene's attributes has exactly one owner among the scene's models, the version counts the changes,
    and replaying the handover records from the initial map gives the map."""
    scene, link, registry, rmap, clock, ho = _setup()
    for i, op in enumerate(ops):
        clock.set(i)
        if op[0] == "transfer":
            _, e, a, dst, refuse_release, refuse_acquire, refuse_back = op
            src = rmap.owner(e, a)
            link.refuse = {(src, "release")} if refuse_release else set()
            link.refuse |= {(dst, "acquire")} if refuse_acquire else set()
            link.refuse |= {(src, "acquire")} if refuse_back else set()
            before = dict(rmap.owners)
            moved = ho.transfer(e, a, dst, "t")
            assert moved == (rmap.owner(e, a) == dst != src)
            if moved:
                assert not refuse_release and not refuse_acquire
            elif rmap.owners != before:  # neither took it: the main model did
                assert rmap.owner(e, a) == "phys" and refuse_acquire and refuse_back and src != dst
        else:
            link.refuse = set()
            ho.fallback(op[1])
            # what the main model can own fell back to it; what it cannot stays with the lost model (said, degraded)
            assert all(a not in registry.declares("phys", "attributes") for _, a in rmap.owned_by(op[1]))
            registry.agents[op[1]].ready = True  # it rejoins
        assert rmap.invariant_holds()
        assert set(rmap.owners) == set(scene.initial_owners())
        assert rmap.version == len(rmap.handovers)
    replay = scene.initial_owners()
    for h in rmap.handovers:
        assert replay[(h.entity, h.attribute)] == h.src
        replay[(h.entity, h.attribute)] = h.dst
    assert replay == rmap.owners


def test_transfer_hands_the_value_and_extras_over():
    """release -> acquire moves the old owner's value; the new ownership is published with the change."""
    scene, link, registry, rmap, clock, ho = _setup()
    link.held[("phys", "ball", "pose")] = [1, 2, 3, 0, 0, 0, 1]
    clock.set(7)
    assert ho.transfer("ball", "pose", "hand", "grasp", {"near": "ball"})
    assert link.held[("hand", "ball", "pose")] == [1, 2, 3, 0, 0, 0, 1]
    assert rmap.value("ball", "pose") == [1, 2, 3, 0, 0, 0, 1]
    (key, msg), = link.published
    assert key.endswith("/ownership") and msg["owners"]["ball"]["pose"] == "hand" and msg["version"] == 1
    assert msg["change"]["tick"] == 7 and msg["change"]["variables"] == {"near": "ball"}
    assert [n for n, _ in link.events] == ["handover"]


def test_refused_acquire_gives_the_value_back():
    """If the new owner refuses, the old one is handed the value back and nothing changes."""
    scene, link, registry, rmap, clock, ho = _setup()
    link.held[("phys", "ball", "pose")] = "v"
    link.refuse = {("hand", "acquire")}
    assert not ho.transfer("ball", "pose", "hand", "grasp")
    assert rmap.owner("ball", "pose") == "phys" and link.held[("phys", "ball", "pose")] == "v"
    assert any("ownership stays with phys" in e for e in ho.record.errors)


def test_a_value_neither_side_of_a_refused_handover_takes_goes_to_the_main_model():
    """The new owner refuses and the old one cannot take the value back: the main model gets it (the map names a
    model that moves it); if the main model cannot own it, the map keeps the old owner and says nobody moves it."""
    scene, link, registry, rmap, clock, ho = _setup()
    assert ho.transfer("ball", "pose", "hand", "grasp")
    link.held[("hand", "ball", "pose")] = [0.9, 0, 0.3, 0, 0, 0, 1]  # where hand has moved it since
    link.refuse = {("conn", "acquire"), ("hand", "acquire")}
    clock.set(5)
    assert not ho.transfer("ball", "pose", "conn", "snap")
    assert rmap.owner("ball", "pose") == "phys" and link.held[("phys", "ball", "pose")] == [0.9, 0, 0.3, 0, 0, 0, 1]
    # the map's value is what phys was given (it kept the value of before: triggers of the same tick read that)
    assert rmap.value("ball", "pose") == [0.9, 0, 0.3, 0, 0, 0, 1]
    (said,) = [e for e in ho.record.errors if "snap" in e]  # said once, as it ended (not 'stays with hand' first)
    assert "hand could not take it back either" in said and "ownership stays" not in said, said
    h = rmap.handovers[-1]
    assert (h.src, h.dst, h.tick) == ("hand", "phys", 5) and h.trigger.startswith("snap")
    assert any("it went to the main model phys" in e for e in ho.record.errors)
    assert rmap.invariant_holds() and rmap.version == 2
    # the temperature: phys cannot own it, so it stays with conn, said
    link.refuse = {("hand", "acquire"), ("conn", "acquire")}
    registry.agents["hand"].desc = {"kind": "hand", "attributes": ["pose", "temperature"]}
    assert not ho.transfer("cup", "temperature", "hand", "heat")
    assert rmap.owner("cup", "temperature") == "conn"
    assert any("no live model moves it now" in e for e in ho.record.errors)


def test_an_attribute_goes_only_to_a_model_that_can_own_it():
    scene, link, registry, rmap, clock, ho = _setup()
    assert not ho.transfer("cup", "temperature", "hand", "t")
    assert rmap.owner("cup", "temperature") == "conn"
    assert any("cannot own attribute 'temperature'" in e for e in ho.record.errors)


def test_losing_the_main_model_aborts_the_run():
    scene, link, registry, rmap, clock, ho = _setup()
    with pytest.raises(RunAborted, match="main model 'phys'"):
        ho.fallback("phys")


def test_inputs_are_what_others_own():
    """A model reads only what others own, by pattern, and never its own attributes."""
    scene, link, registry, rmap, clock, ho = _setup()
    rmap.values[("dip", "collision")] = True
    assert rmap.inputs_for("conn", ["*.pose", "dip.*"]) == {
        "ball": {"pose": [0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]}, "dip": {"pose": [0.2, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0],
                                                                      "collision": True},
        "cup": {"pose": [0.4, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]}}
    assert rmap.inputs_for("phys", ["*.pose"]) == {}
    assert rmap.owners_read_by("phys", ["cup.*"]) == {"conn"}
    rmap.absorb_state("hand", {"ball": {"pose": [9] * 7}})
    assert rmap.unauthorized_writes == 1 and rmap.value("ball", "pose")[0] == 0.0


def test_static_poses_do_not_count_as_read_and_a_moved_one_is_noted():
    cup = "cup: {shape: {type: sphere, radius: 0.05}, pose: [0.4, 0, 0.1],"
    scene = parse_scene(SCENE.replace(cup, cup + " tags: [static],"), "owners.yaml")
    m = Responsibilities(scene)
    assert m.static == {("cup", "pose")}
    # conn reads every pose: phys owns ball, dip and cup; the cup's (static) pose alone would not count
    assert m.owners_read_by("conn", ["*.pose"]) == {"phys"}
    assert m.owners_read_by("conn", ["cup.pose"]) == set()
    m.absorb_state("phys", {"cup": {"pose": [0.4, 0.0, 0.1005, 0, 0, 0, 1]}})  # within a millimetre: fixed
    assert m.static_moved == {}
    m.absorb_state("phys", {"cup": {"pose": [0.4, 0.02, 0.1, 0, 0, 0, 1]}})
    assert m.static_moved == {"cup": pytest.approx(0.02)}


def test_a_value_that_is_no_value_is_left_out_and_never_handed_on():
    """A model's NaN pose was kept, handed to physics at the next handover and simulated as NaN to the end of the
    run, complete; a None its next owner failed on was blamed on the receiver. Such a value (None, a number that is
    not finite, a pose not of 7 numbers) is now counted, named and left out: the map keeps the last good one, and a
    released one that is no value is replaced by it."""
    from protocol.messages import unusable

    assert unusable("pose", [0.0] * 7) is None and unusable("pose", [[0.0, 0.1, 0.2]] * 3) is None  # (a fluid's)
    assert unusable("pose", [0, 0, float("nan"), 0, 0, 0, 1]) == "not a finite number"
    assert unusable("pose", [0.0, 0.0, 0.1]) == "a pose of 3 numbers, not 7"
    assert unusable("temperature", None) == "no value" and unusable("grasped", True) is None
    # numpy arrays as the codec decodes them (the fluid's positions, physics' particles) are looked into too
    import numpy as np

    assert unusable("pose", np.full(7, np.nan)) == "not a finite number" and unusable("pose", np.zeros(3)) == \
        "a pose of 3 numbers, not 7"
    assert unusable("pose", np.array([[0.1, 0.2, np.nan], [0.0, 0.0, 0.0]])) == "not a finite number"
    assert unusable("pose", np.zeros(7)) is None and unusable("pose", np.zeros((5, 3))) is None
    assert unusable("level", np.float64("inf")) == "not a finite number" and unusable("tags", np.array(["a"])) is None
    scene, link, registry, rmap, clock, ho = _setup()
    good = [0.5, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]
    rmap.set_owner("ball", "pose", "hand", 0, 0.0, "x", {})
    rmap.absorb_state("hand", {"ball": {"pose": good}})
    rmap.absorb_state("hand", {"ball": {"pose": [0.5, 0.0, float("nan"), 0, 0, 0, 1]}})
    assert rmap.value("ball", "pose") == good and rmap.bad_values == {"hand": 1}
    assert rmap.bad_examples[0].startswith("hand's ball.pose = [0.5, 0.0, nan") and "not a finite number" in \
        rmap.bad_examples[0]
    assert rmap.set_output("obs", "grasped", float("nan")) is False and rmap.bad_values == {"hand": 1, "obs": 1}
    link.held[("hand", "ball", "pose")] = [float("nan")] * 7  # what hand releases
    assert ho.transfer("ball", "pose", "phys", "t")
    assert link.held[("phys", "ball", "pose")] == good  # physics was given the last good value, and it was said
    assert any("hand released ball.pose as no value (not a finite number)" in e for e in ho.record.errors)


def test_a_release_whose_velocity_is_no_value_hands_on_no_velocity():
    """A release's extra state was handed on unchecked: a NaN velocity beside a good pose (or beside a NaN pose,
    replaced by the last good one) made the body NaN in physics, frozen for the rest of the run. A part that is
    no value is now left out and said; the rest (None among it, the SPU's connected_to) goes on."""
    scene, link, registry, rmap, clock, ho = _setup()
    good = [0.5, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]
    nan = float("nan")
    for released in (good, [nan] * 7):
        rmap.set_owner("ball", "pose", "hand", 0, 0.0, "x", {})
        rmap.absorb_state("hand", {"ball": {"pose": good}})
        link.held[("hand", "ball", "pose")] = released
        link.extra["hand"] = {"velocity": [nan, nan, nan, 0, 0, 0], "connected_to": None, "spin": 2.0}
        ho.record.errors.clear()
        assert ho.transfer("ball", "pose", "phys", "drop")
        (acquired,) = [m for n, op, m in link.asked if op == "acquire" and n == "phys"][-1:]
        assert acquired["value"] == good
        # a release whose pose is no value gives nothing of its own; a good one all but its NaN velocity
        assert acquired["extra"] == ({} if released is not good else {"connected_to": None, "spin": 2.0}), acquired
        if released is good:
            assert any("hand released ball.pose with velocity as no value (not a finite number): it is not handed on"
                       in e for e in ho.record.errors), ho.record.errors


def test_a_publication_of_what_a_model_never_owned_is_unauthorized_not_late():
    """A clock-driven or free model's value of an attribute handed away from it may come after the release (it
    published before the release reached it): a late write, counted apart. One of an attribute it never owned was
    excused the same way and the run stayed complete; it is an unauthorized write, as in a step answer."""
    scene, link, registry, rmap, clock, ho = _setup()
    pose = [0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]
    rmap.set_owner("ball", "pose", "hand", 5, 0.05, "grab", {})
    rmap.set_owner("ball", "pose", "phys", 9, 0.09, "drop", {})
    rmap.absorb_state("hand", {"ball": {"pose": pose}}, stepped=False)  # it owned it until tick 9
    assert (rmap.late_writes, rmap.unauthorized_writes) == (1, 0)
    rmap.absorb_state("conn", {"ball": {"pose": pose}}, stepped=False)  # it never did
    assert (rmap.late_writes, rmap.unauthorized_writes, rmap.unauthorized_by) == (1, 1, {"conn": 1})
    rmap.absorb_state("hand", {"ball": {"pose": pose}})  # from a step answer: it knew it no longer owned it
    assert (rmap.late_writes, rmap.unauthorized_writes) == (1, 2)
