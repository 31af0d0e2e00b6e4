"""Every built-in model keeps the model contract when run as a real agent process (agents.testing.check_model),
the checker catches models that break it, and the author API refuses bad declarations at class definition."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from agents import Model, Param
from agents.registry import BUILTIN, resolve_kind
from agents.robot.index import BodyIndex  # noqa: F401  (kept importable)
from agents.testing import ConformanceError, check_model
from protocol.robot import resolve_robot

PANDA = resolve_robot({"use": "panda"})
JOINTS, READY = PANDA.joints, PANDA.ready

BALL = {"shape": {"type": "sphere", "radius": 0.033}, "tags": ["graspable"]}


def joint_state(tick: int, rate: float, fingers: tuple[float, float], effort: float) -> dict[str, Any]:
    """The Panda in its ready posture with the fingers at ``fingers`` (m) squeezing with ``effort`` (N)."""
    return {"stamp": tick / rate, "name": list(JOINTS), "position": [*READY[:7], *fingers],
            "velocity": [0.0] * 9, "effort": [0.0] * 7 + [effort, effort]}


# -------------------------------------------------------------------------------- one case per kind
def physics_case() -> dict[str, Any]:
    """A ball dropped next to a box and a bin with a few particles in it (the one-world fluid), the robot
    holding its ready posture from the telemetry."""
    entities = {"ball": {**BALL, "pose": [0.5, 0.0, 0.3, 0, 0, 0, 1]},
                "box": {"shape": {"type": "box", "size": [0.06, 0.06, 0.06]}, "pose": [0.6, 0.2, 0.03, 0, 0, 0, 1]},
                "bin": {"shape": {"type": "container", "style": "bin"}, "pose": [0.5, -0.3, 0.0, 0, 0, 0, 1]}}
    return {"params": {"time_step": 1 / 240, "particles": {"container": "bin", "count": 10, "radius": 0.01}},
            "scene": {"entities": entities}, "rate": 120.0, "ticks": 30,
            "owns": [("ball", "pose"), ("box", "pose"), ("bin", "pose"), ("ball", "collision")],
            "telemetry": lambda k: joint_state(k, 120.0, (0.04, 0.04), 0.0)}


def mujoco_case() -> dict[str, Any]:
    """The physics case in MuJoCo: a ball dropped next to a box, a bin and the insertion's socket, the robot
    holding its ready posture from the telemetry with its fingers closed on nothing."""
    entities = {"ball": {**BALL, "pose": [0.5, 0.0, 0.3, 0, 0, 0, 1]},
                "box": {"shape": {"type": "box", "size": [0.06, 0.06, 0.06]}, "pose": [0.6, 0.2, 0.03, 0, 0, 0, 1]},
                "bin": {"shape": {"type": "container", "style": "bin"}, "pose": [0.5, -0.3, 0.0, 0, 0, 0, 1]},
                "spu": {"shape": {"type": "socket", "size": [0.06, 0.06, 0.08], "hole": 0.0075, "depth": 0.02,
                                  "chamfer": 0.006}, "pose": [0.3, 0.3, 0.04, 0, 0, 0, 1]}}
    return {"params": {"time_step": 0.002}, "scene": {"entities": entities}, "rate": 120.0, "ticks": 30,
            "owns": [("ball", "pose"), ("box", "pose"), ("bin", "pose"), ("ball", "collision")],
            "telemetry": lambda k: joint_state(k, 120.0, (0.0, 0.0), 0.0)}


def grasp_monitor_case() -> dict[str, Any]:
    """The fingers close on a ball (from tick 5) and press on it: a grasp starts."""
    def telemetry(k: int) -> dict[str, Any]:
        return joint_state(k, 15.0, (0.04, 0.04) if k < 5 else (0.033, 0.033), 0.0 if k < 5 else -20.0)
    return {"params": {}, "scene": {}, "rate": 15.0, "ticks": 20, "owns": [], "telemetry": telemetry}


def in_hand_case() -> dict[str, Any]:
    """A ball held between the fingers (placed where the hand's forward kinematics puts it)."""
    from agents.robot.kinematics import RobotKinematics, compose

    fk = RobotKinematics(PANDA)
    try:
        hand = fk.link_pose(dict(zip(JOINTS, [*READY[:7], 0.033, 0.033], strict=True)), "panda_hand")
    finally:
        fk.close()
    ball = [float(v) for v in compose(hand, [0.0, 0.0, 0.105, 0, 0, 0, 1])]
    return {"params": {}, "scene": {"entities": {"ball": {**BALL, "pose": ball}}}, "rate": 60.0, "ticks": 20,
            "owns": [("ball", "pose")], "telemetry": lambda k: joint_state(k, 60.0, (0.033, 0.033), -20.0)}


def spu_case() -> dict[str, Any]:
    """A probe 2 mm off the socket's ideal connection pose, owned from the start: it snaps."""
    socket_pose = [0.5, -0.15, 0.0, 0, 0, 0, 1]
    entities = {"socket": {"shape": {"type": "box", "size": [0.08, 0.08, 0.06]}, "pose": socket_pose},
                "plug": {"shape": {"type": "cylinder", "radius": 0.006, "length": 0.05},
                         "pose": [0.502, -0.15, 0.06, 0, 0, 0, 1]}}
    return {"params": {"dip": "plug", "spu": "socket", "connection_offset": [0, 0, 0.06]},
            "scene": {"entities": entities}, "rate": 100.0, "ticks": 20,
            "owns": [("plug", "pose"), ("plug", "collision")], "inputs": {"socket": {"pose": socket_pose}}}


def fluid_case() -> dict[str, Any]:
    """Twenty particles settling in a cup that stands still."""
    cup = [0.5, 0.25, 0.0, 0, 0, 0, 1]
    entities = {"cup": {"shape": {"type": "container", "style": "cup"}, "pose": cup},
                "water": {"shape": {"type": "sphere", "radius": 0.008}, "pose": cup, "tags": ["virtual"]}}
    return {"params": {"cup": "cup", "entity": "water", "particles": 20, "settle": 0.1},
            "scene": {"entities": entities}, "rate": 60.0, "ticks": 20, "owns": [("water", "pose")],
            "inputs": {"cup": {"pose": cup}}}


COOLING = Path(__file__).resolve().parent.parent / "scenes" / "units" / "cooling.py"
COOLING2 = Path(__file__).resolve().parent / "units" / "cooling2.py"  # the same law as an FMI 2 unit


def fmu_case() -> dict[str, Any]:
    """The cooling unit by kind fmu (its parameters in one map): a coffee at 90 °C cools for two seconds."""
    return {"params": {"unit": str(COOLING), "parameters": {"temperature_start": 90.0, "tau": 60.0}},
            "scene": {}, "rate": 10.0, "ticks": 20, "owns": []}


def trivial_case() -> dict[str, Any]:
    return {"params": {}, "scene": {}, "rate": 1000.0, "ticks": 20, "owns": []}


CASES = {"physics": physics_case, "mujoco": mujoco_case, "grasp_monitor": grasp_monitor_case, "in_hand": in_hand_case,
         "spu": spu_case, "fluid": fluid_case, "trivial": trivial_case,
         "fmu": fmu_case}
SLOW = {"physics", "mujoco", "fluid", "in_hand", "fmu"}  # pybullet worlds and forward kinematics at start-up


def test_every_builtin_kind_has_a_case():
    """A new built-in kind needs a conformance case here."""
    assert set(CASES) == set(BUILTIN)


@pytest.mark.parametrize("kind", [pytest.param(k, marks=pytest.mark.slow) if k in SLOW else k for k in CASES])
def test_builtin_model_conforms(kind):
    """The built-in kind registers as its class declares, steps with status ok, owns what its state holds,
    hands each owned attribute over and back unchanged, exits cleanly, and two runs answer alike."""
    case = CASES[kind]()
    params, scene = case.pop("params"), case.pop("scene")
    record = check_model(kind, params, scene, **case)
    steps = [r for r in record if r.get("type") == "step_reply"]
    assert len(steps) == case["ticks"] + 1
    if kind == "grasp_monitor":  # the case is realistic: the monitor does see the grasp
        assert [e["name"] for r in steps for e in r["events"]] == ["grasp_started"]
        assert steps[-1]["outputs"]["grasped"] is True
    if kind == "physics":
        assert steps[-1]["outputs"]["spilled"] == 0 and steps[-1]["outputs"]["particles"].shape == (10, 3)
    if kind == "spu":
        assert steps[-1]["outputs"]["connected"] is True
    if kind == "fmu":  # 21 steps of 0.1 s at tau = 60 s from 90 °C towards 20 °C
        assert steps[-1]["outputs"]["variables"]["temperature"] == pytest.approx(20 + 70 * math.exp(-2.1 / 60))


@pytest.mark.slow
@pytest.mark.parametrize("unit", [COOLING, COOLING2], ids=["fmi3", "fmi2"])
def test_an_fmu_unit_is_a_kind_that_owns_its_outputs(unit):
    """kind fmu:PATH, an FMI 3 unit (pythonfmu3) and an FMI 2 one (pythonfmu), both built from source here: the
    unit's parameters are the model's (checked at registration), its output temperature an attribute it owns and
    hands over (a handed-over value restarts the unit from temperature_start)."""
    entities = {"coffee": {"shape": {"type": "sphere", "radius": 0.03}, "pose": [0.5, 0, 0.1, 0, 0, 0, 1]}}
    from agents.registry import resolve_kind

    cls = resolve_kind(f"fmu:{unit}")
    assert {"temperature_start", "tau", "ambient_temperature", "inputs"} <= set(cls.params)
    assert cls.params["tau"].default == 1500.0
    assert unit == COOLING2 or "[s]" in cls.params["tau"].doc  # the FMI 3 unit declares units
    assert cls.attributes == ("temperature",)
    record = check_model(f"fmu:{unit}", {"temperature_start": 85.0, "tau": 30.0}, {"entities": entities},
                         owns=[("coffee", "temperature")], rate=10.0, ticks=10)
    steps = [r for r in record if r.get("type") == "step_reply"]
    # 10 steps, the round trip (released and handed back unchanged: the unit restarts there), one more step
    assert steps[-1]["state"]["coffee"]["temperature"] == pytest.approx(20 + 65 * math.exp(-1.1 / 30), rel=1e-9)


# -------------------------------------------------------------------------- the checker can fail
HOLDER_SCENE = {"entities": {"ball": {**BALL, "pose": [0.5, 0.0, 0.3, 0, 0, 0, 1]}}}


@pytest.mark.parametrize(("model", "check", "words"), [
    ("Dice", "determinism", "roll"),
    ("Leaky", "handover", "ball.pose"),
    ("Chatty", "step", "'secret'"),
    ("Blank", "step", "tick 2: values that are no values, which a run leaves out: ball.pose = None (no value)"),
    ("Clumsy", "step", "tick 3: status error: RuntimeError: dropped it"),
])
def test_checker_catches_a_broken_model(model, check, words):
    """A model that is not deterministic, hands over a value it does not hold, publishes an undeclared
    output, reads None for what it owns or fails a step is reported with the check that failed."""
    with pytest.raises(ConformanceError) as err:
        check_model(f"tests.models.broken:{model}", scene=HOLDER_SCENE, owns=[("ball", "pose")], ticks=5)
    assert err.value.check == check, str(err.value)
    assert words in str(err.value)


def test_checker_says_a_query_was_not_answered_in_time():
    """A model whose init outlasts the checker's wait: Zenoh answers the query with its own timeout error, which
    the checker reports as no answer, not as an error reply it cannot decode."""
    with pytest.raises(ConformanceError) as err:
        check_model("tests.models.broken:Sleepy", scene=HOLDER_SCENE, owns=[("ball", "pose")], ticks=5, timeout=15.0)
    assert err.value.check == "init", str(err.value)
    assert "no answer to init within 15 s" in str(err.value) and "undecodable" not in str(err.value)


def test_checker_allows_a_float_tolerance():
    """A release that is off by a micrometre passes with a tolerance above it."""
    from tests.models.broken import Leaky

    with pytest.raises(ConformanceError, match="handover"):
        check_model(Leaky, scene=HOLDER_SCENE, owns=[("ball", "pose")], ticks=2, tolerance=1e-6)
    check_model(Leaky, scene=HOLDER_SCENE, owns=[("ball", "pose")], ticks=2, tolerance=2e-3)


def test_checker_needs_an_importable_class():
    """A class the agent process cannot import is refused before anything starts."""
    class Local(Model):
        kind = "local"

    with pytest.raises(ValueError, match="top level of an importable module"):
        check_model(Local)


# ------------------------------------------------------------- declarations checked at definition
def test_owning_model_must_define_read():
    """A model that declares attributes but no read is refused when the class is defined."""
    with pytest.raises(TypeError, match="Forgetful declares attributes .* does not define read"):
        class Forgetful(Model):
            attributes = ("pose",)


def test_observer_owns_nothing():
    """An observer that declares attributes is refused when the class is defined."""
    with pytest.raises(TypeError, match="Watcher is an observer but declares attributes"):
        class Watcher(Model):
            role = "observer"
            attributes = ("pose",)

            def read(self, entity: str, attribute: str) -> Any:
                return None


@pytest.mark.parametrize(("param", "message"), [
    (Param(float, "fast"), "default 'fast' does not fit: parameter 'x' must be float"),
    (Param(int, 1.5), "default 1.5 does not fit: parameter 'x' must be int"),
    (Param(list, {"a": 1}), "must be list"),
    (Param(str, "fast", choices=("slow",)), "default 'fast' does not fit: parameter 'x' must be one of slow"),
    (Param(float, 0.0, positive=True), "must be a finite number above 0"),
    (Param(float, float("nan")), "must be a finite number, got nan"),
    (Param(str, "a", positive=True), "positive is for an int or float parameter"),
    (Param(int, 1, within_period=True), "within_period is for a float parameter"),
    (Param(tuple, ()), "type must be one of"),
    ("0.5", "must be a Param"),
])
def test_param_defaults_fit_their_types(param, message):
    """A parameter whose default does not fit its type (or that is not a Param) is refused."""
    with pytest.raises(TypeError, match=message):
        type("Bad", (Model,), {"params": {"x": param}})


def test_param_declarations_that_are_fine():
    """None fits any parameter that is not required, a required one needs no default, an int fits a float,
    and the base class's params cannot be filled by accident."""
    class Fine(Model):
        params = {"a": Param(float, None), "b": Param(str, required=True), "c": Param(float, 1),
                  "d": Param(object, object()), "e": Param(list, (1, 2))}

    assert set(Fine.params) == {"a", "b", "c", "d", "e"}
    with pytest.raises(TypeError):
        Model.params["x"] = Param()


def test_role_and_step_modes_are_checked():
    """An unknown role or step mode is refused when the class is defined, not at registration."""
    with pytest.raises(TypeError, match="role must be one of"):
        type("Robot", (Model,), {"role": "robot"})
    with pytest.raises(TypeError, match="step_modes must list some of"):
        type("Never", (Model,), {"step_modes": ()})
    with pytest.raises(TypeError, match="step_modes must list some of"):
        type("Fast", (Model,), {"step_modes": ("asap",)})


def test_an_evaluator_s_names_are_declared_by_parameter_and_kind():
    """``names`` says which of an evaluator's parameters take a name of the scene (registered as
    ``evaluator_args``, position by position); a parameter it does not have, or a kind there is no check for, is
    refused when the class is defined."""
    from agents import evaluator

    class Finder(Model):
        @evaluator("nearest", names={"tag": "tag", "link": "body"})
        def nearest(self, tag: str, radius: float = 1.0, link: str = "hand") -> str:
            return tag

    assert Finder.evaluator_names() == {"nearest": ["tag", None, "body"]}
    assert resolve_kind("physics").evaluator_names()["closest"] == ["tag", "body"]

    def find(self: Any, tag: str) -> str:
        return tag

    with pytest.raises(TypeError, match="evaluator find: names .*no parameter tg"):
        evaluator(names={"tg": "tag"})(find)
    with pytest.raises(TypeError, match="kinds are entity, tag, body"):
        evaluator(names={"tag": "label"})(find)


def test_resolved_params_are_copies_of_the_defaults():
    """A model that changes a default it was given does not change the class's declaration."""
    from agents.runtime import resolve_params

    class Mutating(Model):
        params = {"gains": Param(list, [1.0, 2.0]), "rate": Param(float, 1)}

    resolved = resolve_params(Mutating, {})
    resolved["gains"].append(3.0)
    assert Mutating.params["gains"].default == [1.0, 2.0]
    assert resolve_params(Mutating, {"rate": 2}) == {"gains": [1.0, 2.0], "rate": 2.0}
    assert isinstance(resolve_params(Mutating, {"rate": 2})["rate"], float)


def test_a_substep_longer_than_the_step_period_is_refused_at_init():
    """A ``within_period`` parameter (an engine's substep) is refused by the runtime when it is longer than the
    model's step period, as ``twin check`` refuses it in the scene: a model of one's own gets it too."""
    from agents.runtime import resolve_params

    class Stepper(Model):
        params = {"substep": Param(float, 0.005, "s", positive=True, within_period=True)}

    assert resolve_params(Stepper, {}, rate=100.0) == {"substep": 0.005}
    assert resolve_params(Stepper, {"substep": 0.01}, rate=100.0) == {"substep": 0.01}  # one substep a step
    with pytest.raises(ValueError, match=r"parameter 'substep' is 0.02 s, longer than the model's step period "
                                         r"0.01 s \(rate 100 Hz\)"):
        resolve_params(Stepper, {"substep": 0.02}, rate=100.0)
    with pytest.raises(ValueError, match="longer than the model's step period 0.004 s"):
        resolve_params(Stepper, {}, rate=250.0)  # the default does not fit this rate either


def test_a_decorator_without_its_parentheses_is_refused():
    """``@evaluator`` (or ``@service``) without parentheses took the method for its name: the method vanished from
    the class and from the model's declarations, without a word."""
    from agents.model import evaluator, service

    with pytest.raises(TypeError, match=r"@evaluator on 'temp_of': write @evaluator\(\) with parentheses"):
        class NoParens(Model):
            @evaluator
            def temp_of(self, entity):
                return 0.0
    with pytest.raises(TypeError, match=r"@service on 'poke': write @service\(\) with parentheses"):
        class NoParens2(Model):
            @service
            def poke(self):
                return None


TWO_LEVELS = Path(__file__).resolve().parent / "units" / "two_levels.py"


@pytest.mark.slow
def test_an_fmu_unit_keeps_its_other_outputs_its_state_and_its_word_through_handovers():
    """What a helper's review found, each on a real FMI 3 unit built here:
    - every integer went through Int32: the unit's Int64 parameter failed fatally;
    - a handover of one output restarted the unit, resetting its other output to its start value;
    - a handed-over value the unit cannot take ('hot', NaN) was stored and the unit reset before it was refused:
      the old owner kept the attribute of a unit now at its defaults (NaN was taken and stayed);
    - a step that failed was followed by more steps at the same time, and their values handed over.
    """
    from agents.registry import resolve_kind

    cls = resolve_kind(f"fmu:{TWO_LEVELS}")
    assert cls.params["fail_after"].default == 0 and set(cls.attributes) == {"a", "b"}

    def unit(**params):
        m = cls()
        m.owned = {("tank1", "a"), ("tank2", "b")}
        m.init({k: p.default for k, p in cls.params.items()} | params, {"entities": {}})
        return m

    m = unit(fail_after=0)
    try:
        for k in range(30):
            m.step(k, (k + 1) * 0.1, 0.1, {}, {})
        assert (m.read("tank1", "a"), m.read("tank2", "b")) == pytest.approx((7.0, 7.0))
        value, extra = m.release("tank1", "a")
        m.acquire("tank1", "a", value + 1.0, extra)  # a new value for a: b goes on where it was
        assert (m.read("tank1", "a"), m.read("tank2", "b")) == pytest.approx((8.0, 7.0))
        for bad in ("hot", float("nan"), [5.0]):
            with pytest.raises(ValueError, match="cannot start from"):
                m.acquire("tank1", "a", bad, {})
        assert (m.read("tank1", "a"), m.read("tank2", "b")) == pytest.approx((8.0, 7.0))  # untouched by the refusals
        m.step(30, 3.1, 0.1, {}, {})
        assert m.read("tank2", "b") == pytest.approx(6.9)
    finally:
        m.close()
    m = unit(fail_after=3)
    try:
        for k in range(3):
            m.step(k, (k + 1) * 0.1, 0.1, {}, {})
        for k in (3, 4):  # the fourth step fails, and the unit is not stepped again
            with pytest.raises(RuntimeError, match="failed .* it is not stepped again"):
                m.step(k, (k + 1) * 0.1, 0.1, {}, {})
        assert m.release("tank1", "a") == (pytest.approx(9.7), {})  # as it was after its last good step
    finally:
        m.close()


def test_an_fmu_unit_s_bound_input_survives_a_restart_by_handover():
    """A handover restarts the unit from its parameters; a bound input (the room's temperature) went back to its
    parameter value there until the next step that carried it, so a step without it cooled the drink towards 20 °C
    in a room at 0 °C. It goes on with the input's last value now."""
    cls = resolve_kind(f"fmu:{COOLING}")
    m = cls()
    m.owned = {("mug", "temperature")}
    m.init({k: p.default for k, p in cls.params.items()} | {"temperature_start": 90.0, "tau": 60.0,
                                                              "inputs": {"ambient_temperature": "room.temperature"}},
           {"entities": {}})
    try:
        m.step(0, 0.1, 0.1, {}, {"room": {"temperature": 0.0}})
        value, extra = m.release("mug", "temperature")
        m.acquire("mug", "temperature", value, extra)
        assert m.value("ambient_temperature") == 0.0
        m.step(1, 0.2, 0.1, {}, {})  # the room's temperature not among this step's inputs
        assert m.read("mug", "temperature") == pytest.approx(value * math.exp(-0.1 / 60.0))
    finally:
        m.close()
