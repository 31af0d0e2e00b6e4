"""A run never lies: whatever ends it, it says how far its answer can be trusted, in its summary and its exit
code, and the summary is never lost."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from conductor.core import Conductor, RunOptions
from conductor.scene import load_scene
from protocol.keys import CONDUCTOR, Keys
from recordings.simple import core_recording

from .conftest import spawn_agents

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
SCENE = ROOT / "tests" / "core_scene.yaml"


def _start(rec: Path, run_dir: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "conductor.cli", "run", str(SCENE), "--recording", str(rec),
                             "--run-dir", str(run_dir), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV, cwd=ROOT)


def _wait_for(p: subprocess.Popen, text: str, timeout: float = 90) -> str:
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = p.stdout.readline()
        if not line:
            break
        seen.append(line)
        if text in line:
            return "".join(seen)
    raise AssertionError(f"{text!r} never came:\n{''.join(seen)}")


def _communicate_or_explain(p: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """``p``'s output once it ends; if it does not within ``timeout``, fail with where each of its threads was
    (``kill -USR1``: a twin process writes its stacks to stderr) and what it wrote."""
    try:
        return p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        p.kill()
        out, err = p.communicate(timeout=30)
        raise AssertionError(f"the run did not end within {timeout:g} s; its threads, then its output:\n"
                             f"{err[-6000:]}\n{out[-3000:]}") from None


def _children(pid: int) -> list[str]:
    return subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()


@pytest.mark.slow
def test_sigterm_interrupts_the_run_and_its_summary_says_so(tmp_path):
    """SIGTERM in the middle of a replay: the run ends at the next tick, the summary (status interrupted) is
    written, the exit code is 5, and no agent process is left behind. (SIGUSR1 before it only writes where each
    thread is.)"""
    rec = core_recording(tmp_path / "rec.mcap", seconds=30.0)
    p = _start(rec, tmp_path / "run", "--rtf", "1", "--summary", str(tmp_path / "s.json"))
    try:
        _wait_for(p, "handover")
        kids = _children(p.pid)
        assert len(kids) == 4
        p.send_signal(signal.SIGUSR1)  # where its threads are, written to stderr; the run goes on
        time.sleep(0.5)
        assert p.poll() is None
        p.send_signal(signal.SIGTERM)
        out, err = _communicate_or_explain(p, 60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 5, out + err
    assert "(most recent call first)" in err and "in run" in err, err[-2000:]
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["status"] == "interrupted" and "SIGTERM" in s["status_reasons"][0], s["status_reasons"]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["status"] == "interrupted"
    assert "INTERRUPTED" in out
    time.sleep(0.5)
    assert not any(Path(f"/proc/{k}").exists() and "zombie" not in Path(f"/proc/{k}/status").read_text().lower()
                   for k in kids)


def test_what_a_model_never_declared_is_left_out_and_said_and_its_warnings_printed(tmp_path):
    """A model that publishes an output and raises an event it never declared (``check_model`` refuses it; a model
    written in another language or not checked may do it anyway): nothing of the scene can use them, so they were
    kept and logged as if declared and the run said complete. Now they are left out, counted per model, and the
    run is degraded (exit 3) naming them; its StepWarnings are printed with their count and last message."""
    text = SCENE.read_text().replace('kind: "tests.models.simple:Holder"', 'kind: "tests.models.broken:ChattyHolder"')
    assert "ChattyHolder" in text
    scene = tmp_path / "chatty.yaml"
    scene.write_text(text)
    rec = core_recording(tmp_path / "rec.mcap")
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(scene), "--recording", str(rec),
                        "--run-dir", str(tmp_path / "run"), "--summary", str(tmp_path / "s.json")],
                       capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=240)
    assert r.returncode == 3, r.stdout + r.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["status"] == "degraded", s["status_reasons"]
    undeclared = [w for w in s["status_reasons"] if "never declared" in w]
    assert len(undeclared) == 1 and "holder: event gossip (1x), output secret (" in undeclared[0], s["status_reasons"]
    steps = s["models"]["holder"]["steps"]
    assert s["models"]["holder"]["warned_steps"] >= steps // 10 > 0, s["models"]["holder"]
    assert s["step_warnings"][0].startswith("model holder: ") and "nothing to hold at tick" in s["step_warnings"][0]
    assert "warning: model holder: " in r.stdout and "never declared" in r.stdout
    assert s["handovers"] and s["semantic_state"] == {"in(bin, ball)": True}  # the run itself went on


@pytest.mark.slow
def test_a_full_disk_fails_the_run_and_the_summary_survives(tmp_path):
    """The run log's file system fills up in the middle of a run: the run stops at once as failed with the
    reason, exits 1, and the summary it cannot write beside the log goes to the temporary directory."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small file system needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=72m", "tmpfs", str(mnt)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        rec = core_recording(tmp_path / "rec.mcap", seconds=30.0)
        p = _start(rec, mnt / "run", "--rtf", "2")
        try:
            _wait_for(p, "handover")
            with open(mnt / "filler", "wb") as f:  # take every byte that is left
                try:
                    while True:
                        f.write(b"\0" * (1 << 20))
                        f.flush()
                except OSError:
                    pass
            out, err = p.communicate(timeout=90)
        finally:
            if p.poll() is None:
                p.kill()
        assert p.returncode == 1, out + err
        assert "FAILED" in out and "writing failed" in out, out
        moved = [line.split(" it is in ")[1].strip() for line in err.splitlines() if " it is in " in line]
        assert moved, err
        s = json.loads(Path(moved[0]).read_text())
        assert s["status"] == "failed" and "run log" in s["status_reasons"][0], s["status_reasons"]
        assert s["ticks"] < 3000  # stopped at once, not at the end of the 30 s recording
        Path(moved[0]).unlink()
    finally:
        subprocess.run(["umount", "-l", str(mnt)])


def test_a_second_conductor_for_an_ensemble_is_refused(router, tmp_path):
    """Two conductors on one ensemble would step and hand over the same agents: the second is refused before it
    declares anything, its run failed with the reason."""
    session, endpoint = router
    other = session.liveliness().declare_token(Keys("taken").alive(CONDUCTOR))
    try:
        with Conductor(load_scene(SCENE), session, Keys("taken"), None, RunOptions(max_ticks=5)) as c:
            s = c.run()
    finally:
        other.undeclare()
    assert s["status"] == "failed" and "already has a conductor" in s["status_reasons"][0]


@pytest.mark.slow
def test_max_ticks_and_the_deadline_truncate(router, procs, tmp_path):
    """A run that stops before the end of its source is truncated, never complete."""
    session, endpoint = router
    scene = load_scene(SCENE)
    spawn_agents(procs, scene, endpoint, "trunc")
    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource

    rec = load_recording(core_recording(tmp_path / "rec.mcap", seconds=3.0))
    with Conductor(scene, session, Keys("trunc"), ReplaySource(rec), RunOptions(max_ticks=50)) as c:
        s = c.run()
    assert s["status"] == "truncated" and "max_ticks 50" in s["status_reasons"][0], s["status_reasons"]
    with Conductor(scene, session, Keys("trunc"), ReplaySource(rec), RunOptions(rtf=0.5, deadline=1.0)) as c:
        s = c.run()
    assert s["status"] == "truncated" and "deadline" in s["status_reasons"][0], s["status_reasons"]
    assert s["ticks"] < 300

    # a stop (or a signal) that comes after the last tick, while the run is summed up, changes nothing it reports:
    # it made a run that had replayed all of its source truncated (a review's finding)
    with Conductor(scene, session, Keys("trunc"), ReplaySource(rec), RunOptions()) as c:
        semantics = c.triggers.semantics

        def late(*args: Any) -> Any:
            c.stop("a stop request after the end")
            c.stop("Ctrl-C", signal="SIGINT")
            return semantics(*args)

        c.triggers.semantics = late
        s = c.run()
    assert s["status"] == "complete" and s["ticks"] == 300, (s["status"], s["status_reasons"], s["ticks"])


def test_a_free_running_model_that_hangs_is_said(tmp_path):
    """A free-running model that hung with its liveliness token alive was never noticed: it steps on its own, so
    nothing waited for it, its steps were not even counted (models.beat.steps 0), and the run ended complete. Its
    steps are now said on done/<id>, counted, and one that stepped fewer than half the times its rate gives makes
    the run degraded, naming it. The same run with the healthy heartbeat is complete, its steps counted."""
    rec = core_recording(tmp_path / "rec.mcap")

    def run(scene: Path, name: str) -> tuple[subprocess.CompletedProcess, dict]:
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(scene), "--recording", str(rec),
                            "--rtf", "1", "--run-dir", str(tmp_path / name)], capture_output=True, text=True,
                           env=ENV, cwd=ROOT, timeout=240)
        return r, json.loads((tmp_path / name / "summary.json").read_text())

    r, s = run(SCENE, "healthy")
    assert r.returncode == 0 and s["status"] == "complete", s["status_reasons"]
    assert s["models"]["beat"]["steps"] >= 0.5 * 20 * s["wall_s"] - 2, (s["models"]["beat"], s["wall_s"])
    text = SCENE.read_text().replace('"tests.models.simple:Heartbeat"', '"tests.models.broken:StallingBeat"')
    assert "StallingBeat" in text
    (tmp_path / "stall.yaml").write_text(text)
    r, s = run(tmp_path / "stall.yaml", "stall")
    assert r.returncode == 3 and s["status"] == "degraded", r.stdout + r.stderr
    (why,) = [w for w in s["status_reasons"] if w.startswith("model beat (free-running at 20 Hz) stepped ")]
    assert "it stalled or fell behind" in why and s["models"]["beat"]["steps"] < 20, s["models"]["beat"]
    assert s["semantic_state"] == {"in(bin, ball)": True}


def test_a_fault_in_the_conductor_fails_the_run_with_a_summary_and_a_whole_run_log(router, procs, tmp_path):
    """Anything the tick loop raises that nobody expected (a model's answer Python could not compare, a bug of
    ours) went through Conductor.run: no summary, the agents not told to stop, the run log cut without its end. It
    is now a failed run with the fault in its reasons, and the log is finished (its summary in it)."""
    session, endpoint = router
    scene = load_scene(SCENE)
    spawn_agents(procs, scene, endpoint, "fault")
    from conductor.runlog.reader import read_metadata
    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource

    rec = load_recording(core_recording(tmp_path / "rec.mcap"))
    with Conductor(scene, session, Keys("fault"), ReplaySource(rec),
                   RunOptions(run_log=str(tmp_path / "run.mcap"))) as c:
        absorb = c.triggers.absorb_tick

        def faulty(replies):
            if c.clock.tick >= 40:
                raise RuntimeError("a fault nobody expected")
            absorb(replies)

        c.triggers.absorb_tick = faulty  # type: ignore[method-assign]
        s = c.run()
    assert s["status"] == "failed" and s["status_reasons"][0].startswith("the conductor failed at tick 4"), \
        s["status_reasons"]
    assert "RuntimeError: a fault nobody expected" in s["status_reasons"][0]
    assert json.loads(read_metadata(str(tmp_path / "run.mcap"))["twin.summary"]["json"])["status"] == "failed"


def test_bad_command_lines_get_one_line_errors(tmp_path):
    def twin(*args):
        return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                              timeout=60, env=ENV, cwd=ROOT)

    rec = core_recording(tmp_path / "rec.mcap", seconds=0.5)
    for args, expect, code in [
        (("run", str(SCENE)), "nothing to run on", 2),
        (("run", str(SCENE), "--recording", str(rec), "--rerun", "bogus"), "unknown --rerun mode", 2),
        (("run", str(SCENE), "--recording", str(rec), "--listen", "127.0.0.1:7447"), "must start with a protocol", 2),
        (("router", "--listen", "tcp/127.0.0.1:notaport"), "must be tcp/HOST:PORT", 2),
        (("status", "--timeout", "1", "--connect", "tcp/127.0.0.1:9"), "no Zenoh router answered", 1),
    ]:
        r = twin(*args)
        assert r.returncode == code and expect in r.stderr, (args, r.returncode, r.stderr)
        assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.slow
def test_a_model_that_stops_answering_is_lost_and_rejoins_when_it_answers_again(router, procs):
    """A step not answered within the step timeout makes the agent lost (its responsibilities fall back, the run
    is degraded) even though its liveliness token lives; when its late answer comes, it is initialised again
    and steps on."""
    session, endpoint = router
    from conductor.scene import parse_scene

    scene = parse_scene("name: stall\nclock: {rate: 100, batch: 1}\nmain: a\nmodels:\n"
                        "  a: {kind: 'tests.models.simple:Counter', step: service}\n"
                        "  b: {kind: 'tests.models.simple:Counter', step: service, "
                        "args: {stall_tick: 10, stall_s: 1.5}}\n", "<stall>")
    spawn_agents(procs, scene, endpoint, "stall")
    events = []
    c = Conductor(scene, session, Keys("stall"), None, RunOptions(max_ticks=300, step_timeout=0.5, rtf=1.0),
                  on_event=lambda kind, data: events.append((kind, data.get("model"))))
    with c:
        s = c.run()
    assert ("agent_lost", "b") in events and ("rejoin", "b") in events, events
    assert s["status"] == "degraded", s["status_reasons"]
    assert any("model b lost at tick 10 (no answer within the 0.5 s step timeout)" in r for r in s["status_reasons"])
    assert s["ticks"] == 300 and 10 < s["models"]["b"]["steps"] < 300 and s["models"]["a"]["steps"] == 300


def test_a_new_process_of_a_model_taken_out_for_not_answering_steps_on(router, procs):
    """A model taken out of the run for not answering in time, whose process was then replaced by a new one (a
    supervisor's restart): the new process rejoined, but its first step answer was taken for the old process's
    late one and not counted, so it was taken out again a step timeout later. It now steps on after it rejoins,
    and the old process's end, once it was out, is not a second loss."""
    from conductor.launch import agent_command
    from conductor.scene import parse_scene

    session, endpoint = router
    scene = parse_scene("name: swap\nclock: {rate: 100, batch: 1}\nmain: a\nmodels:\n"
                        "  a: {kind: 'tests.models.simple:Counter', step: service}\n"
                        "  b: {kind: 'tests.models.simple:Counter', step: service, "
                        "args: {stall_tick: 10, stall_s: 600}}\n", "<swap>")
    spawn_agents(procs, scene, endpoint, "swap")
    events: list[tuple[str, Any]] = []

    def on_event(kind: str, data: dict) -> None:
        events.append((kind, data.get("model")))
        if (kind, data.get("model")) == ("agent_lost", "b") and events.count(("agent_lost", "b")) == 1:
            procs.procs["b"].kill()  # the hung process goes; a new one comes in its place
            procs.spawn("b", agent_command("tests.models.simple:Counter", "b", endpoint, "swap"))

    # (10 s at --rtf 1: the new process starts, imports and registers within the first 7 s on a loaded machine)
    c = Conductor(scene, session, Keys("swap"), None, RunOptions(max_ticks=1000, step_timeout=0.5, rtf=1.0),
                  on_event=on_event)
    with c:
        s = c.run()
    assert ("rejoin", "b") in events and events.count(("agent_lost", "b")) == 1, events  # (its kill: no news)
    assert s["ticks"] == 1000 and s["models"]["b"]["steps"] > 300, s["models"]["b"]
    assert s["status"] == "degraded" and s["status_reasons"][0].startswith("model b lost at tick 10"), s
    assert sum(r.startswith("model b lost") for r in s["status_reasons"]) == 1, s["status_reasons"]


def test_a_clock_driven_model_that_hangs_where_nothing_waits_for_it_is_said(router, procs):
    """Live, or in a replay with ``max_lag: null``, nothing waits for a clock-driven model, so one that hung with
    its liveliness token alive was never noticed and the run ended complete. One that answers no new clock tick
    for the step timeout while ticks are due now makes the run degraded, naming it; the same run with it healthy
    is complete."""
    session, endpoint = router
    from conductor.scene import parse_scene

    def scene_of(stall_s: float) -> Any:
        return parse_scene("name: clockstall\nclock: {rate: 100, max_lag: null}\nmain: a\nmodels:\n"
                            "  a: {kind: 'tests.models.simple:Counter', step: service}\n"
                            "  b: {kind: 'tests.models.simple:Counter', step: clock, "
                            f"args: {{stall_tick: 20, stall_s: {stall_s}}}}}\n", "<clockstall>")

    spawn_agents(procs, scene_of(0.0), endpoint, "clockstall")  # (the agents stay for the second run)

    def run(stall_s: float) -> dict:
        with Conductor(scene_of(stall_s), session, Keys("clockstall"), None,
                       RunOptions(max_ticks=250, step_timeout=0.6, rtf=1.0)) as c:
            return c.run()

    s = run(0.0)
    # (nothing waits for b: its last ticks may still be on the way when the run ends)
    assert s["status"] == "complete" and s["models"]["b"]["steps"] >= 200, (s["status_reasons"], s["models"])
    s = run(1.6)
    assert s["status"] == "degraded", s["status_reasons"]
    (why,) = [r for r in s["errors"] if "clock-driven model b: answered no clock tick for" in r]
    assert "it hung or fell behind" in why, why
    assert s["ticks"] == 250 and s["models"]["b"]["max_lag_ticks"] > 60, s["models"]["b"]


def test_a_paced_replay_that_fell_behind_and_caught_up_says_so(router, procs):
    """A paced run (--rtf 1) whose model stalled for 2 s then went as fast as the models allowed until it had
    caught up, and its summary said nothing of it: what was watched at that pace was not at it. It is now a note
    (no defect: every tick was stepped) and the summary's ``pace``."""
    session, endpoint = router
    from conductor.scene import parse_scene

    scene = parse_scene("name: pace\nclock: {rate: 100, batch: 1}\nmain: a\nmodels:\n"
                        "  a: {kind: 'tests.models.simple:Counter', step: service}\n"
                        "  b: {kind: 'tests.models.simple:Counter', step: service, "
                        "args: {stall_tick: 30, stall_s: 2.0}}\n", "<pace>")
    spawn_agents(procs, scene, endpoint, "pace")
    with Conductor(scene, session, Keys("pace"), None, RunOptions(max_ticks=300, rtf=1.0)) as c:
        s = c.run()
    assert s["status"] == "complete" and s["ticks"] == 300, s["status_reasons"]
    assert s["pace"]["rtf"] == 1.0 and 1.5 < s["pace"]["behind_max_s"] < 6.0 and s["pace"]["at_t"] >= 0.3, s["pace"]
    (note,) = [n for n in s.get("input_notes", []) if "behind its --rtf 1 pace" in n]
    assert "went as fast as the models allowed until it caught up" in note


@pytest.mark.slow
def test_the_embedded_bus_admits_only_its_own_processes(tmp_path):
    """A local process without this run's secret cannot even connect to the embedded router, so it can forge
    nothing (no step, no stop, no liveliness token, nothing oversized); with the run's access.json it can."""
    from conductor.launch import free_port
    from protocol.config import ZenohOptions, read_credentials

    rec = core_recording(tmp_path / "rec.mcap", seconds=8.0)
    port = free_port()
    p = _start(rec, tmp_path / "run", "--rtf", "1", "--listen", f"tcp/127.0.0.1:{port}")
    try:
        _wait_for(p, "handover")
        rogue = ZenohOptions(mode="client", connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=1500)
        with pytest.raises(Exception, match="Unable to connect"):
            rogue.open()
        user, password = read_credentials(str(tmp_path / "run" / "access.json"))
        guest = ZenohOptions(mode="client", connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=5000,
                             user=user, password=password).open()
        try:
            answers = [r for r in guest.get(Keys("default").conductor("status"), timeout=5) if r.ok is not None]
            assert len(answers) == 1
        finally:
            guest.close()
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, out + err
    assert not (tmp_path / "run" / "access.json").exists()  # the run's secrets end with it


def run_ball_drop_changed(tmp_path: Path, old: str, new: str, *flags: str) -> tuple[Any, dict[str, Any]]:
    """``twin run`` of ball_drop.yaml with ``old`` replaced by ``new``, on ball_drop_00: the process's result and its
    summary."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    changed = text.replace(old, new)
    assert changed != text
    (tmp_path / "changed.yaml").write_text(changed)
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(tmp_path / "changed.yaml"), "--recording",
                        str(ROOT / "recordings" / "ball_drop_00.mcap"), "--run-dir", str(tmp_path / "run"),
                        "--summary", str(tmp_path / "s.json"), *flags], capture_output=True, text=True, timeout=300,
                       env=ENV, cwd=ROOT)
    return r, json.loads((tmp_path / "s.json").read_text())


def test_a_model_that_refuses_its_init_fails_the_run_with_a_summary(tmp_path):
    """An agent that answers its init with an error (here physics, asked for a robot link the robot does not have:
    a value no declaration can rule out before the robot is loaded): the run fails before its first tick, and
    still writes its summary, saying which model refused and why."""
    r, s = run_ball_drop_changed(tmp_path, "grasp_binding: none}", "grasp_binding: none, links: [no_such_link]}")
    assert r.returncode == 1, r.stdout + r.stderr
    assert s["status"] == "failed" and s["ticks"] == 0, s["status_reasons"]
    assert "model physics" in s["status_reasons"][0] and "unknown robot links" in s["status_reasons"][0], s
    assert "Traceback" not in r.stderr


def test_an_agent_started_by_the_run_that_never_registers_is_named_with_its_log(tmp_path):
    """The run starts the agents itself, so when one is still silent at --register-timeout the advice is not to
    start agents by hand: the run names the agent, says it was started and still runs, and shows its log."""
    r, s = run_ball_drop_changed(tmp_path, "in_hand: {kind: in_hand,", 'in_hand: {kind: "tests.models.late:Late",',
                                 "--register-timeout", "15")  # (the other agents register within it, loaded)
    assert r.returncode == 1, r.stdout + r.stderr
    reason = s["status_reasons"][0]
    assert "agent in_hand (pid " in reason and "started by this twin) did not register in time" in reason, reason
    assert "--register-timeout" in reason and "agent-in_hand.log" in reason and "twin agent" not in reason, reason


def test_an_agent_that_is_stopped_is_said_to_be_stopped_not_slow(tmp_path):
    """A warm agent stopped with SIGSTOP (a debugger, a ^Z) never registers: it was said to need a longer
    --register-timeout, which would never help."""
    import signal
    import sys
    import time

    from conductor.launch import AgentProcs
    from protocol.errors import RunAborted

    procs = AgentProcs(tmp_path)
    p = procs.spawn("in_hand", [sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        os.kill(p.pid, signal.SIGSTOP)
        deadline = time.monotonic() + 10
        while Path(f"/proc/{p.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "T":
            assert time.monotonic() < deadline
            time.sleep(0.02)
        with pytest.raises(RunAborted, match=r"did not register in time \(its process is stopped \(SIGSTOP"):
            procs.check_started({"in_hand"}, final=True)
    finally:
        os.kill(p.pid, signal.SIGCONT)
        procs.stop()


def test_a_commands_own_warm_service_admits_only_its_agents(tmp_path):
    """``twin run --samples`` and ``twin evaluate`` run on a service of their own: its router is closed like ``twin
    run``'s (a local process without its secret cannot connect), and the secrets go with it."""
    from conductor.fleet import local_service
    from protocol.config import ZenohOptions

    session, service, bus = local_service(tmp_path / "svc", "closed", max_pools=1)
    try:
        assert bus.access.exists()
        rogue = ZenohOptions(mode="client", connect=[service.endpoint], connect_timeout_ms=1500)
        with pytest.raises(Exception, match="Unable to connect"):
            rogue.open()
    finally:
        service.close()
        session.close()
        bus.close()
    assert not bus.access.exists() and not bus.dictionary.exists()


@pytest.mark.slow
def test_forged_steps_are_refused_counted_and_change_nothing(router, procs, tmp_path):
    """On an open bus (the embedded default is closed: see the test above) a local process forges step broadcasts
    and clock ticks in the middle of a run: a step of 10^4 s, NaN joints, a tick the run is past. Every agent
    refuses them (nothing is stepped), the run says so (degraded, with each model's count), and the answer and
    the models' step counts are those of the same run untouched."""
    import threading

    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource
    from protocol import codec

    session, endpoint = router
    scene = load_scene(SCENE)
    spawn_agents(procs, scene, endpoint, "tamper")
    rec = load_recording(core_recording(tmp_path / "rec.mcap", seconds=3.0))
    keys = Keys("tamper")

    def forge(c: Conductor, done: threading.Event) -> None:
        deadline = time.monotonic() + 20
        while c.clock.tick < 100 and time.monotonic() < deadline:
            time.sleep(0.01)
        now = c.clock.tick
        joints = {"stamp": 1.0, "name": ["j1", "finger"], "position": [float("nan"), 0.2], "velocity": [],
                  "effort": []}
        section = {"dt": 0.01, "actions": [], "inputs": {}}
        # half a second ahead of the run (paced at 100 Hz): a forged tick that came after the run's own would be
        # an old one, answered again and not counted (3 ticks ahead left 30 ms for this thread on a loaded machine)
        forged = [
            {"tick": now + 50, "t": (now + 50) / 100, "joints": None,
             "models": {m: {**section, "dt": 1e4} for m in ("sim", "holder")}},
            {"tick": now + 51, "t": (now + 51) / 100, "joints": joints,
             "models": {m: section for m in ("sim", "holder")}},
            {"tick": 5, "t": 0.05, "joints": None, "models": {m: section for m in ("sim", "holder")}},
        ]
        for body in forged:
            session.put(keys.step_all, codec.encode("tick", **body))
        session.put(keys.clock, codec.encode("clock", tick=now + 52, t=(now + 52) / 100, dt=1e4))
        session.put(keys.clock, codec.encode("clock", tick=2, t=0.02, dt=0.01))
        done.set()

    summaries = []
    for tamper in (False, True):
        done = threading.Event()
        with Conductor(scene, session, keys, ReplaySource(rec), RunOptions(rtf=1.0)) as c:
            forger = threading.Thread(target=forge, args=(c, done), daemon=True)
            if tamper:
                forger.start()
            s = c.run()
            if tamper:
                forger.join(timeout=30)
                assert done.is_set()
        summaries.append(s)
    clean, tampered = summaries
    assert clean["status"] == "complete", clean["status_reasons"]
    assert tampered["status"] == "degraded", tampered["status_reasons"]
    reasons = "\n".join(tampered["status_reasons"])
    # sim and holder refuse the two forged steps meant for them that they would otherwise have stepped
    # (dt, NaN) and the stale one; grip refuses the clock tick of 10^4 s (an old clock tick is answered again,
    # as when the conductor asks once more, and not stepped)
    assert "model sim refused 3 malformed or out-of-sequence messages" in reasons, reasons
    assert "model holder refused 3 malformed or out-of-sequence messages" in reasons, reasons
    assert "model grip refused 1 malformed or out-of-sequence messages" in reasons, reasons
    assert tampered["semantic_state"] == clean["semantic_state"]
    for m in ("sim", "holder", "grip"):
        assert tampered["models"][m]["steps"] == clean["models"][m]["steps"], (m, tampered["models"][m])


def test_a_slow_paced_run_stops_at_once_on_sigterm(tmp_path):
    """--rtf 0.0001 waits 100 s between ticks: SIGTERM ends the wait at once (it used to sleep it out, deaf to
    signals, --deadline and stop requests), the run ends interrupted with its summary."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    p = _start(rec, tmp_path / "run", "--rtf", "0.0001", "--summary", str(tmp_path / "s.json"))
    try:
        _wait_for(p, "running")
        time.sleep(2.0)  # in the wait after the first tick by now
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 5, out + err
    assert json.loads((tmp_path / "s.json").read_text())["status"] == "interrupted"


@pytest.mark.parametrize("flag, value", [("--rtf", "0"), ("--rtf", "-2"), ("--rtf", "nan"), ("--rtf", "inf"),
                                         ("--deadline", "nan"), ("--deadline", "0"), ("--register-timeout", "-1"),
                                         ("--idle-timeout", "0")])
def test_numbers_that_mean_nothing_are_refused(tmp_path, flag, value):
    """A pacing, a deadline or a timeout that is not a finite number above 0 is a bad command line (exit 2, said),
    not 'as fast as possible' or 'no deadline' in silence."""
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(SCENE), "--max-ticks", "5", flag, value,
                        "--run-dir", str(tmp_path / "run")], capture_output=True, text=True, env=ENV, cwd=ROOT,
                       timeout=60)
    assert r.returncode == 2 and f"argument {flag}: a finite number above 0, not {value}" in r.stderr, r.stderr
    assert not (tmp_path / "run").exists()


def test_the_summary_goes_through_links_and_into_pipes_and_devices(tmp_path, capsys, monkeypatch):
    """--summary FILE writes a regular file atomically, but never replaces what stands at FILE: a symbolic link
    is written through (its target gets the summary), a named pipe with a reader gets it, one without a reader
    is an error that sends the summary to the temporary directory (not a wait forever), and a device node stays
    a device (as root, /dev/null would otherwise have become a file)."""
    import stat

    from conductor.launch import write_summary

    summary = {"status": "complete", "ticks": 3}
    monkeypatch.chdir(tmp_path)  # a relative path (as runs/NAME/summary.json is) goes where it says, without a word
    assert write_summary(Path("rel.json"), summary).samefile(tmp_path / "rel.json")
    assert write_summary(Path("new/sub/s.json"), summary).samefile(tmp_path / "new" / "sub" / "s.json")  # made
    assert capsys.readouterr().err == ""
    real = tmp_path / "real.json"
    real.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to("real.json")
    assert write_summary(link, summary) == real
    assert link.is_symlink() and json.loads(real.read_text()) == summary

    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    rfd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader holds the pipe open
    try:
        assert write_summary(fifo, summary) == fifo
        got = os.read(rfd, 1 << 16)
    finally:
        os.close(rfd)
    assert stat.S_ISFIFO(fifo.stat().st_mode) and json.loads(got) == summary

    lonely = tmp_path / "lonely.json"
    os.mkfifo(lonely)
    went = write_summary(lonely, summary)
    assert went != lonely and json.loads(went.read_text()) == summary and stat.S_ISFIFO(lonely.stat().st_mode)
    assert f"could not be written to {lonely}" in capsys.readouterr().err
    went.unlink()

    if os.geteuid() == 0:  # a device node of our own (the null device's numbers), not the machine's /dev/null
        null = tmp_path / "null.json"
        os.mknod(null, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        assert write_summary(null, summary) == null and stat.S_ISCHR(null.stat().st_mode)


def test_a_run_that_cannot_start_still_writes_its_summary(tmp_path):
    """--summary is written on every ending, a run that could not start included: a recording that is not one and a
    broken scene (both bad input, exit 2) leave a 'failed' summary with the reason, as twin submit reports them."""
    (tmp_path / "text.mcap").write_text("not a recording\n")
    for i, (argv, code, said) in enumerate((
            ([str(SCENE), "--recording", str(tmp_path / "text.mcap")], 2, "text.mcap"),
            ([str(ROOT / "tests" / "scenes" / "broken" / "bad_rate.yaml"), "--max-ticks", "5"], 2, "bad_rate.yaml"))):
        out = tmp_path / f"s{i}.json"
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", *argv, "--summary", str(out), "--run-dir",
                            str(tmp_path / "run")], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=60)
        assert r.returncode == code, r.stdout + r.stderr
        s = json.loads(out.read_text())
        assert s["status"] == "failed" and s["ticks"] == 0 and said in s["status_reasons"][0], s


def test_a_run_log_whose_run_never_began_is_ended_whole(tmp_path, monkeypatch):
    """The run log opens with the conductor; when what comes between that and the run failed (here an agent process
    that cannot be started), its file was left without an end, read as a run cut short (a review's finding). The
    conductor's close ends it."""
    from conductor import launch
    from conductor.runlog import cut_short
    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource

    def cannot(*args: Any, **kw: Any) -> None:
        raise OSError("no such program (this test's)")

    monkeypatch.setattr(launch.AgentProcs, "spawn", cannot)
    rec = load_recording(core_recording(tmp_path / "rec.mcap", seconds=1.0))
    with pytest.raises(OSError, match="this test's"):
        launch.run_embedded(load_scene(SCENE), ReplaySource(rec), run_dir=tmp_path / "run", ensemble="neverbegan")
    assert (tmp_path / "run" / "run.mcap").exists() and not cut_short(tmp_path / "run" / "run.mcap")
