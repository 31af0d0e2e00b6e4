"""Uncertainty as a distribution (``--samples K``): what the twin does not know for sure, drawn K times, each draw
run as a whole ensemble, and the answers reported as probabilities.

What varies, and how:

- **perceived positions**: an entity whose perception states ``position_sigma`` (metres, one standard deviation:
  the insertion recordings' SPU states 5 mm) is moved horizontally by a normal draw of that sigma on x and on y
  (the table holds its height; a perceived object does not float);
- **masses and frictions**: the ranges the scene declares in ``uncertain:`` (``ball.mass: [0.050, 0.065]``),
  drawn uniformly.

Sample ``i`` uses the generator seeded ``seed + i``: the same K and seed give the same variations, on any machine.
A variation is a perception (``{entities: {name: {pose, mass, friction}}}``), so it travels as the perception of
an ordinary run: to local embedded runs, to ``twin serve``, or to workers of a cluster (:mod:`conductor.fleet`).

The report (:func:`distribution`): each semantic predicate's probability over the samples that completed, with
its 95 % Wilson interval (a semantic value that is a number, such as a temperature or a count of spilled
particles: its median and 10th-90th percentiles); each handover's time (by trigger, entity, attribute and
occurrence) as median and 10th-90th percentiles, and in how many samples it happened; the statuses. A sample
that did not complete is never counted, and the report says how many did not.
"""
from __future__ import annotations

import copy
import json
import math
import os
import statistics
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import TwinError

from .scene import Scene, load_scene
from .scene.perception import load_perception, perception_from_metadata
from .sources.recording import load_recording

MAX_SEED = 2**32 - 1
"""The largest ``--seed`` (a whole number from 0; sample ``i`` is drawn with ``seed + i``)."""


def check_seed(seed: Any) -> int:
    """``seed`` if it is a whole number from 0 to :data:`MAX_SEED`; ValueError saying so otherwise."""
    if seed.__class__ is not int or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be a whole number from 0 to {MAX_SEED}, not {seed!r}")
    return seed


def variations(scene: Scene, perception: dict[str, Any] | None, k: int, seed: int = 0) -> list[dict[str, Any]]:
    """``k`` perceptions drawn around ``perception`` (the run's own, already applied to ``scene``'s entities) and
    the scene's ``uncertain`` ranges (see the module docstring). Deterministic in (k, seed). Each is the whole
    perception with the drawn values changed: a sample runs the scene a single run of the recording does (its
    perceived shapes, masses and frictions too), and an entity ``perceived_as`` another moves with that one."""
    base = copy.deepcopy((perception or {}).get("entities") or {})
    perceived = set(base)
    for name, ent in scene.entities.items():  # what the scene (after the perception) says, where none is given
        if name not in perceived and ent.extra.get("perceived_as") in perceived:
            continue  # (it takes the pose drawn for what it is perceived as)
        b = base.setdefault(name, {})
        b.setdefault("pose", list(ent.pose))
        if "position_sigma" in ent.extra:
            b.setdefault("position_sigma", ent.extra["position_sigma"])
    spread = any(float(b.get("position_sigma") or 0.0) > 0 and "pose" in b for b in base.values()) \
        or any(lo < hi for lo, hi in scene.uncertain.values())
    out = []
    for i in range(k):
        rng = np.random.default_rng(seed + i)
        ents: dict[str, Any] = {}
        for name in sorted(base):  # a fixed order: the draws do not depend on the dict's history
            b = base[name]
            if "pose" not in b:  # (an entity the scene has not, perceived without a pose: no position to draw)
                ents[name] = {p: copy.deepcopy(v) for p, v in b.items() if p != "position_sigma"}
                continue
            e: dict[str, Any] = {**copy.deepcopy(b), "pose": [float(v) for v in b["pose"]]}
            e.pop("position_sigma", None)
            sigma = float(b.get("position_sigma") or 0.0)
            if sigma > 0:
                dx, dy = rng.normal(0.0, sigma, 2)
                e["pose"][0] += float(dx)
                e["pose"][1] += float(dy)
                e["position_sigma"] = sigma
            ents[name] = e
        for (name, prop), (lo, hi) in sorted(scene.uncertain.items()):
            ents.setdefault(name, {})[prop] = float(rng.uniform(lo, hi))
        # "perceived": what the run's own perception named (the scene's poses filled in for the rest are no
        # perception: a perception of another scene stays one in every sample); "varied": anything was drawn
        out.append({"entities": ents, "sample": i, "seed": seed + i, "perceived": sorted(perceived),
                    "varied": spread})
    return out


def unvaried(perceptions: list[dict[str, Any]]) -> str | None:
    """Why K samples are one run K times (None when they differ): nothing uncertain was stated to draw from (said by
    :func:`variations`; for perceptions from elsewhere, when they are all alike)."""
    ents = [p.get("entities") for p in perceptions]
    said = [p.get("varied") for p in perceptions if isinstance(p.get("varied"), bool)]
    if not ents or (any(said) if said else (len(ents) < 2 or any(e != ents[0] for e in ents[1:]))):
        return None
    n = len(ents)
    runs = "the sample is the run itself" if n == 1 else f"the {n} samples are one run {n} times"
    return (f"nothing was varied: the perception states no position_sigma and the scene declares no 'uncertain:' "
            f"ranges, so {runs} (their interval says nothing about what the twin does not know)")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % Wilson score interval of a proportion k/n ((0, 1) when n is 0)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, c - h), min(1.0, c + h)


def _quantile(xs: list[float], q: float) -> float:
    return float(np.quantile(np.asarray(xs), q))


def distribution(summaries: list[dict[str, Any]]) -> dict[str, Any]:
    """What K runs of the same recording concluded, as a distribution (see the module docstring)."""
    complete = [s for s in summaries if s.get("status") == "complete"]
    predicates: dict[str, Any] = {}
    labels = sorted({label for s in complete for label in s.get("semantic_state", {})})
    for label in labels:
        values = [s["semantic_state"].get(label) for s in complete]
        numbers = [float(v) for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)
                   and math.isfinite(v)]
        if numbers and not any(isinstance(v, bool) for v in values):  # a quantity: its spread, not a probability
            predicates[label] = {"p": None, "median": round(statistics.median(numbers), 6),
                                 "p10": round(_quantile(numbers, 0.1), 6), "p90": round(_quantile(numbers, 0.9), 6),
                                 "of": len(numbers), "unknown": len(values) - len(numbers)}
            continue
        known = [v for v in values if isinstance(v, bool)]
        k, n = sum(known), len(known)
        lo, hi = wilson(k, n)
        predicates[label] = {"p": round(k / n, 4) if n else None, "interval95": [round(lo, 4), round(hi, 4)],
                             "true": k, "of": n, "unknown": len(values) - n}
    times: dict[str, list[float]] = {}
    for s in complete:
        seen: Counter[str] = Counter()
        for h in s.get("handovers", []):
            what = f"{h['trigger']}: {h['entity']}.{h['attribute']} {h['from']} -> {h['to']}"
            seen[what] += 1
            times.setdefault(f"{what} #{seen[what]}" if seen[what] > 1 else what, []).append(float(h["t"]))
    handovers = {what: {"in": len(ts), "of": len(complete), "median_s": round(statistics.median(ts), 3),
                        "p10_s": round(_quantile(ts, 0.1), 3), "p90_s": round(_quantile(ts, 0.9), 3)}
                 for what, ts in sorted(times.items())}
    statuses = Counter(str(s.get("status")) for s in summaries)
    # every sample failed on the user's input (a misspelt model argument): the command exits 2 (record.exit_code)
    bad_input = {"bad_input": True} if summaries and all(s.get("bad_input") for s in summaries) else {}
    return {"samples": len(summaries), "complete": len(complete), "statuses": dict(statuses), **bad_input,
            "predicates": predicates, "handovers": handovers,
            "not_complete": [{"sample": i, "status": s.get("status"), "why": (s.get("status_reasons") or [])[:2]}
                             for i, s in enumerate(summaries) if s.get("status") != "complete"]}


SEVERITY = ("complete", "degraded", "truncated", "interrupted", "failed")
"""Statuses from the best to the worst: the status of a set of samples is its worst sample's."""


def worst_status(summaries: list[dict[str, Any]]) -> str:
    return max((str(s.get("status", "failed")) for s in summaries), key=lambda st: SEVERITY.index(st)
               if st in SEVERITY else len(SEVERITY), default="failed")


def brier(p: float | None, truth: bool) -> float | None:
    """The Brier score of one probabilistic answer against the truth ((p - truth)^2; None without p)."""
    return None if p is None else (p - float(truth)) ** 2


def print_sample(i: int, summary: dict[str, Any]) -> None:
    """One sample's outcome, as it finishes: its number, status and answer."""
    print(f"  sample {i:3d}: {summary.get('status', '?'):9s} {json.dumps(summary.get('semantic_state', {}))}",
          flush=True)


def print_distribution(d: dict[str, Any], scene: str, recording: str) -> None:
    """The distribution for a person: probabilities with intervals, handover spreads, what did not complete."""
    print(f"\n{d['samples']} samples of {scene} on {recording}: {d['complete']} complete "
          f"({', '.join(f'{k} {v}' for k, v in sorted(d['statuses'].items()))})")
    if d.get("note"):
        print(f"  note: {d['note']}")
    for label, p in d["predicates"].items():
        if "median" in p:
            print(f"  {label} = {p['median']:g}  (p10 {p['p10']:g}, p90 {p['p90']:g}; over {p['of']} samples)")
            continue
        if p["p"] is None:
            print(f"  {label}: no complete sample could evaluate it")
            continue
        lo, hi = p["interval95"]
        print(f"  P[{label}] = {p['p']:.2f}  (95 % interval {lo:.2f}-{hi:.2f}; true in {p['true']} of {p['of']})")
    for what, h in d["handovers"].items():
        print(f"  {what}: in {h['in']}/{h['of']}, t = {h['median_s']:.2f} s (p10 {h['p10_s']:.2f}, "
              f"p90 {h['p90_s']:.2f})")
    for nc in d["not_complete"]:
        print(f"  sample {nc['sample']}: {nc['status'].upper()}: {'; '.join(nc['why'])}")


def sample_dir(root: Path, i: int) -> Path:
    """The run folder of sample ``i`` of a sampled run kept in ``root``."""
    return root / f"sample-{i:03d}"


def print_outcome(d: dict[str, Any]) -> None:
    """The last line of a sampled run: its status (the worst sample's), its wall time and where the samples' run
    folders are (what a service that ran them says of these, when it says)."""
    wall = f"; {d['wall_s']:.1f} s in all" if isinstance(d.get("wall_s"), (int, float)) else ""
    runs = d.get("runs") or []
    where = f"; runs in {os.path.commonpath(runs) if len(runs) > 1 else Path(runs[0]).parent}" if runs else ""
    print(f"status: {d.get('status')} (the worst sample's){wall}{where}")


def sample_jobs(scene_path: str, recording: str, k: int, seed: int, run_root: Path, *, perception: str | None = None,
                remap: list[str] | None = None, joint_order: list[str] | None = None,
                deadline: float | None = None, tag: str = "", max_ticks: int | None = None,
                rtf: float | None = None, register_timeout: float | None = None) -> tuple[list[dict[str, Any]], str]:
    """The K jobs of ``scene_path`` on ``recording`` (each a drawn perception) and the scene's name. Their run
    folders under ``run_root`` are made, emptied of an earlier run's files, and the folders of an earlier run's
    samples beyond K go (each sample's folder is then this run's, or none)."""
    scene = load_scene(scene_path)
    rec = load_recording(recording, remap=remap, joint_order=joint_order)
    if perception:
        base = load_perception(perception)
    elif "twin.scene" in rec.metadata:
        base = perception_from_metadata(rec.metadata["twin.scene"], rec.path)
    else:
        base = {"entities": {}}
    scene.apply_perception(base)
    text = Path(scene_path).read_text(encoding="utf-8")
    jobs = [{"scene_text": text, "scene_file": str(Path(scene_path).resolve()), "recording": os.path.abspath(recording),
             "perception": v, "ensemble": f"s{os.getpid()}{tag}x{i}",
             "run_dir": os.path.abspath(sample_dir(run_root, i)),  # (as the command sees it: a worker's is not)
             "remap": remap, "joint_order": joint_order, "deadline": deadline, "max_ticks": max_ticks, "rtf": rtf,
             "register_timeout": register_timeout}
            for i, v in enumerate(variations(scene, base, k, seed))]
    _clear_sample_dirs(Path(run_root), k)
    return jobs, scene.name


def _clear_sample_dirs(run_root: Path, k: int) -> None:
    import shutil

    from .parcels import clear, only_run_files

    try:
        for i in range(k):
            clear(sample_dir(run_root, i))
        beyond = [d for d in run_root.glob("sample-[0-9][0-9][0-9]*") if d.name[7:].isdigit() and int(d.name[7:]) >= k]
    except OSError as e:  # (as a single run says a folder it cannot write: exit 1)
        raise TwinError(f"--run-dir {run_root}: its samples' run folders cannot be written ({e.strerror or e})") \
            from None
    for d in beyond:
        if only_run_files(d):
            shutil.rmtree(d, ignore_errors=True)
