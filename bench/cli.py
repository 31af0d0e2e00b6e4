"""The benchmark and evaluation commands: ``twin bench overhead|scale`` and ``twin evaluate``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from conductor.cli.run import DefaultsHelp, count, seed_arg
from conductor.record import EXIT_CODES

from .common import ROOT
from .evaluate import cmd_evaluate, cmd_rtf, merge_results, write_table1, write_table2
from .overhead import cmd_overhead
from .scale import cmd_scale


def parallel_arg(text: str) -> int | str:
    """``--parallel``'s value: ``auto``, or a count of at least 1."""
    return text if text == "auto" else count(text)


# what an earlier --json of twin evaluate (table2) and of twin evaluate rtf holds, that --render needs
FIGURES = {"table2": ("runs", "overall", "by_reality", "by_kind"), "rtf": ("recording", "setups")}


def read_figures(path: str, what: str) -> dict:
    """The figures of an earlier ``--json`` for ``--render``; ValueError saying why they cannot be read (no such
    file, not JSON, or not the figures of ``twin evaluate`` in mode ``what``)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"cannot read {path}: {e}") from None
    mode = "twin evaluate rtf" if what == "rtf" else "twin evaluate"

    def refused(why: str) -> ValueError:
        return ValueError(f"cannot read {path}: not the figures of {mode} --json ({why})")

    if not isinstance(data, dict):
        raise refused("not a JSON object")
    ended = str(data.get("status", "complete")) in ("complete", "degraded")
    need = FIGURES[what] if ended or what == "rtf" else ("runs",)  # (one that stopped early has no summary)
    missing = [k for k in need if k not in data]
    if missing:
        raise refused(f"no {', '.join(missing)}")
    rows = data["runs" if what == "table2" else "setups"]
    if not isinstance(rows, list) or (what == "rtf" and len(rows) < 2):
        raise refused("too few rows")
    return data


def register_bench(sub) -> None:
    b = sub.add_parser("bench", help="benchmarks (conductor overhead against raw Zenoh and mosaik, scale)",
                       description="Benchmarks. Figures are measured side by side in one run; compare ratios.")
    bs = b.add_subparsers(dest="bench_command", metavar="BENCH")
    o = bs.add_parser("overhead", help="conductor ticks/s with N trivial agents vs raw Zenoh and mosaik",
                      description="Ticks per second of the conductor stepping N trivial service-stepped agents, "
                                  "beside a raw Zenoh baseline (one process querying N queryable processes) and "
                                  "mosaik 3 stepping N trivial simulator processes, all in this run.",
                                  formatter_class=DefaultsHelp)
    o.add_argument("--agents", default="1,4,16", help="comma-separated agent counts (default 1,4,16)")
    o.add_argument("--ticks", type=int, default=2000, help="ticks per measurement (default 2000)")
    o.add_argument("--repeat", type=count, default=3, help="alternating repetitions per N (median reported)")
    o.add_argument("--no-mosaik", action="store_true", help="skip the mosaik comparison")
    o.add_argument("--out", metavar="FILE.json", help="write the results as JSON")
    o.set_defaults(func=cmd_overhead)
    add_scale_parser(bs)
    b.set_defaults(func=lambda a: (b.print_help(), 2)[1])


def add_scale_parser(bench_subparsers) -> None:
    s = bench_subparsers.add_parser(
        "scale", help="conductor ticks/s as agents multiply and spread over emulated hosts",
        description="Ticks per second of the conductor stepping N trivial service-stepped agents placed on 1 "
                    "host (loopback) or spread over H network-namespace hosts (needs root), beside raw Zenoh "
                    "query and pub/sub baselines with the same placement; writes JSON and a PNG plot.",
                    formatter_class=DefaultsHelp)
    s.add_argument("--agents", default="4,16,64", help="comma-separated agent counts (default 4,16,64)")
    s.add_argument("--hosts", default="1,4", help="comma-separated host counts (default 1,4)")
    s.add_argument("--ticks", type=int, default=500, help="ticks (rounds) per measurement (default 500)")
    s.add_argument("--repeat", type=count, default=1, help="repetitions per point (median reported)")
    s.add_argument("--out", default=str(ROOT / "docs" / "results" / "bench_scale.json"), metavar="FILE.json",
                   help="results (default docs/results/bench_scale.json)")
    s.add_argument("--plot", metavar="FILE.png", help="plot (default: the JSON path with .png)")
    s.add_argument("--logdir", default="/tmp/twin-bench-scale", help="agent logs")
    s.set_defaults(func=cmd_scale)


def register_evaluate(sub) -> None:
    e = sub.add_parser("evaluate", help="interpret recordings with the ensemble and the baselines (Table 2); "
                                        "'evaluate rtf' for Table 1",
                       description="Run every recording through the ensemble and the three single-simulation "
                                   "baselines, compare each interpretation with the recording's ground truth and "
                                   "print the verdicts; with --table write the paper's Table 2 (markdown + PNG), with "
                                   "--json all the figures. "
                                   "'twin evaluate rtf' measures Table 1's five setups in one run. Exit codes: 0 "
                                   "every run complete, 2 bad input (a recording it cannot evaluate, a configuration "
                                   "with no scene for any recording, an output it cannot write), 3 some run not "
                                   "complete (never counted correct), 4 stopped (what ran is reported).",
                                   formatter_class=DefaultsHelp)
    e.add_argument("what", nargs="?", choices=["table2", "rtf"], default="table2",
                   help="table2 (default) or rtf (Table 1)")
    e.add_argument("--recordings", default=str(ROOT / "recordings"),
                   help="folder of .mcap recordings, or one recording (default recordings/)")
    e.add_argument("--recording", help="rtf: the recording to replay (default: the first ball_drop recording)")
    e.add_argument("--configs", default=None,
                   help="which configurations to run (default ensemble,baseline1,baseline2,baseline3; with --render: "
                        "the configurations in the figures)")
    e.add_argument("--json", metavar="FILE", help="write all figures as JSON")
    e.add_argument("--table", default=None, metavar="FILE.md",
                   help="also write the table as markdown (Table 2 also as a PNG beside it; make evaluate writes "
                        "docs/results/table2.md and table1.md)")
    e.add_argument("--run-dir", default="runs/evaluate", help="where run logs go")
    e.add_argument("--parallel", type=parallel_arg, default="auto", metavar="N|auto",
                   help="interpret N recordings at once on the warm service, each on agents of its own (with "
                        "--samples: one recording at a time, its samples N at a time). auto (the default): one "
                        "per idle core, at most one per GiB of memory available. The runs are CPU-bound: on a "
                        "two-core machine 2 interpreted 18-55 %% more recordings a minute than 1 (more for more "
                        "recordings); 3 was not reliably faster than 2. --cold interprets one recording at a time "
                        "whatever N is")
    e.add_argument("--samples", type=count, default=None, metavar="K",
                   help="also run K variations of each run (twin run --samples) and report the Brier score of the "
                        "predicate's probability beside the hit rate")
    e.add_argument("--seed", type=seed_arg, default=None,
                   help="with --samples: sample i is drawn with seed + i (so seeds 5 and 6 share all "
                        "draws but one: for independent repeats, space the seeds by K or more)")
    e.add_argument("--cluster", metavar="ADDRESS", help="with --samples: run the samples on a Dask cluster")
    e.add_argument("--cold", action="store_true",
                   help="start fresh agent processes (and a router) for every run, as twin run does (default: one "
                        "warm service in this process, each scene's agents started once and initialised per run)")
    e.add_argument("--repeat", type=count, default=None, help="rtf: runs per setup (median reported; default 3)")
    e.add_argument("--render", metavar="FILE.json", action="append",
                   help="run nothing: write the table (markdown, PNG) again from the figures of an earlier --json "
                        "(e.g. after editing the notes file next to it); given several times, their runs are merged "
                        "(configurations run later join those run before; with --json the merged figures are "
                        "written too)")

    DEFAULT_CONFIGS = ("ensemble", "baseline1", "baseline2", "baseline3")

    def run(args):
        if args.render:
            if args.table is None:
                print("twin evaluate: --render needs --table FILE.md (where to write the table)", file=sys.stderr)
                return 2
            try:
                parts = [read_figures(f, args.what) for f in args.render]
            except ValueError as err:
                print(f"twin evaluate: {err}", file=sys.stderr)
                return 2
            data = parts[0] if len(parts) == 1 or args.what == "rtf" else merge_results(parts)
            if args.json and len(parts) > 1:
                Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                Path(args.json).write_text(json.dumps(data, indent=2, default=str))
                print(f"wrote {args.json}")
            if args.what == "rtf":
                write_table1(data, Path(args.table))
                print(f"wrote {args.table}")
                return 0
            status = str(data.get("status", "complete"))
            if status not in ("complete", "degraded"):  # as an evaluation that stopped writes no table itself
                print(f"twin evaluate: {args.table} not written: the figures are of an evaluation that did not run "
                      f"to its end ({status}: {data.get('stopped') or '; '.join(data.get('status_reasons') or [])})",
                      file=sys.stderr)
                return EXIT_CODES.get(status, 1)
            wanted = args.configs.split(",") if args.configs else list(data.get("configs") or DEFAULT_CONFIGS)
            shown = [c for c in wanted if any(c in r["interpretations"] for r in data["runs"])]
            if not shown:
                print(f"twin evaluate: {args.table} not written: no run of {', '.join(wanted) or 'any configuration'} "
                      "in the figures", file=sys.stderr)
                return 2
            write_table2(data, Path(args.table), shown)
            print(f"wrote {args.table}")
            if status == "degraded":  # (its runs that did not complete are counted as not correct, as when run)
                print(f"status: degraded: {'; '.join(data.get('status_reasons') or [])}")
                return EXIT_CODES["degraded"]
            return 0
        alone = [o for o, given in (("--seed", args.seed is not None), ("--cluster", args.cluster is not None))
                 if given]
        if alone and args.samples is None:  # else silently one run each, on this machine
            print(f"twin evaluate: {', '.join(alone)} go{'es' if len(alone) == 1 else ''} only with --samples K",
                  file=sys.stderr)
            return 2
        rtf_only = [o for o, given in (("--recording", args.recording is not None),
                                       ("--repeat", args.repeat is not None)) if given]
        if rtf_only and args.what != "rtf":  # else silently ignored
            print(f"twin evaluate: {', '.join(rtf_only)} go{'es' if len(rtf_only) == 1 else ''} only with "
                  "'twin evaluate rtf'", file=sys.stderr)
            return 2
        args.repeat = args.repeat or 3
        args.configs = args.configs or ",".join(DEFAULT_CONFIGS)
        return cmd_rtf(args) if args.what == "rtf" else cmd_evaluate(args)

    e.set_defaults(func=run)
