"""The tool commands of the recordings package: ``twin record synth`` and ``twin robot play``."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from pathlib import Path

import zenoh

from conductor.cli.run import (
    DefaultsHelp,
    add_recording_options,
    count,
    finite,
    positive,
    ros2_domain,
    ros2_namespace,
    seed_arg,
)
from conductor.record import EXIT_CODES
from conductor.sources.recording import load_recording, parse_joint_order
from protocol.config import add_zenoh_args, options_from_args
from protocol.keys import CONDUCTOR, LISTENER, Keys

from .player import Player, wait_for_twin
from .synth import CONTAINERS, OUTCOMES, REALITIES, SCENARIOS, SynthError
from .synth.arm import ROBOTS

SYNTH_DESCRIPTION = """\
Generate a robot recording (MCAP, rosbag2 layout) from a scripted robot task (a Franka Panda, or with
--robot xarm6 a UFactory xArm 6) in a separate, simulated reality (1 kHz, its own contact settings,
randomized friction and masses): pybullet (the default) or MuJoCo (--reality mujoco: another engine, so
that the twin is not judged by its own).

The file holds /joint_states (every joint of the robot, the Panda's nine or the xArm's seven, at 250 Hz,
with sensor noise and timing jitter), /action annotations (move_arm, move_hand, release; phases
start/end) and three metadata records:
  twin.ground_truth  what the run really produced, measured in the simulated world
                     (ball_drop: in_container; insertion: connected)
  twin.scene         what the robot perceived (entity poses and shapes) -- the conductor places the
                     scene's entities there before a replay
  twin.generation    every parameter used, the reality (reality=mujoco; none: pybullet) and the
                     command that regenerates the file

Every random choice (positions, friction, masses, noise, timing, heights) is drawn from --seed:
the same arguments give the same file, and another seed gives another valid case.

examples:
  twin record synth --scenario ball_drop --seed 3 --container cup --outcome success --out cup3.mcap
  twin record synth --scenario ball_drop --seed 4 --outcome empty_grasp --out empty4.mcap
  twin record synth --scenario insertion --seed 11 --localization-error 0.006 --out ins11.mcap
  twin record synth --scenario ball_drop --seed 5 --outcome slipped --reality mujoco --out slip5.mcap
"""

OUTCOME_HELP = ("ball_drop script (default success): success = drop the ball over the container; "
                "released_early = the hand opens on the way, well before the container; missed = it opens "
                "beside the container; empty_grasp = the fingers close on nothing (the ball is not where the "
                "robot believes, or the hand stops too high) and the robot carries on; slipped = the grip "
                "holds, then the gripper's force fails during the carry (the xArm's linkage also gives way) and "
                "the ball slides out while the robot still commands the grasp (it opens at the release); "
                "knocked = the robot believes the ball 3-4 cm off along the fingers' closing line, so a "
                "fingertip comes down on the ball, presses it until the arm yields, "
                "and the closing fingers push it off its stand; the robot carries on. The ground truth is "
                "what physically happened, not this choice.")


def _progress(enabled: bool):
    if not enabled:
        return None
    tty = sys.stderr.isatty()

    def show(msg: str) -> None:
        if tty:
            print(f"\r  {msg:<60}", end="", file=sys.stderr, flush=True)
        elif not msg.startswith("t ="):
            print(f"  {msg}", file=sys.stderr, flush=True)

    return show


def cmd_synth(args) -> int:
    if args.scenario == "insertion" and (args.container or args.outcome):
        print("twin record synth: --container and --outcome apply to ball_drop only", file=sys.stderr)
        return 2
    if args.scenario == "ball_drop" and args.localization_error is not None:
        print("twin record synth: --localization-error applies to insertion only", file=sys.stderr)
        return 2
    if Path(args.out).is_dir():  # (it simulated for a minute, then could not write there)
        print(f"twin record synth: cannot write {args.out}: it is a folder (give a file in it, e.g. "
              f"{Path(args.out) / 'recording.mcap'})", file=sys.stderr)
        return 2
    where = Path(args.out).resolve().parent
    try:
        where.mkdir(parents=True, exist_ok=True)  # (the help says so: --out runs/new/x.mcap makes runs/new)
    except OSError:
        pass  # (said below, as for a folder it cannot write to)
    if not where.is_dir() or not os.access(where, os.W_OK):  # (before minutes of simulation, not after)
        print(f"twin record synth: cannot write {args.out}: {where} is not a folder this process may write to",
              file=sys.stderr)
        return 2
    progress = _progress(not args.quiet)
    try:
        from .synth import synthesize

        res = synthesize(args.scenario, args.seed, args.out, container=args.container or "bin",
                         outcome=args.outcome or "success",
                         localization_error=0.002 if args.localization_error is None else args.localization_error,
                         time_scale=args.time_scale, progress=progress, reality=args.reality, robot=args.robot)
    except (SynthError, ValueError, OSError) as e:  # a bad value is bad input (2); a script that failed is not
        if progress and sys.stderr.isatty():
            print(file=sys.stderr)
        print(f"twin record synth: {e}", file=sys.stderr)
        return 2 if isinstance(e, ValueError) else 1
    if progress and sys.stderr.isatty():
        print(file=sys.stderr)
    truth = ", ".join(f"{k}={v}" for k, v in res.ground_truth.items() if k in ("in_container", "connected"))
    print(f"{res.path}: {args.scenario} seed {args.seed} ({args.reality}, {args.robot}): {truth}; "
          f"{res.duration:.1f} s, {res.joint_states} joint states, {res.actions} actions, "
          f"{res.size_bytes / 1024:.0f} KiB (generated in {res.wall_s:.1f} s)")
    return 0


def register_record(sub) -> None:
    r = sub.add_parser("record", help="make robot recordings (synthetic, from a simulated reality)",
                       description="Make robot recordings. 'twin record synth' generates one from a scripted "
                                   "robot (the Franka Panda, or --robot's) in a simulated reality.")
    rs = r.add_subparsers(dest="record_command", metavar="SOURCE")
    s = rs.add_parser("synth", help="generate a recording of a scripted robot task (a Panda, or --robot) with measured "
                                              "ground truth",
                      description=SYNTH_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--scenario", required=True, choices=SCENARIOS,
                   help="ball_drop: pick a tennis ball from a stand, drop it into a container; insertion: insert "
                        "a held DIP (plug) into an SPU (socket)")
    s.add_argument("--seed", type=seed_arg, required=True, help="seed of every random choice (numpy default_rng)")
    s.add_argument("--out", required=True, metavar="FILE.mcap", help="recording to write (folders are created)")
    s.add_argument("--container", choices=CONTAINERS, default=None,
                   help="ball_drop: container style (default bin): wide bin, box, bowl, narrow cup")
    s.add_argument("--outcome", choices=OUTCOMES, default=None, help=OUTCOME_HELP)
    s.add_argument("--localization-error", type=float, default=None, metavar="METRES",
                   help="insertion: how far (m) the robot's belief of the SPU's position is off, in a random "
                        "horizontal direction drawn from the seed (default 0.002)")
    s.add_argument("--time-scale", type=float, default=1.0, metavar="F",
                   help="multiply every scripted duration by F (0.25-4; default 1; below 1 makes shorter, "
                        "faster recordings, e.g. for tests)")
    s.add_argument("--reality", choices=REALITIES, default=REALITIES[0],
                   help="the simulated reality that plays the robot: pybullet (default) or mujoco (another engine "
                        "than the twin's own physics)")
    s.add_argument("--robot", choices=ROBOTS, default="panda",
                   help="the robot the reality plays: panda (default) or xarm6 (the UFACTORY xArm 6 with its gripper; "
                        "ball_drop in the pybullet reality)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    s.set_defaults(func=cmd_synth)
    r.set_defaults(func=lambda a: (r.print_help(), 2)[1])


def nonnegative(text: str) -> float:
    """An argparse type: a finite number of at least 0 (seconds)."""
    return finite(text, strict=False)


JOIN_S = 10.0
"""Seconds ``twin robot play`` tries to join the router (or ``--wait-twin``'s, if longer) before it says why not."""


def cmd_play(args) -> int:
    if args.ros2_namespace and args.ros2_domain is None:  # (said, as twin run says it: not ignored)
        print("twin robot play: --ros2-namespace goes only with --ros2-domain N", file=sys.stderr)
        return 2
    rec = load_recording(args.recording, remap=args.remap, joint_order=parse_joint_order(args.joint_order))
    if not any(kind == "joint_state" for _, kind, _ in rec.items):  # (twin run refuses it: nothing moves a robot)
        print(f"twin robot play: {args.recording}: it has no joint states with joint names: nothing would move a "
              "twin's robot", file=sys.stderr)
        return 2
    opts = options_from_args(args)
    keys = Keys(opts.ensemble)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    join_s = max(JOIN_S, args.wait_twin)
    if opts.config_file:  # (a configuration file's endpoints are not retried a second at a time: bounded instead)
        opts.connect_timeout_ms = int(join_s * 1000)
    try:  # (tried a second at a time: an open waiting for its router in native code was deaf to Ctrl-C)
        session = opts.open_patiently(stop.is_set, give_up_s=join_s)
    except zenoh.ZError:
        session = None
    if session is None:
        if stop.is_set():
            print("twin robot play: stopped before the play began (nothing was sent)", file=sys.stderr)
            return EXIT_CODES["interrupted"]
        print(f"twin robot play: {opts.unanswered(join_s)}", file=sys.stderr)
        return 1
    flawed = rec.warnings()  # what the recording lacks is played as it is, and said: its twin will see it too
    for line in flawed:
        print(f"  warning: {line}", file=sys.stderr)
    left: dict[str, float] = {}  # the twin played to went away: when, and how many joint states it had been sent
    player: Player | None = None
    twins: set[str] = set()  # its tokens there: a conductor's, a twin serve live run's (protocol.keys.LISTENER)
    lock = threading.Lock()

    def on_twin(sample: zenoh.Sample) -> None:
        with lock:
            (twins.add if sample.kind == zenoh.SampleKind.PUT else twins.discard)(str(sample.key_expr))
            if not twins and not left:
                left.update(at=time.monotonic(), sent=player.sent["joint_state"] if player is not None else 0)

    try:
        if args.wait_twin > 0:
            print(f"waiting up to {args.wait_twin:.0f} s for the twin of ensemble {opts.ensemble!r}", flush=True)
            if not wait_for_twin(session, keys, args.wait_twin, stop):
                if stop.is_set():
                    print("twin robot play: stopped while waiting for the twin (nothing was sent)", file=sys.stderr)
                    return EXIT_CODES["interrupted"]
                print(f"twin robot play: no conductor of ensemble {opts.ensemble!r} got ready within "
                      f"{args.wait_twin:.0f} s", file=sys.stderr)
                return 1
            for token in (CONDUCTOR, LISTENER):  # (the twin's token is there now: history brings it)
                session.liveliness().declare_subscriber(keys.alive(token), on_twin, history=True)
        player = Player(session, keys, rec, args.speed, args.ros2_domain, args.ros2_namespace)
        began = time.monotonic()
        where = (f"ROS 2 domain {args.ros2_domain} (rmw_zenoh keys)" if args.ros2_domain is not None
                 else keys.telemetry("**"))
        print(f"playing {args.recording} ({rec.duration:.2f} s, {len(rec.items)} messages) at x{args.speed:g} "
              f"on {where}" + (f" {args.loops} times" if args.loops else " in a loop" if args.loop else ""),
              flush=True)
        loops = 0
        stop.wait(args.lead_in)  # let subscriptions reach this session's new publishers
        looping = bool(args.loop or args.loops)
        done = False  # every pass asked for was played
        while not stop.is_set():
            last = not looping or bool(args.loops and loops + 1 >= args.loops)
            if not player.play_once(stop, then_pause=not last):
                break
            loops += 1
            if last:
                done = True
                break
        player.close()
        print(f"sent {player.sent['joint_state']} joint states and {player.sent['action']} actions in {loops} "
              f"whole pass(es); latest send {1e3 * player.late_max:.1f} ms behind schedule", flush=True)
        if not done and not (args.loop and not args.loops):  # (--loop alone plays until it is stopped)
            print(f"twin robot play: stopped after {loops} whole pass(es) of {args.loops or 1}: the recording was "
                  "not played to its end", file=sys.stderr)
            return EXIT_CODES["interrupted"]
        unheard = player.unheard_lines(where)
        for line in unheard:  # (a robot goes on whoever listens: without --wait-twin, said and no more)
            print(f"  {'warning' if args.wait_twin > 0 else 'note'}: {line}", file=sys.stderr)
        if left:  # (a robot goes on whoever listens; this one was played for that twin, so it says so)
            print(f"twin robot play: the twin of ensemble {opts.ensemble!r} went away {left['at'] - began:.1f} s "
                  f"into the play, after {left['sent']:.0f} joint states: what followed reached no twin (its own "
                  "output says why)", file=sys.stderr)
            return 3
        if unheard and args.wait_twin > 0:  # (played for a twin that was there, and it did not hear it all)
            print(f"twin robot play: the twin of ensemble {opts.ensemble!r} did not hear "
                  f"{'all of the play' if player.reached else 'the play'}", file=sys.stderr)
            return 3
        return EXIT_CODES["degraded"] if flawed else 0
    finally:
        session.close()


def register_robot(sub) -> None:
    r = sub.add_parser("robot", help="stand in for a robot: publish a recording as live telemetry",
                       description="Commands that behave like a robot on the network.")
    rs = r.add_subparsers(dest="robot_command", metavar="ROBOT")
    p = rs.add_parser("play", help="publish a recording on twin/<ensemble>/telemetry/** at its recorded rate",
                      description="Publish a robot recording (MCAP or rosbag2) as live telemetry at the recorded "
                                  "rate, each message stamped with this machine's wall clock at the time it is due "
                                  "(as a robot stamps a measurement; a send held up shows as lag), so "
                                  "'twin conductor SCENE --live' on another machine can attach to it. Exit 0; 1: no "
                                  "router, or no twin within --wait-twin; 2: bad input; 3: the recording has flaws "
                                  "(said; played as it is), or with --wait-twin the twin went away or did not hear "
                                  "the play (its joint states reached no subscriber); 5: stopped before the end.",
                      formatter_class=DefaultsHelp)
    p.add_argument("recording", help="the recording to play: an MCAP file, a rosbag2 directory or a .db3 file")
    add_recording_options(p)
    p.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")
    p.add_argument("--loops", type=count, default=None, metavar="N",
                   help="play N passes, then stop (implies --loop; --loop alone plays until Ctrl-C)")
    p.add_argument("--speed", type=positive, default=1.0, help="play this many times faster than recorded")
    p.add_argument("--wait-twin", type=nonnegative, default=0.0, metavar="SECONDS",
                   help="first wait (up to SECONDS) until the ensemble's conductor has initialised its agents; it "
                        f"also tries as long to join the router (at least {JOIN_S:g} s). If that twin goes away "
                        "before the play ends, the play goes on (a robot does), says so, and exits 3")
    p.add_argument("--lead-in", type=nonnegative, default=0.3, metavar="SECONDS",
                   help="pause between declaring the publishers and the first message")
    p.add_argument("--ros2-domain", type=ros2_domain, default=None, metavar="N",
                   help="publish as a ROS 2 robot on rmw_zenoh would (domain N, CDR) instead of the twin's keys")
    p.add_argument("--ros2-namespace", type=ros2_namespace, default="",
                   help="ROS 2 namespace of the topics (with --ros2-domain)")
    add_zenoh_args(p)
    p.set_defaults(func=cmd_play)
    r.set_defaults(func=lambda a: (r.print_help(), 2)[1])
