"""The step planner and the clock gate, alone.

The batch rule is correct when running a scene with batches gives every model exactly what one message per
tick gives it. The property test drives random ensembles (periods, reads, owners, topic triggers that move
responsibilities, action annotations) through the same window logic as the conductor's loop -- bodies built
for every tick of a window before any of its answers is taken in, answers taken in tick by tick, triggers
fired after each answer and action -- once with batches and once with one tick per message, and compares
every model's inputs at every tick, every handover and every final value.
"""
from __future__ import annotations

import threading
import time

from hypothesis import given, settings
from hypothesis import strategies as st

from conductor.record import RunRecord
from conductor.responsibility import Responsibilities
from conductor.scene import parse_scene
from conductor.stepping import (
    BatchRule,
    BroadcastStepper,
    ClockGate,
    TickPlan,
    step_deadline,
    tick_body,
    window_payload,
)

ENTITIES = ("a", "b", "c", "d")


@st.composite
def ensembles(draw):
    n = draw(st.integers(2, 4))
    models = [f"m{i}" for i in range(n)]
    period = {m: draw(st.sampled_from([1, 1, 2, 3])) for m in models}
    owner = {e: draw(st.sampled_from(models)) for e in ENTITIES}
    reads = {m: draw(st.lists(st.sampled_from([f"{e}.pose" for e in ENTITIES] + ["*.pose"]), max_size=2,
                              unique=True)) for m in models}
    # topic triggers: when model X's output turns True, entity E goes to model Y
    triggers = draw(st.lists(st.tuples(st.sampled_from(models), st.sampled_from(ENTITIES), st.sampled_from(models)),
                             max_size=2))
    actions = draw(st.lists(st.tuples(st.integers(0, 40), st.sampled_from(ENTITIES), st.sampled_from(models)),
                            max_size=3))
    return models, period, owner, reads, triggers, actions


def _scene(models, period, owner):
    lines = ["name: sim", "clock: {rate: 6}", f"main: {models[0]}", "models:"]
    lines += [f"  {m}: {{kind: k, rate: {6 / period[m]}}}" for m in models]
    lines += ["entities:"]
    lines += [f"  {e}: {{shape: {{type: sphere, radius: 0.1}}, pose: [0, 0, 0], attributes: {{pose: {owner[e]}}}}}"
              for e in ENTITIES]
    return parse_scene("\n".join(lines) + "\n", "<sim>")


def _simulate(ens, limit: int, ticks: int = 48):
    """Run the ensemble with windows of at most ``limit`` ticks; return the trace."""
    models, period, owner, reads, triggers, actions = ens
    scene = _scene(models, period, owner)
    rmap = Responsibilities(scene)
    for e in ENTITIES:
        rmap.values[(e, "pose")] = 0
    state = {m: 0 for m in models}  # each model's own running state
    sources = frozenset(x for x, _, _ in triggers)
    rule = BatchRule(limit, sources, tuple((m, period[m]) for m in models if reads[m]))
    sections = {m: (period[m], False, bool(reads[m])) for m in models}
    inputs, owners = {}, {}
    tick = 0
    while tick < ticks:
        read_owners = {m: rmap.owners_read_by(m, reads[m]) for m, _ in rule.readers}
        window, stepped, j = [], set(), tick
        while True:  # as Conductor._fill
            body, names = tick_body(j, j / 6, 1 / 6, sections, lambda m: True, lambda m: [],
                                    lambda m: rmap.inputs_for(m, reads[m]), None)
            acts = [(e, dst) for at, e, dst in actions if at == j]
            window.append(TickPlan(j, j / 6, body, names, acts))
            stepped.update(names)
            if j + 1 >= ticks or rule.ends_after(len(window), bool(acts), names, stepped, j + 1, read_owners):
                break
            j += 1
        msg = window_payload(window)  # one message: the first tick with a body, the later ones in 'more'
        bodies = [p.body for p in window if p.body is not None]
        assert (msg is None and not bodies) or [msg["tick"], *(b["tick"] for b in msg.get("more", []))] == \
            [b["tick"] for b in bodies]
        replies = {}
        for plan in window:  # every model steps its ticks of the message in order
            for m in plan.names:
                sec = plan.body["models"].get(m) or plan.body["shared"]
                state[m] = hash((state[m], plan.tick, repr(sorted(sec["inputs"].items())))) % 997
                inputs[(plan.tick, m)] = repr(sorted(sec["inputs"].items()))
                replies[(plan.tick, m)] = {e: state[m] + i for i, (e, a) in enumerate(rmap.owned_by(m))}
        for plan in window:  # as Conductor._take
            for m in models:
                if (plan.tick, m) not in replies:
                    continue
                mine = {e: v for e, v in replies[(plan.tick, m)].items() if rmap.owner(e, "pose") == m}
                rmap.absorb_state(m, {e: {"pose": v} for e, v in mine.items()})
                if rmap.set_output(m, "o", state[m] % 3 == 0) and state[m] % 3 == 0:
                    for src, e, dst in triggers:
                        if src == m and rmap.owner(e, "pose") != dst:
                            rmap.set_owner(e, "pose", dst, plan.tick, plan.t, "topic", {})
            for e, dst in plan.actions:
                if rmap.owner(e, "pose") != dst:
                    rmap.set_owner(e, "pose", dst, plan.tick, plan.t, "action", {})
            owners[plan.tick] = dict(rmap.owners)
        tick = window[-1].tick + 1
    return inputs, owners, [h.as_dict() for h in rmap.handovers], dict(rmap.values)


@settings(max_examples=250, deadline=None)
@given(ens=ensembles(), limit=st.integers(2, 12))
def test_batches_give_every_model_what_one_tick_per_message_gives(ens, limit):
    batched, one = _simulate(ens, limit), _simulate(ens, 1)
    assert batched == one


def test_a_window_ends_where_something_could_change():
    rule = BatchRule(8, frozenset({"mon"}), (("reader", 2),))
    owners = {"reader": {"phys"}}
    assert not rule.ends_after(1, False, ["phys"], {"phys"}, 1, owners)  # reader not due on tick 1
    assert rule.ends_after(1, False, ["phys"], {"phys"}, 2, owners)  # due on 2, its owner stepped
    assert rule.ends_after(1, True, [], set(), 1, owners)  # an action is due
    assert rule.ends_after(1, False, ["mon"], {"mon"}, 1, owners)  # a trigger source stepped
    assert rule.ends_after(8, False, [], set(), 1, owners)  # the limit
    assert not rule.ends_after(3, False, ["x"], {"x"}, 2, owners)


def _answer(tick, *more):
    return {"tick": tick, "more": [{"tick": j} for j in more]}


def test_an_answer_to_the_next_message_waits_for_its_collect():
    """Two models, the next window already out (flow.Pipeline): a's answer to it comes before b's answer to this
    one. It is kept for the next collect, not taken for this one; a late answer to an older message is dropped."""
    scene = parse_scene("name: s\nmodels:\n  a: {kind: k}\n  b: {kind: k}\n", "<s>")
    stepper = BroadcastStepper(RunRecord(scene), step_timeout=1.0)
    nobody_gone = lambda names: set()  # noqa: E731
    stepper.put("a", _answer(0, 1))
    stepper.put("a", _answer(2, 3))
    stepper.put("b", _answer(0, 1))
    got: dict = {}
    assert stepper.collect({"a": [0, 1], "b": [0, 1]}, got, nobody_gone) == set()
    assert {m: sorted(r) for m, r in got.items()} == {"a": [0, 1], "b": [0, 1]}
    stepper.put("a", _answer(0, 1))  # the same answer again, late
    stepper.put("b", _answer(2, 3))
    got = {}
    assert stepper.collect({"a": [2, 3], "b": [2, 3]}, got, nobody_gone) == set()
    assert {m: sorted(r) for m, r in got.items()} == {"a": [2, 3], "b": [2, 3]}
    assert not stepper.timed_out  # a's was kept: had it been dropped, a would have timed out


def test_a_flood_of_answers_to_later_messages_is_bounded_per_model_and_crowds_out_no_one():
    """Answers to ticks never sent were all kept for later, without bound (a model, or someone with its keys,
    flooding them grew the conductor's memory for the whole run). A model now keeps at most a pipeline's few; the
    rest are left out and a problem of that model, said once; another model's answer to the next message is
    still kept."""
    from conductor.stepping import LATER_PER_MODEL

    scene = parse_scene("name: s\nmodels:\n  a: {kind: k}\n  b: {kind: k}\n", "<s>")
    record = RunRecord(scene)
    stepper = BroadcastStepper(record, step_timeout=1.0)
    nobody_gone = lambda names: set()  # noqa: E731
    for k in range(5000):
        stepper.put("a", _answer(10_000 + k, 10_001 + k))
    stepper.put("a", _answer(0, 1))
    stepper.put("b", _answer(2, 3))  # the pipeline's next answer, after the flood
    stepper.put("b", _answer(0, 1))
    got: dict = {}
    assert stepper.collect({"a": [0, 1], "b": [0, 1]}, got, nobody_gone) == set()
    assert len(stepper._later) <= LATER_PER_MODEL + 1
    assert record.stats("a").errors == 1 and "were never sent" in record.stats("a").last_error
    assert record.stats("b").errors == 0
    stepper.put("a", _answer(2, 3))
    got = {}
    assert stepper.collect({"a": [2, 3], "b": [2, 3]}, got, nobody_gone) == set()
    assert sorted(got["b"]) == [2, 3] and not stepper.timed_out


def test_a_batched_step_gives_a_second_a_tick_not_the_whole_timeout_again():
    """A hung model of a 32-tick window held the run for 32 step timeouts (320 s): each tick after the first now
    adds at most 1 s (and never more than the step timeout, so a test's short timeouts keep their meaning)."""
    assert step_deadline(10.0, 1) == 10.0 and step_deadline(10.0, 32) == 41.0 and step_deadline(10.0, 0) == 10.0
    assert step_deadline(0.2, 8) == 0.2 * 8


def test_tick_body_shares_one_section_among_plain_models():
    sections = {"phys": (1, True, True), "a": (1, False, False), "b": (1, False, False), "slow": (2, False, False)}
    body, names = tick_body(3, 0.03, 0.01, sections, lambda m: True, lambda m: [{"op": m}], lambda m: {"x": {}},
                            {"name": []})
    assert names == ("phys", "a", "b") and body["due"] == ["a", "b"] and body["joints"] == {"name": []}
    assert body["models"] == {"phys": {"dt": 0.01, "actions": [{"op": "phys"}], "inputs": {"x": {}}}}
    assert tick_body(3, 0.03, 0.01, {"slow": (2, False, False)}, lambda m: True, list, dict, None) == (None, ())


# ------------------------------------------------------------------------------------------ clock gate
def _gate(timeout=0.3, gone=lambda names: set()):
    rec = RunRecord(parse_scene("name: g\nmodels:\n  m: {kind: k, step: clock}\n", "<g>"))
    nudges = []
    gate = ClockGate(frozenset({"m"}), rec, timeout, nudges.append, lambda: False, slack=2, waitable=lambda m: True,
                     stop=threading.Event(), gone=gone)
    return gate, rec, nudges


def test_clock_gate_waits_for_a_model_within_its_slack():
    """Tick 10 with slack 2 goes out once the model has answered tick 7; the wait ends when the answer comes."""
    gate, rec, _ = _gate(timeout=5.0)
    gate._sent = 9  # (ticks 0-9 went out: an answer to a tick never sent is none)
    gate.note("m", 5)
    threading.Timer(0.2, lambda: (gate.note("m", 6), gate.note("m", 7))).start()
    t0 = time.monotonic()
    gate.wait(10, 2)
    assert 0.1 < time.monotonic() - t0 < 4
    assert rec.stats("m").clock["max_lag_ticks"] == 2 and rec.stats("m").clock["waited_s"] > 0.1
    assert rec.errors == []


def test_an_answer_to_a_clock_tick_never_sent_is_left_out_and_said():
    """A clock-driven model's answer for a tick far ahead of the clock (stale from another run, forged) was taken:
    the model seemed ahead for the rest of the run, never waited for, its real answers no news. It is left out,
    a problem of that model (said once), and the gate still waits for its real answers."""
    gate, rec, _ = _gate(timeout=5.0)
    gate.send(0, 0.0, 0.01)
    assert gate.note("m", 0) is True
    assert gate.note("m", 1_000_000) is False and gate.note("m", 2_000_000) is False
    assert gate.done["m"] == 0
    gate.send(1, 0.01, 0.01)
    threading.Timer(0.2, lambda: gate.note("m", 1)).start()
    t0 = time.monotonic()
    gate.wait(4, 2)  # (waits for tick 1's answer: the far one did not count)
    assert time.monotonic() - t0 > 0.1 and gate.done["m"] == 1
    assert len(rec.errors) == 1 and "answered clock tick 1000000, which was never sent" in rec.errors[0]
    assert rec.stats("m").errors == 1


def test_clock_gate_gives_up_on_a_model_that_does_not_catch_up():
    """After the step timeout the model is a problem of the run, nudged meanwhile, and not waited for again."""
    gate, rec, nudges = _gate(timeout=0.6)
    gate._sent = 3  # (ticks 0-3 went out)
    gate.note("m", 2)
    gate.send(4, 0.04, 0.01)  # within its slack of 2: sent at once
    gate.wait(6, 1)
    assert "m" in gate.behind and len(nudges) == 2 and nudges[0] == nudges[1]
    assert len(rec.errors) == 1 and "clock ticks unanswered" in rec.errors[0]
    t0 = time.monotonic()
    gate.wait(7, 1)  # not waited for again
    assert time.monotonic() - t0 < 0.3 and rec.stats("m").clock["max_lag_ticks"] == 4
    gate.note("m", 6)
    gate.wait(7, 1)
    assert "m" not in gate.behind  # caught up by itself


def test_a_clock_driven_model_is_not_taken_for_hung_after_the_conductor_itself_paused():
    """Where nothing waits (live), silence was counted from the model's last answer: after the conductor itself
    paused longer than the step timeout (its network gone, a rejoin) and then sent its ticks back to back, a
    healthy model that had not yet answered the tick sent a moment before was said to have hung. It is counted
    from when the tick it owes went out; a model that owes a tick sent long ago is still said."""
    gate, rec, _ = _gate(timeout=0.5)
    gate.slack = None
    for k in range(6):
        gate.send(k, k / 100, 0.01)
        gate.note("m", k)
    time.sleep(0.7)  # the conductor pauses (the model has answered everything)
    gate.send(6, 0.06, 0.01)
    gate.send(7, 0.07, 0.01)  # tick 6 went out a moment ago: not yet answered, not hung
    assert rec.errors == [], rec.errors
    time.sleep(0.7)  # now it owes tick 6 for longer than the step timeout
    gate.send(8, 0.08, 0.01)
    assert len(rec.errors) == 1 and "answered no clock tick for" in rec.errors[0], rec.errors


def test_clock_gate_does_not_wait_live_or_for_the_dead():
    gate, rec, _ = _gate(timeout=5.0)
    t0 = time.monotonic()
    gate.wait(50, None)  # live: only reports the lag
    dead, _, _ = _gate(timeout=5.0, gone=lambda names: set(names))
    dead.wait(51, 0)  # its token is gone
    rec = dead.record if dead.record.models else rec
    assert time.monotonic() - t0 < 1 and gate.record.stats("m").clock["max_lag_ticks"] == 50
    assert dead.record.stats("m").clock["max_lag_ticks"] == 51


def test_a_live_run_counts_its_pace_from_the_robot_s_first_message():
    """A robot already publishing when the twin began (its agents took seconds to start): tick 0 was paced from the
    loop's start, so the twin stayed those seconds behind the robot to the end of the run. Its pace now counts from
    when the first message came: what waited is caught up as fast as the models allow. A replay is unchanged."""
    from types import SimpleNamespace

    from conductor.stepping import Pacer

    def conductor(live: bool) -> SimpleNamespace:
        return SimpleNamespace(clock=SimpleNamespace(dt=0.01), opts=SimpleNamespace(rtf=None if live else 1.0),
                               _live=lambda: live, progress=None, record=None,
                               source=SimpleNamespace(first_arrival=time.monotonic() - 3.0, duration=None))

    live = Pacer.of(conductor(True))
    assert time.perf_counter() - live.start >= 3.0
    done = threading.Event()
    worker = threading.Thread(target=lambda: (live.after(250), done.set()), daemon=True)  # 2.5 s of ticks: behind
    worker.start()
    assert done.wait(2.0), "a live run behind its robot waited for the wall clock"
    replay = Pacer.of(conductor(False))
    assert time.perf_counter() - replay.start < 1.0


def test_a_deadline_longer_than_a_timer_can_wait_is_none():
    """--deadline 1e10 passes as a positive number, but a timer that long fails in its own thread (a traceback, and
    the run went on without one): it is taken as no deadline (292 years). A short one stops with its reason."""
    import threading

    from conductor.stepping import deadline_timer

    said: list[str] = []
    assert deadline_timer(1e10, said.append) is None and deadline_timer(None, said.append) is None
    timer = deadline_timer(0.05, said.append)
    assert isinstance(timer, threading.Timer)
    timer.join(timeout=30)
    assert said == ["its deadline of 0.05 s"]
