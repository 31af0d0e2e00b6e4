"""An owner that registers again while the conductor's network is down (its supervisor restarted it, or its link
came back): the conductor's handling of the agent events it kept through the outage, with the wire stood in for."""
from __future__ import annotations

from conductor.core import Conductor, RunOptions
from conductor.link import Liveliness, Registered
from conductor.registry import AgentInfo
from conductor.scene import parse_scene
from protocol.keys import Keys
from protocol.messages import Message

SCENE = """
name: outage
main: sim
models:
  sim: {kind: "tests.models.simple:BallSim", step: service}
  holder: {kind: "tests.models.simple:Holder", step: service}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5]}
"""

def _running(scene) -> Conductor:
    """A conductor of ``scene`` in a client's network mode, its agents registered and ready, the holder owning the
    ball: a run under way, its wire stood in for by each test."""
    c = Conductor(scene, None, Keys("outage"), None, RunOptions(network_mode="client", network_timeout=2.0))
    for name in scene.models:
        c.registry.agents[name] = AgentInfo(name, {"kind": name, "attributes": ["pose"], "pid": 100, "host": "h"},
                                            alive=True, ready=True)
    c.running = True
    c.map.set_owner("ball", "pose", "holder", 5, 0.05, "pick", {})
    return c


def test_an_owner_back_from_a_network_outage_gives_back_what_it_owned_before_it_is_initialised_anew():
    """A token's end while the network is down is no death, so it is dropped; the registration that follows is
    kept. The owner was then initialised owning nothing while the map still named it the ball's owner: nothing
    moved the ball to the end, and the run said complete. What it owned now falls back to the main model first
    (degraded, said), and it rejoins owning nothing."""
    scene = parse_scene(SCENE, "outage.yaml")
    c = _running(scene)
    inits: list[tuple[str, list]] = []
    asked: list[tuple[str, str]] = []
    cut = {"off": True}
    c._init_model = lambda name, owned, lost_wait=0.0: inits.append((name, list(owned)))  # type: ignore[method-assign]
    c.link.ask = lambda model, op, payload, expect, **kw: (asked.append((model, op)),  # type: ignore[method-assign]
                                                           Message({"type": "ack", "ok": True}))[1]
    c.link.publish = lambda key, payload: None  # type: ignore[method-assign]
    c.link.cut_off = lambda grace=0.0: cut["off"]  # type: ignore[method-assign]
    c.link.gone = lambda names: set()  # type: ignore[method-assign]

    c.link.inbox.put(Liveliness("holder", False))  # the network is down: the holder's end is no death ...
    c._agent_events()
    assert c.network.down and c.map.owner("ball", "pose") == "holder"
    c.link.inbox.put(Liveliness("holder", True))  # ... and a new holder registers before the network is back
    c.link.inbox.put(Registered("holder", {"kind": "holder", "attributes": ["pose"], "pid": 200, "host": "h"}))
    cut["off"] = False
    c._deferred += c.network.wait({"sim", "holder"}, True)
    c._agent_events()

    assert c.map.owner("ball", "pose") == "sim"
    assert [(h.trigger, h.src, h.dst) for h in c.map.handovers[1:]] == [("fallback:holder lost", "holder", "sim")]
    assert ("holder", []) in inits and ("holder", "start") in asked  # it rejoined, owning nothing
    assert any(r.startswith("model holder lost") and "registered again while the network was down" in r
               for r in c.record.degraded), c.record.degraded


def test_an_outage_no_step_waited_for_is_ended_and_a_later_death_is_a_death():
    """The conductor's network drops between a step's answers and its window's end (a token vanishes, so it is
    down) and is back before any step misses anyone: no step waited for it, so it stayed down, and every later
    death was taken for the network's: the holder died, kept the ball, and the run said nothing. The outage is now
    ended when the network is back (said), and the later death falls back as any death does."""
    scene = parse_scene(SCENE.replace("entities:", "  grip: {kind: \"tests.models.simple:GripSwitch\", step: clock}\n"
                                                   "entities:"), "outage.yaml")
    c = _running(scene)
    cut = {"off": True}
    dead: set[str] = set()
    c.link.ask = lambda *a, **kw: Message({"type": "ack", "ok": True})  # type: ignore[method-assign]
    c.link.publish = lambda key, payload: None  # type: ignore[method-assign]
    c.link.cut_off = lambda grace=0.0: cut["off"]  # type: ignore[method-assign]
    c.link.gone = lambda names: dead & set(names)  # type: ignore[method-assign]

    c.link.inbox.put(Liveliness("grip", False))
    c._agent_events()
    assert c.network.down
    cut["off"] = False  # the network is back, every token with it, before any step missed anyone
    c.link.inbox.put(Liveliness("grip", True))
    c._agent_events()
    assert not c.network.down
    assert any("lost its network" in n for n in c.record.notes), c.record.notes
    dead.add("holder")  # much later, the network fine, the holder really dies
    c.link.inbox.put(Liveliness("holder", False))
    c._agent_events()
    assert c.map.owner("ball", "pose") == "sim"
    assert any(r.startswith("model holder lost") for r in c.record.degraded), c.record.degraded
