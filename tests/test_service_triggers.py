"""Triggers fired by service calls (the paper's §3.3: "activated by service calls or by topic values"): a client
calls ``conductor/trigger/<name>`` during a live run; the conductor fires the scene's ``on: {service: name}``
triggers between two ticks and answers with what they did, or refuses with the reason."""
from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from conductor.core import Conductor, RunOptions
from conductor.scene import parse_scene
from conductor.sources.recording import load_recording
from conductor.sources.replay import ReplaySource
from protocol import codec
from protocol.errors import SceneError
from protocol.keys import Keys
from recordings.simple import core_recording

from .conftest import spawn_agents, wait_until

SCENE = """\
name: service_demo
clock: {rate: 100}
main: sim
models:
  sim: {kind: "tests.models.simple:BallSim", step: service, rate: 100}
  holder: {kind: "tests.models.simple:Holder", step: service, rate: 50, args: {hold_z: 0.8}}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5]}
  bin: {shape: {type: container, style: bin}, pose: [0.5, 0, 0]}
triggers:
  - name: operator_hold
    on: {service: hold, args: [target]}
    when: "owner(target, 'pose') == 'sim'"
    do:
      - transfer: {entity: target, attribute: pose, to: holder}
  - name: hold_lowest
    on: {service: hold_lowest}
    do:
      - call: {model: sim, service: lowest, as: low}
      - transfer: {entity: low, attribute: pose, to: holder}
"""


def call(session, ensemble: str, name: str, args: dict | None = None, timeout: float = 10.0, selector: str = ""):
    """('ok', value) or ('refused', reason), as an outside client sees the answer ('timeout': none in time)."""
    key = Keys(ensemble).conductor(f"trigger/{name}")
    for reply in session.get(key + selector, payload=codec.encode("control", args=args or {}), timeout=timeout):
        if reply.ok is not None:
            return "ok", codec.decode(key, reply.ok.payload, "value_reply").value
        if reply.err.payload.to_bytes() == codec.ZENOH_TIMEOUT:
            return "timeout", None
        return "refused", codec.decode(key, reply.err.payload, "error").message
    return "silent", None


def stalled_call(client, procs, ensemble: str, name: str, args: dict) -> tuple:
    """A call made (waiting 1.5 s, and saying so in the selector) while the main model is paused, so that the run
    cannot take it in time; the model goes on 2.1 s after it was paused, by a timer, however late the call returns
    on a loaded machine: well within the link's 3 s lease, which a pause of 2.8 s came within a keep-alive of."""
    sim = procs.procs["sim"].pid
    os.kill(sim, signal.SIGSTOP)
    resume = threading.Timer(2.1, os.kill, (sim, signal.SIGCONT))
    resume.start()
    try:
        time.sleep(0.3)  # (the tick loop now waits for sim's answer)
        return call(client, ensemble, name, args, timeout=1.5, selector="?timeout=1.5")
    finally:
        resume.join(timeout=10)
        os.kill(sim, signal.SIGCONT)  # (sent already by the timer, unless it failed)


@pytest.mark.slow
def test_a_client_fires_service_triggers_during_a_live_run(router, procs, client, tmp_path):
    session, endpoint = router
    scene = parse_scene(SCENE, "service_demo.yaml")
    rec = load_recording(core_recording(tmp_path / "rec.mcap", seconds=20.0))
    spawn_agents(procs, scene, endpoint, "svcdemo")
    c = Conductor(scene, session, Keys("svcdemo"), ReplaySource(rec),
                  RunOptions(rtf=1.0, register_timeout=60, run_log=str(tmp_path / "run.mcap")))
    out: dict = {}
    t = threading.Thread(target=lambda: out.setdefault("summary", c.run()), daemon=True)
    t.start()
    try:
        assert wait_until(lambda: c.running and c.clock.tick > 20, timeout=60)
        answers = {
            # taken by the run only after its caller stopped waiting (told nothing answered): never fired
            "stalled": stalled_call(client, procs, "svcdemo", "hold", {"target": "ball"}),
            "with --run": call(client, "svcdemo", "hold", {"target": "ball"}, selector="?run=3"),
            # arguments of a type the precondition cannot take: refused, the run goes on, not degraded
            "a list": call(client, "svcdemo", "hold", {"target": ["ball"]}),
            "a map": call(client, "svcdemo", "hold", {"target": {"a": 1}}),
            "missing": call(client, "svcdemo", "hold"),
            "unknown": call(client, "svcdemo", "nope"),
            "hold": call(client, "svcdemo", "hold", {"target": "ball"}),
            "again": call(client, "svcdemo", "hold", {"target": "ball"}),
            "misspelt": call(client, "svcdemo", "hold", {"target": "bal"}),
            "lowest": call(client, "svcdemo", "hold_lowest"),
        }
    finally:
        c.stop("the test")
        t.join(timeout=60)
        try:  # the run is over, its conductor still answers: a call now is told so
            answers["after"] = call(client, "svcdemo", "hold", {"target": "ball"})
        finally:
            c.close()
    assert answers["after"][0] == "refused" and answers["after"][1].startswith("the run has ended"), answers["after"]
    assert answers["stalled"] == ("timeout", None)
    assert answers["with --run"][0] == "refused" and "not a twin serve" in answers["with --run"][1]
    for bad in ("a list", "a map"):
        kind, why = answers[bad]
        assert kind == "refused" and why.startswith("operator_hold: cannot be evaluated with the arguments given: "
                                                    "owner("), answers[bad]
    assert answers["missing"] == ("refused", "operator_hold: missing arguments: target")
    assert answers["unknown"][0] == "refused" and "listens to service 'nope'" in answers["unknown"][1]
    assert "hold" in answers["unknown"][1] and "hold_lowest" in answers["unknown"][1]
    kind, (done,) = answers["hold"]
    assert kind == "ok" and done["fired"] is True and done["variables"] == {"target": "ball"}
    assert done["effects"] == [{"transfer": "pose of ball to holder", "moved": ["ball"]}]
    # now the ball is the holder's: the precondition fails, and the call is refused with it
    assert answers["again"] == ("refused", "operator_hold: precondition false: owner(target, 'pose') == 'sim' "
                                           "(with target='ball')")
    assert answers["misspelt"] == ("refused", "operator_hold: precondition false: owner(target, 'pose') == 'sim' "
                                              "(with target='bal', which is no entity or model of the scene)")
    kind, (done,) = answers["lowest"]
    assert kind == "ok" and done["effects"][0] == {"call": "sim.lowest", "value": "bin"}  # bound to 'low'
    assert done["effects"][1] == {"transfer": "pose of bin to holder", "moved": ["bin"]}
    s = out["summary"]
    moved = [(h["entity"], h["to"], h["trigger"]) for h in s["handovers"]]
    assert moved == [("ball", "holder", "operator_hold"), ("bin", "holder", "hold_lowest")]
    assert s["final_ownership"] == {"ball.pose": "holder", "bin.pose": "holder"}
    assert all(h["t"] > 0.2 for h in s["handovers"])  # fired between ticks of the running replay
    assert s["status"] == "truncated" and len(s["status_reasons"]) == 1, s["status_reasons"]  # (stopped, no more)


@pytest.mark.parametrize("trigger, problem", [
    ("{name: a, on: {service: 'bad/name'}, do: [{transfer: {entity: ball, to: holder}}]}", "invalid service name"),
    ("{name: a, on: {service: x, args: [ball]}, do: [{transfer: {entity: ball, to: holder}}]}", "shadows"),
    ("{name: a, on: {service: x, args: 3}, do: [{transfer: {entity: ball, to: holder}}]}", "list of names"),
    ("{name: a, on: {service: x, when: 1}, do: [{transfer: {entity: ball, to: holder}}]}", "unknown key 'when'"),
    ("{name: a, on: {service: x}, do: [{call: {model: sim, service: s, as: ball}}]}", "bound already"),
    ("{name: a, on: {service: x}, do: [{transfer: {entity: low, to: holder}}, {call: {model: sim, service: s, "
     "as: low}}]}", "low"),  # a result is bound only for the effects after its call
])
def test_service_trigger_and_call_binding_are_checked(trigger, problem):
    text = SCENE.split("triggers:")[0] + f"triggers:\n  - {trigger}\n"
    with pytest.raises(SceneError) as e:
        parse_scene(text, "s.yaml")
    assert problem in str(e.value), str(e.value)
    assert "s.yaml:" in str(e.value)


def test_the_demo_scene_is_valid():
    scene = parse_scene(SCENE, "service_demo.yaml")
    assert [t.on for t in scene.triggers] == [{"service": "hold", "args": ["target"]}, {"service": "hold_lowest"}]
    assert scene.triggers[1].do[0].fields["as"] == "low"
