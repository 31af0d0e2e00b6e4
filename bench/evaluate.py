"""``twin evaluate``: interpret recordings with the ensemble and the single-simulation baselines
(the paper's Table 2), and ``twin evaluate rtf``: real-time factors of split simulations (Table 1)."""
from __future__ import annotations

import json
import os
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from conductor.fleet import DaskFleet, LocalFleet, WarmFleet, local_service
from conductor.launch import Stopper, ctrl_c_stops, output_dir, run_embedded
from conductor.record import EXIT_CODES, unrun
from conductor.sampling import brier, distribution, sample_jobs, unvaried, wilson, worst_status
from conductor.scene import load_scene
from conductor.scene.perception import perceive
from conductor.service import Job
from conductor.sources.recording import load_recording
from conductor.sources.replay import ReplaySource
from protocol.errors import TwinError

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"

# scenario -> how to judge it: the predicate of the semantic state and the ground-truth key it answers
SCENARIOS: dict[str, dict[str, Any]] = {
    "ball_drop": {"predicate": "in(container, ball)", "truth": "in_container",
                  "labels": {True: "successful (ball in container)", False: "failed (ball not in container)"},
                  "configs": {"ensemble": "ball_drop.yaml", "baseline1": "ball_drop_baseline1.yaml",
                              "baseline2": "ball_drop_baseline2.yaml", "baseline3": "ball_drop_baseline3.yaml",
                              "mujoco_grasp": "ball_drop_mujoco_grasp.yaml", "mujoco": "ball_drop_mujoco.yaml"}},
    "insertion": {"predicate": "connected(dip, spu)", "truth": "connected",
                  "labels": {True: "successful (connected)", False: "failed (not connected)"},
                  "configs": {"ensemble": "insertion.yaml", "baseline1": "insertion_baseline1.yaml",
                              "baseline2": "insertion_baseline2.yaml", "baseline3": "insertion_baseline3.yaml"}},
}
CONFIG_TITLES = {"ensemble": "Ensemble (this twin)", "baseline1": "Baseline 1: pure physics",
                 "baseline2": "Baseline 2: binding on signals", "baseline3": "Baseline 3: force binding",
                 "mujoco_grasp": "Ensemble across engines (MuJoCo grasp)", "mujoco": "MuJoCo alone"}
PAPER_TABLE2 = {  # the paper's reported figures (correct / runs), for comparison
    "ball_drop/true": {"ensemble": "4/5", "best baseline": "2/5"},
    "ball_drop/false": {"ensemble": "5/5", "best baseline": "5/5"},
    "insertion/true": {"ensemble": "3/5", "best baseline": "0/5"},
}


SLOT_BYTES = 1 << 30
"""Memory one recording interpreted at a time needs at most: its warm agents (a pool per configuration) took
0.6 GiB more at two at a time than at one (peak resident set of the evaluation's processes, 20 recordings)."""


def parallel_auto(recordings: int) -> tuple[int, str]:
    """How many recordings ``twin evaluate --parallel auto`` interprets at once, and why: one per core this process
    may use that is idle now (:func:`idle_cores`), at most one per :data:`SLOT_BYTES` of memory available, at most
    the recordings, at least one. The runs are CPU-bound (two at a time used 87 % of both cores of a two-core
    machine, three did no better), so more than the idle cores only makes each slower."""
    cores = machine_cores()
    free = min(cores, max(0, round(idle_cores(cores))))
    idle = max(1, free)
    mem = _available_bytes()
    slots = max(1, mem // SLOT_BYTES) if mem is not None else idle
    n = max(1, min(idle, slots, recordings))
    why = f"{free} of {cores} cores idle" + (f", {mem / SLOT_BYTES:.0f} GiB available" if mem is not None else "")
    return n, why


def idle_cores(cores: int, window: float = 0.3) -> float:
    """How many of the machine's cores were idle over the last ``window`` seconds (``/proc/stat``; where there is
    none, ``cores`` less the last minute's load average, which lags a minute behind)."""
    def ticks() -> tuple[int, int]:
        with open("/proc/stat") as f:
            values = [int(v) for v in f.readline().split()[1:]]
        return values[3] + values[4], sum(values[:8])  # idle + iowait, and all but guests (counted in user)

    try:
        idle0, all0 = ticks()
        time.sleep(window)
        idle1, all1 = ticks()
        n = os.cpu_count() or cores
        return n * (idle1 - idle0) / max(1, all1 - all0) if all1 > all0 else float(cores)
    except (OSError, ValueError, IndexError):
        return cores - os.getloadavg()[0]


def _available_bytes() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` (None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def scenario_of(rec) -> str:
    gen = rec.metadata.get("twin.generation", {})
    sc = gen.get("scenario")
    if sc:
        try:
            sc = json.loads(sc)
        except ValueError:
            pass
        return str(sc)
    name = Path(rec.path).name
    for s in SCENARIOS:
        if name.startswith(s):
            return s
    raise ValueError(f"{rec.path}: cannot tell the scenario (no twin.generation metadata)")


class Warm:
    """A warm service in this process (``twin serve``'s :class:`~conductor.service.Service` on an embedded router
    of its own, admitting only its agents): every scene's agents are started once and initialised again for each run."""

    def __init__(self, root: Path, max_pools: int = 8) -> None:
        self.session, self.service, self.bus = local_service(root, f"eval{os.getpid()}", max_pools)

    def run(self, scene_path: Path, rec: Any, run_dir: Path) -> dict[str, Any]:
        job = Job(scene_text=Path(scene_path).read_text(encoding="utf-8"), scene_file=str(scene_path),
                  recording=rec.path)
        return self.service.run(job, run_dir, lambda: STOP.reason)  # (Ctrl-C as it starts: not run)

    def close(self) -> None:
        self.service.close()
        self.session.close()
        self.bus.close()


WARM: Warm | None = None
"""The warm service ``twin evaluate`` runs through (None: ``--cold``, fresh processes for every run)."""
SAMPLES: tuple[int, int, Any] | None = None
"""``--samples K``: (K, seed, the fleet that runs them), or None."""
STOP = Stopper()
"""Ends the cold runs going on, and tells the evaluation to start no more (Ctrl-C: :func:`stop_all`)."""


def stop_all(reason: str) -> None:
    """End the runs going on (``truncated``) and start no more, on whatever runs them."""
    STOP.stop(reason)
    if WARM is not None:
        WARM.service.stop_all(reason)
    if SAMPLES is not None:
        SAMPLES[2].stop(reason)


def sampled(scene_path: Path, rec: Any, run_dir: Path, predicate: str, truth: bool, tag: str) -> dict[str, Any]:
    """K variations of one run (``--samples``): the predicate's probability, its interval, its Brier score."""
    assert SAMPLES is not None
    k, seed, fleet = SAMPLES
    jobs, _ = sample_jobs(str(scene_path), rec.path, k, seed, run_dir, tag=tag)
    d = distribution(fleet.map(jobs))
    p = d["predicates"].get(predicate, {})
    exact = p["true"] / p["of"] if p.get("p") is not None else None  # (the score of the unrounded probability)
    return {"p": p.get("p"), "interval95": p.get("interval95"), "complete": d["complete"], "samples": k,
            "brier": brier(exact, truth), "note": unvaried([j["perception"] for j in jobs]),
            "seed": seed, "variations": [j["perception"] for j in jobs]}  # (each sample's draw: reproducible)


def run_one(scene_path: Path, rec, run_dir: Path, ensemble: str, rerun: str = "none",
            perception: dict | None = None) -> dict:
    """One run of ``scene_path`` on ``rec``, the entities where the recording perceived them (or as
    ``perception`` places them)."""
    if STOP.reason is not None:
        return unrun(f"not run: stopped by {STOP.reason}", "truncated")
    if WARM is not None and rerun == "none" and perception is None:
        return WARM.run(scene_path, rec, run_dir)
    scene = load_scene(scene_path)
    src = ReplaySource(rec)
    if perception is not None:
        scene.apply_perception(perception)
    else:
        perceive(scene, src)
    return run_embedded(scene, src, ensemble=ensemble, run_dir=run_dir, rerun=rerun,
                        metadata={"twin.recording": {"path": rec.path}}, stopper=STOP)


INSERTION_BANDS = ((0.006, "error <= 6 mm"), (0.012, "6-12 mm"), (0.030, "12-30 mm (rim)"),
                   (float("inf"), "> 30 mm (beside)"))
"""Insertion recordings grouped by the robot's localization error of the SPU (the reality's script argument)."""


def generation(rec: Any) -> dict[str, Any]:
    """A recording's generation metadata, values decoded from JSON where they are JSON."""
    out: dict[str, Any] = {}
    for k, v in rec.metadata.get("twin.generation", {}).items():
        try:
            out[k] = json.loads(v)
        except (ValueError, TypeError):
            out[k] = v
    return out


# robot of a recording (its generation's ``robot``; the Panda names none) -> prefix of its scenes
ROBOT_SCENES = {"panda": "", "xarm6": "xarm_"}


def machine_cores() -> int:
    """The cores this process may run on (the figures' machine, kept in their JSON)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def on_machine(figures: dict[str, Any]) -> str:
    """Where ``figures`` were measured, for their table: the cores their JSON kept (older figures kept none)."""
    n = figures.get("cores")
    return f"a {n}-core machine" if isinstance(n, int) else "the machine it ran on"


def cannot_write(path: Path) -> str | None:
    """Why a file of figures cannot be written at ``path`` (None: it can; its folder is made if need be)."""
    if path.is_dir():
        return "a folder, not a file"
    existed = path.exists()
    try:  # tried, not asked of os.access (root passes that where the file system refuses: /proc, read-only)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a"):
            pass
    except OSError as e:
        return f"cannot be written ({e.strerror or e})"
    if not existed:
        path.unlink(missing_ok=True)
    return None


def read_whole(path: Path, read: dict[Path, Any], i: int, n: int) -> str | None:
    """Read the recording at ``path`` (the ``i``-th of ``n``) as a run will, into ``read``; why it cannot be (None:
    it can). Progress is shown for a long folder."""
    if n >= 20 and i % 10 == 0:
        print(f"reading the recordings: {i} of {n}", flush=True)
    try:
        rec = load_recording(path)
    except TwinError as e:
        return str(e) if str(e).startswith(str(path)) else f"{path}: {e}"
    if rec.damaged:  # (scored against the whole recording's ground truth, a run of part of it says little)
        return (f"{path}: {rec.damaged[0]}: twin evaluate takes whole recordings only ('twin run' replays what it "
                "holds)")
    read[path] = rec
    return None


def unfit(path: Path) -> str | None:
    """Why ``twin evaluate`` cannot evaluate the file at ``path`` (None: it can), from its MCAP header and
    metadata alone: not a file (a dangling link), not a readable MCAP file, a scenario or robot it cannot tell or
    has no scenes for (a run log, say)."""
    from mcap.reader import make_reader

    from conductor.runlog.reader import LOG_INFO, MAGIC, ends_early
    from conductor.sources.recording import ended_short

    if not path.is_file():
        return ("not a file (a link to nothing?)" if path.is_symlink() else "not a file" if path.exists() else
                "no such file or folder")
    try:
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:  # (said so, not as the MCAP reader's tuple of the first bytes)
                return "not a recording: not an MCAP file by its first bytes (twin evaluate reads MCAP recordings)"
            if ends_early(f):  # an MCAP file without its end
                return ("cut short (no end: its recorder was killed, or the copy stopped): twin evaluate takes whole "
                        "recordings only ('twin run' replays what it holds)")
            f.seek(0)
            meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    except Exception as e:  # what mcap raises on a file that is not MCAP varies with the damage
        return f"not a readable MCAP recording ({type(e).__name__}: {e})"
    if LOG_INFO in meta:  # (a run log holds the robot's telemetry, but not what the robot's run was)
        replayed, partial = meta.get("twin.recording", {}).get("path"), ended_short(meta)
        return "a twin run log, not a robot recording" + (
            f": evaluate the recording it replayed ({replayed})" if replayed else "") + (
            f"; and {partial}" if partial else "")
    header = SimpleNamespace(metadata=meta, path=str(path))  # what scenario_of and robot_of read
    try:
        scenario = scenario_of(header)
    except ValueError:
        return "cannot tell the scenario (no twin.generation metadata, and the name starts with no scenario)"
    if scenario not in SCENARIOS:
        return f"scenario {scenario!r}, which twin evaluate has no configurations for"
    if robot_of(header) not in ROBOT_SCENES:
        return f"a recording of robot {robot_of(header)!r}, which has no scenes here"
    truth_key = SCENARIOS[scenario]["truth"]
    if meta.get("twin.ground_truth", {}).get(truth_key) not in ("true", "false"):
        return (f"no ground truth to score against ({truth_key!r}, true or false, in its twin.ground_truth "
                "metadata): 'twin run' interprets it")
    partial = ended_short(meta)  # the log of a run that stopped early, or whose own input was not whole
    if partial:
        return (f"{partial}; scored against the whole recording's ground truth it would be wrong: evaluate the "
                "recording itself")
    return None


def robot_of(rec: Any) -> str:
    return str(generation(rec).get("robot", "panda"))


def scene_for(rec: Any, scenario: str, cfg: str) -> Path | None:
    """The scene file configuration ``cfg`` interprets a recording of ``scenario`` with (for the recording's robot);
    None where that scenario or robot has no scene for it. ValueError for a robot no scene is made for."""
    robot = robot_of(rec)
    if robot not in ROBOT_SCENES:
        raise ValueError(f"{rec.path}: a recording of robot {robot!r}, which has no scenes here")
    name = SCENARIOS[scenario]["configs"].get(cfg)
    path = SCENES / f"{ROBOT_SCENES[robot]}{name}" if name else None
    return path if path is not None and path.is_file() else None


def configs_without_scenes(read: dict[Path, Any], configs: list[str]) -> list[tuple[str, bool]]:
    """A line per configuration that has no scene for some of the recordings ``read`` (their cells stay empty),
    saying for which scenarios and robots, and whether it has one for none of them (it would run on nothing)."""
    out = []
    for cfg in configs:
        missing = [(scenario_of(rec), robot_of(rec)) for rec in read.values()
                   if scene_for(rec, scenario_of(rec), cfg) is None]
        if missing:
            kinds = ", ".join(f"{sc} ({robot})" for sc, robot in sorted(set(missing)))
            none = len(missing) == len(read)
            out.append((f"configuration {cfg} has no scene for " + (
                f"any of the recordings ({kinds}): it would run on none" if none else
                f"{len(missing)} of the {len(read)} recordings ({kinds}): their cells stay empty"), none))
    return out


def kind_of(rec: Any, scenario: str) -> tuple[str, str]:
    """(reality, kind) of a recording: the engine that made it (and the robot, when not the Panda) and its
    failure kind (ball_drop: the script's outcome; insertion: the band of the localization error)."""
    gen = generation(rec)
    reality = str(gen.get("reality", "pybullet"))
    if robot_of(rec) != "panda":
        reality += f" ({robot_of(rec)})"
    if scenario == "ball_drop":
        return reality, str(gen.get("outcome", "?"))
    err = float(gen.get("localization_error", 0.0))
    return reality, next(label for bound, label in INSERTION_BANDS if err <= bound + 1e-12)


def evaluate_one(i: int, n: int, path: Path, configs: list[str], run_dir: Path) -> dict[str, Any] | None:
    """Run one recording through every configuration; the run's entry of the results (None: the evaluation was
    stopped before it began). A run the stop cut short keeps its status, but is not counted either way."""
    if STOP.reason is not None:
        return None
    # through the warm service's cache: its runs of this recording then do not read it again
    rec = WARM.service.recording(str(path)) if WARM is not None else load_recording(path)
    scenario = scenario_of(rec)
    spec = SCENARIOS[scenario]
    gt = rec.ground_truth()
    if not isinstance(gt.get(spec["truth"]), bool):  # (unfit refuses such files before any run)
        raise ValueError(f"{path}: no ground truth {spec['truth']!r} to score against")
    truth = bool(gt[spec["truth"]])
    reality, kind = kind_of(rec, scenario)
    entry: dict[str, Any] = {"recording": str(path), "scenario": scenario, "reality": reality, "kind": kind,
                             "ground_truth": gt, "truth": truth, "interpretations": {}, "correct": {},
                             "status": {}, "wall_s": {}, "rtf": {}, "handovers": {}, "errors": {}}
    for cfg in configs:
        scene_path = scene_for(rec, scenario, cfg)
        if scene_path is None:
            continue  # a configuration this scenario (or robot) has no scene for (its cells stay empty)
        s = run_one(scene_path, rec, run_dir / path.stem / cfg, ensemble=f"eval{os.getpid()}{i}{cfg}")
        if STOP.reason is not None and s["status"] in ("truncated", "interrupted"):
            entry["status"][cfg] = s["status"]  # cut short by the stop: neither right nor wrong
            break
        value = s["semantic_state"].get(spec["predicate"])
        entry["interpretations"][cfg] = s["semantic_state"]
        # a run that is not complete is never counted correct, whatever it concluded
        entry["status"][cfg] = s["status"]
        entry["correct"][cfg] = s["status"] == "complete" and value is not None and bool(value) == truth
        entry["wall_s"][cfg] = s["wall_s"]
        entry["rtf"][cfg] = s["rtf"]
        entry["handovers"][cfg] = [
            f"t={h['t']:.2f} {h['entity']}.{h['attribute']} {h['from']}->{h['to']} ({h['trigger']})"
            for h in s["handovers"]]
        if s["errors"] or s["status"] != "complete":
            entry["errors"][cfg] = (s.get("status_reasons") or [])[:3] + s["errors"][:5]
        mark = "ok " if entry["correct"][cfg] else ("WRONG" if s["status"] == "complete" else s["status"].upper())
        extra = ""
        if SAMPLES is not None:
            sp = entry.setdefault("samples", {})[cfg] = sampled(scene_path, rec, run_dir / path.stem / f"{cfg}-samples",
                                                                 spec["predicate"], truth, f"{i}{cfg}")
            extra = f" P={sp['p']} brier={sp['brier'] if sp['brier'] is None else round(sp['brier'], 3)}" + (
                f" ({sp['complete']} of {sp['samples']} samples complete)" if sp["complete"] < sp["samples"] else "") \
                + (" (nothing varied: K times one run)" if sp.get("note") else "")
            if STOP.reason is not None and sp["complete"] < sp["samples"]:
                del entry["samples"][cfg]  # cut short by the stop: no probability made of part of the samples
                extra = f" samples stopped ({sp['complete']} of {sp['samples']} complete)"
        rtf = s["rtf"] if s["rtf"] is None else f"{s['rtf']:.1f}"
        print(f"[{i + 1}/{n}] {path.name:34s} {cfg:9s} {reality[:2]} {kind[:14]:14s} truth={truth!s:5s} "
              f"{spec['predicate']}={value!s:5s} {mark} rtf={rtf}{extra}", flush=True)
    return entry


def tally(runs: list[dict[str, Any]], key: Any) -> dict[str, dict[str, list[int]]]:
    """correct/runs per configuration for each group ``key(run)`` of the runs."""
    table: dict[str, dict[str, list[int]]] = {}
    for r in runs:
        row = table.setdefault(key(r), {})
        for cfg, ok in r["correct"].items():
            c = row.setdefault(cfg, [0, 0])
            c[0] += int(ok)
            c[1] += 1
    return table


PER_CONFIG = ("interpretations", "correct", "status", "handovers", "errors", "wall_s_by_config", "rtf_by_config",
              "samples")


def brier_scores(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per configuration, with ``--samples``: the mean Brier score of the predicate's probability against the truth
    (samples that did not complete are not counted; a recording none of whose samples completed counts as p = 0.5
    would not be honest either, so it is left out and counted), beside the hit rate of the nominal run."""
    out: dict[str, dict[str, Any]] = {}
    for r in runs:
        for cfg, sp in (r.get("samples") or {}).items():
            o = out.setdefault(cfg, {"scores": [], "unscored": 0, "hits": 0, "runs": 0, "unvaried": 0, "short": 0})
            o["runs"] += 1
            o["short"] += int(sp["samples"]) - int(sp["complete"])  # samples that did not complete: left out
            o["unvaried"] += int(bool(sp.get("note")))  # nothing uncertain: K times the nominal run
            o["hits"] += int(bool(r["correct"].get(cfg)))
            if sp.get("brier") is None:
                o["unscored"] += 1
            else:
                o["scores"].append(sp["brier"])
    return {cfg: {"brier": round(sum(o["scores"]) / len(o["scores"]), 4) if o["scores"] else None,
                  "scored": len(o["scores"]), "unscored": o["unscored"], "hit_rate": f"{o['hits']}/{o['runs']}",
                  "unvaried": o["unvaried"], "samples_not_complete": o["short"]}
            for cfg, o in out.items()}


def summarise(runs: list[dict[str, Any]], configs: list[str], recordings: str, wall_s: float) -> dict[str, Any]:
    """The figures of ``twin evaluate``: the runs and their tallies."""
    return {"brier": brier_scores(runs), "recordings": recordings, "runs": runs, "configs": configs,
            "cores": machine_cores(),
            "table2": tally(runs, lambda r: f"{r['scenario']}/{'true' if r['truth'] else 'false'}"),
            "by_reality": tally(runs, lambda r: f"{r['scenario']}/{'true' if r['truth'] else 'false'}"
                                                f"/{r['reality']}"),
            "by_kind": tally(runs, lambda r: f"{r['scenario']}/{r['kind']}/{r['reality']}"),
            "overall": tally(runs, lambda r: "all"), "wall_s": wall_s}


def degraded_by(runs: list[dict[str, Any]]) -> list[str]:
    """Why an evaluation whose every recording was run is still ``degraded`` (nothing: it is complete): runs that did
    not end complete (counted as not correct), and with ``--samples``, samples that did not (left out of their
    probabilities: a probability of 1 of 8 samples is no probability of 8)."""
    not_complete = [(Path(r["recording"]).name, c, st) for r in runs for c, st in r["status"].items()
                    if st != "complete"]
    short = [(Path(r["recording"]).name, c, sp["samples"] - sp["complete"], sp["samples"]) for r in runs
             for c, sp in (r.get("samples") or {}).items() if sp["complete"] < sp["samples"]]
    out = []
    if not_complete:
        out.append(f"{len(not_complete)} run(s) did not end complete (counted as not correct): "
                   + ", ".join(f"{n} {c} {st}" for n, c, st in not_complete[:10]))
    if short:
        out.append(f"{sum(s for _, _, s, _ in short)} sample(s) did not end complete (left out of their probabilities "
                   "and Brier scores): " + ", ".join(f"{n} {c} {s} of {k}" for n, c, s, k in short[:10]))
    return out


def merge_results(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Several ``--json`` results of the same recordings (e.g. more configurations run later) as one: per
    recording, each configuration's figures from the last result that has them."""
    runs: dict[str, dict[str, Any]] = {}
    configs: list[str] = []
    for res in results:
        configs += [c for c in res.get("configs", []) if c not in configs]
        for r in res["runs"]:
            key = Path(r["recording"]).name
            if key not in runs:
                runs[key] = {k: (dict(v) if k in PER_CONFIG else v) for k, v in r.items()}
                continue
            for k in PER_CONFIG:
                runs[key].setdefault(k, {}).update(r.get(k) or {})
    merged = summarise(sorted(runs.values(), key=lambda r: Path(r["recording"]).name), configs,
                       " + ".join(dict.fromkeys(str(r.get("recordings", "?")) for r in results)),
                       round(sum(float(r.get("wall_s", 0)) for r in results), 1))
    merged["status"] = worst_status(results)  # (one part stopped or degraded: so is the whole)
    reasons = [why for r in results for why in (r.get("status_reasons") or [])]
    if reasons:
        merged["status_reasons"] = reasons
    if any(r.get("stopped") for r in results):
        merged["stopped"] = "; ".join(str(r["stopped"]) for r in results if r.get("stopped"))
        merged["not_run"] = [p for r in results for p in (r.get("not_run") or [])]
    merged["produced_by"] = " + ".join(str(r.get("produced_by", "?")) for r in results)
    kept = {r.get("cores") for r in results}  # (the machine they were measured on, not this one)
    merged["cores"] = kept.pop() if len(kept) == 1 else None
    return merged


def _shown(path: Path) -> str:
    """``path`` as the results name it: relative to the working directory when it lies below it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def cmd_evaluate(args) -> int:
    if getattr(args, "what", None) == "rtf":
        return cmd_rtf(args)
    src = Path(args.recordings)
    recs = sorted(src.glob("*.mcap")) if src.is_dir() else [src]
    if not recs:
        print(f"twin evaluate: no .mcap recordings in {args.recordings}", file=sys.stderr)
        return 2
    configs = args.configs.split(",")
    known = {c for spec in SCENARIOS.values() for c in spec["configs"]}
    unknown = [c for c in configs if c not in known]
    if unknown:
        print(f"twin evaluate: unknown configuration {', '.join(map(repr, unknown))} (known: "
              f"{', '.join(sorted(known))})", file=sys.stderr)
        return 2
    twice = sorted({c for c in configs if configs.count(c) > 1})
    if twice:  # the second would run into the first's folder and overwrite its figures
        print(f"twin evaluate: configuration {', '.join(map(repr, twice))} given twice", file=sys.stderr)
        return 2
    unwritable = [f"{opt} {path}: {why}" for opt, path in (("--json", args.json), ("--table", args.table))
                  if path and (why := cannot_write(Path(path))) is not None]
    if unwritable:  # said now, not after an hour of runs whose figures would then be lost
        print("twin evaluate: " + "; ".join(unwritable), file=sys.stderr)
        return 2
    bad = [f"{p}: {why}" for p in recs if (why := unfit(p)) is not None]
    read: dict[Path, Any] = {}
    if not bad:  # each read whole (its CRCs checked), so that damage inside a file is said now, not after hours
        bad = [why for i, p in enumerate(recs) if (why := read_whole(p, read, i, len(recs))) is not None]
    if bad:  # said before anything runs: an evaluation of part of the folder would be taken for the whole
        print("twin evaluate: recordings it cannot evaluate (move them out of the folder):\n  " + "\n  ".join(bad),
              file=sys.stderr)
        return 2
    unfitting = configs_without_scenes(read, configs)
    if any(none for _, none in unfitting):  # asked for and run on nothing: "none run" would be read as a result
        print("twin evaluate: " + "; ".join(line for line, none in unfitting if none), file=sys.stderr)
        return 2
    for line, _ in unfitting:
        print(f"note: {line}", flush=True)
    try:  # a read-only or unmakeable --run-dir is said now, not as a traceback from the first run
        output_dir(Path(args.run_dir), "--run-dir")
    except TwinError as e:
        print(f"twin evaluate: {e}", file=sys.stderr)
        return 2
    t_start = time.perf_counter()
    global WARM, STOP
    STOP = Stopper()
    k = getattr(args, "samples", None)
    wanted = getattr(args, "parallel", 1) or 1
    if wanted == "auto":  # recordings at a time, or with --samples each recording's samples at a time
        parallel, why = parallel_auto(int(k) if k else len(recs))
        if k or not getattr(args, "cold", False):
            what = ("sample" if k else "recording") + ("s" if parallel > 1 else "")
            print(f"{parallel} {what} at a time (--parallel auto: {why})", flush=True)
    else:
        parallel = max(1, int(wanted))
    WARM = None if getattr(args, "cold", False) else Warm(Path(args.run_dir) / "service", max_pools=8 * parallel)
    if WARM is not None:  # read once: the warm runs take them as read
        for path, rec in read.items():
            WARM.service.keep(str(path), rec)
    read.clear()  # (a cold run reads its recording afresh, as a run of its own does)
    global SAMPLES
    if k:
        fleet: Any = (DaskFleet(args.cluster) if getattr(args, "cluster", None) is not None else
                      WarmFleet(WARM.service, parallel) if WARM is not None else LocalFleet(parallel))
        SAMPLES = (int(k), int(getattr(args, "seed", 0) or 0), fleet)
        print(f"{k} samples per run on {fleet.where}", flush=True)
    try:
        with ctrl_c_stops(stop_all):  # Ctrl-C: the runs going on end truncated, no more start, the rest reported
            if parallel > 1 and WARM is not None and SAMPLES is None:  # side by side, each on warm agents of its own
                with ThreadPoolExecutor(parallel) as pool:
                    entries = list(pool.map(lambda ip: evaluate_one(ip[0], len(recs), ip[1], configs,
                                                                    Path(args.run_dir)), enumerate(recs)))
            else:
                entries = [evaluate_one(i, len(recs), path, configs, Path(args.run_dir))
                           for i, path in enumerate(recs)]
    finally:
        if SAMPLES is not None:
            SAMPLES[2].close()
            SAMPLES = None
        if WARM is not None:
            WARM.close()
            WARM = None
    out_runs = [e for e in entries if e is not None]
    result = summarise(out_runs, configs, _shown(src), round(time.perf_counter() - t_start, 1))
    result["status"] = "complete"  # every recording was run to its end (each run's own status is in its entry)
    result["produced_by"] = "twin evaluate --recordings {} --configs {}{}".format(  # what makes these figures again
        _shown(src), ",".join(configs), f" --samples {k} --seed {getattr(args, 'seed', 0) or 0}" if k else "")
    not_complete = [(Path(r["recording"]).name, c, st) for r in out_runs for c, st in r["status"].items()
                    if st != "complete"]
    reasons = degraded_by(out_runs)
    if STOP.reason is not None:  # what was evaluated before the stop, and that it is not all
        result.update(status="truncated", stopped=f"stopped by {STOP.reason}",
                      not_run=[str(p) for p, e in zip(recs, entries, strict=True) if e is None])
    elif reasons:  # every recording was run, but not every run could do its work: the figures say less
        result.update(status="degraded", status_reasons=reasons)
    for r in out_runs:  # the JSON contract: wall_s/rtf of the ensemble run per recording
        r["wall_s_by_config"], r["rtf_by_config"] = r.pop("wall_s"), r.pop("rtf")
        r["wall_s"] = r["wall_s_by_config"].get("ensemble")
        r["rtf"] = r["rtf_by_config"].get("ensemble")
    overall = result["overall"].get("all", {})  # (nothing at all: stopped before the first run ended)
    print(("correct, of the runs that ended before the stop (each configuration over the recordings it reached): "
           if STOP.reason is not None else "correct: ")
          + ", ".join(f"{c} {overall[c][0]}/{overall[c][1]}" if c in overall else f"{c} none run" for c in configs),
          flush=True)
    if result["brier"]:
        print("Brier score (samples' probability against the truth; 0 best, 0.25 a coin): " + ", ".join(
            f"{c} {b['brier']} (hit rate {b['hit_rate']}" + (f"; {b['unvaried']} of {b['scored'] + b['unscored']} "
                                                             "with nothing varied" if b.get("unvaried") else "")
            + (f"; {b['samples_not_complete']} samples not complete, left out" if b.get("samples_not_complete")
               else "") + ")"
            for c, b in result["brier"].items()), flush=True)
    if args.json:  # only what was asked for: tables are written with --table (or make evaluate)
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2, default=str))
        print(f"wrote {args.json}")
    if args.table and STOP.reason is not None:
        cut = sum(st in ("truncated", "interrupted") for r in out_runs for st in r["status"].values())
        print(f"{args.table} not written: the evaluation was stopped ({len(result['not_run'])} of {len(recs)} "
              f"recordings not begun, {cut} run{'s' if cut != 1 else ''} cut short)", flush=True)
    elif args.table:
        write_table2(result, Path(args.table), configs)
        print(f"wrote {args.table} and {Path(args.table).with_suffix('.png')}")
    for name, c, st in not_complete:
        print(f"not complete (never counted correct): {name} {c}: {st}", flush=True)
    if STOP.reason is not None:
        print(f"status: truncated: stopped by {STOP.reason}; {len(out_runs)} of {len(recs)} recordings begun, the "
              "runs it cut short counted neither right nor wrong", flush=True)
        return EXIT_CODES["truncated"]
    if reasons:
        print(f"status: degraded: {'; '.join(reasons)}", flush=True)
        return EXIT_CODES["degraded"]
    return 0


def _cell(k: int, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{k}/{n} ({100 * lo:.0f}–{100 * hi:.0f} %)"


def write_table2(result: dict[str, Any], path: Path, configs: list[str]) -> None:
    """Table 2 in markdown (and a PNG): correct/runs with 95 % Wilson intervals per scenario, ground truth and
    reality, a row per failure kind, the paper's figures beside ours, every run with its handovers."""
    path.parent.mkdir(parents=True, exist_ok=True)
    head = "| " + " | ".join(CONFIG_TITLES[c] for c in configs) + " |"
    rule = "---|" * len(configs)
    runs = result["runs"]
    produced = result.get("produced_by") or f"twin evaluate --recordings {result.get('recordings', 'recordings')}"
    lines = ["# Table 2: interpreting what happened", "",
             "Correct interpretations / runs (95 % Wilson interval), per scenario, ground truth (measured in the",
             "reality run that made each recording) and reality (the engine that played the robot: pybullet, the",
             "twin's own engine, or MuJoCo, another one). A run that did not end `complete` is never counted",
             f"correct. Produced by `{produced} --table {path.as_posix()}`",
             "(`make evaluate` for the shipped recordings); nothing here is edited by hand except the notes at the",
             "end.", "",
             "## Overall", "", "| | " + head[2:], "|---|" + rule]
    lines.append("| all recordings | " + " | ".join(_cell(*result["overall"]["all"].get(c, [0, 0])) for c in configs)
                 + " |")
    lines += ["", "## By scenario, ground truth and reality", "",
              "| scenario | ground truth | reality | " + head[2:] + " paper: ensemble | paper: best baseline |",
              "|---|---|---|" + rule + "---|---|"]
    for key in sorted(result["by_reality"]):
        scenario, truth, reality = key.split("/")
        row = result["by_reality"][key]
        paper = PAPER_TABLE2.get(f"{scenario}/{truth}", {}) if reality == "pybullet" else {}
        lines.append(f"| {scenario} | {SCENARIOS[scenario]['labels'][truth == 'true']} | {reality} | "
                     + " | ".join(_cell(*row[c]) if c in row else "–" for c in configs)
                     + f" | {paper.get('ensemble', '–')} | {paper.get('best baseline', '–')} |")
    if result.get("brier"):  # --samples: the probabilities against the truth
        lines += ["", "## With samples: Brier score", "",
                  "The mean Brier score of each run's probability of the predicate (its samples' share) against the "
                  "truth (0 best, 0.25 a coin), beside the hit rate of the nominal runs; a recording with nothing "
                  "uncertain to vary counts K times one run.", "",
                  "| configuration | Brier score | scored | no sample complete | nothing varied | hit rate |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {CONFIG_TITLES.get(c, c)} | {b['brier']} | {b['scored']} | {b['unscored']} | "
                  f"{b.get('unvaried', '–')} | {b['hit_rate']} |" for c, b in result["brier"].items()]
    lines += ["", "## By failure kind", "",
              "ball_drop: the script's outcome (the reality measured what happened; a few differ from the intent:",
              "see the runs); insertion: the robot's localization error of the SPU.", "",
              "| scenario | kind | reality | in the container / connected | " + head[2:],
              "|---|---|---|---|" + rule]
    for key in sorted(result["by_kind"], key=lambda k: (k.split("/")[0], k.split("/")[2], k.split("/")[1])):
        scenario, kind, reality = key.split("/")
        row = result["by_kind"][key]
        group = [r for r in runs if r["scenario"] == scenario and r["kind"] == kind and r["reality"] == reality]
        truths = f"{sum(r['truth'] for r in group)}/{len(group)}"
        lines.append(f"| {scenario} | {kind} | {reality} | {truths} | "
                     + " | ".join(_cell(*row[c]) if c in row else "–" for c in configs) + " |")
    lines += ["", "## Runs", "",
              "| recording | reality | kind | ground truth | " + " | ".join(configs) + " | ensemble rtf | "
              "ensemble handovers |", "|---|---|---|---|" + "---|" * len(configs) + "---|---|"]
    for r in runs:
        spec = SCENARIOS[r["scenario"]]
        cells = []
        for c in configs:
            if c not in r["interpretations"]:
                cells.append("–")
                continue
            v = r["interpretations"][c].get(spec["predicate"])
            st = r["status"].get(c, "complete")
            cells.append(f"{v} {'✓' if r['correct'][c] else '✗'}" + ("" if st == "complete" else f" ({st})"))
        hs = "; ".join(r["handovers"].get("ensemble", [])) or "none"
        lines.append(f"| {Path(r['recording']).name} | {r['reality']} | {r['kind']} | "
                     f"{spec['truth']}={r['ground_truth'].get(spec['truth'])} | " + " | ".join(cells)
                     + f" | {r['rtf']} | {hs} |")
    lines += ["", "## Speed", "",
              "Real-time factor (simulated s / wall s of the tick loop) of every run, replaying as fast as the "
              f"models allow, all agents on {on_machine(result)}: median (min–max) per scenario.", "",
              "| scenario | " + head[2:], "|---|" + rule]
    for scenario in sorted({r["scenario"] for r in runs}):
        cells = []
        for c in configs:
            v = [r["rtf_by_config"][c] for r in runs
                 if r["scenario"] == scenario and (r.get("rtf_by_config") or {}).get(c) is not None]
            cells.append(f"{statistics.median(v):.2f} ({min(v):.2f}–{max(v):.2f})" if v else "–")
        lines.append(f"| {scenario} | " + " | ".join(cells) + " |")
    notes = path.with_name(path.stem + "_notes.md")
    if notes.exists():
        lines += ["", notes.read_text().strip()]
    path.write_text("\n".join(lines) + "\n")
    _plot_table2(result, path.with_suffix(".png"), configs)


def _plot_table2(result: dict[str, Any], png: Path, configs: list[str]) -> None:
    try:
        import matplotlib  # optional: the [viz] extra

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    keys = sorted(result["by_reality"])
    fig, ax = plt.subplots(figsize=(11, 4.6))
    w = 0.8 / len(configs)
    for j, c in enumerate(configs):
        cells = [result["by_reality"][k].get(c, [0, 0]) for k in keys]
        # no runs: no bar and no interval (a configuration the scenario has no scene for)
        run = [(i, k_, n) for i, (k_, n) in enumerate(cells) if n]
        vals = [k_ / n for _, k_, n in run]
        err = [[max(0.0, v - wilson(k_, n)[0]) for v, (_, k_, n) in zip(vals, run)],
               [max(0.0, wilson(k_, n)[1] - v) for v, (_, k_, n) in zip(vals, run)]]
        ax.bar([i + j * w for i, _, _ in run], vals, w, yerr=err, capsize=2, label=CONFIG_TITLES[c])
    ax.set_xticks([i + w * (len(configs) - 1) / 2 for i in range(len(keys))])
    ax.set_xticklabels([k.replace("/true/", "\nsuccessful\n").replace("/false/", "\nfailed\n") for k in keys],
                       fontsize=7)
    ax.set_ylabel("correct interpretations (95 % interval)")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.3), ncol=min(len(configs), 3), frameon=False)
    ax.set_title("Did the twin tell what really happened?")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


RTF_SETUPS = [
    ("bare robot world", "fluid_bare.yaml"),
    ("robot + 50 particles, one world", "fluid_one_world_50.yaml"),
    ("robot world + 50 particles in a fluid model", "fluid_split_50.yaml"),
    ("robot world + 100 particles in a fluid model", "fluid_split_100.yaml"),
    ("robot world + 100 particles in a fluid model at 1.5x step", "fluid_split_100_coarse.yaml"),
]


# the paper's Table 1 (Gazebo/ODE): real-time factor of the same five setups
PAPER_TABLE1 = [0.98, 0.55, 0.97, 0.75, 1.09]


def vs_one_world(rows: list[dict[str, Any]]) -> None:
    """Each setup's factor against the one-world setup's (``rows[1]``), round by round (the two measured side by
    side): ``vs_one_world_50`` the median of the rounds' ratios less 1, ``vs_one_world_50_spread`` their range.
    Figures of an older run, not in rounds: the ratio of the medians, no range (its runs were not side by side)."""
    if "rounds" not in rows[1]:
        for r in rows:
            r["vs_one_world_50"] = round(r["rtf"] / rows[1]["rtf"] - 1, 3) if r["rtf"] and rows[1]["rtf"] else None
            r["vs_one_world_50_spread"] = None
        return
    base = dict(zip(rows[1]["rounds"], rows[1]["rtf_all"]))
    for r in rows:
        mine = dict(zip(r["rounds"], r["rtf_all"]))
        ratios = [mine[i] / base[i] - 1 for i in sorted(mine.keys() & base.keys()) if base[i]]
        r["vs_one_world_50"] = round(statistics.median(ratios), 3) if ratios else None
        r["vs_one_world_50_spread"] = [round(min(ratios), 3), round(max(ratios), 3)] if ratios else None


def write_table1(out: dict, path: Path) -> None:
    rows = out["setups"]
    vs_one_world(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    left_out = out.get("left_out") or []
    lines = ["# Table 1: real-time factor of split simulations", "",
             f"Replay of `{Path(out['recording']).name}` as fast as the models allow, medians of "
             f"{out.get('repeat', len(rows[0].get('rtf_all', [])))} " +
             ("rounds, each round running every setup once (in alternating order)" if out.get("order") else
              "runs per setup, one setup's runs after another's (an older run's order)") +
             f", all in one `twin evaluate rtf` run on {on_machine(out)}; *vs. one world* is " +
             ("the median of the rounds' own ratios (their range in brackets). " if out.get("order") else
              "the ratio of the medians. ") +
             "Real-time factor = simulated seconds / wall seconds of the tick loop. The paper's figures (Gazebo/ODE, "
             "its setups 1–5) are beside ours; compare the ratios, not the absolute values." +
             (f" **Left out, not complete:** {'; '.join(left_out)}." if left_out else ""), "",
             "| setup | scene | real-time factor | vs. 50 particles in one world | paper: real-time factor "
             "| paper: vs. one world |",
             "|---|---|---|---|---|---|"]
    for r, p in zip(rows, PAPER_TABLE1):
        vs, spread = r["vs_one_world_50"], r["vs_one_world_50_spread"]
        vs_text = "–" if vs is None else f"{vs:+.0%}" + (f" ({spread[0]:+.0%} to {spread[1]:+.0%})"
                                                          if spread and spread[0] != spread[1] else "")
        rtf = "–" if r["rtf"] is None else f"{r['rtf']:.2f}"
        lines.append(f"| {r['setup']} | `scenes/{r['scene']}` | {rtf} | {vs_text} | {p:.2f} | "
                     f"{p / PAPER_TABLE1[1] - 1:+.0%} |")
    notes = path.with_name(path.stem + "_notes.md")
    if notes.exists():
        lines += ["", notes.read_text().strip()]
    path.write_text("\n".join(lines) + "\n")


def cmd_rtf(args) -> int:
    """Table 1: replay one recording (``--recording``, else the first ball_drop recording of ``--recordings``)
    through the five setups, ``--repeat`` times each."""
    src = Path(args.recordings)
    found = [src] if src.is_file() else sorted(src.glob("ball_drop*.mcap"))
    if not (args.recording or found):
        print(f"twin evaluate rtf: no ball_drop*.mcap recording in {src} (give --recording FILE)", file=sys.stderr)
        return 2
    rec = load_recording(args.recording or found[0])
    got: dict[str, list[tuple[int, float]]] = {scene_file: [] for _, scene_file in RTF_SETUPS}
    left_out: list[str] = []
    for rep in range(args.repeat):  # rounds outside, setups inside, in alternating order: measured side by side
        for title, scene_file in (RTF_SETUPS if rep % 2 == 0 else RTF_SETUPS[::-1]):
            # (the recording drives the robot only: it is a ball drop, and its perception names none of these
            # scenes' entities, which made every run degraded; the cup stands where the scene puts it)
            s = run_one(SCENES / scene_file, rec, Path(args.run_dir) / "rtf" / f"{Path(scene_file).stem}-{rep}",
                        ensemble=f"rtf{os.getpid()}{rep}", perception={"entities": {}})
            print(f"round {rep + 1}: {title:60s} rtf {s['rtf']} {s['status']}", flush=True)
            if s["status"] == "complete" and s.get("rtf"):
                got[scene_file].append((rep, s["rtf"]))
            else:  # (a run that did not end complete is no measure of the setup)
                left_out.append(f"{scene_file} round {rep + 1}: {s['status']} "
                                f"({'; '.join(s.get('status_reasons') or []) or 'no reason given'})")
    rows = [{"setup": title, "scene": scene_file, "rounds": [i for i, _ in got[scene_file]],
             "rtf": statistics.median(v for _, v in got[scene_file]) if got[scene_file] else None,
             "rtf_all": [v for _, v in got[scene_file]]} for title, scene_file in RTF_SETUPS]
    vs_one_world(rows)
    out = {"recording": rec.path, "repeat": args.repeat, "order": "rounds, setups alternating", "setups": rows,
           "cores": machine_cores(), "left_out": left_out, "status": "degraded" if left_out else "complete"}
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2))
        print(f"wrote {args.json}")
    if args.table:
        write_table1(out, Path(args.table))
        print(f"wrote {args.table}")
    for why in left_out:
        print(f"left out: {why}", file=sys.stderr)
    return 3 if left_out else 0
