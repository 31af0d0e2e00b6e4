"""The agent runtime over the real protocol, driven by hand: every hook runs on the agent's main thread, a
repeated step broadcast or clock tick is answered again without stepping twice, a failed tick does not end a
batch, and query errors come back as data (the conductor-side view is in test_batch, test_malformed and
test_faults)."""
from __future__ import annotations

import queue
import time

import pytest

from conductor.launch import agent_command
from protocol import codec
from protocol.keys import Keys

ENSEMBLE = "runtime"
KEYS = Keys(ENSEMBLE)
SCENE = {"name": "runtime", "entities": {"ball": {"shape": {"type": "sphere", "radius": 0.03},
                                                  "pose": [0.5, 0.0, 0.3, 0, 0, 0, 1]}},
         "main": "m", "rate": 100.0, "robot": {}}


class Driver:
    """A hand-held conductor: answers registration, queries the agent, publishes steps, collects done/<id>."""

    def __init__(self, session, name: str):
        self.session, self.name = session, name
        self.desc: dict = {}
        self.registrations: queue.SimpleQueue = queue.SimpleQueue()
        self.done: queue.SimpleQueue = queue.SimpleQueue()
        self.decl = [session.declare_queryable(KEYS.register, self.registrations.put),
                     session.declare_subscriber(KEYS.done(name), self.done.put)]

    def accept(self, timeout: float = 30.0) -> dict:
        query = self.registrations.get(timeout=timeout)
        with query:
            desc = codec.decode("r", query.payload, "register")
            query.reply(query.key_expr, codec.encode("register_reply", id=desc.name, accepted=True))
        return desc

    def ask(self, op: str, payload: bytes, expect: str = "ack"):
        """The decoded answer, or ('error', Error message)."""
        for r in self.session.get(KEYS.model(self.name, op), payload=payload, timeout=10.0):
            if r.ok is not None:
                return codec.decode(op, r.ok.payload, expect)
            return "error", codec.decode(op, r.err.payload, "error")
        raise AssertionError(f"no answer to {op}")

    def start(self, step_mode: str, owned=()) -> None:
        self.ask("init", codec.encode("init", params={}, scene=SCENE, owned=[list(o) for o in owned], rate=100.0,
                                      step_mode=step_mode, models={self.name: "probe"}))
        self.ask("start", codec.encode("start", tick=0, t=0.0))

    def answer(self, timeout: float = 10.0) -> tuple[dict, bytes]:
        sample = self.done.get(timeout=timeout)
        data = sample.payload.to_bytes()
        return codec.decode_hot("done", sample.payload, "step_reply"), data

    def close(self) -> None:
        for d in self.decl:
            d.undeclare()


@pytest.fixture
def driver(router, procs):
    session, endpoint = router

    def spawn(kind: str, name: str = "m") -> Driver:
        d = Driver(session, name)
        procs.spawn(name, agent_command(kind, name, endpoint, ENSEMBLE))
        d.desc = d.accept()
        drivers.append(d)
        return d

    drivers: list[Driver] = []
    yield spawn
    for d in drivers:
        d.close()


def tick(k: int, name: str = "m", more=(), until=None, mark=None):
    body = {"tick": k, "t": k / 100, "joints": None, "models": {name: {"dt": 0.01, "actions": [], "inputs": {}}}}
    if more:
        body["more"] = [{**body, "tick": j, "t": j / 100} for j in more]
    if until is not None:
        body["until"] = until
    if mark is not None:
        body["mark"] = mark
    return codec.encode_unchecked("tick", body)


def test_every_hook_runs_on_the_main_thread(driver):
    """init, start, step, read, release, acquire and evaluators all run on the agent's main thread. A handover is
    told its time (``now``, the message's ``t``) beside the model's last step's ``t``."""
    d = driver("tests.models.probe:ThreadProbe")
    d.start("service", owned=[("ball", "pose")])
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["state"] == {"ball": {"pose": SCENE["entities"]["ball"]["pose"]}}
    where = {"entity": "ball", "attribute": "pose", "tick": 1, "t": 0.01}
    rel = d.ask("release", codec.encode("release", where), "release_reply")
    d.ask("acquire", codec.encode("acquire", where, value=rel.value, extra=rel.extra))
    threads = d.ask("eval/threads", codec.encode("eval", args=[], tick=1, t=0.01), "value_reply").value
    assert threads == ["MainThread"]
    times = d.ask("eval/handovers", codec.encode("eval", args=[], tick=1, t=0.01), "value_reply").value
    assert times == [["release", 0.0, 0.01], ["acquire", 0.0, 0.01]]


def test_what_a_run_raised_after_its_last_step_is_not_the_next_run_s(driver):
    """An event a model raised after its run's last step (a release's, as physics' signal binding raises
    grasp_unbound) went out with the first step of the next run on the same warm agent, where it could fire a
    trigger; a warm agent's new run now begins with nothing raised, as a fresh one does."""
    d = driver("tests.models.probe:ThreadProbe")
    d.start("service", owned=[("ball", "pose")])
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["events"] == []
    d.ask("release", codec.encode("release", entity="ball", attribute="pose", tick=1, t=0.01), "release_reply")
    d.ask("stop", codec.encode("stop"))
    d.start("service", owned=[("ball", "pose")])  # the next run, on the same process
    pub.put(tick(0))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["events"] == [] and rep["outputs"] == {"steps": 1}, rep


def test_a_step_whose_joint_state_does_not_hold_together_is_counted_not_stepped(driver):
    """A step whose joint positions were not a list raised a TypeError out of the check (not counted, the
    handler's last-resort catch), and one with three names and one position reached the models (an index out of
    range in one, the wrong values paired in another). Both are now malformed: counted, not stepped."""
    d = driver("tests.models.simple:Counter")
    d.start("service")
    pub = d.session.declare_publisher(KEYS.step_all)

    def with_joints(k: int, **joints) -> bytes:
        body = codec.unpack(tick(k))
        body["joints"] = {"stamp": 0.0, "name": ["j1"], "position": [0.1], "velocity": [], "effort": [], **joints}
        return codec.encode_unchecked("tick", body)

    pub.put(with_joints(0))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["tick"] == 0
    pub.put(with_joints(1, position=5))
    pub.put(with_joints(1, name=["j1", "j2", "j3"]))
    pub.put(with_joints(1, effort=[1.0, 2.0]))
    pub.put(with_joints(1))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["tick"] == 1
    assert d.ask("health", b"", "value_reply").value["malformed"] == 3


def test_a_step_that_comes_after_stop_is_not_stepped(driver):
    """A step message that came after the run's stop (a pipelined window, a forged one) was stepped: the model
    moved on after its run had ended. It is now not stepped nor answered, until the next start."""
    d = driver("tests.models.simple:Counter")
    d.start("service")
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["tick"] == 0
    d.ask("stop", codec.encode("stop"))
    pub.put(tick(1))
    with pytest.raises(queue.Empty):
        d.answer(timeout=1.5)
    d.start("service")
    pub.put(tick(1))
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["tick"] == 1


def test_repeated_broadcast_is_answered_without_stepping_twice(driver):
    """The same step message again gets the same answer and steps nothing; a batch with a failing tick is
    answered for every tick, the failed one with status error."""
    d = driver("tests.models.simple:Counter")
    assert d.ask("params", codec.encode("query"), "params_reply").params["bad_tick"]["default"] == -1
    d.ask("init", codec.encode("init", params={"bad_tick": 3}, scene=SCENE, owned=[], rate=100.0,
                               step_mode="service", models={"m": "counter"}))
    d.ask("start", codec.encode("start", tick=0, t=0.0))
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0))
    first, data = d.answer()
    assert first["outputs"] == {"count": 1}
    pub.put(tick(0))
    again, data_again = d.answer()
    assert data_again == data
    pub.put(tick(1, more=(2, 3, 4)))
    rep, _ = d.answer()
    reps = [rep, *rep["more"]]
    assert [r["tick"] for r in reps] == [1, 2, 3, 4]
    assert [r["status"] for r in reps] == ["ok", "ok", "error", "ok"]
    assert "TypeError" in reps[2]["message"]
    assert [r["outputs"].get("count") for r in reps] == [2, 3, None, 5]


def test_an_earlier_message_is_answered_again_after_a_later_one(driver):
    """The conductor may send the next window before the answer to this one is lost (flow.Pipeline): asked again
    for it, the agent answers what it answered, and steps nothing; and it goes on from where it was."""
    d = driver("tests.models.simple:Counter")
    d.start("service")
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0, more=(1,)))
    pub.put(tick(2, more=(3,)))
    first, data = d.answer()
    second, _ = d.answer()
    assert (first["tick"], second["tick"]) == (0, 2) and second["more"][0]["outputs"] == {"count": 4}
    pub.put(tick(0, more=(1,)))
    again, data_again = d.answer()
    assert data_again == data
    pub.put(tick(4))
    rep, _ = d.answer()
    assert rep["tick"] == 4 and rep["outputs"] == {"count": 5}
    assert d.ask("health", b"", "value_reply").value["malformed"] == 0


def test_step_messages_on_the_broadcast_and_addressed_keys_are_stepped_in_the_order_they_were_sent(driver):
    """A step message addressed to some models (``step/<ids>``) and the broadcast sent after it come on two
    subscriptions: each was queued by a thread of its own, and in a loaded CI the broadcast for tick 219 was stepped
    before the message for tick 187 sent earlier, which was then refused as out of sequence; its answer never
    came, and the run failed at the step timeout. Sent back to back, alternating, every tick is stepped in order."""
    d = driver("tests.models.simple:Counter")
    d.start("service")
    broadcast = d.session.declare_publisher(KEYS.step_all)
    addressed = d.session.declare_publisher(KEYS.step_to(["m"]))
    n = 400
    for k in range(n):
        (addressed if k % 2 else broadcast).put(tick(k))
    got = [d.answer()[0] for _ in range(n)]
    assert [r["tick"] for r in got] == list(range(n))
    assert [r["outputs"]["count"] for r in got] == list(range(1, n + 1))
    assert d.ask("health", b"", "value_reply").value["malformed"] == 0


def test_a_batch_stops_early_where_its_until_says(driver):
    """``tick.until``: the agent stops after the first tick that changes a named output (or raises a named
    event), answers the ticks it stepped with ``stopped``, and takes the rest in the next message; an until
    naming nothing that happens steps the whole batch; a malformed until is counted and not stepped."""
    d = driver("tests.models.simple:Counter")
    d.start("service")
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0, more=(1, 2, 3), until={"m": {"events": [], "outputs": ["count"]}}))
    rep, _ = d.answer()
    assert rep["tick"] == 0 and "more" not in rep and rep["stopped"] is True
    assert rep["outputs"] == {"count": 1}
    pub.put(tick(1, more=(2, 3), until={"m": {"events": ["nothing"], "outputs": ["other"]}}))
    rep, _ = d.answer()
    assert [rep["tick"], *(r["tick"] for r in rep["more"])] == [1, 2, 3] and "stopped" not in rep
    assert [r["outputs"]["count"] for r in (rep, *rep["more"])] == [2, 3, 4]
    pub.put(tick(4, more=(5,), until={"m": {"events": "all", "outputs": []}}))
    pub.put(tick(4, more=(5,)))
    rep, _ = d.answer()
    assert [rep["tick"], *(r["tick"] for r in rep["more"])] == [4, 5] and rep["outputs"]["count"] == 5
    assert d.ask("health", b"", "value_reply").value["malformed"] == 1


def test_a_marked_batch_can_be_stepped_back(driver):
    """``tick.mark``: a model that can (snapshot/restore, declared ``rewind``) keeps a checkpoint before the batch;
    ``model/<id>/rewind`` takes it back to any tick of it (its later ticks as if never stepped, nothing answered
    again), and the ticks after are stepped as they were the first time. Going back further, twice, or a model
    that cannot, is refused with the reason."""
    d = driver("tests.models.simple:RewindCounter")
    assert d.desc["rewind"] is True
    d.start("service")
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0, more=(1,)))
    assert d.answer()[0]["outputs"] == {"count": 1}
    pub.put(tick(2, more=(3, 4, 5), mark=["m"]))
    first, _ = d.answer()
    assert [r["outputs"]["count"] for r in (first, *first["more"])] == [3, 4, 5, 6]
    assert d.ask("rewind", codec.encode("rewind", tick=3)).ok is True
    pub.put(tick(4, more=(5, 6)))
    again, _ = d.answer()
    assert [r["outputs"]["count"] for r in (again, *again["more"])] == [5, 6, 7]  # ticks 4 and 5 as the first time
    kind, err = d.ask("rewind", codec.encode("rewind", tick=5))  # its checkpoint is used up
    assert kind == "error" and "cannot go back to tick 5" in err.message
    pub.put(tick(7, more=(8,), mark=["m"]))
    d.answer()
    pub.put(tick(9))  # a message not marked: the checkpoint before tick 7 is gone
    d.answer()
    kind, err = d.ask("rewind", codec.encode("rewind", tick=8))
    assert kind == "error" and "cannot go back" in err.message
    pub.put(tick(10, more=(11,), mark=["m"]))
    d.answer()
    kind, err = d.ask("rewind", codec.encode("rewind", tick=8))  # before the marked message
    assert kind == "error" and "cannot go back" in err.message
    assert d.ask("rewind", codec.encode("rewind", tick=9)).ok is True  # to just before it
    pub.put(tick(10))
    assert d.answer()[0]["outputs"] == {"count": 11}  # ticks 0 to 10, each once as it stands

    c = driver("tests.models.simple:Counter", "c")  # no snapshot/restore: a mark is not kept
    assert c.desc["rewind"] is False
    c.start("service")
    pub.put(tick(0, "c", more=(1,), mark=["c"]))
    c.answer()
    kind, err = c.ask("rewind", codec.encode("rewind", tick=0))
    assert kind == "error" and "cannot go back" in err.message


def test_a_marked_batch_publishes_only_the_ticks_that_stood(driver):
    """What a marked message's ticks publish on ``out``/``state``/``event`` is held back until it is known which of
    them stand: through the rewind's tick when the conductor sends the model back, all of them when it goes on (its
    next message) or the run stops; the message sent again (its answer lost) is answered again, its ticks still
    held. A subscriber sees each tick once, as it stood: never a tick that was undone."""
    from .conftest import wait_until

    d = driver("tests.models.simple:RewindCounter")
    d.start("service")
    seen: queue.SimpleQueue = queue.SimpleQueue()
    sub = d.session.declare_subscriber(KEYS.out("m", "count"), seen.put)
    got: list[tuple[int, int]] = []

    def until_tick(k: int) -> None:  # what came, up to (and with) tick k's
        def arrived() -> bool:
            while not seen.empty():
                m = codec.decode("out", seen.get().payload, "out")
                got.append((m.tick, m.value))
            return any(t == k for t, _ in got)
        assert wait_until(arrived, 30), f"no out/m/count of tick {k}: {got}"

    try:
        pub = d.session.declare_publisher(KEYS.step_all)
        for k in range(3):  # until the agent's publisher sees this subscriber (it publishes only then)
            pub.put(tick(k))
            d.answer()
            if not seen.empty():
                break
        until_tick(k)
        marked = tick(k + 1, more=(k + 2, k + 3, k + 4), mark=["m"])
        pub.put(marked)
        d.answer()
        pub.put(marked)  # again (its answer lost): answered again, its ticks still held
        d.answer()
        assert d.ask("rewind", codec.encode("rewind", tick=k + 2)).ok is True  # ticks k+3, k+4 undone
        pub.put(tick(k + 3, more=(k + 4,)))  # stepped again (not marked: published at once)
        d.answer()
        until_tick(k + 4)
        pub.put(tick(k + 5, more=(k + 6,), mark=["m"]))  # stood: the next message says so
        d.answer()
        pub.put(tick(k + 7))
        d.answer()
        until_tick(k + 7)
        pub.put(tick(k + 8, mark=["m"]))  # the run's last message: its stop says it stood
        d.answer()
        d.ask("stop", codec.encode("stop"))
        until_tick(k + 8)
    finally:
        sub.undeclare()
    ticks = [t for t, _ in got]
    assert ticks == list(range(ticks[0], k + 9)) and ticks[0] <= k, got  # each tick once, in order: none undone
    assert all(v == t + 1 for t, v in got), got  # as it stood (the count of ticks 0..t)


def test_repeated_clock_tick_is_answered_without_stepping(driver):
    """A clock-driven model answers each clock tick on done/<id>; a repeated or older tick is answered
    again and not stepped."""
    d = driver("tests.models.simple:GripSwitch")
    d.start("clock")
    pub = d.session.declare_publisher(KEYS.clock)
    for k in (0, 1, 1, 0, 2):
        pub.put(codec.encode("clock", tick=k, t=k / 100, dt=0.01))
    answers = [d.answer()[0]["tick"] for _ in range(5)]
    assert answers == [0, 1, 1, 1, 2]
    assert d.ask("eval/ticks", codec.encode("eval", args=[], tick=2, t=0.02), "value_reply").value == 3


def test_query_errors_come_back_as_data(driver):
    """A model's exception is an error reply with its type, message and traceback; a malformed request is
    a ProtocolError reply and is counted."""
    d = driver("tests.models.simple:Counter")
    kind, err = d.ask("init", codec.encode("init", params={"delay": "slow"}, scene=SCENE, owned=[], rate=100.0,
                                           step_mode="service", models={}))
    assert kind == "error" and err.kind == "TypeError" and "parameter 'delay' must be float" in err.message
    assert "Traceback" in err.traceback
    kind, err = d.ask("eval/nothing", codec.encode("eval", args=[], tick=0, t=0.0))
    assert kind == "error" and err.kind == "KeyError"
    kind, err = d.ask("start", b"\xc1")
    assert kind == "error" and err.kind == "ProtocolError" and "traceback" not in err
    health = d.ask("health", b"", "value_reply").value
    assert health["malformed"] == 1 and health["started"] is False


def test_a_bad_init_is_refused_before_the_model_is_touched_and_a_failed_one_does_not_poison_the_next(driver):
    """What a helper's review found on warm agents:
    - an init whose ``owned`` holds no pairs, sent during a run, closed the running model and was then refused: the
      run's next step was never answered (and it was not counted as malformed);
    - an unknown step mode was acked, and the agent never stepped; so was a start before any init;
    - an init that failed (a bad argument) left the agent 'initialized': every later init closed the model a second
      time, and a model that cannot be closed twice (pybullet's) failed every run after on that warm agent."""
    d = driver("tests.models.probe:Connected")
    kind, err = d.ask("start", codec.encode("start", tick=0, t=0.0))
    assert kind == "error" and err.kind == "ProtocolError" and "start before an init" in err.message
    d.start("service", owned=[("ball", "pose")])
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0))
    assert d.answer()[0]["status"] == "ok"
    for bad, said in (({"owned": [["ball", "pose", "x"]]}, "pairs"), ({"step_mode": "bogus"}, "step_mode"),
                      ({"owned": [["ball", "colour"]]}, "cannot own attribute 'colour'"),  # (acked, then every
                      ({"owned": [["ghost", "pose"]]}, "no entity 'ghost'")):  # step failed: a review's finding)
        body = {"params": {}, "scene": SCENE, "owned": [], "rate": 100.0, "step_mode": "service", "models": {}} | bad
        kind, err = d.ask("init", codec.encode("init", body))
        assert kind == "error" and err.kind == "ProtocolError" and said in err.message, err
    pub.put(tick(1))  # the run goes on: the model was not closed
    rep, _ = d.answer()
    assert rep["status"] == "ok" and rep["outputs"] == {"steps": 2}, rep
    assert d.ask("health", b"", "value_reply").value["malformed"] == 5  # (the start before init too)
    d.ask("stop", codec.encode("stop"))
    kind, err = d.ask("init", codec.encode("init", params={"fail": True}, scene=SCENE, owned=[], rate=100.0,
                                           step_mode="service", models={}))
    assert kind == "error" and err.kind == "ValueError" and "a bad argument" in err.message
    for _ in range(2):  # the runs after it on the same warm agent
        d.start("service", owned=[("ball", "pose")])
        pub.put(tick(0))
        rep, _ = d.answer()
        assert rep["status"] == "ok" and rep["outputs"] == {"steps": 1}, rep
        d.ask("stop", codec.encode("stop"))


def test_a_handover_the_model_cannot_take_is_refused_and_counted(driver):
    """An acquire of an entity the scene does not have was acked (and the entity reported in the model's state), one
    of a NaN pose too (the real physics put it in its world and reported it every step); a release of what the model
    does not own, and an acquire of an attribute it cannot own, were the model's KeyErrors, not counted as the
    malformed requests they are."""
    d = driver("tests.models.probe:ThreadProbe")
    d.start("service", owned=[("ball", "pose")])
    at = {"tick": 1, "t": 0.01}
    for op, body, said in [
        ("acquire", {"entity": "ghost", "attribute": "pose", "value": [0.0] * 6 + [1.0]}, "no entity 'ghost'"),
        ("acquire", {"entity": "ball", "attribute": "pose", "value": [float("nan")] * 3 + [0.0] * 3 + [1.0]},
         "ball.pose handed over as no value: not a finite number"),
        ("acquire", {"entity": "ball", "attribute": "colour", "value": 1.0}, "cannot own attribute 'colour'"),
        ("release", {"entity": "ghost", "attribute": "pose"}, "does not own ghost.pose"),
    ]:
        extra = {"extra": {}} if op == "acquire" else {}
        kind, err = d.ask(op, codec.encode(op, body | at | extra))
        assert kind == "error" and err.kind == "ProtocolError" and said in err.message, (op, err)
    assert d.ask("health", b"", "value_reply").value["malformed"] == 4
    pub = d.session.declare_publisher(KEYS.step_all)
    pub.put(tick(0))
    rep, _ = d.answer()
    assert rep["state"] == {"ball": {"pose": SCENE["entities"]["ball"]["pose"]}}, rep


def test_free_running_model_steps_at_its_rate_and_serves_calls(driver):
    """A free-running model steps on its own (its outputs go out on out/<id>/<name>) and answers a service
    call between its steps."""
    from .conftest import wait_until

    d = driver("tests.models.simple:Heartbeat")
    beats: queue.SimpleQueue = queue.SimpleQueue()
    sub = d.session.declare_subscriber(KEYS.out("m", "beats"), beats.put)
    try:
        d.ask("init", codec.encode("init", params={}, scene=SCENE, owned=[], rate=50.0, step_mode="free",
                                   models={"m": "heartbeat"}))
        d.ask("start", codec.encode("start", tick=0, t=0.0))
        assert wait_until(lambda: beats.qsize() >= 5, timeout=20)
        ticks = [codec.decode("b", beats.get().payload, "out").tick for _ in range(5)]
        assert ticks == list(range(5))
        assert d.ask("call/reset", codec.encode("call", args=[], kwargs={}, tick=0, t=0.0), "value_reply").value
    finally:
        sub.undeclare()


def test_an_agent_with_no_router_to_reach_ends_on_its_timeout_or_a_signal():
    """An agent whose router never answers waited for ever inside Zenoh's open, deaf to SIGTERM and to
    --register-timeout (only SIGKILL ended it): it now gives up after --register-timeout (exit 3, saying where
    it looked), and a SIGTERM ends its wait (exit 0)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from conductor.launch import free_port

    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [sys.executable, "-m", "agents", "tests.models.simple:Counter", "--name", "c", "--connect",
           f"tcp/127.0.0.1:{free_port()}"]
    r = subprocess.run([*cmd, "--register-timeout", "2"], capture_output=True, text=True, env=env, cwd=root,
                       timeout=60)
    assert r.returncode == 3 and "no Zenoh router answered at tcp/127.0.0.1:" in r.stderr, r.stderr
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=root)
    try:
        time.sleep(2.0)  # waiting for its router by now
        assert p.poll() is None
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=20) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_a_clock_driven_model_s_inputs_are_what_the_others_own(driver):
    """A clock-driven model gathers its inputs from the others' ``state`` messages. Those are what the others own,
    as a service-stepped model's are: a pose it acquired is not overwritten by the last owner's last message, and
    after it hands the pose on, its input is the value it handed on until the new owner speaks (it kept the
    previous owner's value from before it took the pose, and moved the ball back there)."""
    d = driver("tests.models.simple:BallSim")
    d.ask("init", codec.encode("init", params={"floor": -10.0}, scene=SCENE, owned=[], rate=100.0,
                               step_mode="clock", models={"m": "ballsim", "other": "ballsim"}))
    d.ask("start", codec.encode("start", tick=0, t=0.0))
    clock = d.session.declare_publisher(KEYS.clock)
    k = 0

    def step() -> None:
        nonlocal k
        clock.put(codec.encode("clock", tick=k, t=k / 100, dt=0.01))
        assert d.answer()[0]["tick"] == k
        k += 1

    def height() -> float:
        return d.ask("eval/height", codec.encode("eval", args=["ball"], tick=k, t=k / 100), "value_reply").value

    other = [0.5, 0.0, 5.0, 0, 0, 0, 1]
    for _ in range(20):  # until the agent's subscription hears the other's state
        d.session.put(KEYS.state("other"), codec.encode("state", model="other", tick=k, t=k / 100,
                                                        values={"ball": {"pose": other}}))
        time.sleep(0.05)
        step()
        if height() == 5.0:
            break
    assert height() == 5.0
    where = {"entity": "ball", "attribute": "pose", "tick": k, "t": k / 100}
    d.ask("acquire", codec.encode("acquire", where, value=[0.5, 0.0, 2.0, 0, 0, 0, 1], extra={"vz": 0.0}))
    for _ in range(5):
        step()
    assert 1.9 < height() < 2.0  # falling from 2 m where it was handed, not from the other's 5 m
    rel = d.ask("release", codec.encode("release", where), "release_reply")
    step()
    assert height() == rel.value[2]  # what it handed on, not the other's value from before it took the ball
