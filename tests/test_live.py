"""Live attach: ``twin robot play`` stands in for the robot on one host, the twin attaches on another.

::

    host "robot":  twin robot play REC --connect tcp/twin:7447   ──LAN──▶   host "twin":  twin run SCENE --live
"""
from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import pytest

from bench.netns import python_cmd, wait_exit
from conductor.launch import open_router
from conductor.runlog import read_run_log
from conductor.sources.recording import load_recording
from protocol import codec
from protocol.keys import Keys
from recordings.simple import core_recording

from .conftest import wait_until
from .test_compose import explain, handover_story, single_host_reference
from .test_service_triggers import SCENE as SERVICE_SCENE

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
SCENE = "tests/core_scene.yaml"


@pytest.mark.slow
def test_live_attach_across_hosts_matches_replay(lan, tmp_path):
    """The twin on one host follows a robot on another: the summary reports lag p50/p99 and the same
    interpretation (semantic state, handovers) as replaying the recording."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    twin_host, robot_host = lan.add_host("twin"), lan.add_host("robot")
    summary = tmp_path / "live.json"
    twin = twin_host.spawn("twin", python_cmd(
        "run", SCENE, "--live", "--listen", "tcp/0.0.0.0:7447", "--ensemble", "live", "--idle-timeout", "2",
        "--summary", str(summary), "--run-dir", str(tmp_path / "live")), cwd=str(ROOT))
    lan.wait_reachable(robot_host, twin_host)
    access = tmp_path / "live" / "access.json"  # the embedded bus admits only holders of this run's secret
    deadline = time.monotonic() + 60
    while not access.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    robot = robot_host.spawn("robot", python_cmd(
        "robot", "play", str(rec), "--connect", "tcp/twin:7447", "--ensemble", "live", "--wait-twin", "90",
        "--credentials", str(access)))
    assert wait_exit(robot, 120, lan.logdir / "agent-robot.log") == 0
    assert wait_exit(twin, 60, lan.logdir / "agent-twin.log") == 0
    live = json.loads(summary.read_text())
    assert live["errors"] == [], live["errors"]
    # no --perception: the run says that its entities start at the scene's poses (it said nothing in twin run)
    from conductor.scene.perception import NO_PERCEPTION_LIVE
    assert NO_PERCEPTION_LIVE in live["input_notes"], live.get("input_notes")
    lag = live["lag"]
    print(f"\nlive lag (core scene, robot on another host): {lag}, rtf {live['rtf']}")
    assert lag["samples"] == 300  # every joint state of the recording arrived over the LAN
    assert 0 <= lag["p50_ms"] <= lag["p99_ms"] <= lag["max_ms"]
    assert lag["malformed"] == 0
    # what the twin logged came from the robot's host, stamped with the robot's wall clock
    stamps = [m["stamp"] for k, _, m in read_run_log(live["run_log"]) if k.endswith("/telemetry/joint_states")]
    assert len(stamps) == 300 and stamps[-1] - stamps[0] >= 2.8  # paced: never sent ahead of the recording
    ref = single_host_reference(tmp_path, SCENE, rec)
    assert live["semantic_state"] == ref["semantic_state"] == {"in(bin, ball)": True}, explain(live, ref)
    assert handover_story(live) == handover_story(ref), explain(live, ref)
    # the live run's log runs again on its own: from the robot's first message on (its stamps are the robot's wall
    # clock, since the epoch; read as they were, the re-run had billions of seconds to tick through)
    again = subprocess.run(python_cmd("run", "--from-log", live["run_log"], "--run-dir", str(tmp_path / "again"),
                                      "--summary", str(tmp_path / "again.json")), capture_output=True, text=True,
                           cwd=ROOT, timeout=300)
    assert again.returncode == 0, again.stdout + again.stderr
    rerun = json.loads((tmp_path / "again.json").read_text())
    assert rerun["semantic_state"] == live["semantic_state"] and rerun["sim_s"] < 10, rerun


def test_robot_play_paces_and_stamps_with_the_wall_clock(tmp_path):
    """`twin robot play` sends every message at its recorded time (divided by --speed), stamped with the
    sender's wall clock; --loop --loops N plays N passes."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    session, endpoint = open_router()
    got: list[tuple[float, str, dict]] = []
    lock = threading.Lock()

    def on_sample(sample):
        key = str(sample.key_expr)
        msg = codec.decode(key, sample.payload, ("joint_state", "action"))
        with lock:
            got.append((time.time(), msg.mtype, dict(msg)))

    sub = session.declare_subscriber(Keys("play").telemetry("**"), on_sample)
    try:
        r = subprocess.run(python_cmd("robot", "play", str(rec), "--connect", endpoint, "--ensemble", "play",
                                      "--speed", "2", "--loop", "--loops", "2", "--lead-in", "0.5"),
                           capture_output=True, text=True, timeout=60, env=ENV, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        assert "sent 200 joint states and 2 actions in 2 whole pass(es)" in r.stdout, r.stdout
        deadline = time.monotonic() + 10  # (the last of them may still be on their way to this subscriber)
        while sum(1 for _, k, _ in got if k == "joint_state") < 200 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.2)  # (and nothing more comes)
    finally:
        sub.undeclare()
        session.close()
    joints = [(arr, m) for arr, k, m in got if k == "joint_state"]
    assert len(joints) == 200 and sum(1 for _, k, _ in got if k == "action") == 2
    first = [m["stamp"] for _, m in joints[:100]]
    # 100 messages recorded over 0.99 s, played twice as fast: a pass never goes faster than 0.495 s
    second = [m["stamp"] for _, m in joints[100:]]
    assert first[-1] - first[0] >= 0.45 and second[-1] - second[0] >= 0.45
    assert second[0] - first[-1] >= 0.0045  # a pass lasts one spacing (10 ms at x2) more: no two sent at once
    # stamps are the sender's wall clock when sending (same clock here): never after the arrival
    assert all(m["stamp"] <= arr for arr, m in joints)
    assert all(b["stamp"] >= a["stamp"] for (_, a), (_, b) in zip(joints, joints[1:]))
    # each stamp is the time its message was due, as a robot stamps a measurement: spaced exactly as recorded (at
    # x2), whenever it was sent (stamps of the moment of sending squeezed the motion after any hold-up into a burst)
    recorded = [t for t, kind, _ in load_recording(rec).items if kind == "joint_state"]
    for sent in (first, second):
        assert [b - a for a, b in zip(sent, sent[1:])] == pytest.approx(
            [(b - a) / 2 for a, b in zip(recorded, recorded[1:])], abs=1e-6)


def test_a_robot_that_never_speaks_fails_the_run_instead_of_ticking_on_empty(router):
    """No telemetry within the wait for the first message: the live source says so (the run fails with that
    reason) rather than ticking forever on nothing, since its idle time counts only from a first message. A stop
    during the wait is a stop, not that failure; a robot that speaks ends the wait."""
    from conductor.sources.live import LiveSource
    from protocol.errors import RunAborted

    session, _ = router
    keys = Keys("quiet")
    src = LiveSource(session, keys, idle_timeout=1.0, wait_first=0.5)
    t = time.monotonic()
    with pytest.raises(RunAborted, match=r"no telemetry came on twin/quiet/telemetry/\*\* within 0.5 s"):
        src.wait_for_data(threading.Event())
    assert time.monotonic() - t < 10
    stop = threading.Event()
    stop.set()
    assert src.wait_for_data(stop) is False
    heard = LiveSource(session, keys, wait_first=10.0)
    session.put(keys.telemetry("joint_states"), codec.encode("joint_state", stamp=time.time(), name=["j1"],
                                                              position=[0.0], velocity=[0.0], effort=[0.0]))
    assert heard.wait_for_data(threading.Event()) is True


LIVE_SCENE = SERVICE_SCENE  # a ball, a bin, a model that steps as told and a holder


def end_run(c, runner: threading.Thread) -> None:
    """A test's run, ended whatever happened: stopped if it still goes on, then closed."""
    if runner.is_alive():
        c.stop("the test")
        runner.join(timeout=30)
    c.close()


@pytest.mark.slow
def test_live_telemetry_the_twin_cannot_use_is_left_out_and_said(router, procs, client, tmp_path):
    """One joint state with a NaN used to fail the whole run (its main model refused the step it was given); one
    stamped an hour ahead held back every message after it, so the run never ended; malformed ones never made a
    run degraded; and a robot that went quiet in the middle of an action ended it complete. Now each such message
    is left out and counted, a gap in the joint states and an action begun and never ended are said, and the run
    goes to its end, degraded, with a note of how it ended."""
    from conductor.core import Conductor, RunOptions
    from conductor.scene import parse_scene
    from conductor.sources.live import GAP_S, LiveSource

    from .conftest import spawn_agents

    session, endpoint = router
    scene = parse_scene(LIVE_SCENE, "live_inputs.yaml")
    keys = Keys("liveinputs")
    spawn_agents(procs, scene, endpoint, "liveinputs")
    c = Conductor(scene, session, keys, LiveSource(session, keys, idle_timeout=3.0, wait_first=60.0),
                  RunOptions(rtf=1.0, register_timeout=60, run_log=str(tmp_path / "run.mcap")))
    out: dict = {}
    runner = threading.Thread(target=lambda: out.setdefault("summary", c.run()), daemon=True)
    runner.start()
    joints, actions = keys.telemetry("joint_states"), keys.telemetry("action")

    def joint(position: float = 0.1, ahead: float = 0.0) -> bytes:
        return codec.encode_unchecked("joint_state", {"stamp": time.time() + ahead, "name": ["j1"],
                                                      "position": [position], "velocity": [], "effort": []})

    def action(operation: str, phase: str) -> bytes:
        return codec.encode("action", stamp=time.time(), operation=operation, phase=phase, params={})

    try:
        client.put(actions, action("grip", "end"))  # the end of an action begun before the twin heard anything
        client.put(actions, action("move_arm", "start"))
        for i in range(40):
            client.put(joints, joint())
            if i == 20:
                client.put(joints, joint(float("nan")))  # a sensor's NaN
                client.put(joints, joint(ahead=3600.0))  # a clock that jumped an hour
                client.put(joints, b"\x00not a message")
            time.sleep(0.01)
        client.put(actions, action("move_arm", "end"))
        time.sleep(GAP_S + 0.3)  # the robot stops publishing for a while
        client.put(actions, action("move_hand", "start"))  # ... and goes quiet for good during this one
        for _ in range(40):
            client.put(joints, joint())
            time.sleep(0.01)
        runner.join(timeout=60)
    finally:
        end_run(c, runner)
    s = out["summary"]
    assert s["status"] == "degraded", (s["status"], s["status_reasons"])
    warned = "\n".join(s["input_warnings"])
    assert "2 telemetry messages left out: malformed" in warned, warned
    assert "1 telemetry message left out: stamped far ahead of when it came" in warned, warned
    assert "the robot's joint states stopped 1 time for more than 0.5 s" in warned, warned
    assert "went quiet during its action move_hand" in warned and "move_arm" not in warned, warned
    assert "began in the middle of its task (the twin joined late?): its action grip ended" in warned, warned
    assert any("quiet for 3 s" in n for n in s["input_notes"]), s.get("input_notes")
    assert s["ticks"] > 100 and s["lag"]["samples"] == 80  # every good joint state reached its tick
    # and where its entities started, with no --perception: said, as a replay of a bag without one says it
    from conductor.scene.perception import NO_PERCEPTION_LIVE, perceive

    assert perceive(parse_scene(LIVE_SCENE, "live_inputs.yaml"), c.source) == NO_PERCEPTION_LIVE


@pytest.mark.slow
def test_the_run_log_keeps_what_a_robot_sent_before_the_run_began(router, procs, client, tmp_path):
    """A twin attaching to a robot that is already publishing: the joint states that came while the agents started
    were used (the live source queued them) but not logged, since the run log's own subscription was declared
    only when the conductor began serving (a late join logged 2097 joint states of 2106). The log now takes the
    robot's messages from the source, those before it opened first, in the order they came."""
    from conductor.core import Conductor, RunOptions
    from conductor.scene import parse_scene
    from conductor.sources.live import LiveSource

    from .conftest import spawn_agents

    session, endpoint = router
    scene = parse_scene(LIVE_SCENE, "live_early.yaml")
    keys = Keys("liveearly")
    source = LiveSource(session, keys, idle_timeout=3.0, wait_first=60.0)
    joints = keys.telemetry("joint_states")
    sent: list[float] = []
    stop = threading.Event()

    def publish() -> None:  # a robot at 100 Hz, without a pause (a pause over 0.5 s is a gap, said)
        while not stop.is_set() and len(sent) < 6000:
            sent.append(time.time())
            client.put(joints, codec.encode("joint_state", stamp=sent[-1], name=["j1"], position=[0.1],
                                            velocity=[], effort=[]))
            time.sleep(0.01)

    robot = threading.Thread(target=publish, daemon=True)
    robot.start()  # before there is any conductor or run log
    c = runner = None
    out: dict = {}
    try:
        assert wait_until(lambda: len(source._q) >= 30, timeout=20), len(source._q)
        spawn_agents(procs, scene, endpoint, "liveearly")
        c = Conductor(scene, session, keys, source, RunOptions(rtf=1.0, register_timeout=60,
                                                               run_log=str(tmp_path / "run.mcap")))
        runner = threading.Thread(target=lambda: out.setdefault("summary", c.run()), daemon=True)
        runner.start()
        assert wait_until(lambda: c.running or not runner.is_alive(), timeout=60)
        early = len(sent)
        assert wait_until(lambda: len(sent) >= early + 30, timeout=20)  # and while the run goes on
        stop.set()
        robot.join(timeout=10)
        runner.join(timeout=60)
    finally:
        stop.set()
        if c is not None:
            if runner is not None and runner.is_alive():
                c.stop("the test")
                runner.join(timeout=30)
            c.close()
    assert early > 30  # (the robot had sent that many before the run's first tick)
    s = out["summary"]
    assert s["status"] == "complete", (s["status"], s["status_reasons"])
    assert s["lag"]["samples"] == len(sent)  # the twin used every one
    logged = [m["stamp"] for k, _, m in read_run_log(s["run_log"]) if k.endswith("/telemetry/joint_states")]
    assert logged == pytest.approx(sent, abs=1e-6), (len(logged), len(sent))  # and its log holds every one, in order
    # the log's simulated clock is the robot's: time 0 at its first stamp, where the log files that joint state (it
    # was when the run log opened, and every tick sat after the robot's messages by as long as the start took)
    from conductor.runlog import read_metadata

    assert int(read_metadata(s["run_log"])["twin.log"]["origin_ns"]) == round(sent[0] * 1e9)
    first_tick = next(t for k, t, _ in read_run_log(s["run_log"]) if k == keys.step_all)
    assert first_tick == round(sent[0] * 1e9), (first_tick, sent[0])
    # (as ROS 2 stamps: whole nanoseconds)


def test_what_does_not_fit_before_the_run_log_opens_is_said(router, client, monkeypatch, tmp_path):
    """A robot that publishes long before the run begins fills what the source keeps for the run log: the rest is
    counted and said (the run is then degraded), never silently lost; what came, malformed or not, is logged in
    the order it came, and what comes after the log opened goes straight to it."""
    from conductor.runlog import RunLog
    from conductor.sources import live

    monkeypatch.setattr(live, "LOG_WAITING", 5)
    session, _ = router
    keys = Keys("logwaiting")
    source = live.LiveSource(session, keys, idle_timeout=1.0)
    joints = keys.telemetry("joint_states")
    payloads = [codec.encode("joint_state", stamp=time.time(), name=["j1"], position=[0.1 * i], velocity=[],
                             effort=[]) for i in range(8)]
    for p in [b"\x00not a message", *payloads[:7]]:
        client.put(joints, p)
    assert wait_until(lambda: len(source._q) == 7, timeout=20)
    assert source.log_missed == 3
    assert any("3 telemetry messages that came before the run began are not in its run log" in w
               for w in source.warnings()), source.warnings()
    log = RunLog(tmp_path / "run.mcap")
    assert source.log_to(log.take)
    client.put(joints, payloads[7])
    assert wait_until(lambda: len(source._q) == 8, timeout=20)
    log.close()
    kept = [m and m["position"][0] for k, _, m in read_run_log(tmp_path / "run.mcap") if k == joints]
    assert kept[0] is None and kept[1:] == pytest.approx([0.1 * i for i in (0, 1, 2, 3, 7)]), kept


@pytest.mark.slow
def test_robot_play_says_when_the_twin_it_waited_for_goes_away(router, procs, tmp_path):
    """`twin robot play --wait-twin` plays for one twin: when that twin ends before the play does (here cut short by
    --max-ticks), the play goes on to its end as a robot would, but says that the rest reached no twin and exits 3
    (it exited 0, as if the twin had heard it all)."""
    from conductor.core import Conductor, RunOptions
    from conductor.scene import parse_scene
    from conductor.sources.live import LiveSource

    from .conftest import spawn_agents

    session, endpoint = router
    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    scene = parse_scene(LIVE_SCENE, "live_gone.yaml")
    keys = Keys("livegone")
    spawn_agents(procs, scene, endpoint, "livegone")
    c = Conductor(scene, session, keys, LiveSource(session, keys, idle_timeout=1.0, wait_first=60.0),
                  RunOptions(rtf=1.0, register_timeout=60, max_ticks=50))
    out: dict = {}

    def run() -> None:
        out["summary"] = c.run()
        c.close()  # (as twin run's process ends when its run does)

    runner = threading.Thread(target=run, daemon=True)
    runner.start()
    try:
        r = subprocess.run(python_cmd("robot", "play", str(rec), "--connect", endpoint, "--ensemble", "livegone",
                                      "--wait-twin", "60"), capture_output=True, text=True, timeout=120, env=ENV,
                           cwd=ROOT)
        runner.join(timeout=30)
    finally:
        end_run(c, runner)
    assert out["summary"]["status"] == "truncated", out["summary"]["status_reasons"]
    assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
    assert "sent 300 joint states" in r.stdout, r.stdout  # it played to the end
    assert "the twin of ensemble 'livegone' went away" in r.stderr and "reached no twin" in r.stderr, r.stderr


def test_a_live_source_files_under_the_run_logs_keys_keeps_nothing_without_a_log_and_closes(router, client):
    """twin serve attaches to a robot on an ensemble of its own while the run's log files telemetry under its
    pool's: the robot's messages are handed under the log's keys (they went in as another topic, so --from-log found
    no joint states). A run without a run log keeps nothing for one (the buffer filled and made it degraded), and a
    source closed after its run stops hearing the robot (a warm service's old subscriptions went on filling)."""
    from conductor.sources.live import LiveSource

    session, _ = router
    robot = Keys("robotens")
    joints = robot.telemetry("joint_states")

    def put(n: int) -> None:
        for _ in range(n):
            client.put(joints, codec.encode("joint_state", stamp=time.time(), name=["j1"], position=[0.1],
                                            velocity=[], effort=[]))

    taken: list[str] = []
    moved = LiveSource(session, robot)
    bare = LiveSource(session, robot)
    put(3)
    assert wait_until(lambda: len(moved._q) == 3 and len(bare._q) == 3, timeout=20)
    assert moved.log_to(lambda key, payload, t: taken.append(key), Keys("svc-w0").telemetry(""))
    assert not bare.log_to(None)  # no run log: nothing kept
    put(2)
    assert wait_until(lambda: len(moved._q) == 5 and len(bare._q) == 5, timeout=20)
    assert taken == ["twin/svc-w0/telemetry/joint_states"] * 5, taken
    assert bare._log_waiting is None and bare.log_missed == 0
    moved.close()
    bare.close()
    put(2)
    time.sleep(0.5)
    assert len(moved._q) == 5 and len(bare._q) == 5 and len(taken) == 5  # (closed: nothing more heard)


@pytest.mark.slow
def test_a_live_run_whose_robot_never_speaks_ends_at_its_deadline(router, procs, tmp_path):
    """--deadline bounds the whole run: a live run waiting for its robot's first message went on waiting its 60 s
    (wait_first), past a deadline of 3 s, then failed for want of telemetry. It now ends at the deadline, truncated,
    saying so."""
    from conductor.core import Conductor, RunOptions
    from conductor.scene import parse_scene
    from conductor.sources.live import LiveSource

    from .conftest import spawn_agents

    session, endpoint = router
    scene = parse_scene(LIVE_SCENE, "live_deadline.yaml")
    keys = Keys("livedeadline")
    spawn_agents(procs, scene, endpoint, "livedeadline")
    # (the agents register first, within the test's 60 s; the deadline counts from there)
    assert wait_until(lambda: len([r for r in session.liveliness().get(keys.alive("**"), timeout=2)
                                   if r.ok is not None]) >= len(scene.models), timeout=60)
    with Conductor(scene, session, keys, LiveSource(session, keys, wait_first=60.0),
                   RunOptions(register_timeout=60, deadline=3.0, run_log=None)) as c:
        s = c.run()
    assert s["status"] == "truncated" and s["ticks"] == 0, (s["status"], s["status_reasons"])
    assert s["status_reasons"] == ["stopped at tick 0 by its deadline of 3 s"], s["status_reasons"]


@pytest.mark.slow
def test_robot_play_says_when_the_twin_it_waited_for_heard_none_of_it(router, procs, tmp_path):
    """`twin robot play --wait-twin` found its twin, played ROS 2's keys where the twin listened on its own, and
    exited 0 having reached no one (the twin then failed for want of telemetry). The play now knows what subscribed
    to its joint states (Zenoh's matching status), says that none reached a subscriber, and exits 3."""
    from conductor.core import Conductor, RunOptions
    from conductor.scene import parse_scene
    from conductor.sources.live import LiveSource

    from .conftest import spawn_agents

    session, endpoint = router
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    scene = parse_scene(LIVE_SCENE, "live_elsewhere.yaml")
    keys = Keys("liveelsewhere")
    spawn_agents(procs, scene, endpoint, "liveelsewhere")
    c = Conductor(scene, session, keys, LiveSource(session, keys, wait_first=120.0),
                  RunOptions(register_timeout=60, run_log=None))
    runner = threading.Thread(target=c.run, daemon=True)
    runner.start()
    try:
        r = subprocess.run(python_cmd("robot", "play", str(rec), "--connect", endpoint, "--ensemble", "liveelsewhere",
                                      "--wait-twin", "60", "--ros2-domain", "9"), capture_output=True, text=True,
                           timeout=120, env=ENV, cwd=ROOT)
    finally:
        end_run(c, runner)
    assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
    assert "sent 100 joint states" in r.stdout, r.stdout  # it played to the end
    assert "warning: none of its 100 joint states reached a subscriber: nothing listened on ROS 2 domain 9" \
        in r.stderr and "did not hear the play" in r.stderr, r.stderr
