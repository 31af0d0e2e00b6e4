"""The speed limit the twin is compared against: the same models in one process, without the framework.

    .venv/bin/python -m bench.limit --rounds 5 --json docs/results/limit.json
    .venv/bin/python -m bench.limit --rounds 1 --scenarios baseline

*The limit* loads the scene and the recording as ``twin run`` does (:func:`conductor.scene.load_scene`,
:func:`conductor.sources.recording.load_recording`, the recording's perception applied), instantiates the
scene's model classes in this process (:func:`agents.registry.resolve_kind`, ``init`` with the parameters,
scene and ownership the conductor sends), and steps them tick by tick at their rates as the conductor does:
the step sections come from the conductor's own :func:`conductor.stepping.tick_body`, the answers go to the
conductor's own :class:`~conductor.triggers.TriggerEngine`, :class:`~conductor.handover.Handovers` and
:class:`~conductor.responsibility.Responsibilities`, whose queries (evaluators, release, acquire, services)
an in-process link (:class:`InProcessLink`) answers by calling the model's methods as the agent runtime
would. No Zenoh, no agent process, no message encoding on the step path: what is left is the models' own
work plus the trigger and handover logic, the fastest the same answers can be had in Python.

*Side by side*: each round runs, for each scenario, ``twin run`` and the limit, each in a fresh process, in
alternating order (ABBA: drift of a busy machine hits both alike). ``twin_rtf`` is the summary's real-time
factor (simulated seconds per wall second of the conductor's tick loop); ``limit_rtf`` the same for the
limit's tick loop (imports and ``init`` excluded; ``init_s`` says what they took). Every run's answers (the
handovers: entity, attribute, from, to, trigger, its variables, tick within one; the semantic state; the final
ownership) are compared with the twin's, and any difference is listed in the JSON (``same_answers``).

*The wire's floor*: every round also times bare Zenoh rounds in the step broadcast's shape (one put answered by
a put from each of N subscriber processes, N the scene's models, no framework: :func:`bench.common.pubsub_rounds`).
``windows`` is the twin's step messages (its summary's ``step_messages``); ``wire_floor_s`` is that many bare
rounds; ``floor_ratio`` = (limit loop + ``wire_floor_s``) / limit loop is the ratio a twin would have that added
nothing to the limit but one bare round per step message while its models took turns on one core. Models in
processes of their own can overlap on several cores, so the twin could in principle go below it; with
fewer cores than busy processes they mostly take turns.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

SCENARIOS: dict[str, tuple[str, str]] = {
    "ball_drop": ("scenes/ball_drop.yaml", "recordings/ball_drop_00.mcap"),
    "baseline": ("scenes/ball_drop_baseline1.yaml", "recordings/ball_drop_00.mcap"),
    "insertion": ("scenes/insertion.yaml", "recordings/insertion_00.mcap"),
}
"""Scenario name -> (scene, recording), relative to the checkout."""

TOLERANCE = 1e-6  # a number in the answers may differ this much (a trigger's distance; semantics are booleans)


# ------------------------------------------------------------------------------------------ the limit
class InProcessLink:
    """What the trigger engine and the handovers ask of the wire, answered in this process: ``eval/<name>``,
    ``call/<name>``, ``release`` and ``acquire`` call the model as :class:`agents.runtime.AgentRuntime`
    does (with its checks); a model's exception becomes the :class:`~protocol.errors.AgentError` the
    conductor would get. Publications and events go nowhere (no run log, no viewer)."""

    def __init__(self, models: dict[str, Any], ensemble: str = "limit") -> None:
        from protocol.keys import Keys

        self.keys = Keys(ensemble)
        self.models = models
        self.asked = 0
        self.tick: int | None = None

    def ask(self, model: str, op: str, payload: bytes, expect: str, timeout: float | None = None) -> Any:
        from protocol import codec
        from protocol.errors import AgentError
        from protocol.messages import Message

        self.asked += 1
        msg = codec.unpack(payload)  # the trigger code encoded it; rare (triggers and handovers only)
        m = self.models[model]
        try:
            if op == "release":
                key = (msg["entity"], msg["attribute"])
                if key not in m.owned:
                    raise KeyError(f"{model} does not own {key[0]}.{key[1]}")
                m.now = msg["t"]
                value, extra = m.release(*key)
                m.owned.discard(key)
                return Message({"type": "release_reply", "entity": key[0], "attribute": key[1], "value": value,
                                "extra": dict(extra or {})})
            if op == "acquire":
                if msg["attribute"] not in type(m).attributes:
                    raise KeyError(f"{model} ({m.kind}) cannot own attribute {msg['attribute']!r}")
                m.now = msg["t"]
                m.acquire(msg["entity"], msg["attribute"], msg["value"], msg["extra"])
                m.owned.add((msg["entity"], msg["attribute"]))
                return Message({"type": "ack", "ok": True})
            kind, _, name = op.partition("/")
            table = type(m).evaluators() if kind == "eval" else type(m).services()
            if name not in table:
                raise KeyError(f"{model} has no {'evaluator' if kind == 'eval' else 'service'} {name!r}")
            value = getattr(m, table[name])(*msg["args"], **(msg.get("kwargs") or {}))
            return Message({"type": "value_reply", "value": value})
        except Exception as e:
            raise AgentError(model, f"model/{model}/{op}", self.tick, type(e).__name__, str(e)) from None

    def publish(self, key: str, payload: bytes) -> None:
        """Nobody listens: the limit has no run log, viewer or clock-driven models."""

    def event(self, name: str, data: dict[str, Any], tick: int, t: float) -> None:
        """The conductor's events go to its run log and console: the limit keeps none."""


class Limit:
    """One scene replayed on one recording in this process (see the module docstring): :meth:`run` returns
    the answers and the timings. Only service-stepped models (the conductor's step broadcast)."""

    def __init__(self, scene_path: str | Path, recording: Any) -> None:
        t0 = time.perf_counter()
        from agents.registry import resolve_kind
        from agents.runtime import resolve_params
        from conductor.handover import Handovers
        from conductor.record import RunRecord
        from conductor.registry import AgentInfo, Registry
        from conductor.responsibility import Responsibilities
        from conductor.scene import check_against_agents, load_scene, reads_of
        from conductor.scene.perception import perceive
        from conductor.sources.fit import JointFit
        from conductor.sources.recording import Recording, load_recording
        from conductor.sources.replay import ReplaySource
        from conductor.stepping import Clock
        from conductor.triggers import TriggerEngine

        self.scene = scene = load_scene(str(scene_path))
        # a recording already read (a warm evaluation reads each once): taken as it is
        self.source = ReplaySource(recording if isinstance(recording, Recording) else load_recording(str(recording)))
        perceive(scene, self.source)  # the recording's twin.scene, as twin run does
        not_service = sorted(n for n, s in scene.models.items() if s.step != "service")
        if not_service:
            raise ValueError(f"the limit steps service models only; {', '.join(not_service)} are not")
        classes = {n: resolve_kind(s.kind) for n, s in scene.models.items()}
        # what each agent would declare at registration (AgentRuntime.descriptor), for the scene check,
        # the reads and the registry that the handovers ask
        desc = {n: {"name": n, "kind": c.kind, "role": c.role, "step_modes": list(c.step_modes),
                    "params": {k: p.describe() for k, p in c.params.items()}, "attributes": list(c.attributes),
                    "outputs": list(c.outputs), "events": list(c.events), "evaluators": sorted(c.evaluators()),
                    "services": sorted(c.services()), "reads": list(c.reads), "telemetry": bool(c.wants_telemetry)}
                for n, c in classes.items()}
        problems = check_against_agents(scene, desc)
        if problems:
            from protocol.errors import SceneError

            raise SceneError.of(problems)
        self.reads = reads_of(scene, desc)
        self.telemetry = {n: bool(d["telemetry"]) for n, d in desc.items()}
        self.clock = Clock(1.0 / scene.rate)
        self.record = RunRecord(scene)
        self.map = Responsibilities(scene)
        self.registry = Registry(scene.models)
        self.models: dict[str, Any] = {}
        self.link = InProcessLink(self.models)
        self.handovers = Handovers(self.link, self.registry, self.map, self.record, scene.main,  # type: ignore[arg-type]
                                   self.clock)
        self.triggers = TriggerEngine(scene, self.map, self.link, self.handovers, self.record,  # type: ignore[arg-type]
                                      self.clock)
        self.fit = JointFit(scene.declared_robot, self.source, self.record.degraded.extend)
        self.fit.before_run()
        # the init the conductor sends (Conductor._init_model), as AgentRuntime._init takes it
        geometry = {"name": scene.name, "entities": scene.geometry(), "main": scene.main, "rate": scene.rate,
                    "robot": scene.robot.as_dict() if scene.robot else {}}
        kinds = {m: s.kind for m, s in scene.models.items()}
        for name, spec in scene.models.items():
            cls = classes[name]
            params = dict(spec.args)
            if "_main" in cls.params:
                params.setdefault("_main", scene.main)
            m = cls()
            m.id, m.scene, m.models, m.rate = name, geometry, kinds, float(spec.rate)
            m.owned = set(self.map.owned_by(name))
            m.init(resolve_params(cls, params), geometry)
            self.models[name] = m
            self.registry.agents[name] = AgentInfo(name, desc[name], alive=True, ready=True)
        self.handovers.publish_ownership()
        for m in self.models.values():  # start (Conductor.start): tick 0
            m.tick, m.t = 0, 0.0
            m.start()
        self._latest_joints: dict[str, Any] | None = None
        self._pending: dict[str, list[dict[str, Any]]] = {n: [] for n in scene.models}
        self.init_s = time.perf_counter() - t0
        self.loop_s = 0.0

    # ------------------------------------------------------------------------------ the tick loop
    def run(self, max_ticks: int | None = None) -> dict[str, Any]:
        """Tick to the end of the recording (as Conductor.loop with one step message per tick, which its batch
        rule makes equivalent), then the semantics; the answers and timings."""
        from conductor.stepping import tick_body

        scene, clock, rmap = self.scene, self.clock, self.map
        service = {n: (s.period, self.telemetry[n], bool(self.reads[n])) for n, s in scene.models.items()}
        order = list(scene.models)
        ready = self.registry.ready
        t0 = time.perf_counter()
        tick = 0
        checked = rmap.version
        while not self.source.exhausted(tick * clock.dt) and (max_ticks is None or tick < max_ticks):
            clock.set(tick)
            self.link.tick = tick
            actions = self._feed(tick)
            body, names = tick_body(tick, clock.t, clock.dt, service, ready, self._take_actions, self._inputs,
                                    self._latest_joints)
            if body is not None:
                # the agents step in parallel processes, each on the map as it was before the tick; their
                # answers are taken in scene order, whatever the order they came in
                replies = {n: self._step(n, body) for n in names}
                reps = [(n, replies[n]) for n in order if replies.get(n) is not None]
                for name, rep in reps:
                    self.record.stats(name).count(name, tick, rep)
                self.triggers.absorb_tick(reps)
            for a in actions:
                self.triggers.on_action(a)
            if rmap.version != checked:
                if not rmap.invariant_holds():
                    self.record.invariant_violations += 1
                checked = rmap.version
            tick += 1
        clock.set(tick)
        self.loop_s = time.perf_counter() - t0
        return self.finish()

    def _feed(self, tick: int) -> list[dict[str, Any]]:
        """Conductor._feed without the republication on telemetry/*."""
        actions: list[dict[str, Any]] = []
        for kind, msg in self.source.due(tick * self.clock.dt):
            if kind == "joint_state":
                self._latest_joints = self.fit.take(msg)
            else:
                actions.append(msg)
                for n, wants in self.telemetry.items():
                    if wants:
                        self._pending[n].append(msg)
        return actions

    def _take_actions(self, name: str) -> list[dict[str, Any]]:
        acts, self._pending[name] = self._pending[name], []
        return acts

    def _inputs(self, name: str) -> dict[str, Any]:
        return self.map.inputs_for(name, self.reads[name])

    def _step(self, name: str, body: dict[str, Any]) -> dict[str, Any]:
        """One model's step of one tick, with the agent runtime's own step (its reply; nothing published)."""
        from agents.runtime import step_reply

        sec = body["models"].get(name) or body["shared"]
        return step_reply(self.models[name], body["tick"], body["t"], sec["dt"],
                          {"joints": body["joints"], "actions": sec["actions"]}, sec["inputs"])

    def finish(self) -> dict[str, Any]:
        """The answers (as the run summary words them) and the timings; closes the models."""
        from conductor.record import plain

        sem = self.triggers.semantics() if self.clock.tick > 0 else {}
        for m in self.models.values():
            m.close()
        sim_s = self.clock.tick * self.clock.dt
        return {
            "scene": self.scene.name,
            "ticks": self.clock.tick,
            "sim_s": round(sim_s, 6),
            "init_s": round(self.init_s, 4),
            "wall_s": round(self.loop_s, 4),
            "rtf": round(sim_s / self.loop_s, 4) if self.loop_s > 0 else None,
            "handovers": [h.as_dict() for h in self.map.handovers],
            "final_ownership": {f"{e}.{a}": m for (e, a), m in sorted(self.map.owners.items())},
            "semantic_state": plain(sem),
            "errors": self.record.errors[:50],
            "failed_steps": {n: st.failed for n, st in self.record.models.items() if st.failed},
            "invariant_violations": self.record.invariant_violations,
            "queries": self.link.asked,
        }


def run_limit(scene: str | Path, recording: Any) -> dict[str, Any]:
    """The limit on one scene and recording (a path, or a :class:`~conductor.sources.recording.Recording` read
    once): its answers, ``rtf``, ``wall_s`` (tick loop) and ``init_s``."""
    return Limit(scene, recording).run()


def limit_evaluation(recordings: list[Path], configs: list[str]) -> dict[str, Any]:
    """The limit on every run ``twin evaluate`` makes of ``recordings`` with ``configs`` (the same scene for each
    recording and configuration, :func:`bench.evaluate.scene_for`), one after another in this process, each
    recording read once for all its runs (as the warm service does): each run's semantic state and timings, and
    the sums. A run the limit cannot make (a model that is not service-stepped)
    is listed under ``skipped`` with why."""
    from bench.evaluate import scenario_of, scene_for
    from conductor.sources.recording import load_recording

    runs: dict[str, dict[str, Any]] = {}
    skipped: dict[str, str] = {}
    for path in recordings:
        rec = load_recording(path)
        scenario = scenario_of(rec)
        for cfg in configs:
            scene = scene_for(rec, scenario, cfg)
            if scene is None:
                continue
            try:
                r = run_limit(scene, rec)
            except ValueError as e:
                skipped[f"{path.name}/{cfg}"] = str(e)
                continue
            runs[f"{path.name}/{cfg}"] = {k: r[k] for k in ("semantic_state", "wall_s", "init_s", "ticks")}
    return {"runs": runs, "skipped": skipped, "loops_s": round(sum(r["wall_s"] for r in runs.values()), 3),
            "inits_s": round(sum(r["init_s"] for r in runs.values()), 3)}


# ------------------------------------------------------------------------------------ same answers
def differences(twin: dict[str, Any], limit: dict[str, Any]) -> list[str]:
    """Where the limit's answers differ from the twin's summary ([] if nowhere): the handovers (entity,
    attribute, from, to, trigger equal, the trigger's variables within :data:`TOLERANCE`, tick within one), the
    semantic state, the final ownership."""
    out = []
    th, lh = twin.get("handovers") or [], limit.get("handovers") or []
    if len(th) != len(lh):
        out.append(f"{len(th)} handovers in the twin, {len(lh)} in the limit")
    for i, (a, b) in enumerate(zip(th, lh)):
        for k in ("entity", "attribute", "from", "to", "trigger"):
            if a.get(k) != b.get(k):
                out.append(f"handover {i}: {k} {a.get(k)!r} in the twin, {b.get(k)!r} in the limit")
        if not _same(a.get("variables"), b.get("variables")):
            out.append(f"handover {i} ({a.get('trigger')}): variables {a.get('variables')!r} in the twin, "
                       f"{b.get('variables')!r} in the limit")
        if abs(int(a["tick"]) - int(b["tick"])) > 1:
            out.append(f"handover {i} ({a.get('trigger')}): tick {a['tick']} in the twin, {b['tick']} in the limit")
    ts, ls = twin.get("semantic_state") or {}, limit.get("semantic_state") or {}
    for label in sorted(set(ts) | set(ls)):
        if not _same(ts.get(label), ls.get(label)):
            out.append(f"semantics {label}: {ts.get(label)!r} in the twin, {ls.get(label)!r} in the limit")
    to, lo = twin.get("final_ownership") or {}, limit.get("final_ownership") or {}
    for key in sorted(set(to) | set(lo)):
        if to.get(key) != lo.get(key):
            out.append(f"final owner of {key}: {to.get(key)!r} in the twin, {lo.get(key)!r} in the limit")
    return out


def _same(a: Any, b: Any) -> bool:
    numbers = (isinstance(a, (int, float)) and isinstance(b, (int, float))
               and not isinstance(a, bool) and not isinstance(b, bool))
    if numbers:
        return math.isclose(a, b, rel_tol=TOLERANCE, abs_tol=TOLERANCE)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return set(a) == set(b) and all(_same(a[k], b[k]) for k in a)
    return bool(a == b)


# ----------------------------------------------------------------------------------- side by side
def twin_once(scene: str, recording: str, workdir: Path) -> dict[str, Any]:
    """``twin run`` as a subprocess: its summary, and the process's wall time."""
    summary = workdir / "summary.json"
    cmd = [sys.executable, "-m", "conductor.cli", "run", str(ROOT / scene), "--recording", str(ROOT / recording),
           "--summary", str(summary), "--run-dir", str(workdir / "run")]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    process_s = time.perf_counter() - t0
    if not summary.exists():
        raise RuntimeError(f"twin run exited with {proc.returncode} and no summary:\n{proc.stderr[-2000:]}")
    s = json.loads(summary.read_text())
    return {"rtf": s["rtf"], "wall_s": s["wall_s"], "setup_s": s["setup_s"], "process_s": round(process_s, 3),
            "status": s["status"], "ticks": s["ticks"], "handovers": s["handovers"],
            "windows": s.get("step_messages"), "models": len(s.get("models") or {}),
            "semantic_state": s["semantic_state"], "final_ownership": s["final_ownership"]}


def limit_once(scene: str, recording: str, workdir: Path) -> dict[str, Any]:
    """The limit in a fresh process (``python -m bench.limit --one``): its answers and the process's wall time."""
    out = workdir / "limit.json"
    cmd = [sys.executable, "-m", "bench.limit", "--one", str(ROOT / scene), str(ROOT / recording), "--json", str(out)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    process_s = time.perf_counter() - t0
    if proc.returncode != 0 or not out.exists():
        raise RuntimeError(f"the limit exited with {proc.returncode}:\n{proc.stderr[-2000:]}")
    res: dict[str, Any] = json.loads(out.read_text())
    res["process_s"] = round(process_s, 3)
    return res


def raw_round_ms(n: int, rounds: int = 400) -> float:
    """Milliseconds of one bare Zenoh round with ``n`` subscriber processes
    (:func:`bench.overhead.bench_raw_pubsub`)."""
    from bench.overhead import bench_raw_pubsub

    return 1000.0 / bench_raw_pubsub(n, rounds)


def wire_floor(twin: dict[str, Any], limit: dict[str, Any], round_ms: float) -> dict[str, Any]:
    """The twin's step messages at the bare round's cost, and the ratio they alone would give (module docstring)."""
    windows = twin.get("windows")
    if not windows or not limit.get("wall_s"):
        return {}
    wire = windows * round_ms / 1000.0
    return {"windows": windows, "raw_round_ms": round(round_ms, 4), "wire_floor_s": round(wire, 4),
            "floor_ratio": round((limit["wall_s"] + wire) / limit["wall_s"], 3)}


def _spread(values: list[float]) -> dict[str, float]:
    return {"median": round(statistics.median(values), 4), "min": round(min(values), 4), "max": round(max(values), 4)}


def faults(r: dict[str, Any]) -> list[str]:
    """Why a round's figures are no measure of the twin against its limit (empty: they are): a twin run that did
    not end complete, a limit whose models failed steps, raised or broke an invariant."""
    out = [] if r["twin"]["status"] == "complete" else [f"twin run {r['twin']['status']}"]
    lim = r["limit"]
    out += [f"limit: {n} failed {k} steps" for n, k in sorted((lim.get("failed_steps") or {}).items())]
    out += [f"limit: {len(lim['errors'])} errors ({lim['errors'][0]})"] if lim.get("errors") else []
    out += [f"limit: {lim['invariant_violations']} invariant violations"] if lim.get("invariant_violations") else []
    return out


def scenario_result(name: str, all_runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One scenario's figures over its rounds: medians and the spread of the ratio, the answers compared. A round
    with a fault (:func:`faults`) is left out of the figures and said under ``faulty_rounds``."""
    faulty = {i: faults(r) for i, r in enumerate(all_runs) if faults(r)}
    runs = [r for i, r in enumerate(all_runs) if i not in faulty]
    scene, recording = SCENARIOS[name]
    if not runs:
        return {"scene": scene, "recording": recording, "rounds": 0, "same_answers": False,
                "differences": ["no round without a fault"], "faulty_rounds": faulty}
    twin_rtf = [r["twin"]["rtf"] for r in runs]
    limit_rtf = [r["limit"]["rtf"] for r in runs]
    ratios = [b / a for a, b in zip(twin_rtf, limit_rtf)]
    diffs = sorted({d for r in all_runs for d in r["differences"]})
    return {
        "scene": scene, "recording": recording, "rounds": len(runs), "faulty_rounds": faulty,
        "twin_rtf": round(statistics.median(twin_rtf), 3),
        "limit_rtf": round(statistics.median(limit_rtf), 3),
        "ratio": round(statistics.median(ratios), 3),
        "ratio_min": round(min(ratios), 3), "ratio_max": round(max(ratios), 3),
        "ratio_of_medians": round(statistics.median(limit_rtf) / statistics.median(twin_rtf), 3),
        "twin_rtf_spread": _spread(twin_rtf), "limit_rtf_spread": _spread(limit_rtf),
        "twin_process_s": _spread([r["twin"]["process_s"] for r in runs]),
        "limit_process_s": _spread([r["limit"]["process_s"] for r in runs]),
        "limit_init_s": _spread([r["limit"]["init_s"] for r in runs]),
        "twin_setup_s": _spread([r["twin"]["setup_s"] for r in runs]),
        **_floor_figures(runs),
        "ticks": runs[0]["twin"]["ticks"],
        "handovers": len(runs[0]["twin"]["handovers"]),
        "twin_status": sorted({r["twin"]["status"] for r in all_runs}),
        "same_answers": not diffs,
        "differences": diffs,
        "runs": [{"twin_rtf": r["twin"]["rtf"], "limit_rtf": r["limit"]["rtf"],
                  "twin_process_s": r["twin"]["process_s"], "limit_process_s": r["limit"]["process_s"],
                  "limit_init_s": r["limit"]["init_s"], "order": r["order"]} for r in runs],
    }


def _floor_figures(runs: list[dict[str, Any]]) -> dict[str, Any]:
    floors = [r["floor"] for r in runs if r.get("floor")]
    if not floors:
        return {}
    return {"windows": floors[0]["windows"],
            "raw_round_ms": _spread([f["raw_round_ms"] for f in floors]),
            "wire_floor_s": _spread([f["wire_floor_s"] for f in floors]),
            "floor_ratio": round(statistics.median([f["floor_ratio"] for f in floors]), 3),
            "floor_ratio_spread": _spread([f["floor_ratio"] for f in floors])}


def side_by_side(names: list[str], rounds: int, workdir: Path) -> dict[str, list[dict[str, Any]]]:
    """Every round runs every scenario's twin and limit, the order of the two alternating by round."""
    runs: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    for r in range(rounds):
        order = ("twin", "limit") if r % 2 == 0 else ("limit", "twin")
        for name in names:
            scene, recording = SCENARIOS[name]
            got: dict[str, Any] = {"order": "-".join(order)}
            for which in order:
                d = workdir / f"r{r}-{name}-{which}"
                d.mkdir(parents=True)
                res = (twin_once if which == "twin" else limit_once)(scene, recording, d)
                got[which] = res
                print(f"round {r + 1}/{rounds} {name:9s} {which:5s}: real-time factor {res['rtf']:7.2f} "
                      f"({res['ticks']} ticks, loop {res['wall_s']:.3f} s, process {res['process_s']:.2f} s)",
                      flush=True)
            n = got["twin"]["models"]
            if n:
                got["floor"] = wire_floor(got["twin"], got["limit"], raw_round_ms(n))
                if got["floor"]:
                    f = got["floor"]
                    print(f"round {r + 1}/{rounds} {name:9s} wire : {f['windows']} step messages x bare round "
                          f"{f['raw_round_ms']:.3f} ms ({n} processes) = {f['wire_floor_s']:.3f} s; floor ratio "
                          f"{f['floor_ratio']:.2f}", flush=True)
            got["differences"] = differences(got["twin"], got["limit"])
            for d in got["differences"]:
                print(f"  DIFFERENT ANSWER: {d}", flush=True)
            runs[name].append(got)
    return runs


def print_table(results: dict[str, dict[str, Any]]) -> None:
    print(f"\n{'scenario':10s} {'twin rtf':>9s} {'limit rtf':>10s} {'ratio':>7s} {'min..max':>13s} "
          f"{'floor':>6s} {'windows':>8s} {'twin proc s':>12s} {'limit proc s':>13s}  same answers")
    for name, r in results.items():
        for i, why in r["faulty_rounds"].items():
            print(f"{name:10s} round {i + 1} left out: {'; '.join(why)}")
        if not r["rounds"]:
            continue
        floor = f"{r['floor_ratio']:6.2f} {r['windows']:8d}" if "floor_ratio" in r else f"{'-':>6s} {'-':>8s}"
        print(f"{name:10s} {r['twin_rtf']:9.2f} {r['limit_rtf']:10.2f} {r['ratio']:7.2f} "
              f"{r['ratio_min']:6.2f}..{r['ratio_max']:<6.2f} {floor} {r['twin_process_s']['median']:12.2f} "
              f"{r['limit_process_s']['median']:13.2f}  {'yes' if r['same_answers'] else 'NO'}")


def _say(res: dict[str, Any], where: str | None) -> int:
    """``res`` as JSON, to the file ``where`` (standard output for none or ``-``)."""
    text = json.dumps(res, indent=2, default=str)
    if where and where != "-":
        Path(where).write_text(text + "\n")
    else:
        print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help=f"comma-separated, of {', '.join(SCENARIOS)}")
    ap.add_argument("--json", help="write the figures as JSON to FILE ('-' = standard output)")
    ap.add_argument("--one", nargs=2, metavar=("SCENE", "RECORDING"),
                    help="run the limit once on SCENE and RECORDING (what each round starts as a process)")
    ap.add_argument("--evaluation", metavar="DIR",
                    help="run the limit on every run twin evaluate makes of DIR's recordings (with --configs), one "
                         "after another; JSON of the answers and timings (what bench.warm's limit modes start)")
    ap.add_argument("--configs", default="ensemble,baseline1,baseline2,baseline3",
                    help="with --evaluation: twin evaluate's configurations (default its default four)")
    ap.add_argument("--part", default="1/1", metavar="I/N",
                    help="with --evaluation: only the I-th of N shares of the recordings (every N-th from the I-th)")
    args = ap.parse_args(argv)
    if args.evaluation:
        try:
            i, n = (int(x) for x in args.part.split("/"))
            if not 1 <= i <= n:
                raise ValueError
        except ValueError:
            ap.error(f"--part {args.part}: give I/N with 1 <= I <= N")
        recs = sorted(Path(args.evaluation).glob("*.mcap"))[i - 1::n]
        return _say(limit_evaluation(recs, [c.strip() for c in args.configs.split(",") if c.strip()]), args.json)
    if args.one:
        return _say(run_limit(*args.one), args.json)
    names = [n.strip() for n in args.scenarios.split(",") if n.strip()]
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown or not names or args.rounds < 1:
        ap.error(f"unknown scenarios {unknown} (known: {', '.join(SCENARIOS)})" if unknown else "nothing to run")

    from bench.common import machine_info

    load_before = os.getloadavg()  # another user of the machine shows here (the ratio is side by side anyway)
    with tempfile.TemporaryDirectory(prefix="twin-limit-") as tmp:
        runs = side_by_side(names, args.rounds, Path(tmp))
    results = {n: scenario_result(n, runs[n]) for n in names}
    print_table(results)
    doc = {"benchmark": "limit", "rounds": args.rounds,
           "same_answers": all(r["same_answers"] for r in results.values()),
           "scenarios": results, "machine": machine_info(),
           "load_average": {"before": [round(x, 2) for x in load_before],
                            "after": [round(x, 2) for x in os.getloadavg()]}}
    if args.json:
        text = json.dumps(doc, indent=2)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(text + "\n")
            print(f"figures: {args.json}")
    return 0 if doc["same_answers"] and not any(r["faulty_rounds"] for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
