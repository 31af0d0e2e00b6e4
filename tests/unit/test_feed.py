"""The feed alone: fetching a replay's telemetry ahead, in any chunks, enters the same joints and actions at the
same ticks as fetching each tick as it begins, republishes the same messages in the same order at the same
ticks, and ends the run at the same tick."""
from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from conductor.sources.feed import Feeder
from conductor.sources.recording import Recording
from conductor.sources.replay import ReplaySource
from protocol.joints import LatestJoints
from protocol.keys import Keys

DT = 0.01


class NoFit:
    def take(self, msg):
        return msg

    def finish(self):
        pass


def recording(stamps: list[tuple[float, bool]]) -> Recording:
    items = []
    for i, (t, action) in enumerate(sorted(stamps)):
        if action:
            items.append((t, "action", {"stamp": t, "name": f"a{i}", "phase": "start", "params": {}}))
        else:
            items.append((t, "joint_state", {"stamp": t, "name": ["j"], "position": [float(i)]}))
    return Recording(path="test.mcap", items=items)


def run(rec: Recording, lookahead: list[int], defer: bool = True) -> tuple[list, list]:
    """Tick through ``rec`` as the loop does; before each tick's window of ``lookahead[k]`` ticks is entered, its
    successors are fetched ahead (0: none). Returns what each tick entered and what was published."""
    published: list = []
    feed = Feeder(ReplaySource(rec), NoFit(), Keys("t"), lambda k, p: published.append((k, p)),
                  lambda: ["m"], ["m"], defer=defer)
    entered = []
    tick, k = 0, 0
    while not feed.exhausted(tick, DT) and tick < 10_000:
        n = max(1, lookahead[k % len(lookahead)]) if lookahead else 1
        window = range(tick, tick + n)
        for j in window:
            if feed.exhausted(j, DT) and j > tick:
                break
            actions = feed.enter(j, DT)
            # ... with what had been published by then: deferred, a tick's telemetry goes out when it is entered,
            # never before (a clock-driven model steps on the latest it got)
            entered.append((j, feed.latest, [a["name"] for a in actions], [a["name"] for a in feed.take_actions("m")],
                            len(published)))
            last = j
        if lookahead:
            feed.ahead(last + 1, last + lookahead[k % len(lookahead)], DT)
        tick, k = last + 1, k + 1
    return entered, published


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 1.0), st.booleans()), min_size=1, max_size=40),
       st.lists(st.integers(0, 12), min_size=1, max_size=5))
def test_fetching_ahead_enters_and_publishes_the_same(stamps, lookahead):
    rec = recording(stamps)
    assert run(rec, lookahead) == run(rec, [])
    # not deferred (no model steps on the bus's telemetry), the same goes out in the same order, only earlier
    entered, published = run(rec, lookahead, defer=False)
    at_its_tick, same = run(rec, [])
    assert [e[:4] for e in entered] == [e[:4] for e in at_its_tick] and published == same
    assert all(e[4] >= d[4] for e, d in zip(entered, at_its_tick))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.lists(st.sampled_from("abcd"), min_size=1, max_size=4, unique=True), st.booleans()),
                min_size=1, max_size=30))
def test_joint_states_naming_some_joints_merge_into_the_latest_of_every_joint(messages):
    """An arm's driver and a gripper's publishing apart on one topic: each message names some joints. The step
    broadcast took only the last message of a tick, so the arm never moved (a bag of such messages replayed as
    COMPLETE with the wrong answer). Merged, every joint heard has its latest value, and the efforts go with them
    while the latest message naming each joint gave its effort."""
    latest = LatestJoints()
    position: dict[str, float] = {}
    effort: dict[str, float | None] = {}
    for i, (names, with_effort) in enumerate(messages):
        msg = {"stamp": float(i), "name": names, "position": [i + 0.1 * k for k in range(len(names))],
               "velocity": [], "effort": [2.0 * i + k for k in range(len(names))] if with_effort else []}
        state = latest.take(msg)
        position.update(zip(names, msg["position"]))
        effort.update(zip(names, msg["effort"] or [None] * len(names)))
        assert state["stamp"] == float(i) and len(set(state["name"])) == len(state["name"])
        assert dict(zip(state["name"], state["position"], strict=True)) == position
        if all(e is not None for e in effort.values()):
            assert dict(zip(state["name"], state["effort"], strict=True)) == effort
        else:
            assert state["effort"] == []
        assert state["velocity"] == []
    assert list(state["name"]) == list(dict.fromkeys(n for names, _ in messages for n in names))  # a steady order


def test_a_split_joint_state_reaches_the_step_broadcast_whole():
    """Arm and gripper 1 us apart on one topic, in one tick: the tick's joints are the arm's and the gripper's."""
    items = []
    for i in range(5):
        t = i * DT
        items.append((t, "joint_state", {"stamp": t, "name": ["j1", "j2"], "position": [i, -i], "velocity": [],
                                         "effort": []}))
        items.append((t + 1e-6, "joint_state", {"stamp": t + 1e-6, "name": ["finger"], "position": [0.04],
                                                "velocity": [], "effort": []}))
    entered, _ = run(Recording(path="split.mcap", items=items), [])
    for _, latest, *_ in entered:
        assert latest["name"] == ["j1", "j2", "finger"], latest
