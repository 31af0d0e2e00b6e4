"""``twin run SCENE --recording R --samples K``: K variations of what the twin does not know for sure, each run as
a whole ensemble (here on warm agents, ``--cold`` with fresh processes for each, or on a Dask cluster with
``--cluster``), reported as probabilities."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from ..fleet import DaskFleet, Fleet, LocalFleet, WarmLocal
from ..launch import ctrl_c_stops, write_summary
from ..record import exit_code
from ..sampling import (
    distribution,
    print_distribution,
    print_outcome,
    print_sample,
    sample_jobs,
    unvaried,
    worst_status,
)
from ..sources.recording import parse_joint_order

NOT_WITH_SAMPLES = (("--live", "live"), ("--ros2-domain", "ros2_domain"), ("--from-log", "from_log"),
                    ("--connect", "connect"), ("--open-bus", "open_bus"), ("--idle-timeout", "idle_timeout"),
                    ("--ros2-namespace", "ros2_namespace"), ("--no-hold", "no_hold"))
"""Options of one run that samples do not take (each sample is a replay of the recording on a bus of its own, with
a run log and no stream): refused, never silently left out. (``--rtf`` paces each sample, as on twin serve.)"""


def cmd_samples(args) -> int:
    given = [flag for flag, attr in NOT_WITH_SAMPLES if getattr(args, attr, None) not in (None, False, "")]
    given += ["--rerun"] if str(getattr(args, "rerun", "none")).lower() != "none" else []
    for flag, attr, env, default in (("--listen", "listen", "", None),  # (TWIN_LISTEN is read after: not given)
                                     ("--ensemble", "ensemble", "TWIN_ENSEMBLE", "default")):
        if getattr(args, attr, None) not in (None, os.environ.get(env, default)):  # (given, not the environment's)
            given.append(flag)
    if given:
        print(f"twin run --samples: {', '.join(given)} do{'es' if len(given) == 1 else ''} not go with --samples K "
              "(each sample replays the recording on a bus and an ensemble of its own, with a run "
              "log and no Rerun stream): run one run without --samples for that", file=sys.stderr)
        return 2
    if not args.recording:
        print("twin run --samples: give --recording (samples vary a replay)", file=sys.stderr)
        return 2
    if args.samples < 1:
        print("twin run --samples: K must be at least 1", file=sys.stderr)
        return 2
    run_root = Path(args.run_dir or Path("runs") / f"samples-{time.strftime('%Y%m%d-%H%M%S')}")
    jobs, name = sample_jobs(args.scene, args.recording, args.samples, args.seed, run_root,
                             perception=args.perception, remap=args.remap,
                             joint_order=parse_joint_order(args.joint_order), deadline=args.deadline,
                             max_ticks=args.max_ticks, rtf=args.rtf, register_timeout=args.register_timeout)
    fleet: Fleet = (DaskFleet(args.cluster) if args.cluster is not None else LocalFleet(args.jobs or 1) if args.cold
                    else WarmLocal(run_root / "service", args.jobs or 1, args.register_timeout))
    print(f"{args.samples} samples of {name} (seed {args.seed}) on {fleet.where}", flush=True)
    t0 = time.perf_counter()

    try:
        with ctrl_c_stops(fleet.stop):  # Ctrl-C: the samples going on end truncated, no more start
            summaries = fleet.map(jobs, print_sample)
    finally:
        fleet.close()
    d = distribution(summaries)
    d.update(scene=name, recording=args.recording, seed=args.seed, where=fleet.where,
             wall_s=round(time.perf_counter() - t0, 2), status=worst_status(summaries),
             variations=[j["perception"] for j in jobs], runs=[str(Path(j["run_dir"])) for j in jobs],
             note=unvaried([j["perception"] for j in jobs]))
    print_distribution(d, name, args.recording)
    print_outcome(d)
    if args.summary:
        print(f"summary: {write_summary(args.summary, d)}")
    return exit_code(d)  # (2 when every sample failed on the scene itself: ``bad_input``, see distribution)
