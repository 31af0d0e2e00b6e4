"""Malformed payloads on every key the conductor and an agent serve or subscribe to: no crash,
each one counted and logged."""
from __future__ import annotations

import os
import time
from pathlib import Path

import msgpack
import pytest

from conductor.core import Conductor, RunOptions
from conductor.scene import load_scene
from protocol import codec
from protocol.keys import Keys

from .conftest import spawn_agents, wait_until

HERE = Path(__file__).parent

PAYLOADS = {
    "random bytes": os.urandom(64) + b"\xc1",  # 0xc1 is never valid msgpack
    "wrong types": msgpack.packb({"v": 1, "type": "tick", "tick": "one", "t": [], "joints": 3, "models": "x"}),
    "wrong version": msgpack.packb({"v": 99, "type": "clock", "tick": 1, "t": 0.0, "dt": 0.01}),
    # a batch of ticks whose second tick goes back in time (nothing of it may be stepped)
    "bad tick batch": msgpack.packb({"v": 1, "type": "tick", "tick": 5, "t": 0.05, "joints": None,
                                     "models": {"sim": {"dt": 0.01, "actions": [], "inputs": {}}},
                                     "more": [{"tick": 4, "t": 0.04, "joints": None, "models": {}}]}),
    # a batched step answer whose later reply is not a step reply
    "bad reply batch": msgpack.packb({"v": 1, "type": "step_reply", "tick": 1, "status": "ok", "state": {},
                                      "outputs": {}, "events": [], "more": [{"tick": 2}]}),
}


def _ask(session, key, payload, timeout=3.0):
    oks, errs = 0, 0
    for r in session.get(key, payload=payload, timeout=timeout):
        if r.ok is not None:
            oks += 1
        else:
            errs += 1
    return oks, errs


@pytest.mark.slow
def test_malformed_messages_are_counted_not_fatal(router, client, procs, tmp_path):
    session, endpoint = router
    scene = load_scene(HERE / "core_scene.yaml")
    spawn_agents(procs, scene, endpoint)
    keys = Keys("default")
    c = Conductor(scene, session, keys, None, RunOptions(run_log=str(tmp_path / "run.mcap"), max_ticks=20))
    try:
        c.prepare()
        c.start()  # the clock-driven agent subscribes to clock, telemetry and state; the service one to the step
        time.sleep(1.0)  # (their subscriptions reach the router: 0.3 s was enough on a quiet machine)
        conductor_queries = [keys.register_as("sim"), keys.conductor("start"), keys.conductor("stop"),
                             keys.conductor("status")]
        # the conductor hears the clock-driven and free-running models' results (a service model's come in its
        # step answers on done/<id>); state/beat also reaches grip, which reads state/*
        subscribed = [keys.state("beat"), keys.out("beat", "beats"), keys.event("grip", "x"), keys.done("sim")]
        agent_grip_subs = [keys.clock, keys.telemetry("joint_states"), keys.state("sim")]
        sim_ops = ["params", "init", "start", "stop", "release", "acquire", "eval/height"]
        for name, bad in PAYLOADS.items():
            for k in conductor_queries:
                oks, errs = _ask(client, k, bad)
                assert errs == 1 and oks == 0, (k, name)
            for op in sim_ops:
                oks, errs = _ask(client, keys.model("sim", op), bad)
                assert errs == 1 and oks == 0, (op, name)
            for k in set(subscribed + agent_grip_subs + [keys.step_all]):
                client.put(k, bad)
        # a well-formed message naming another model than the key it came on (the key is what access control
        # vouches for: the free model beat's values credited to it from grip's key) is refused and counted
        client.put(keys.state("grip"), codec.encode("state", model="beat", tick=0, t=0.0,
                                                    values={"ball": {"pose": [9.0, 9.0, 9.0, 0.0, 0.0, 0.0, 1.0]}}))
        n = len(PAYLOADS)
        # conductor: 4 queryables + 4 subscriptions (state, out, event, done), and the message on the wrong key
        assert wait_until(lambda: c.link.malformed >= n * 8 + 1, timeout=20)
        time.sleep(0.2)
        assert c.link.malformed == n * 8 + 1, c.link.malformed_by_key
        assert c.link.malformed_by_key[keys.state("grip")] == 1
        assert not c.stop_requested.is_set()  # a malformed stop did not stop anything

        def health(model):
            for r in client.get(keys.model(model, "health"), timeout=3):
                if r.ok is not None:
                    return codec.decode("h", r.ok.payload, "value_reply").value

        assert wait_until(lambda: health("sim")["malformed"] == n * (len(sim_ops) + 1), timeout=20), health("sim")
        assert wait_until(lambda: health("grip")["malformed"] == n * (len(agent_grip_subs) + 1), timeout=20), \
            health("grip")
        # everyone is still alive and working: run the scene for a few ticks
        assert all(p.poll() is None for p in procs.procs.values())
        c.loop()
        assert c.record.stats("sim").steps == 20 and c.record.stats("sim").errors == 0
        s = c.finish()
        assert s["malformed_messages"] == n * 8 + 1
    finally:
        c.close()
