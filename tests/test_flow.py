"""Data-flow order (conductor/flow.py): which models lead, which scenes keep the batch rule, and where an agent
stops a batch (agents/runtime.py ``step_until``). That the windows it makes give every model exactly what one
message per tick gives it is shown with the real ensemble in test_batch."""
from __future__ import annotations

from pathlib import Path

import pytest

from agents.registry import resolve_kind
from agents.runtime import step_until
from conductor.flow import FlowScheduler, flow_roles, uncoupled
from conductor.registry import AgentInfo, Registry
from conductor.responsibility import Responsibilities
from conductor.scene import load_scene, parse_scene, reads_of
from conductor.stepping import batch_rule

ROOT = Path(__file__).resolve().parent.parent


def _declared(text: str, until: bool = True, rewind: bool = True):
    """A scene, the registry of its agents declaring what their model classes declare, and what each reads."""
    scene = parse_scene(text, "scene.yaml")
    registry = Registry(scene.models)
    for name, spec in scene.models.items():
        cls = resolve_kind(spec.kind)
        registry.agents[name] = AgentInfo(name, {"batch": True, "until": until, "reads": list(cls.reads),
                                                 "owner_events": list(cls.owner_events), "telemetry": True,
                                                 "rewind": rewind and cls.rewinds()})
    return scene, registry, reads_of(scene, {n: a.desc for n, a in registry.agents.items()})


def _roles(text: str, until: bool = True, rewind: bool = True):
    """The leads of a scene."""
    scene, registry, reads = _declared(text, until, rewind)
    return flow_roles(scene, registry, reads, batch_rule(scene, registry, reads, False))


BALL_DROP = (ROOT / "scenes" / "ball_drop.yaml").read_text()


def test_ball_drop_leads_with_the_grasp_monitor_then_in_hand():
    roles = _roles(BALL_DROP)
    assert roles is not None
    assert roles.free == ("grasp_monitor",)  # reads, owns and is given nothing; hand_free is asked at actions only
    assert roles.coupled == "in_hand"  # 'lost' fires a trigger while it owns the ball; grasp_lost takes it away
    assert roles.until == {"grasp_monitor": {"events": [], "outputs": ["grasped"]},
                           "in_hand": {"events": ["lost"], "outputs": []}}
    # the grasp trigger asks hand_free when the hand has closed: the monitor steps no further ahead than that
    assert roles.fences == (("move_hand", "end"),)
    assert roles.coupled_ahead  # no service trigger can take the ball from in_hand at the end of a window


HANDED = """name: handed
clock: {rate: 100}
main: sim
models:
  sim: {kind: "tests.models.simple:BallSim", step: service, rate: 100}
  fall: {kind: "tests.models.simple:BallSim", step: service, rate: 100}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5]}
triggers:
  - name: give
    on: {action: move_hand, phase: end}
    let: {who: "'fall'"}
    do:
      - transfer: {entity: ball, attribute: pose, to: who}
  - name: back
    on: {event: fall.landed}
    do:
      - transfer: {entity: ball, attribute: pose, to: sim}
"""


@pytest.mark.parametrize("how", ["a variable", "owned at the start", "named"])
def test_a_model_a_trigger_may_give_something_or_that_owns_something_is_no_free_lead(how):
    """A free lead steps up to four windows ahead: one that a trigger hands the ball to (here through a variable,
    which was taken for a model called 'who') or that owns it from the start (never looked at) had stepped past
    the tick it got or lost the ball at, and its answers for it were stale (the ball hung 128 ticks)."""
    text = {"a variable": HANDED,
            "owned at the start": HANDED.replace("pose: [0.5, 0, 0.5]}",
                                                 "pose: [0.5, 0, 0.5], attributes: {pose: fall}}").replace("to: who",
                                                                                                           "to: sim"),
            "named": HANDED.replace("to: who", "to: fall")}[how]
    roles = _roles(text)
    assert roles is None or "fall" not in roles.free, roles


def test_a_service_trigger_keeps_the_coupled_lead_from_stepping_ahead():
    """A client may fire a service trigger at the end of any window: in_hand must not have stepped past it."""
    text = BALL_DROP.replace("semantics:", """  - name: let_go
    on: {service: let_go}
    do:
      - transfer: {entity: "owned('in_hand')", attribute: pose, to: physics}
semantics:""", 1)
    roles = _roles(text)
    assert roles is not None and roles.coupled == "in_hand" and not roles.coupled_ahead


def test_insertion_leads_with_in_hand_then_the_connector_that_reads_it():
    """The connector reads the DIP's pose in_hand owns, and its events take that pose from in_hand: in_hand leads,
    the connector steps after it, given what it reported; in_hand, stepped past the connector's stop, goes back."""
    roles = _roles((ROOT / "scenes" / "insertion.yaml").read_text())
    assert roles is not None
    assert (roles.free, roles.coupled, roles.reader) == ((), "in_hand", "connector")
    assert roles.until["connector"] == {"events": ["enter_outer", "enter_inner", "leave_inner", "leave_outer"],
                                        "outputs": []}
    assert not roles.coupled_ahead  # it goes back only within the message the reader follows


@pytest.mark.parametrize("change,why", [
    # the connector reads the DIP pose in_hand owns, and its events take that pose away from in_hand: without a
    # way back, in_hand cannot step ahead of the connector's events
    ("rewind", "in_hand of another make, that cannot go back"),
    # an agent that cannot stop a batch early
    ("until", "an agent of another make"),
    # a trigger gives the grasp monitor something: it is coupled too, and two coupled leads have no order
    ("to: physics\n", "a trigger gives the grasp monitor the ball"),
    # its evaluator asked when its own output fires a trigger: it may not run ahead of that tick
    ("value == true and len(owned('in_hand')) == 0", "its evaluator asked by a topic trigger"),
    # the same, asked in a call effect's arguments (a list of expressions the planner did not look into)
    ("call", "its evaluator asked in a call's arguments by a topic trigger"),
])
def test_scenes_the_data_flow_order_cannot_serve_keep_the_batch_rule(change, why):
    if change == "rewind":
        assert _roles((ROOT / "scenes" / "insertion.yaml").read_text(), rewind=False) is None, why
    elif change == "until":
        assert _roles(BALL_DROP, until=False) is None, why
    elif change.startswith("to:"):
        text = BALL_DROP.replace("      - transfer: {entity: event.data.entity, attribute: pose, to: physics}",
                                 "      - transfer: {entity: event.data.entity, attribute: pose, to: grasp_monitor}")
        assert text != BALL_DROP
        assert _roles(text) is None, why
    elif change == "call":
        assert _roles(BALL_DROP) is not None  # (the scene as shipped: the grasp monitor leads)
        text = BALL_DROP.replace("semantics:", "  - name: poke\n    on: {topic: grasp_monitor.grasped}\n    do:\n"
                                 "      - call: {model: physics, service: poke, args: [\"hand_free('hand')\"]}\n"
                                 "semantics:")
        assert _roles(text) is None, why
    else:
        text = BALL_DROP.replace(change, change + " and not hand_free('hand')", 1)
        assert text != BALL_DROP
        assert _roles(text) is None, why


def test_the_shipped_scenes_lead_only_where_triggers_listen(tmp_path):
    """A scene without topic or event triggers keeps the batch rule (nothing to lead)."""
    base = load_scene(ROOT / "scenes" / "ball_drop_baseline1.yaml")
    assert not any("topic" in t.on or "event" in t.on for t in base.triggers)
    assert _roles((ROOT / "scenes" / "ball_drop_baseline1.yaml").read_text()) is None


class _Steps:
    """A model's step that reports the outputs and events it is given for each tick."""

    def __init__(self, script):
        self.script = script

    def __call__(self, tick, t, dt, telemetry, inputs):
        outputs, events = self.script[tick]
        return {"tick": tick, "outputs": outputs, "events": [{"name": e, "data": {}} for e in events]}, []


def _steps(ticks):
    return [(k, k / 100, 0.01, [], {}, None) for k in ticks]


def test_step_until_stops_after_a_change_or_an_event_and_remembers_across_messages():
    script = {0: ({"grasped": False}, []), 1: ({"grasped": False}, []), 2: ({"grasped": True}, []),
              3: ({"grasped": True}, []), 4: ({"grasped": True}, ["lost"]), 5: ({"grasped": True}, [])}
    step, seen = _Steps(script), {}
    until = {"events": ["lost"], "outputs": ["grasped"]}
    reps, _ = step_until(step, _steps([0, 1, 2, 3]), until, seen)
    assert [r["tick"] for r in reps] == [0]  # the first value is a change (nothing reported before)
    reps, _ = step_until(step, _steps([1, 2, 3]), until, seen)
    assert [r["tick"] for r in reps] == [1, 2]  # False again is no change; True is
    reps, _ = step_until(step, _steps([3, 4, 5]), until, seen)
    assert [r["tick"] for r in reps] == [3, 4]  # the event
    reps, _ = step_until(step, _steps([5]), None, seen)
    assert [r["tick"] for r in reps] == [5] and seen == {"grasped": True}


def test_step_until_notes_outputs_it_was_not_told_to_watch():
    """Steps without an until still count as reported: a later until judges changes from them."""
    script = {0: ({"grasped": False}, []), 1: ({"grasped": True}, []), 2: ({"grasped": True}, [])}
    step, seen = _Steps(script), {}
    step_until(step, _steps([0, 1]), None, seen)
    reps, _ = step_until(step, _steps([2]), {"events": [], "outputs": ["grasped"]}, seen)
    assert [r["tick"] for r in reps] == [2]  # True was reported at tick 1: no change, no stop (and no more ticks)
    assert seen == {"grasped": True}


@pytest.mark.parametrize("name,paced,expected", [
    ("ball_drop_baseline1", False, True),  # physics reads every pose, but owns them all: nothing can change them
    ("insertion_baseline1", False, True),
    ("fluid_bare", False, True),
    ("ball_drop_baseline1", True, False),  # paced: one tick per message, each when its time comes
    ("ball_drop", False, False),  # triggers move the ball between models
    ("fluid_split_50", False, False),  # physics reads every pose, and the fluid model owns the water's
])
def test_windows_go_out_one_ahead_only_where_no_answer_can_change_the_next_message(name, paced, expected):
    scene, registry, reads = _declared((ROOT / "scenes" / f"{name}.yaml").read_text())
    assert uncoupled(scene, Responsibilities(scene), reads, batch_rule(scene, registry, reads, paced)) is expected


MJ_GRASP = (ROOT / "scenes" / "ball_drop_mujoco_grasp.yaml").read_text()


def _tiers(text: str, holder: str | None = None):
    """The followers' tiers of a scene, with ``holder`` owning the ball's pose if given."""
    scene, registry, reads = _declared(text)
    roles = flow_roles(scene, registry, reads, batch_rule(scene, registry, reads, False))
    assert roles is not None
    rmap = Responsibilities(scene)
    if holder:
        rmap.set_owner("ball", "pose", holder, 0, 0.0, "test", {})
    service = {n: (1, True, bool(reads[n])) for n in scene.models}
    sched = FlowScheduler(roles, rmap, reads, None, None, service, None, None, None, [])  # type: ignore[arg-type]
    return sched._tiers({*roles.free, *([roles.coupled] if roles.coupled else [])})


def test_followers_step_in_the_order_their_values_flow_which_follows_who_owns_what():
    """MuJoCo's hand reads the ball's pose from physics until it holds the ball; physics reads it from the hand
    while it does. Each order lets a window of ticks go in one message per tier, not one per tick."""
    assert _tiers(MJ_GRASP) == [["physics"], ["hand"]]
    assert _tiers(MJ_GRASP, holder="hand") == [["hand"], ["physics"]]
    # the stand not declared static: while the hand holds the ball, each reads what the other owns and changes
    moving = MJ_GRASP.replace("pose: [0.45, -0.25, 0.05], tags: [static]", "pose: [0.45, -0.25, 0.05]")
    assert moving != MJ_GRASP
    assert _tiers(moving) == [["physics"], ["hand"]]
    assert _tiers(moving, holder="hand") == [["physics", "hand"]]
    assert _tiers(BALL_DROP) == [["physics"]]  # the others lead
