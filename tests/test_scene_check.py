"""The scene checker: every problem of a scene at once, with its line; what a broken part hides; the
``robot:`` block; the checks against what the agents declare (plain register dicts, no processes); what
each model reads; and a checked scene that stays as it was returned."""
from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Any

import pytest

from conductor.scene import check_against_agents, load_scene, parse_scene, reads_of
from protocol.errors import SceneError


def problems_of(text: str) -> list[str]:
    with pytest.raises(SceneError) as e:
        parse_scene(text, "x.yaml")
    return [str(p) for p in e.value.problems]


# ------------------------------------------------------------------------------- every problem at once
SEVERAL = """\
name: several
clock: {rate: 120}
models:
  sim: {kind: ballsim, stepp: service, rate: 120}
  gm: {kind: gripswitch, rate: -15}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0]}
triggers:
  - name: t
    on: {action: move_hand}
    do:
      - transfer: {entity: ball, to: nowhere}
"""


def test_a_broken_scene_reports_every_problem_with_its_line():
    with pytest.raises(SceneError) as e:
        parse_scene(SEVERAL, "x.yaml")
    assert [str(p) for p in e.value.problems] == [
        "x.yaml:4: models.sim.stepp: unknown key 'stepp' (allowed: args, doc, kind, rate, reads, step)",
        "x.yaml:5: models.gm.rate: bad rate -15: must be a positive number of Hz",
        "x.yaml:7: entities.ball.pose: pose must be [x, y, z] or [x, y, z, qx, qy, qz, qw] (numbers)",
        "x.yaml:12: triggers[0].do[0].transfer.to: unknown model 'nowhere'",
    ]
    assert str(e.value).startswith("4 problems:\n  x.yaml:4: models.sim.stepp: unknown key")
    # the first problem is also the error's own file, line and key
    assert (e.value.file, e.value.line, e.value.key) == ("x.yaml", 4, "models.sim.stepp")


def test_one_problem_reads_as_before():
    with pytest.raises(SceneError) as e:
        parse_scene("models:\n  sim: {kind: ballsim, rate: 0}\n", "x.yaml")
    assert str(e.value) == "x.yaml:2: models.sim.rate: bad rate 0: must be a positive number of Hz"


def test_a_broken_models_map_hides_what_refers_to_models():
    text = """\
main: sim
models: [sim]
entities:
  ball: {shape: {type: sphere, radius: 0.03}, attributes: {pose: sim}}
evaluators:
  height: {model: sim}
triggers:
  - {on: {topic: sim.height}, do: [{transfer: {entity: ball, to: sim}}, {call: {model: sim, service: s}}]}
semantics:
  up: "height(ball) > 0 and owner(ball) == sim"
"""
    assert problems_of(text) == ["x.yaml:2: models: a scene needs a 'models' map with at least one model"]


def test_a_model_with_a_problem_is_still_a_model():
    text = """\
models:
  sim: {kind: ballsim, rate: fast}
  gm: {kind: gripswitch}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, attributes: {pose: sim}}
triggers:
  - {on: {event: sim.hit}, do: [{transfer: {entity: ball, to: sim}}]}
"""
    assert problems_of(text) == ["x.yaml:2: models.sim.rate: bad rate 'fast': must be a positive number of Hz"]


def test_a_broken_clock_skips_the_rate_checks_that_need_it():
    text = "clock: {rate: zero}\nmodels:\n  sim: {kind: ballsim, rate: 7}\n  gm: {kind: gripswitch}\n"
    assert problems_of(text) == ["x.yaml:1: clock.rate: bad rate 'zero': the clock rate must be a positive number "
                                 "of Hz (below 1 MHz)"]


def test_broken_entities_and_lets_do_not_make_their_names_undefined():
    text = """\
models:
  sim: {kind: ballsim}
entities: [ball]
triggers:
  - on: {action: grasp}
    let: {obj: "closest(("}
    when: "obj != null and distance(obj, ball) < 0.1"
    do: [{transfer: {entity: obj, attribute: temperature, to: sim}}]
"""
    assert problems_of(text) == [
        "x.yaml:3: entities: entities must be a map of names to entity specs",
        "x.yaml:6: triggers[0].let.obj: bad expression 'closest((': unexpected 'end of expression' (at column 10)",
    ]


def test_a_built_in_called_with_too_few_or_too_many_arguments_is_a_scene_problem():
    """inside(container) was valid: the predicate failed when evaluated at the end of the run (left null, degraded);
    a trigger's when, each time it fired (a trigger error, degraded). Each built-in's arguments are counted now."""
    text = """\
models:
  sim: {kind: ballsim}
entities:
  ball: {shape: {type: sphere, radius: 0.03}}
  bin: {shape: {type: container, style: bin}}
triggers:
  - on: {action: grasp}
    when: "distance(ball) < 0.1 and max(1, 2, 3) > 0 and owner(ball) == 'sim'"
    do: [{transfer: {entity: ball, to: sim}}]
semantics:
  in: "inside(bin)"
  far: "abs(distance(ball, bin), 1) > 0"
  ok: "seated(ball, bin, [0, 0, 0], 0.01, 0.02) or len(tagged('x')) == int('0')"
"""
    assert problems_of(text) == [
        "x.yaml:8: triggers[0].when: distance() takes 2 arguments, 1 given in "
        "\"distance(ball) < 0.1 and max(1, 2, 3) > 0 and owner(ball) == 'sim'\"",
        "x.yaml:11: semantics.in: inside() takes 2 arguments, 1 given in 'inside(bin)'",
        "x.yaml:12: semantics.far: abs() takes 1 argument, 2 given in 'abs(distance(ball, bin), 1) > 0'",
    ]


def test_a_let_variable_may_name_the_model_a_transfer_goes_to():
    text = """\
models:
  sim: {kind: ballsim}
  hand: {kind: holder}
entities:
  ball: {shape: {type: sphere, radius: 0.03}}
triggers:
  - on: {action: grasp}
    let: {dst: "'hand'"}
    do: [{transfer: {entity: ball, to: dst}}, {transfer: {entity: ball, to: nobody}}]
"""
    assert problems_of(text) == ["x.yaml:9: triggers[0].do[1].transfer.to: unknown model 'nobody'"]


def test_an_unexpected_failure_names_where_it_happened_and_the_rest_is_still_checked(monkeypatch):
    def broken_shape_check(shape: Any) -> str | None:
        raise TypeError("boom")

    monkeypatch.setattr("conductor.scene.check.validate_shape", broken_shape_check)
    text = """\
models:
  sim: {kind: ballsim}
entities:
  ball: {shape: {type: sphere, radius: 0.03}}
  cup: {shape: {type: sphere, radius: 0.03}}
semantics:
  up: "height(ball) > 0"
"""
    assert problems_of(text) == [
        "x.yaml:4: entities.ball: invalid value here (TypeError: boom)",
        "x.yaml:7: semantics.up: unknown evaluator or function 'height' in 'height(ball) > 0'",
    ]


# -------------------------------------------------------------------------------------------- robot
GOOD = "models:\n  sim: {kind: ballsim}\n"


MAP = "x.yaml:3: robot: robot must be a map like {use: panda, base: [x, y, z]} (shipped robots: panda, xarm6)"
ALLOWED = "arm, arm_force, arm_inertia, base, gripper, joints, ready, urdf, use"


@pytest.mark.parametrize("robot, problem", [
    ("42", MAP),
    ("[urdf]", MAP),
    ("{colour: red}", f"x.yaml:3: robot.colour: unknown key 'colour' (allowed: {ALLOWED})"),
    ("{urdf: 5}", "x.yaml:3: robot.urdf: urdf must be the robot's URDF file (a string)"),
    ("{base: [0, 0]}", "x.yaml:3: robot.base: base must be [x, y, z] or [x, y, z, qx, qy, qz, qw] (numbers)"),
    ("{base: [0, 0, .inf]}", "x.yaml:3: robot.base: base must be [x, y, z] or [x, y, z, qx, qy, qz, qw] (numbers)"),
    ("{use: ur5}", "x.yaml:3: robot.use: use must name a shipped robot description (panda, xarm6), got 'ur5'"),
    ("{use: panda, urdf: nowhere/arm.urdf}", "x.yaml:3: robot.urdf: robot URDF 'nowhere/arm.urdf' not found "
                                             "(absolute, relative to the scene, the working directory or "
                                             "pybullet_data)"),
    ("{urdf: kuka_iiwa/model.urdf, gripper: {}}", "x.yaml:3: robot.arm: arm is required for a URDF without a shipped "
                                                  "description (give it, or use: panda|xarm6)"),
    ("{use: xarm6, joints: {j1: panda_joint1}}", "x.yaml:3: robot.joints.j1: panda_joint1: not a movable joint of "
                                                 "the URDF"),
    ("{use: panda, gripper: {fingers: [panda_leftfinger, claw]}}", "x.yaml:3: robot.gripper.fingers: claw: not a "
                                                                   "link of the URDF"),
    ("{use: panda, ready: [0, 0]}", "x.yaml:3: robot.ready: ready must list 9 joint positions (the arm's, then the "
                                    "gripper's)"),
])
def test_a_bad_robot_block_is_refused(robot, problem):
    assert problems_of(GOOD + f"robot: {robot}\n") == [problem]


@pytest.mark.parametrize("robot", ["", "null", "{}", "{urdf: franka_panda/panda.urdf}", "{base: [0, 0, 0]}",
                                   "{use: xarm6, base: [0, 0, 0, 0, 0, 0, 1]}", "{urdf: null, base: null}",
                                   "{use: xarm6, joints: {arm_1: joint1, gripper: drive_joint}}"])
def test_a_good_robot_block_loads(robot):
    scene = parse_scene(GOOD + f"robot: {robot}\n", "x.yaml")
    assert scene.main == "sim"
    assert scene.robot is not None and scene.robot.name == ("xarm6" if "xarm6" in robot else "panda")


def test_a_robot_of_its_own_needs_only_a_robot_block(tmp_path):
    """A URDF the twin does not ship (here the xArm's, copied under another name) with its arm and gripper
    written out, and a joints map: it resolves, its mimic joints come from the URDF, and the map renames."""
    import shutil

    import pybullet_data

    src = Path(pybullet_data.getDataPath()) / "xarm"
    shutil.copytree(src, tmp_path / "arm")
    (tmp_path / "arm" / "xarm6_with_gripper.urdf").rename(tmp_path / "arm" / "my_arm.urdf")
    text = GOOD + """robot:
  urdf: arm/my_arm.urdf
  arm: [joint1, joint2, joint3, joint4, joint5, joint6]
  gripper: {joints: [drive_joint], fingers: [left_finger, right_finger], hand: xarm_gripper_base_link,
            tip_offset: [0, 0, 0.172], open: [0], closed: [0.85], force: 5}
  joints: {a1: joint1, g: drive_joint}
"""
    (tmp_path / "s.yaml").write_text(text)
    scene = load_scene(tmp_path / "s.yaml")
    r = scene.robot
    assert r is not None and r.name == "my_arm" and r.gripper.tip == "xarm_gripper_base_link"
    assert set(r.gripper.mimic) == {"left_finger_joint", "left_inner_knuckle_joint", "right_outer_knuckle_joint",
                                    "right_finger_joint", "right_inner_knuckle_joint"}
    assert r.rename(["a1", "g", "other"]) == ["joint1", "drive_joint", "other"]
    assert r.fit(["a1", "g"]) == ({"joint1", "drive_joint"}, ["joint2", "joint3", "joint4", "joint5", "joint6"])


# ---------------------------------------------------------------------------------- against the agents
AGENTS_SCENE = """\
name: agents
clock: {rate: 100}
main: sim
models:
  sim: {kind: ballsim, step: service, args: {gravity: -10, label: hello}}
  mon: {kind: monitor, step: clock}
  other: {kind: "tests.models.thing:Thing", step: free, rate: 10, reads: [ball.pose]}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5], attributes: {pose: sim, temperature: other}}
evaluators:
  height: {model: sim}
  grasped: {model: mon, name: is_grasped}
triggers:
  - name: reset
    on: {action: move_hand}
    do:
      - call: {model: sim, service: reset}
      - call: {model: mon, service: poke}
  - name: landed
    on: {event: sim.landed}
    do: [{transfer: {entity: ball, attribute: pose, to: sim}}]
  - name: grasped
    on: {topic: mon.grasped}
    do: [{transfer: {entity: ball, attribute: pose, to: sim}}]
"""


def _param(type_word: str, required: bool = False, doc: str = "") -> dict[str, Any]:
    return {"type": type_word, "default": None, "doc": doc, "required": required}


def _agent(name: str, kind: str, **fields: Any) -> dict[str, Any]:
    """A register message's fields, as an agent sends them."""
    desc = {"name": name, "kind": kind, "role": "simulation", "step_modes": ["service", "clock", "free"],
            "params": {}, "attributes": ["pose"], "outputs": [], "events": [], "evaluators": [], "services": []}
    desc.update(fields)
    return desc


def _agents() -> dict[str, dict[str, Any]]:
    return {
        "sim": _agent("sim", "ballsim", evaluators=["height"], services=["reset"], reads=["ball.pose", "*.collision"],
                      events=["landed", "bounced"],
                      params={"gravity": _param("float"), "label": _param("str"), "seed": _param("int", doc="seed")}),
        "mon": _agent("mon", "monitor", role="observer", attributes=[], step_modes=["clock"],
                      evaluators=["is_grasped"], services=["poke"], outputs=["grasped"]),
        "other": _agent("other", "thing", attributes=["temperature"], step_modes=["free"], reads=["ball.pose"]),
    }


def test_a_scene_that_fits_its_agents_has_no_problems():
    scene = parse_scene(AGENTS_SCENE, "agents.yaml")
    assert check_against_agents(scene, _agents()) == []


def _set(model: str, key: str, value: Any) -> Any:
    return lambda agents: agents[model].__setitem__(key, value)


AGENT_CASES = {
    # the agent is another kind: nothing else of it is checked (its params would not fit either)
    "kind": (lambda a: a["sim"].update(kind="holder", params={}, attributes=[]),
             "agents.yaml:5: models.sim.kind: the scene asks for kind 'ballsim', the agent is 'holder'"),
    "no agent": (lambda a: a.pop("other"),
                 "agents.yaml:7: models.other: no agent registered as 'other' (start one with "
                 "'twin agent tests.models.thing:Thing --name other')"),
    "unknown parameter": (lambda a: a["sim"]["params"].pop("label"),
                          "agents.yaml:5: models.sim.args.label: unknown parameter 'label' of ballsim "
                          "(it declares: gravity, seed)"),
    "parameter type": (lambda a: a["sim"]["params"]["label"].update(type="int"),
                       "agents.yaml:5: models.sim.args.label: parameter 'label' of ballsim must be int, got 'hello'"),
    "required parameter": (lambda a: a["sim"]["params"]["seed"].update(required=True),
                           "agents.yaml:5: models.sim.args: missing required parameter 'seed' of ballsim: seed"),
    "step mode": (_set("mon", "step_modes", ["service", "free"]),
                  "agents.yaml:6: models.mon.step: monitor cannot step in mode 'clock' (it supports: service, free)"),
    "cannot own": (_set("sim", "attributes", []),
                   ["agents.yaml:9: entities.ball.attributes.pose: model 'sim' (ballsim) cannot own 'pose' "
                    "(it can own: nothing)"]  # (and the two transfers to it would be refused when they fire)
                   + [f"agents.yaml:{line}: triggers[{i}].do[0].transfer.to: trigger {name}: model 'sim' (ballsim) "
                      "cannot own 'pose' (it can own: nothing): this transfer would be refused when it fires"
                      for line, i, name in ((21, 1, "landed"), (24, 2, "grasped"))]),
    "observer owns": (_set("other", "role", "observer"),
                      "agents.yaml:9: entities.ball.attributes.temperature: model 'other' (thing) is an observer "
                      "and cannot own 'temperature': an observer owns nothing"),
    "evaluator": (_set("mon", "evaluators", []),
                  "agents.yaml:12: evaluators.grasped: unknown evaluator 'is_grasped' of model 'mon' (it has: none)"),
    "service": (_set("sim", "services", ["restart", "stop"]),
                "agents.yaml:17: triggers[0].do[0].call.service: unknown service 'reset' of model 'sim' "
                "(it has: restart, stop)"),
    # a trigger on an event or output its model does not declare would never fire: the run would end complete
    "event": (_set("sim", "events", ["land", "bounced"]),
              "agents.yaml:20: triggers[1].on.event: model 'sim' (ballsim) declares no event 'landed' (did you mean "
              "'land'?): it has land, bounced; this trigger would never fire"),
    "output": (_set("mon", "outputs", []),
               "agents.yaml:23: triggers[2].on.topic: model 'mon' (monitor) declares no output 'grasped': it has none; "
               "this trigger would never fire"),
}


def test_a_substep_longer_than_the_step_period_is_a_problem_of_the_scene():
    """An engine's time step (a parameter declared ``within_period``) longer than the model's step period would
    leave steps that move nothing: the agent refuses it at init, and the scene check says it first, with the line,
    whether the scene gives the value or the model's default does not fit the scene's rate."""
    agents = _agents()
    agents["sim"]["params"]["substep"] = {**_param("float"), "default": 0.004, "within_period": True}
    agents["other"]["params"]["substep"] = {**_param("float"), "default": 0.2, "within_period": True}
    scene = parse_scene(AGENTS_SCENE.replace("label: hello}", "label: hello, substep: 0.02}"), "agents.yaml")
    assert [str(p) for p in check_against_agents(scene, agents)] == [
        "agents.yaml:5: models.sim.args.substep: parameter 'substep' of ballsim is 0.02 s, longer than the model's "
        "step period 0.01 s (rate 100 Hz): give substep at most 0.01, or a lower rate",
        "agents.yaml:7: models.other.rate: the default 'substep' of tests.models.thing:Thing is 0.2 s, longer than "
        "the model's step period 0.1 s (rate 10 Hz): give substep at most 0.1, or a lower rate"]
    agents["other"]["params"]["substep"]["default"] = 0.1  # exactly the period: one substep a step
    assert check_against_agents(parse_scene(AGENTS_SCENE, "agents.yaml"), agents) == []
    from agents.models.mujoco import MuJoCo
    from agents.models.physics import Physics
    assert Physics.params["time_step"].describe().get("within_period") is True  # both engines declare it
    assert MuJoCo.params["time_step"].describe().get("within_period") is True


@pytest.mark.parametrize("case", AGENT_CASES)
def test_each_problem_against_the_agents(case):
    scene = parse_scene(AGENTS_SCENE, "agents.yaml")
    agents = _agents()
    change, expected = AGENT_CASES[case]
    change(agents)
    assert [str(p) for p in check_against_agents(scene, agents)] == (expected if isinstance(expected, list)
                                                                     else [expected])


def test_every_problem_against_the_agents_at_once():
    scene = parse_scene(AGENTS_SCENE, "agents.yaml")
    agents = _agents()
    for case in ("unknown parameter", "step mode", "cannot own", "evaluator", "service"):
        AGENT_CASES[case][0](agents)
    found = [str(p) for p in check_against_agents(scene, agents)]
    assert len(found) == 7 and SceneError.of(check_against_agents(scene, agents)).problems
    assert [p.split(": ")[1] for p in found] == ["models.sim.args.label", "models.mon.step",
                                                 "entities.ball.attributes.pose", "evaluators.grasped",
                                                 "triggers[0].do[0].call.service", "triggers[1].do[0].transfer.to",
                                                 "triggers[2].do[0].transfer.to"]


@pytest.mark.parametrize("type_word, value, fits", [
    ("float", "1", True), ("float", "1.5", True), ("float", "true", False), ("float", "'1.5'", False),
    ("int", "3", True), ("int", "3.0", False), ("int", "false", False),
    ("str", "x", True), ("str", "1", False), ("bool", "false", True), ("bool", "0", False),
    ("list", "[1, 2]", True), ("list", "{a: 1}", False), ("map", "{a: 1}", True), ("map", "[1]", False),
    ("any", "{a: [1]}", True), ("float", "null", True),  # null: the agent's runtime lets it through
])
def test_a_scene_arg_fits_the_declared_type(type_word, value, fits):
    scene = parse_scene(f"models:\n  m: {{kind: k, args: {{v: {value}}}}}\n", "x.yaml")
    agents = {"m": _agent("m", "k", params={"v": _param(type_word)})}
    problems = check_against_agents(scene, agents)
    assert (problems == []) == fits, problems
    if not fits:
        assert problems[0].key == "models.m.args.v" and f"must be {type_word}, got" in problems[0].problem


def test_reads_of_joins_the_scene_and_the_agent_in_order_once():
    scene = parse_scene(AGENTS_SCENE, "agents.yaml")
    agents = _agents()
    before = copy.deepcopy(scene)
    assert reads_of(scene, agents) == {"sim": ["ball.pose", "*.collision"], "mon": [], "other": ["ball.pose"]}
    assert reads_of(scene, {}) == {"sim": [], "mon": [], "other": ["ball.pose"]}
    check_against_agents(scene, agents)
    assert scene == before  # neither changes the scene
    assert scene.models["other"].reads == ["ball.pose"]


# ------------------------------------------------------------------------------- a checked scene stays
FROZEN_SCENE = """\
models:
  sim: {kind: ballsim}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5]}
triggers:
  - {on: {action: move_hand}, do: [{call: {model: sim, service: reset}}]}
"""


def test_a_checked_scene_cannot_be_rebound_but_takes_a_perception():
    scene = parse_scene(FROZEN_SCENE, "x.yaml")
    with pytest.raises(dataclasses.FrozenInstanceError):
        scene.main = "mon"  # type: ignore[misc]
    ball = scene.entities["ball"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        ball.pose = [0.0] * 7  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        scene.triggers[0].do[0].line = 1  # type: ignore[misc]
    scene.apply_perception({"entities": {"ball": {"pose": [0.1, 0.2, 0.3], "mass": 0.05},
                                         "ghost": {"pose": [0, 0, 0]}}})
    assert scene.entities["ball"].pose == [0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0]
    assert scene.entities["ball"].extra == {"mass": 0.05}
    assert ball.pose == [0.5, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0] and ball.extra == {}  # the checked entity is intact
    assert "ghost" not in scene.entities


def test_a_virtual_entity_owns_only_what_it_lists():
    """A ``virtual`` entity (no body) without ``attributes`` had its pose owned by the main physics, which has no
    body to give it (a reviewer's scene), against the design's word: a virtual entity owns only what it lists."""
    scene = parse_scene(FROZEN_SCENE.replace("entities:\n", "entities:\n  water: {shape: {type: sphere, radius: "
                                                              "0.01}, pose: [0, 0, 0], tags: [virtual]}\n"), "x.yaml")
    owners = scene.initial_owners()
    assert ("ball", "pose") in owners and not [k for k in owners if k[0] == "water"]


def test_a_quaternion_is_read_at_unit_length_and_a_position_alone_keeps_the_scenes_turn():
    """A bin written ``[0, 0, 1, 1]`` (a quarter turn, not normalised): physics normalises it, while the conductor
    kept it as written, and ``inside`` read another bin than the physics built (a reviewer's scene: False against
    True for the same turn normalised). A perception giving a position alone put a turned bin back to no turn."""
    text = FROZEN_SCENE.replace("entities:\n", "entities:\n  bin: {shape: {type: container, style: bin}, "
                                                "pose: [0.5, 0, 0, 0, 0, 1, 1], tags: [static]}\n")
    scene = parse_scene(text, "x.yaml")
    h = math.sqrt(0.5)
    assert scene.entities["bin"].pose == pytest.approx([0.5, 0, 0, 0, 0, h, h])
    scene.apply_perception({"entities": {"bin": {"pose": [0.4, 0.1, 0.0]}, "ball": {"pose": [0, 0, 0, 0, 2, 0, 0]}}})
    assert scene.entities["bin"].pose == pytest.approx([0.4, 0.1, 0.0, 0, 0, h, h])
    assert scene.entities["ball"].pose == [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]


NAMES_AS_STRINGS = AGENTS_SCENE.replace("entities:\n  ball:", "entities:\n  bin: {shape: {type: box, size: [0.1, 0.1, "
                                        "0.1]}, pose: [0, 0, 0], tags: [container]}\n  ball:") + """\
semantics:
  "held": "owner('ball', 'pose') == 'mon'"
  "bounced": "event_count(sim, 'bounced') > 0"
  "grasped": "output('mon', 'grasped') == true"
  "bins": "len(tagged('container')) == 1"
"""


@pytest.mark.parametrize("wrong,right,expected", [
    ("owner('ball',", "owner('bal',", "unknown entity 'bal' (did you mean 'ball'?) in owner(): the scene's "
                                      "entities are ball, bin"),
    ("'pose') == 'mon'", "'pos') == 'mon'", "unknown attribute 'pos' (did you mean 'pose'?) in owner(): the scene's "
                                            "attributes are pose, temperature"),
    ("output('mon',", "output('mn',", "unknown model 'mn' (did you mean 'mon'?) in output(): the scene's models are "
                                      "mon, other, sim"),
    ("tagged('container')", "tagged('containr')", "unknown tag 'containr' (did you mean 'container'?) in tagged(): "
                                                  "the scene's tags are container"),
    ("attribute: pose, to", "attribute: colour, to", "unknown attribute 'colour' of entity 'ball' (has: pose, "
                                                     "temperature)"),
    # of an entity the run decides: it said "undefined variable 'colour' in 'colour'"
    ("entity: ball, attribute: pose, to", "entity: \"owned('sim')[0]\", attribute: colour, to",
     "unknown attribute 'colour': no entity has it (the scene's attributes are pose, temperature)"),
    # quoted: 'pose' is pose; a misspelt one is said as a bare one is
    ("entity: ball, attribute: pose, to", "entity: \"owned('sim')[0]\", attribute: \"'pse'\", to",
     "unknown attribute 'pse' (did you mean 'pose'?): no entity has it"),
    ("entity: ball, attribute: pose, to", "entity: bin, attribute: \"'temperature'\", to",
     "unknown attribute 'temperature' of entity 'bin' (has: pose)"),
])
def test_a_name_written_as_a_string_is_checked(wrong, right, expected):
    """A misspelt name in quotes was never checked: owner('bal', 'pose') read null, == 'mon' made it a silent false,
    and the run ended complete with a wrong answer. Bare names were checked already."""
    assert parse_scene(NAMES_AS_STRINGS, "names.yaml").semantics  # the scene as written is fine
    with pytest.raises(SceneError) as e:
        parse_scene(NAMES_AS_STRINGS.replace(wrong, right), "names.yaml")
    assert expected in str(e.value), str(e.value)


def test_a_transfer_s_attribute_may_be_quoted_or_an_expression():
    """A transfer's attribute is an expression like its entity: "'pose'" (quoted) and one the run decides
    (``event.data.attribute``) were refused as 'unknown attribute' by their text."""
    for attribute in ("\"'pose'\"", "event.data.attribute", "\"'po' + 'se'\""):
        scene = parse_scene(NAMES_AS_STRINGS.replace("on: {event: sim.landed}\n    do: [{transfer: {entity: ball, "
                                                     "attribute: pose,",
                                                     f"on: {{event: sim.landed}}\n    do: [{{transfer: {{entity: "
                                                     f"ball, attribute: {attribute},"), "names.yaml")
        transfer = next(e for t in scene.triggers for e in t.do if e.kind == "transfer")
        assert transfer.fields["attribute"].evaluate({"event": {"data": {"attribute": "pose"}}}.get, {}) == "pose"


def test_a_tag_that_no_entity_has_yet_is_a_fair_question():
    """tagged('fragile') in a generic scene where nothing is fragile reads [], as meant: only a tag close to one the
    scene has is taken for a misspelling."""
    assert parse_scene(NAMES_AS_STRINGS.replace("tagged('container')", "tagged('fragile')"), "names.yaml")


def test_a_counted_event_or_a_read_output_is_one_its_model_declares():
    """event_count(MODEL, 'NAME') of an event the model never raises counts 0 for ever, output(MODEL, 'NAME') of an
    output it does not have reads null: checked against what the agents declare, as triggers' events are."""
    scene = parse_scene(NAMES_AS_STRINGS, "names.yaml")
    assert check_against_agents(scene, _agents()) == []
    agents = _agents()
    agents["sim"]["events"] = ["landed", "bounce"]
    agents["mon"]["outputs"] = ["grasped", "width"]
    assert [str(p) for p in check_against_agents(scene, agents)] == [
        "names.yaml:28: semantics.bounced: model 'sim' (ballsim) declares no event 'bounced' in "
        "\"event_count(sim, 'bounced') > 0\" (did you mean 'bounce'?): it has landed, bounce"]
    agents["mon"]["outputs"] = ["grasp"]
    found = [str(p) for p in check_against_agents(scene, agents)]
    assert "names.yaml:29: semantics.grasped: model 'mon' (monitor) declares no output 'grasped' in " \
           "\"output('mon', 'grasped') == true\" (did you mean 'grasp'?): it has grasp" in found, found
    # in a trigger's let and in an effect's arguments too (they were checked in the semantics and 'when' only)
    text = NAMES_AS_STRINGS.replace("    on: {event: sim.landed}\n",
                                    "    on: {event: sim.landed}\n    let: {n: \"event_count(sim, 'landd')\"}\n")
    text = text.replace("      - call: {model: mon, service: poke}",
                        "      - call: {model: mon, service: poke, args: [\"output(sim, 'hieght')\"]}")
    let = parse_scene(text, "names.yaml")
    agents = _agents()
    agents["sim"]["outputs"] = ["height"]
    found = [str(p) for p in check_against_agents(let, agents)]
    assert any("triggers[1].let.n: model 'sim' (ballsim) declares no event 'landd'" in f and "'landed'" in f
               for f in found), found
    assert any("triggers[0].do[1].call.args: model 'sim' (ballsim) declares no output 'hieght'" in f
               for f in found), found


@pytest.mark.parametrize("wrong, problem", [
    ("on: {action: move_hand, phse: end}",
     "x.yaml:10: triggers[0].on.phse: unknown key 'phse' (allowed: action, phase)"),
    ("on: {event: sim.hit, once: true}", "x.yaml:10: triggers[0].on.once: unknown key 'once' (allowed: event)"),
])
def test_a_misspelt_key_of_a_trigger_s_on_is_refused(wrong, problem):
    """``phse: end`` was dropped without a word: the trigger fired at the action's start, and the scene was
    'valid'."""
    text = SEVERAL.replace("stepp", "step").replace("rate: -15", "rate: 15").replace("to: nowhere", "to: gm") \
        .replace("[0.5, 0]", "[0.5, 0, 0]").replace("on: {action: move_hand}", wrong)
    assert any(p.startswith(problem) for p in problems_of(text)), problems_of(text)


@pytest.mark.parametrize("shape, key", [
    ("{type: container, syle: cup}", "syle"), ("{type: sphere, radius: 0.03, colour: red}", "colour"),
    ("{type: box, size: [0.1, 0.1, 0.1], radius: 0.1}", "radius"),
])
def test_a_misspelt_shape_key_is_refused(shape, key):
    """A container with ``syle: cup`` stayed a bin, and the scene was 'valid'."""
    text = SEVERAL.replace("stepp", "step").replace("rate: -15", "rate: 15").replace("to: nowhere", "to: gm") \
        .replace("{type: sphere, radius: 0.03}, pose: [0.5, 0]", f"{shape}, pose: [0.5, 0, 0]")
    (p,) = problems_of(text)
    assert p.startswith(f"x.yaml:7: entities.ball.shape: unknown key {key!r} in a ") and "(allowed: type, " in p, p


def test_an_entity_keeps_its_pose_with_the_main_model_when_given_other_attributes():
    """A ball given a temperature kept no pose: nothing moved it, ``inside`` read where the scene put it and the run
    ended complete with the wrong answer. Its pose is now the main model's unless ``attributes`` gives it to another;
    a ``virtual`` entity (no body: a coffee's temperature) owns only what it lists."""
    scene = parse_scene("""\
name: attrs
main: sim
models:
  sim: {kind: ballsim}
  mug: {kind: cooling}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5], attributes: {temperature: mug}}
  held: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5], attributes: {temperature: mug, pose: mug}}
  coffee: {shape: {type: sphere, radius: 0.02}, pose: [0.5, 0, 0.5], tags: [virtual], attributes: {temperature: mug}}
""", "attrs.yaml")
    assert scene.initial_owners() == {("ball", "pose"): "sim", ("ball", "temperature"): "mug",
                                      ("held", "pose"): "mug", ("held", "temperature"): "mug",
                                      ("coffee", "temperature"): "mug"}


def test_calls_give_as_many_arguments_as_the_agents_methods_take():
    """height(ball, 2) of an evaluator taking one argument failed only when evaluated (a predicate left null at the
    end of the run, a trigger's error when it fired); a service given arguments it does not take, the same. The
    agents declare each method's [least, most] positional arguments (``arity``), checked before anything starts;
    an agent that declares none is not checked (an older agent, another language)."""
    text = AGENTS_SCENE.replace("      - call: {model: sim, service: reset}",
                                "      - call: {model: sim, service: reset, args: [ball]}") + \
        "semantics:\n  high: \"height(ball, 2) > 0\"\n  held: \"grasped()\"\n"
    scene = parse_scene(text, "agents.yaml")
    assert check_against_agents(scene, _agents()) == []  # no arity declared: nothing to hold them to
    agents = _agents()
    agents["sim"]["arity"] = {"eval": {"height": [1, 1]}, "call": {"reset": [0, 0]}}
    agents["mon"]["arity"] = {"eval": {"is_grasped": [0, None]}, "call": {"poke": [0, 1]}}
    assert [str(p) for p in check_against_agents(scene, agents)] == [
        "agents.yaml:26: semantics.high: in 'height(ball, 2) > 0': height() takes 1 argument, 2 given",
        "agents.yaml:17: triggers[0].do[0].call.args: service 'reset' of model 'sim' takes 0 arguments, 1 given"]
    agents["sim"]["arity"] = {"eval": {"height": [1, 2]}, "call": {"reset": [1, None]}}
    assert check_against_agents(scene, agents) == []
    agents["mon"]["arity"]["eval"]["is_grasped"] = [1, 1]
    assert [str(p) for p in check_against_agents(scene, agents)] == [
        "agents.yaml:27: semantics.held: in 'grasped()': grasped() takes 1 argument, 0 given"]
    # what an agent declares: its bound methods' positional arguments (physics' closest(tag, body='hand'))
    from agents.model import arity
    from agents.models.physics import Physics

    assert arity(Physics().closest) == [1, 2] and arity(lambda *xs: xs) == [0, None]


def test_an_unnamed_trigger_takes_a_name_no_other_trigger_has():
    """An unnamed trigger is called trigger{i}; one named so by its author made that a 'duplicate trigger name' at
    the unnamed one's 'name' key, which its author never wrote."""
    text = FROZEN_SCENE.split("triggers:")[0] + """triggers:
  - {on: {action: move_hand}, do: [{call: {model: sim, service: reset}}]}
  - {name: trigger0, on: {action: release}, do: [{call: {model: sim, service: reset}}]}
"""
    assert [t.name for t in parse_scene(text, "x.yaml").triggers] == ["trigger0_1", "trigger0"]
