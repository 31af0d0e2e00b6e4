"""``twin record``: make robot recordings. ``twin record synth`` plays the real robot and its world."""
from __future__ import annotations

import argparse
import sys

SYNTH_DESCRIPTION = """\
Generate a robot recording (MCAP, rosbag2 layout) from a scripted Franka Panda task in a separate,
higher-fidelity pybullet world (1 kHz, its own contact settings, randomized friction and masses).

The file holds /joint_states (the nine Panda joints at 250 Hz, with sensor noise and timing jitter),
/action annotations (move_arm, move_hand, release; phases start/end) and three metadata records:
  twin.ground_truth  what the run really produced, measured in the simulated world
                     (ball_drop: in_container; insertion: connected)
  twin.scene         what the robot perceived (entity poses and shapes) -- the conductor places the
                     scene's entities there before a replay
  twin.generation    every parameter used, and the command that regenerates the file

Every random choice (positions, friction, masses, noise, timing, heights) is drawn from --seed:
the same arguments give the same file, and another seed gives another valid case.

examples:
  twin record synth --scenario ball_drop --seed 3 --container cup --outcome success --out cup3.mcap
  twin record synth --scenario ball_drop --seed 4 --outcome empty_grasp --out empty4.mcap
  twin record synth --scenario insertion --seed 11 --localization-error 0.006 --out ins11.mcap
"""

OUTCOME_HELP = ("ball_drop script (default success): success = drop the ball over the container; "
                "released_early = the hand opens on the way, well before the container; missed = it opens "
                "beside the container; empty_grasp = the fingers close on nothing (the ball is not where the "
                "robot believes, or the hand stops too high) and the robot carries on. The ground truth is "
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
    from .synth import SynthError, synthesize

    if args.scenario == "insertion" and (args.container or args.outcome):
        print("twin record synth: --container and --outcome apply to ball_drop only", file=sys.stderr)
        return 2
    if args.scenario == "ball_drop" and args.localization_error is not None:
        print("twin record synth: --localization-error applies to insertion only", file=sys.stderr)
        return 2
    progress = _progress(not args.quiet)
    try:
        res = synthesize(args.scenario, args.seed, args.out, container=args.container or "bin",
                         outcome=args.outcome or "success",
                         localization_error=0.002 if args.localization_error is None else args.localization_error,
                         time_scale=args.time_scale, progress=progress)
    except (SynthError, ValueError) as e:
        if progress and sys.stderr.isatty():
            print(file=sys.stderr)
        print(f"twin record synth: {e}", file=sys.stderr)
        return 1
    if progress and sys.stderr.isatty():
        print(file=sys.stderr)
    truth = ", ".join(f"{k}={v}" for k, v in res.ground_truth.items() if k in ("in_container", "connected"))
    print(f"{res.path}: {args.scenario} seed {args.seed}: {truth}; {res.duration:.1f} s, "
          f"{res.joint_states} joint states, {res.actions} actions, {res.size_bytes / 1024:.0f} KiB "
          f"(generated in {res.wall_s:.1f} s)")
    return 0


def register(sub) -> None:
    from .synth import CONTAINERS, OUTCOMES, SCENARIOS

    r = sub.add_parser("record", help="make robot recordings (synthetic, from a simulated reality)",
                       description="Make robot recordings. 'twin record synth' generates one from a scripted "
                                   "Franka Panda in a simulated reality.")
    rs = r.add_subparsers(dest="record_command", metavar="SOURCE")
    s = rs.add_parser("synth", help="generate a recording of a scripted Panda task with measured ground truth",
                      description=SYNTH_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--scenario", required=True, choices=SCENARIOS,
                   help="ball_drop: pick a tennis ball from a stand, drop it into a container; insertion: insert "
                        "a held DIP (plug) into an SPU (socket)")
    s.add_argument("--seed", type=int, required=True, help="seed of every random choice (numpy default_rng)")
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
    s.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    s.set_defaults(func=cmd_synth)
    r.set_defaults(func=lambda a: (r.print_help(), 2)[1])
