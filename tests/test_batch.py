"""Batched replay: several ticks in one step message where nothing can intervene between them
(scene ``clock.batch``) must give every model exactly what one message per tick gives it.

The real ensembles run twice on a shipped recording, batched (the default) and with ``batch: 1``, real
agent processes, real pybullet, real Zenoh: every message the models published (states, outputs,
events, step answers tick by tick), every trigger and handover the conductor logged must be equal."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import pytest

from conductor.core import Conductor, RunOptions
from conductor.launch import agent_command
from conductor.runlog import read_run_log
from conductor.scene import parse_scene
from protocol.keys import Keys

from .conftest import spawn_agents, wait_until

ROOT = Path(__file__).resolve().parent.parent


def _run(scene: Path, recording: Path, run_dir: Path) -> dict:
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(scene), "--recording", str(recording),
                        "--run-dir", str(run_dir), "--summary", str(run_dir / "summary.json")],
                       capture_output=True, text=True, timeout=600, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, f"{scene.name}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return json.loads((run_dir / "summary.json").read_text())


def _content(run_log: Path) -> tuple[dict, dict]:
    """What the run published, per key in order (wall-clock fields left out, batches unpacked into
    their ticks), and the number of done/ messages per model (several ticks each when batched)."""
    out: dict = defaultdict(list)
    messages: dict = defaultdict(int)
    ticks: dict = {}
    for key, _, msg in read_run_log(run_log):
        suffix = key.split("/", 2)[2]
        if suffix == "event/_conductor/run_end":
            continue  # wall time and real-time factor
        if suffix.startswith("done/"):
            messages[suffix[5:]] += 1
            for rep in [msg, *(msg.get("more") or [])]:
                out[suffix].append({k: v for k, v in rep.items() if k not in ("step_s", "more", "stopped")})
        elif suffix.startswith("conductor/register/"):  # what each agent declared, less its process
            out[suffix].append({k: v for k, v in msg.items() if k not in ("pid", "host")})
        elif suffix == "step":  # the step broadcast: what each model was given, tick by tick, whichever
            for body in [msg, *(msg.get("more") or [])]:  # message gave it (data-flow order splits a tick)
                models = {**body["models"], **{n: body["shared"] for n in body.get("due") or ()}}
                tick = ticks.setdefault(body["tick"], {"tick": body["tick"], "t": body["t"], "joints": body["joints"],
                                                       "models": {}})
                assert tick["t"] == body["t"] and tick["joints"] == body["joints"], body["tick"]
                # a model told to stop early (tick.until), or sent back (model/<id>/rewind), is given its later ticks
                # again in the next message (a reader's inputs may have changed hands meanwhile): what it stepped on
                # is what it was given last
                tick["models"].update(models)
        else:
            out[suffix].append(msg)
    out["step"] = [ticks[j] for j in sorted(ticks)]
    return out, messages


SCHEDULE = {"ball_drop": "data-flow", "insertion": "data-flow", "ball_drop_baseline1": "one ahead",
            "ball_drop_mujoco_grasp": "data-flow"}
"""How each scene's ticks go into step messages (conductor.flow)."""


@pytest.mark.slow
@pytest.mark.parametrize("scene_name,recording,batches", [
    # grasp_monitor's output fires triggers: its steps end a batch; in_hand's 'lost' event does too, but only while
    # it owns something (an owner event: it cannot lose what it does not hold), and it owns the ball pose physics
    # reads then
    ("ball_drop", "ball_drop_03.mcap", True),
    # data-flow order: the grasp monitor steps ahead of the others, but never past the tick of an action whose
    # trigger asks its evaluator (hand_free): here the hand closes at tick 458, the monitor confirms at 464
    ("ball_drop", "ball_drop_mj_success_bin.mcap", True),
    # the connector reads spu.pose, which physics owns and reports every tick; the scene tags the SPU static,
    # so its pose does not end a batch (it did, before: insertion never batched). It reads the DIP's pose from
    # in_hand, which leads: in each window in_hand steps first, then the connector, given what in_hand reported,
    # up to its first event; in_hand, stepped past it, goes back there (model/<id>/rewind)
    ("insertion", "insertion_01.mcap", True),
    # no triggers, and physics reads nothing another model owns: each window goes out before the answers to the one
    # before it are taken (flow.Pipeline)
    ("ball_drop_baseline1", "ball_drop_00.mcap", True),
    # MuJoCo's hand reads the ball's pose from physics until a trigger gives it the ball, then physics reads it from
    # the hand: in each window the owner steps first, then the reader, given per tick what the owner reported
    ("ball_drop_mujoco_grasp", "ball_drop_mj_slipped_bowl.mcap", True),
])
def test_batched_replay_equals_one_message_per_tick(tmp_path, scene_name, recording, batches):
    scene = ROOT / "scenes" / f"{scene_name}.yaml"
    text = scene.read_text()
    assert "clock: {rate: 120}\n" in text  # the shipped scene runs with the default batch
    lockstep_scene = tmp_path / f"{scene_name}.yaml"
    lockstep_scene.write_text(text.replace("clock: {rate: 120}\n", "clock: {rate: 120, batch: 1}\n"))
    rec = ROOT / "recordings" / recording

    batched = _run(scene, rec, tmp_path / "batched")
    lockstep = _run(lockstep_scene, rec, tmp_path / "lockstep")

    for k in ("ticks", "handovers", "final_ownership", "semantic_state", "errors", "unauthorized_writes"):
        assert batched[k] == lockstep[k], k
    assert batched["handovers"] or scene_name.startswith("ball_drop_baseline"), "it should move a responsibility"
    assert (batched["schedule"], lockstep["schedule"]) == (SCHEDULE[scene_name], "one per tick")
    got, n_batched = _content(tmp_path / "batched" / "run.mcap")
    want, n_lockstep = _content(tmp_path / "lockstep" / "run.mcap")
    rewinds = [got.pop(k) for k in list(got) if k.endswith("/rewind")]  # (the queries that sent in_hand back)
    assert bool(rewinds) == (scene_name == "insertion"), rewinds
    assert got.keys() == want.keys()
    for key in want:
        assert got[key] == want[key], f"{key} differs between the batched and the one-message-per-tick run"
    steps = {m: s["steps"] for m, s in batched["models"].items()}
    assert steps == {m: s["steps"] for m, s in lockstep["models"].items()}
    # one message per tick in the lockstep run; the batched run sent fewer, yet stepped every tick
    assert all(n_lockstep[m] == steps[m] for m in steps), (n_lockstep, steps)
    if batches:
        assert n_batched["physics"] < 0.75 * steps["physics"], (n_batched, steps)
    else:
        assert n_batched == n_lockstep
    if SCHEDULE[scene_name] == "data-flow":  # data-flow order: the leads' steps end no window
        assert batched["step_messages"] * 8 < batched["ticks"], batched["step_messages"]


@pytest.mark.slow
def test_data_flow_order_stops_where_the_coupled_lead_raises_its_event(tmp_path):
    """in_hand leads while it holds the ball, and stops a batch at its 'lost' event: without the grasp monitor's
    grasp_lost trigger, a slipped ball goes back to physics only through in_hand's event. Every message still
    equals one message per tick."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    text = text.replace(text[text.index("  - name: grasp_lost"):text.index("  - name: object_lost")], "")
    flow_scene, lockstep_scene = tmp_path / "flow.yaml", tmp_path / "lockstep.yaml"
    flow_scene.write_text(text)
    lockstep_scene.write_text(text.replace("clock: {rate: 120}\n", "clock: {rate: 120, batch: 1}\n"))
    rec = ROOT / "recordings" / "ball_drop_pb_slipped_bin.mcap"
    flow = _run(flow_scene, rec, tmp_path / "flow")
    lockstep = _run(lockstep_scene, rec, tmp_path / "lockstep")
    assert [h["trigger"] for h in flow["handovers"]] == ["grasp_confirmed", "object_lost"], flow["handovers"]
    for k in ("ticks", "handovers", "final_ownership", "semantic_state", "errors", "unauthorized_writes"):
        assert flow[k] == lockstep[k], k
    got, _ = _content(tmp_path / "flow" / "run.mcap")
    want, _ = _content(tmp_path / "lockstep" / "run.mcap")
    assert got == want
    assert flow["step_messages"] * 8 < flow["ticks"], flow["step_messages"]  # the leads' steps end no window


@pytest.mark.slow
def test_batch_survives_a_slow_model_and_a_failing_tick(router, procs):
    """Batches of 8 ticks to a model taking 60 ms per step (a batch 0.48 s), with a 0.3 s step timeout (per tick:
    a batch may take 2.4 s), and to a model whose output on tick 5 cannot be encoded: that tick is an error reply,
    the rest of the batch is stepped and answered."""
    session, endpoint = router
    scene = parse_scene("name: batch_faults\nclock: {rate: 100, batch: 8}\nmain: slow\nmodels:\n"
                        "  slow: {kind: 'tests.models.simple:Counter', step: service, rate: 100, "
                        "args: {delay: 0.06}}\n"
                        "  buggy: {kind: 'tests.models.simple:Counter', step: service, rate: 100, "
                        "args: {bad_tick: 5}}\n",
                        "<test>")
    spawn_agents(procs, scene, endpoint, "batchfaults")
    c = Conductor(scene, session, Keys("batchfaults"), None, RunOptions(run_log=None, max_ticks=24, step_timeout=0.3))
    try:
        summary = c.run()
    finally:
        c.close()
    assert summary["ticks"] == 24
    assert c.record.stats("slow").steps == 24 and c.record.stats("slow").errors == 0, c.record.stats("slow").last_error
    buggy = c.record.stats("buggy")
    assert buggy.steps == 24 and buggy.errors == 1 and "TypeError" in buggy.last_error, buggy.last_error
    # every step of both was taken in, the buggy one's count went on after its failed tick
    assert c.map.outputs[("slow", "count")] == 24 and c.map.outputs[("buggy", "count")] == 24
    assert not any("no step result" in e for e in summary["errors"]), summary["errors"]


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["kill", "pause"])
def test_a_model_lost_or_paused_while_the_next_window_is_out(router, procs, fault):
    """Windows one ahead (flow.Pipeline, a scene without triggers): a model killed, or paused past the step
    timeout, while the conductor has the next window out. The run goes on as the batch rule steps it (the window
    out is sent again, and the main model answers it without stepping twice): the main model steps every tick
    exactly once, the run ends at its last tick, degraded."""
    session, endpoint = router
    scene = parse_scene("name: ahead\nclock: {rate: 100, batch: 8}\nmain: a\nmodels:\n"
                        "  a: {kind: 'tests.models.simple:Counter', step: service, rate: 100, args: {delay: 0.002}}\n"
                        "  b: {kind: 'tests.models.simple:Counter', step: service, rate: 100, args: {delay: 0.002}}\n",
                        "<test>")
    procs.spawn("a", agent_command(scene.models["a"].kind, "a", endpoint, "ahead"))
    victim = procs.spawn("b", agent_command(scene.models["b"].kind, "b", endpoint, "ahead"))
    c = Conductor(scene, session, Keys("ahead"), None, RunOptions(run_log=None, max_ticks=400, step_timeout=0.2))

    def strike() -> None:
        if wait_until(lambda: c.clock.tick >= 100, timeout=120):
            os.kill(victim.pid, signal.SIGKILL if fault == "kill" else signal.SIGSTOP)
            if fault == "pause":  # past the step timeout of a window (0.2 s a tick, 8 ticks)
                time.sleep(2.5)
                os.kill(victim.pid, signal.SIGCONT)
    striker = threading.Thread(target=strike, daemon=True)
    striker.start()
    try:
        summary = c.run()
    finally:
        striker.join(timeout=10)
        c.close()
    assert summary["schedule"] == "one ahead" and summary["ticks"] == 400
    assert c.record.stats("a").steps == 400 and c.map.outputs[("a", "count")] == 400  # each tick once
    assert summary["status"] == "degraded", summary["status_reasons"]
    assert c.record.stats("b").steps < 400


SLIP_SCENE = """name: slip
clock: {rate: 100}
main: sim
models:
  sim: {kind: "tests.models.simple:BallSim", step: service, rate: 100}
  slipper: {kind: "tests.models.slipper:Slipper", step: service, rate: 50, args: {slip_at: 10, lie: LIE}}
entities:
  ball: {shape: {type: sphere, radius: 0.03}, pose: [0.5, 0, 0.5]}
triggers:
  - name: slipped
    on: {event: slipper.slip}
    do:
      - transfer: {entity: ball, attribute: pose, to: slipper}
"""


@pytest.mark.parametrize("lie", [False, True])
def test_an_owner_event_raised_while_owning_nothing_makes_the_run_degraded(tmp_path, lie):
    """A model's owner events do not end a batch while it owns nothing; one raised then anyway is a breach of its
    declaration that the run reports (degraded, naming the model, event and tick), its trigger still firing."""
    scene = tmp_path / "slip.yaml"
    scene.write_text(SLIP_SCENE.replace("LIE", "true" if lie else "false"))
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(scene), "--max-ticks", "60", "--run-dir",
                        str(tmp_path / "run"), "--summary", str(tmp_path / "s.json")], capture_output=True, text=True,
                       timeout=300, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    s = json.loads((tmp_path / "s.json").read_text())
    steps = sum(1 for k, _, _ in read_run_log(tmp_path / "run" / "run.mcap") if k.endswith("/step"))
    assert steps < 30, "while it owns nothing, its steps should not end the batches"
    if not lie:
        assert r.returncode == 0 and s["status"] == "complete" and not s["handovers"], r.stdout + r.stderr
        return
    assert r.returncode == 3 and s["status"] == "degraded", r.stdout + r.stderr
    assert any("slipper raised 'slip' at tick 10 while it owned nothing" in why for why in s["status_reasons"])
    assert [(h["entity"], h["to"], h["trigger"]) for h in s["handovers"]] == [("ball", "slipper", "slipped")]
