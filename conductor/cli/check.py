"""``twin check SCENE [--recording BAG]``: check a scene, and a robot's bag against it, before running anything."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from typing import Any

from protocol.errors import Problem, SceneError

from ..launch import describe_agents
from ..scene import Scene, check_against_agents, launch_problems, load_scene
from ..scene.perception import perceive
from ..sources.fit import check_fit, telemetry_warnings, unheard_actions
from ..sources.recording import READABLE
from ..sources.replay import ReplaySource
from .run import _load_recording, add_recording_options, check_recording_options

HELP = """\
Check a scene file (file:line: key: problem; every problem of its structure at once, then, once that holds,
every problem against what each model's agent will declare: its parameters, attributes, events, evaluators,
services, asked of 'python -m agents KIND --describe', no bus joined), and, with --recording, whether a robot's
bag fits it: which topics are read, how many joint states and actions, what was left out and why, and which of
the scene robot's joints the bag reports after the robot block's joints map. No run is started. Exit 0: it fits;
2: a bad scene or command line, or a bag it cannot run (unreadable, or no joint of the robot in it); 3: it runs,
but the run would be degraded: some robot joints are missing, the bag's perception places none of the scene's
entities (a bag of another scene), malformed messages are left out, or the bag is cut short (its recorder was
killed: what was written up to the cut is replayed).

  twin check scenes/xarm_ball_drop.yaml --recording my_bag/            # a rosbag2 folder, .mcap or .db3
  twin check my_scene.yaml --recording run.mcap --remap /joint_states:=/arm/joint_states
  twin check my_scene.yaml --by-hand          # agents of kinds of their own, started by hand (twin conductor)
"""


def agent_problems(scene: Scene, by_hand: bool = False) -> tuple[list[Problem], dict[str, Any]]:
    """Every problem of ``scene``'s models at once, in file order: kinds twin run cannot start, agents that cannot
    say what they are, and what the others will declare at registration that does not fit the scene; and what
    the agents that could say declared (their register descriptors, by model). ``by_hand``: the agents of kinds
    twin run cannot start are started by hand, so they are no problem (the others are checked all the same)."""
    unknown = launch_problems(scene)
    bad = {name for name in scene.models if any(p.key.startswith(f"models.{name}.") for p in unknown)}
    descs, failed = describe_agents(scene, skip=bad)
    missing = {f"models.{name}" for name in scene.models if name not in descs}  # (said above already)
    fitting = [p for p in check_against_agents(scene, descs) if p.key not in missing]
    found = fitting if by_hand else [*unknown, *failed, *fitting]
    return sorted(found, key=lambda p: (p.line is None, p.line or 0)), descs


def without_fallback(scene: Scene, descs: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The responsibilities (``entity.attribute``) the scene's main model cannot own: if the model that owns one is
    lost, it has no model to fall back to and stays where it was (README, *Trust*)."""
    main = descs.get(scene.main)
    if main is None:
        return []
    can_own = set(main.get("attributes") or ())
    return [f"{e}.{a}" for (e, a) in scene.initial_owners() if a not in can_own]


def cmd_check(args: argparse.Namespace) -> int:
    check_recording_options(args)
    given = [f for f, v in (("--remap", args.remap), ("--joint-order", args.joint_order)) if v]
    if given and not args.recording:  # (they were left out without a word, and the check said nothing of them)
        raise ValueError(f"{' and '.join(given)} {'says' if len(given) == 1 else 'say'} how to read a bag: give it "
                         "with --recording BAG")
    scene = load_scene(args.scene)  # a SceneError is printed by main (exit 2)
    descs: dict[str, Any] = {}
    # what the agents twin run / twin serve can start will declare (with --by-hand, those of other kinds are
    # started by hand and not asked; a built-in kind's misspelt parameter is still said)
    problems, descs = agent_problems(scene, by_hand=args.by_hand)
    if problems:
        raise SceneError.of(problems)
    robot = scene.robot
    print(f"{args.scene}: scene {scene.name} is valid: {len(scene.models)} model{'s' * (len(scene.models) != 1)}, "
          f"{len(scene.entities)} entit{'ies' if len(scene.entities) != 1 else 'y'}"
          + (f"; robot {robot.name} ({robot.urdf}), joints {', '.join(robot.joints)}" if robot else ""))
    stay = without_fallback(scene, descs)
    if stay:  # no defect (a temperature is no pose), but what a lost model leaves behind
        print(f"  note: the main model {scene.main} cannot own {', '.join(stay)}: if the model that owns "
              f"{'it' if len(stay) == 1 else 'one'} is lost, it stays where it was (no model to fall back to)")
    if not args.recording:
        return 0
    rec = _load_recording(args)
    js = [m for _, k, m in rec.items if k == "joint_state"]
    print(f"{rec.path} ({READABLE.get(rec.storage, rec.storage)}): {len(js)} joint states, "
          f"{len(rec.items) - len(js)} actions over {rec.duration:.2f} s"
          + "".join(f"; {k}: {', '.join(v)}" for k, v in (getattr(rec, "topics", None) or {}).items()))
    left_out = rec.warnings()  # malformed messages left out, a file cut short: the run would be degraded
    for line in left_out:
        print(f"  warning: {line}", file=sys.stderr)
    for line in rec.notes():
        print(f"  note: {line}")
    recorded = rec.joints_in_order
    note = perceive(scene, ReplaySource(rec))
    if note:
        print(f"  note: {note}")
    fit_robot = scene.declared_robot or robot
    warnings = list(scene.perception_missed)
    for line, close in unheard_actions(scene.triggers, rec):
        if close:
            warnings.append(line)
        else:
            print(f"  note: {line}")
    if fit_robot is not None:  # InputError (no joint fits): main prints it, exit 2
        warnings += check_fit(fit_robot, recorded, str(rec.path), rec) + telemetry_warnings(fit_robot, rec)
        matched, _ = fit_robot.fit(recorded)
        print(f"  robot joints reported: {len(matched)} of {len(fit_robot.joints)}"
              + (f" (the map renames {len(fit_robot.joint_map)})" if fit_robot.joint_map else ""))
    for w in warnings:
        print(f"  warning: {w}", file=sys.stderr)
    if warnings or left_out:
        return 3
    print("  fits: twin run would replay it" + (" with every robot joint" if fit_robot is not None else ""))
    return 0


def register(subparsers) -> None:
    c = subparsers.add_parser("check", help="check a scene, and a robot's bag against it, without running",
                              description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("scene", help="scene YAML file")
    c.add_argument("--recording", metavar="BAG", help="the robot's recording to check against the scene (an MCAP "
                                                       "file, a rosbag2 folder or a .db3)")
    c.add_argument("--by-hand", action="store_true",
                   help="the scene's agents are started by hand, for twin conductor: a kind that is not built-in "
                        "(and has no ':') is allowed, as twin conductor allows it; its agent says what it is when it "
                        "registers (the built-in kinds' parameters are still checked)")
    add_recording_options(c)
    c.set_defaults(func=cmd_check)
