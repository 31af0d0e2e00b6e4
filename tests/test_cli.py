"""The twin command line, run as a user would."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conductor.launch import free_port
from recordings.simple import core_recording

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def twin(*args, timeout=120, **kw):
    return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=ENV, cwd=kw.get("cwd", ROOT))


def test_every_command_explains_itself():
    top = twin("--help")
    assert top.returncode == 0 and "COMMAND" in top.stdout
    helps = {}
    for cmd in ["router", "agent", "conductor", "run", "status", "serve", "submit", "trigger", "bench", "evaluate",
                "robot play", "certs", "acl"]:
        r = twin(*cmd.split(), "--help")
        assert r.returncode == 0, (cmd, r.stderr)
        assert "usage: twin " + cmd in r.stdout
        assert len(r.stdout) > 200
        assert "(default: None)" not in r.stdout and "(default: )" not in r.stdout, (cmd, r.stdout)
        helps[cmd] = " ".join(r.stdout.split())
    # the defaults a user would otherwise have to guess (they were not shown)
    assert "seconds to wait for the scene's agents (default: 60.0)" in helps["run"], helps["run"]
    assert "where run logs go (default: runs/evaluate)" in helps["evaluate"], helps["evaluate"]
    assert "(env TWIN_ENSEMBLE, default 'default')" in helps["serve"], helps["serve"]


def test_broken_scene_is_reported_with_file_line_key(tmp_path):
    bad = ROOT / "tests" / "scenes" / "broken" / "transfer_unknown_model.yaml"
    r = twin("run", str(bad), "--max-ticks", "5")
    assert r.returncode == 2
    assert f"{bad}:15: triggers[0].do[0].transfer.to: unknown model 'nowhere'" in r.stderr


def test_a_kind_no_agent_knows_is_said_before_anything_starts(tmp_path):
    """A misspelt built-in kind: twin check, twin run and twin submit name the file, line and key (exit 2) before any
    agent starts (it used to start, exit with code 2, and fail the run)."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    assert "kind: grasp_monitor" in text
    bad = tmp_path / "kind.yaml"
    bad.write_text(text.replace("kind: grasp_monitor", "kind: grasp_monitr"))
    line = next(i for i, t in enumerate(bad.read_text().splitlines(), 1) if "grasp_monitr" in t)
    for argv in (["check", str(bad)], ["run", str(bad), "--max-ticks", "5", "--run-dir", str(tmp_path / "run")],
                 ["submit", str(bad), "--max-ticks", "5", "--timeout", "1"]):
        r = twin(*argv)
        assert r.returncode == 2 and "running" not in r.stdout, (argv, r.stdout, r.stderr)
        assert f"{bad}:{line}: models.grasp_monitor.kind: unknown model kind 'grasp_monitr' (did you mean " \
               "'grasp_monitor'?)" in r.stderr, (argv, r.stderr)
    assert not (tmp_path / "run").exists()
    # for agents started by hand (twin conductor), a kind of their own is allowed: they say what they are
    r = twin("check", str(bad), "--by-hand")
    assert r.returncode == 0 and "is valid" in r.stdout, r.stdout + r.stderr
    # ... while a built-in kind's agent is still asked: its misspelt parameter is said as twin run says it
    typo = tmp_path / "typo.yaml"
    typo.write_text(bad.read_text().replace("grasp_binding:", "grasp_bindng:"))
    assert "grasp_bindng:" in typo.read_text()
    r = twin("check", str(typo), "--by-hand")
    assert r.returncode == 2 and "models.physics.args.grasp_bindng: unknown parameter" in r.stderr, r.stdout + r.stderr


def test_a_misspelt_name_given_to_an_evaluator_is_a_scene_error(tmp_path):
    """``closest('graspble', 'panda_hand')`` found nothing for the whole run: no grasp, no handover, the wrong
    answer, and the run said complete. The agents declare which evaluator arguments are names of the scene (a tag,
    a body), so twin check and twin run refuse a misspelt one with its file and line, exit 2."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    cases = {"graspble": ("closest('graspble', 'panda_hand')", "unknown tag 'graspble' (did you mean 'graspable'?)"),
             "panda_hnd": ("closest('graspable', 'panda_hnd')", "unknown body 'panda_hnd' (did you mean "
                                                                 "'panda_hand'?)"),
             "ball": ("closest('ball', 'panda_hand')", "unknown tag 'ball' (an entity's name, not a tag)")}
    for word, (call, said) in cases.items():
        bad = tmp_path / f"{word}.yaml"
        bad.write_text(text.replace("closest('graspable', 'panda_hand')", call))
        line = next(i for i, t in enumerate(bad.read_text().splitlines(), 1) if call in t)
        r = twin("check", str(bad))
        assert r.returncode == 2, r.stdout + r.stderr
        assert f"{bad}:{line}: triggers[0].let.near: in \"{call}\": {said}" in r.stderr, r.stderr
    r = twin("run", str(bad), "--max-ticks", "5", "--run-dir", str(tmp_path / "run"))
    assert r.returncode == 2 and "unknown tag 'ball'" in r.stdout, r.stdout + r.stderr


def test_a_transfer_to_a_model_that_cannot_own_it_is_a_scene_error(tmp_path):
    """``to: grasp_monitor`` (an observer) passed twin check, and the run degraded when the grasp came, its
    transfer refused without a file or line: twin check now says it, from what the agent will declare."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    bad = tmp_path / "to_observer.yaml"
    bad.write_text(text.replace("attribute: pose, to: in_hand}", "attribute: pose, to: grasp_monitor}"))
    line = next(i for i, t in enumerate(bad.read_text().splitlines(), 1) if "to: grasp_monitor" in t)
    r = twin("check", str(bad))
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"{bad}:{line}: triggers[0].do[0].transfer.to: trigger grasp: model 'grasp_monitor' (grasp_monitor) is an " \
           "observer and owns nothing: this transfer would be refused when it fires" in r.stderr, r.stderr


def test_twin_check_knows_what_the_agents_will_declare(tmp_path):
    """twin check asks each kind's agent what it will declare (python -m agents KIND --describe, no bus) and checks
    the scene against it as the conductor does when they register: a misspelt parameter, a value of the wrong
    type, an agent class that does not import are file:line:key problems (exit 2), not a valid scene."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    bad = tmp_path / "args.yaml"
    bad.write_text(text.replace("args: {time_step:", "args: {tme_step:").replace(
        "grasp_monitor: {kind: grasp_monitor, step: service, rate: 15}",
        "grasp_monitor: {kind: grasp_monitor, step: service, rate: 15, args: {effort_on: high}}"))
    lines = bad.read_text().splitlines()
    at = {k: next(i for i, t in enumerate(lines, 1) if k in t) for k in ("tme_step", "effort_on")}
    r = twin("check", str(bad))
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"{bad}:{at['tme_step']}: models.physics.args.tme_step: unknown parameter 'tme_step' of physics" in r.stderr
    assert f"{bad}:{at['effort_on']}: models.grasp_monitor.args.effort_on: parameter 'effort_on' of grasp_monitor " \
           "must be float, got 'high'" in r.stderr, r.stderr
    # twin run finds the same when its agents register, and exits 2 as well (it exited 1, failed, as if a model had)
    summary = tmp_path / "s.json"
    r = twin("run", str(bad), "--max-ticks", "5", "--run-dir", str(tmp_path / "run"), "--summary", str(summary))
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"{bad}:{at['tme_step']}: models.physics.args.tme_step: unknown parameter 'tme_step' of physics" in r.stdout
    s = json.loads(summary.read_text())
    assert s["status"] == "failed" and s["bad_input"] is True, s
    values = tmp_path / "values.yaml"  # of the right type, but values the agent would refuse at init
    values.write_text(text.replace("time_step: 0.004166666666666667", "time_step: -1").replace(
        "grasp_binding: none", "grasp_binding: nonee"))
    line = next(i for i, t in enumerate(values.read_text().splitlines(), 1) if "nonee" in t)
    r = twin("check", str(values))
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"{values}:{line}: models.physics.args.time_step: parameter 'time_step' of physics must be a finite " \
           "number above 0, got -1" in r.stderr, r.stderr
    assert f"{values}:{line}: models.physics.args.grasp_binding: parameter 'grasp_binding' of physics must be one " \
           "of none, signal, force, got 'nonee'" in r.stderr, r.stderr
    gone = tmp_path / "gone.yaml"
    gone.write_text(text.replace("kind: grasp_monitor", "kind: 'no_such_package.monitor:Monitor'"))
    line = next(i for i, t in enumerate(gone.read_text().splitlines(), 1) if "no_such_package" in t)
    r = twin("check", str(gone))
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"{gone}:{line}: models.grasp_monitor.kind: its agent cannot start: " in r.stderr, r.stderr
    assert "no_such_package" in r.stderr.split("its agent cannot start: ")[1]
    every = tmp_path / "every.yaml"  # a kind misspelt, one that cannot start, a value refused: all said at once
    every.write_text(text.replace("grasp_binding: none", "grasp_binding: nonee").replace(
        "kind: grasp_monitor", "kind: grasp_monitr").replace("kind: in_hand", "kind: 'no_such_package.x:Y'"))
    r = twin("check", str(every))
    assert r.returncode == 2 and "3 problems:" in r.stderr, r.stdout + r.stderr
    said = [line.split(": ", 2)[1] for line in r.stderr.splitlines()[1:]]
    assert said == ["models.physics.args.grasp_binding", "models.grasp_monitor.kind", "models.in_hand.kind"], said
    assert twin("check", "scenes/ball_drop.yaml").returncode == 0


def test_a_run_dir_in_use_is_refused(tmp_path):
    """A second run into the folder a run is using is refused (exit 1, said) and the first goes on: they used to
    write over each other's log, both reported complete. Once the first has ended, the folder is free again."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=20.0)
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "conductor.cli", "run", str(ROOT / "tests" / "core_scene.yaml"), "--recording",
            str(rec), "--run-dir", str(run)]
    first = subprocess.Popen([*argv, "--rtf", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                             cwd=ROOT)
    try:
        assert first.stdout is not None
        assert any("running" in first.stdout.readline() for _ in range(10))  # (it has the folder by then)
        second = twin(*argv[3:], "--max-ticks", "5")
        assert second.returncode == 1, second.stdout + second.stderr
        assert f"--run-dir {run}: another run is using it (pid {first.pid})" in second.stderr, second.stderr
        assert first.poll() is None
        first.terminate()
        first.communicate(timeout=60)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 5
    again = twin(*argv[3:], "--max-ticks", "5")
    assert again.returncode == 4, again.stdout + again.stderr


def test_two_sources_for_one_run_are_refused(tmp_path):
    """A run has one source: a recording and a run log, or a recording and a live robot, are a bad command line
    (exit 2, both named), not one of them ignored without a word."""
    rec = str(ROOT / "recordings" / "ball_drop_00.mcap")
    for argv, named in ((["--from-log", rec, "--recording", rec], "--recording and --from-log"),
                        (["scenes/ball_drop.yaml", "--live", "--recording", rec], "--recording and --live")):
        r = twin("run", *argv, "--run-dir", str(tmp_path / "run"))
        assert r.returncode == 2 and f"twin run: {named} are each a source of the run: give one" in r.stderr, r.stderr
    assert not (tmp_path / "run").exists()


def test_where_output_cannot_go_is_said_in_one_line(tmp_path):
    """An output path that cannot be written is one line naming it, no traceback: a --run-dir that cannot be made
    (exit 1), twin view --out on a folder (exit 1), twin evaluate --json on a folder or a duplicated configuration
    (exit 2, before any run). A scene named '../x' keeps its default run folder inside runs/."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    (tmp_path / "afile").write_text("")
    r = twin("run", str(ROOT / "tests" / "core_scene.yaml"), "--recording", str(rec), "--run-dir",
             str(tmp_path / "afile" / "sub"))
    assert r.returncode == 1 and "cannot be made (Not a directory)" in r.stderr and "Traceback" not in r.stderr, \
        r.stderr
    escape = tmp_path / "escape.yaml"
    core = (ROOT / "tests" / "core_scene.yaml").read_text()
    escape.write_text(core.replace("name: core_demo", "name: ../../escaped"))
    work = tmp_path / "work"
    work.mkdir()
    r = twin("run", str(escape), "--recording", str(rec), cwd=work)
    assert r.returncode == 0, r.stdout + r.stderr
    made = list((work / "runs").iterdir())
    assert len(made) == 1 and "/" not in made[0].name and "escaped-" in made[0].name, made
    assert not list(tmp_path.glob("escaped-*"))
    (tmp_path / "adir").mkdir()
    r = twin("view", str(made[0] / "run.mcap"), "--out", str(tmp_path / "adir"))
    assert r.returncode == 1 and "cannot write the Rerun recording" in r.stderr and "Traceback" not in r.stderr, \
        r.stderr
    one = tmp_path / "one"
    one.mkdir()
    (one / "ball_drop_00.mcap").symlink_to(ROOT / "recordings" / "ball_drop_00.mcap")
    for extra, said in ((["--json", str(tmp_path / "adir")], "--json"), (["--configs", "baseline1,baseline1"],
                                                                           "given twice")):
        r = twin("evaluate", "--recordings", str(one), *extra, "--run-dir", str(tmp_path / "evruns"))
        assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "evruns").exists()


@pytest.mark.parametrize("extra, said", [
    (["--ros2-namespace", "/arm"], "--ros2-namespace goes only with --ros2-domain N"),
    (["--idle-timeout", "5"], "--idle-timeout goes only with --live or --ros2-domain N"),
    (["--no-hold"], "--no-hold goes only with --rerun serve")])
def test_an_option_that_would_do_nothing_is_refused(tmp_path, extra, said):
    """A replay given a live source's or a served viewer's option ran without a word that it did nothing."""
    r = twin("run", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_00.mcap", *extra,
             "--run-dir", str(tmp_path / "run"))
    assert r.returncode == 2 and f"twin run: {said}" in r.stderr, r.stderr
    assert not (tmp_path / "run").exists()


def test_a_run_never_replaces_the_recording_it_reads(tmp_path):
    """A run of an earlier run's log (or of a recording named run.mcap) into that run's own folder replaced the log
    it read, for a live run the only copy of the robot's telemetry: it is refused (exit 2), the file untouched."""
    import hashlib

    old, scene = tmp_path / "earlier", str(ROOT / "tests" / "core_scene.yaml")
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    assert twin("run", scene, "--recording", str(rec), "--run-dir", str(old)).returncode == 0
    log = old / "run.mcap"
    digest = hashlib.sha256(log.read_bytes()).hexdigest()
    for source in (["--recording", str(log)], ["--from-log", str(log)]):
        r = twin("run", *([scene] if source[0] == "--recording" else []), *source, "--run-dir", str(old))
        assert r.returncode == 2 and f"--run-dir {old}: this run would replace run.mcap there, the recording it " \
            "reads: give the run another --run-dir" in r.stderr + r.stdout, r.stdout[-2000:] + r.stderr[-2000:]
        assert hashlib.sha256(log.read_bytes()).hexdigest() == digest


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a read-only file system needs root (CI runs as root)")
def test_a_read_only_run_folder_is_said_not_a_traceback(tmp_path):
    """A --run-dir on a read-only file system: twin run (exit 1), twin run --samples (exit 1), twin evaluate
    (exit 2, before any run) and twin serve (exit 1) say which folder cannot be written, with no traceback; each
    was an OSError traceback from whichever first wrote there."""
    ro = tmp_path / "ro"
    ro.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "ro", "tmpfs", str(ro)], check=True)
    try:
        rec = str(ROOT / "recordings" / "ball_drop_00.mcap")
        one = tmp_path / "one"
        one.mkdir()
        (one / "ball_drop_00.mcap").symlink_to(rec)
        for argv, code in ((["run", "scenes/ball_drop.yaml", "--recording", rec], 1),
                           (["run", "scenes/ball_drop.yaml", "--recording", rec, "--samples", "2"], 1),
                           (["evaluate", "--recordings", str(one), "--configs", "ensemble"], 2),
                           (["serve", "--listen", f"tcp/127.0.0.1:{free_port()}"], 1)):
            r = twin(*argv, "--run-dir", str(ro), timeout=120)
            said = r.stdout + r.stderr
            assert r.returncode == code and str(ro) in said and "(Read-only file system)" in said \
                and "Traceback" not in said, (argv, r.returncode, said[-2000:])
    finally:
        subprocess.run(["umount", str(ro)], check=False)


def test_evaluate_refuses_a_configuration_that_would_run_on_nothing(tmp_path):
    """twin evaluate --configs mujoco on an insertion recording ran nothing and reported success ('mujoco none run',
    a Table 2 of 0/0): a configuration with no scene for any of the recordings is refused (exit 2), saying why; one
    with scenes for some of them is noted."""
    one = tmp_path / "one"
    one.mkdir()
    (one / "insertion_pb_08mm.mcap").symlink_to(ROOT / "recordings" / "insertion_pb_08mm.mcap")
    r = twin("evaluate", "--recordings", str(one), "--configs", "ensemble,mujoco", "--json", str(tmp_path / "j.json"),
             "--run-dir", str(tmp_path / "runs"))
    assert r.returncode == 2 and "configuration mujoco has no scene for any of the recordings (insertion (panda)): " \
        "it would run on none" in r.stderr, r.stdout + r.stderr
    assert not (tmp_path / "j.json").exists() and not (tmp_path / "runs").exists()


def test_an_input_file_that_cannot_be_used_is_bad_input(tmp_path):
    """A recording or a perception file that is missing, is not what it says, or holds a value out of shape is
    bad input, as a scene error is: exit 2, one line naming the file (and the key), and a summary saying failed;
    no agent is started."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    (tmp_path / "unclosed.yaml").write_text("entities: [1\n")
    (tmp_path / "short.yaml").write_text("entities: {ball: {pose: [1, 2]}}\n")
    (tmp_path / "typo.yaml").write_text("entities:\n  ball:\n    postion: [0.1, 0.2, 0.3]\n")  # (it was taken)
    (tmp_path / "zero.json").write_text('{"entities": {"ball": {"pose": [0, 0, 1, 0, 0, 0, 0]}}}')
    cases = [(["--recording", str(tmp_path / "none.mcap")], "none.mcap: cannot open recording"),
             (["--recording", str(tmp_path / "short.yaml")], "short.yaml"),
             (["--recording", str(rec), "--perception", str(tmp_path / "unclosed.yaml")],
              "unclosed.yaml:1: YAML syntax error"),
             (["--recording", str(rec), "--perception", str(tmp_path / "short.yaml")],
              "short.yaml:1: entities.ball.pose: pose must be [x, y, z]"),
             (["--recording", str(rec), "--perception", str(tmp_path / "typo.yaml")],
              "typo.yaml:3: entities.ball.postion: unknown key 'postion' (allowed: pose, shape, mass, friction, "
              "position_sigma)"),
             (["--recording", str(rec), "--perception", str(tmp_path / "zero.json")],
              "zero.json:1: entities.ball.pose: pose's quaternion [0, 0, 0, 0] is all zero")]
    for i, (extra, said) in enumerate(cases):
        summary = tmp_path / f"summary{i}.json"
        r = twin("run", str(ROOT / "tests" / "core_scene.yaml"), *extra, "--run-dir", str(tmp_path / f"run{i}"),
                 "--summary", str(summary))
        assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, (extra, r.stderr)
        assert json.loads(summary.read_text())["status"] == "failed"
        assert not list((tmp_path / f"run{i}").glob("agent-*.log")), "no agent started"


def test_unknown_agent_kind_is_a_clear_error():
    r = twin("agent", "no_such_model", "--register-timeout", "1")
    assert r.returncode == 2 and "unknown model kind 'no_such_model'" in r.stderr


def test_a_run_whose_reader_went_away_still_goes_to_its_end(tmp_path):
    """``twin run ... | head -1``: the reader closes the pipe after the first line; the run is not cut off by a
    BrokenPipeError in whichever thread printed next: it goes to its end, writes its summary, exits 0."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "run", str(ROOT / "tests" / "core_scene.yaml"),
                          "--recording", str(rec), "--run-dir", str(tmp_path / "run")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV, cwd=ROOT)
    try:
        assert p.stdout is not None and p.stdout.readline()
        p.stdout.close()  # as head does after its lines
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0 and b"BrokenPipeError" not in err, err.decode()[-2000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["status"] == "complete" and summary["ticks"] > 0


def test_a_run_dir_used_again_holds_only_the_new_run(tmp_path):
    """--run-dir of an earlier run: its log and summary are replaced, and what was made of the earlier run beside
    them (its Rerun recording, its agents' logs) goes with them, so nothing there is taken for the new run's."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    run = tmp_path / "run"
    argv = ["run", str(ROOT / "tests" / "core_scene.yaml"), "--recording", str(rec), "--run-dir", str(run)]
    first = twin(*argv)
    assert first.returncode == 0, first.stdout + first.stderr
    logs = sorted(p.name for p in run.glob("agent-*.log"))
    assert logs
    (run / "run.rrd").write_bytes(b"made of the run before")
    (run / "agent-gone.log").write_text("an agent of the run before\n")
    second = twin(*argv)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "holds an earlier run" in second.stderr, second.stderr
    assert not (run / "run.rrd").exists() and not (run / "agent-gone.log").exists()
    assert sorted(p.name for p in run.glob("agent-*.log")) == logs
    assert json.loads((run / "summary.json").read_text())["status"] == "complete"


@pytest.mark.slow
def test_run_writes_summary_and_status_answers(tmp_path):
    """twin status finds a twin run's router by its access file alone (it listens on a free port of its own, which
    the access file says: with --credentials only, status answered 'no Zenoh router answered at 7447')."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=4.0)
    summary = tmp_path / "summary.json"
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "run", str(ROOT / "tests" / "core_scene.yaml"),
                          "--recording", str(rec), "--rtf", "1.0", "--summary", str(summary),
                          "--run-dir", str(tmp_path / "run")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    try:
        status = None
        deadline = time.monotonic() + 60
        access = tmp_path / "run" / "access.json"  # the bus is closed: twin status needs this run's secret
        while time.monotonic() < deadline and p.poll() is None and not access.exists():
            time.sleep(0.1)
        while time.monotonic() < deadline and p.poll() is None:
            r = twin("status", "--timeout", "2", "--credentials", str(access), timeout=30)
            if r.returncode == 0:
                status = json.loads(r.stdout)
                if status["running"]:
                    break
            time.sleep(0.3)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    s = json.loads(summary.read_text())
    # complete; or, on a loaded machine, degraded for the one thing that can happen there and that the run must say:
    # the free-running model's steps came late (in a loaded CI, beat's went silent for 2.7 s after its 28th step
    # and its other 59 came in a burst after the last tick)
    late = [r for r in s["status_reasons"] if r.startswith("model beat (free-running at 20 Hz) stepped ")]
    assert p.returncode == 0 or (p.returncode == 3 and late == s["status_reasons"]), (p.returncode, s["status_reasons"])
    assert status is not None and status["scene"] == "core_demo"
    assert set(status["agents"]) == {"sim", "holder", "grip", "beat"}
    assert "handover  ball.pose: sim -> holder  (pick)" in out
    for key in ["ticks", "sim_s", "wall_s", "rtf", "handovers", "final_ownership", "semantic_state",
                "malformed_messages", "run_log"]:
        assert key in s
    # one tick per joint state recorded at 100 Hz (0.00 ... 3.99 s; 401 while the replay took the last, stamped
    # 128 ns late by the recording writer, a tick late), paced at real time
    assert s["ticks"] == 400 and 0.5 < s["rtf"] < 1.5
    assert [h["trigger"] for h in s["handovers"]] == ["pick", "drop"]
    assert set(s["handovers"][0]) >= {"tick", "t", "entity", "attribute", "from", "to", "trigger"}
    assert Path(s["run_log"]).exists()


@pytest.mark.slow
def test_killed_run_keeps_its_run_log_and_leaves_no_orphans(tmp_path):
    """SIGKILL of `twin run` mid-run: the run log written so far is readable, the agents exit."""
    import signal as sig

    from conductor.runlog import read_run_log

    rec = core_recording(tmp_path / "rec.mcap", seconds=8.0)
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "run", str(ROOT / "tests" / "core_scene.yaml"),
                          "--recording", str(rec), "--rtf", "1.0", "--run-dir", str(tmp_path / "run")],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
    log = tmp_path / "run" / "run.mcap"
    try:
        line = ""
        deadline = time.monotonic() + 60
        while "handover" not in line and time.monotonic() < deadline:  # wait for the first handover
            line = p.stdout.readline()
        time.sleep(1.0)
        children = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True).stdout.split()
        p.send_signal(sig.SIGKILL)
        p.wait(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
    assert len(children) == 4
    msgs = list(read_run_log(log))
    ticks = [m["tick"] for k, _, m in msgs if k.endswith("/state/sim") and isinstance(m, dict)]
    assert ticks and max(ticks) >= 71, "the handover at t=0.71 s and what came before must be on disk"
    assert any(k.endswith("/event/_conductor/handover") for k, _, _ in msgs)
    deadline = time.monotonic() + 15  # agents get SIGTERM when their launcher dies
    while time.monotonic() < deadline and any(os.path.exists(f"/proc/{c}") for c in children):
        time.sleep(0.2)
    left = [c for c in children if os.path.exists(f"/proc/{c}") and not _zombie(c)]
    states = {c: _state(c) for c in left}
    for c in left:
        os.kill(int(c), sig.SIGKILL)
    assert not left, f"orphaned agents: {states}"


def _state(pid: str) -> str:
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("State:")), "?")
    except OSError:
        return "gone"


def _zombie(pid: str) -> bool:
    """An exited process not yet reaped by its new parent (it holds no resources)."""
    return _state(pid).startswith("Z")


def test_rerun_serve_keeps_the_web_viewer_up_until_ctrl_c(tmp_path):
    """`twin run --rerun serve`: the web viewer's address is printed, it answers over HTTP while the run
    goes and after it (the summary printed, "Ctrl-C ends"); SIGINT then ends the process cleanly and
    the run's .rrd is complete."""
    import signal as sig
    import urllib.request

    rec = core_recording(tmp_path / "rec.mcap", seconds=2.0)
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "run", str(ROOT / "tests" / "core_scene.yaml"),
                          "--recording", str(rec), "--rerun", "serve", "--run-dir", str(tmp_path / "run")],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
    lines, url = [], None
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = p.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "Rerun web viewer (live):" in line:
                url = line.split(":", 1)[1].strip()
            if "goes on serving" in line:
                break
        out = "".join(lines)
        assert url and url.startswith("http://127.0.0.1:"), out
        assert "run of core_demo" in out and "handover" in out and "Ctrl-C ends" in out, out
        with urllib.request.urlopen(url.split("?")[0], timeout=10) as r:  # the viewer outlives the run
            assert r.status == 200 and b"<html" in r.read(2000).lower()
        assert p.poll() is None
        p.send_signal(sig.SIGINT)
        assert p.wait(timeout=30) == 0
    finally:
        if p.poll() is None:
            p.kill()
    rrd = tmp_path / "run" / "run.rrd"
    r = subprocess.run([str(Path(sys.executable).with_name("rerun")), "rrd", "verify", str(rrd)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_the_kinds_the_checker_knows_are_the_agents_own():
    from agents.registry import BUILTIN
    from protocol.messages import BUILTIN_KINDS

    assert set(BUILTIN) == BUILTIN_KINDS


def test_a_recording_of_another_scene_is_said_and_its_run_is_degraded(tmp_path):
    """ball_drop's scene on an insertion recording: its perception names dip and spu, none of the scene's entities.
    twin check says so (exit 3); the run goes to its end from the scene's own poses, degraded, and says why."""
    rec = str(ROOT / "recordings" / "insertion_00.mcap")
    r = twin("check", "scenes/ball_drop.yaml", "--recording", rec)
    assert r.returncode == 3 and "none of this scene's entities" in r.stderr, r.stdout + r.stderr
    r = twin("run", "scenes/ball_drop.yaml", "--recording", rec, "--run-dir", str(tmp_path / "run"), timeout=300)
    assert r.returncode == 3, r.stdout + r.stderr
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "degraded" and any("the perception names dip, spu" in x for x in s["status_reasons"]), s
    r = twin("check", "scenes/insertion.yaml", "--recording", rec)  # its own scene: fits
    assert r.returncode == 0 and "perception" not in r.stderr, r.stdout + r.stderr


def test_a_perception_that_places_some_entities_says_which_stay(tmp_path):
    """A perception file that places the ball only: the run says the container and the stand stay at the scene's
    poses (printed, and in the summary's input_notes); not a defect, so no degraded reason for it."""
    per = tmp_path / "seen.yaml"
    per.write_text("entities: {ball: {pose: [0.5, 0.0, 0.2]}}\n")
    r = twin("run", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_00.mcap", "--perception", str(per),
             "--max-ticks", "30", "--run-dir", str(tmp_path / "run"), timeout=300)
    note = "the perception places ball but not container, stand: they stay where the scene puts them"
    assert r.returncode == 4 and f"input: {note}" in r.stdout, r.stdout + r.stderr  # (4: cut by --max-ticks)
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["input_notes"] == [note] and not any("perception" in x for x in s["status_reasons"]), s


def test_options_of_samples_given_to_one_run_are_said():
    r = twin("run", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_00.mcap", "--cold", "--seed", "3")
    assert r.returncode == 2 and "--cold, --seed go only with --samples K" in r.stderr, r.stderr
    # and the other way: options of one run that samples cannot honour (they were silently left out)
    r = twin("run", "scenes/insertion.yaml", "--recording", "recordings/insertion_00.mcap", "--samples", "3",
             "--rtf", "0.5", "--live", "--rerun", "save")
    assert r.returncode == 2 and "--live, --rerun do not go with --samples K" in r.stderr, r.stderr
    # (a port and an ensemble of one's own, on a shared machine: the samples took others, without a word)
    r = twin("run", "scenes/insertion.yaml", "--recording", "recordings/insertion_00.mcap", "--samples", "3",
             "--listen", "tcp/127.0.0.1:7447", "--ensemble", "mine")
    assert r.returncode == 2 and "--listen, --ensemble do not go with --samples K" in r.stderr, r.stderr
    # (but a listen endpoint from the environment, as a deployment sets it for every twin program, is no refusal)
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/insertion.yaml", "--recording",
                        "/nowhere.mcap", "--samples", "3"], capture_output=True, text=True, timeout=120,
                       env={**ENV, "TWIN_LISTEN": "tcp/0.0.0.0:7447"}, cwd=ROOT)
    assert r.returncode == 2 and "not go with" not in r.stderr and "/nowhere.mcap" in r.stderr, r.stderr
    # a seed out of range is said before anything runs (one below 0 failed in numpy, one over 2^64 on the wire)
    for bad in ("-5", str(2**64)):
        r = twin("run", "scenes/insertion.yaml", "--recording", "recordings/insertion_00.mcap", "--samples", "3",
                 f"--seed={bad}")
        assert r.returncode == 2 and "--seed: seed must be a whole number from 0 to 4294967295" in r.stderr, r.stderr


def test_samples_are_paced_by_rtf_as_one_run_is(tmp_path):
    """--rtf paces each sample, on twin run --samples as on twin serve (twin run refused it, twin submit took it)."""
    r = twin("run", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_00.mcap", "--samples", "2",
             "--rtf", "2", "--max-ticks", "120", "--run-dir", str(tmp_path / "s"), "--summary",
             str(tmp_path / "s.json"), timeout=300)
    assert r.returncode == 4, r.stdout + r.stderr  # (4: cut by --max-ticks)
    for folder in json.loads((tmp_path / "s.json").read_text())["runs"]:
        one = json.loads((Path(folder) / "summary.json").read_text())
        assert one["ticks"] == 120 and 0 < one["rtf"] <= 2.1, one["rtf"]  # (as fast as it goes: 10 and more)


def test_an_agent_lost_is_printed_with_its_time(capsys):
    from conductor.cli.run import _print_event

    _print_event("agent_lost", {"model": "in_hand", "tick": 150, "t": 1.25})
    _print_event("agent_lost", {"model": "spu", "tick": 3})  # (an older conductor's event: no time in it)
    _print_event("agent_lost", {"model": "physics", "tick": 9, "t": 0.09, "main": True})
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "  t=   1.250s  agent lost: in_hand (its responsibilities fall back to the main model)", out
    assert out[1].startswith("  t=           agent lost: spu"), out
    assert out[2] == ("  t=   0.090s  agent lost: physics (the main model: nothing can take its responsibilities, "
                      "the run cannot go on)"), out


def test_robot_play_and_trigger_say_why_they_cannot_start():
    """twin robot play with no router to join tried for ever and ignored SIGTERM; now it says so after its join
    time (exit 1). A speed or timeout that is not a finite number above 0 is refused (exit 2): --speed nan sent
    everything at once, twin trigger --timeout -1 waited for ever."""
    port = free_port()
    r = twin("robot", "play", "recordings/ball_drop_00.mcap", "--connect", f"tcp/127.0.0.1:{port}", timeout=90)
    assert r.returncode == 1 and f"no Zenoh router answered at tcp/127.0.0.1:{port} within 10 s" in r.stderr, \
        r.stdout + r.stderr
    for argv in (["robot", "play", "recordings/ball_drop_00.mcap", "--speed", "nan"],
                 ["robot", "play", "recordings/ball_drop_00.mcap", "--wait-twin", "-1"],
                 ["trigger", "hold", "--timeout", "-1"]):
        r = twin(*argv, timeout=30)
        assert r.returncode == 2 and "a finite number" in r.stderr, (argv, r.stderr)


def test_a_trigger_argument_given_twice_is_refused():
    r = twin("trigger", "hold", "--arg", "target=ball", "--arg", "target=bin", timeout=30)
    assert r.returncode == 2 and "--arg target given more than once" in r.stderr, r.stderr


def test_a_credentials_file_that_is_not_there_is_said_so(tmp_path):
    """The access file of a twin run or twin serve that has ended is gone: said as such, not as a bad file."""
    r = twin("trigger", "hold", "--credentials", str(tmp_path / "access.json"), "--timeout", "1")
    assert r.returncode == 2 and "no such credentials file (the twin run or twin serve" in r.stderr, r.stderr


def test_record_synth_says_bad_input_before_it_simulates(tmp_path):
    """A value out of range and an output folder that cannot be written are bad input (2), said at once: they
    exited 1, and the unwritable folder with a traceback after the whole simulation."""
    out = str(tmp_path / "s.mcap")
    for extra, said in ((["--time-scale", "10"], "time scale must be within [0.25, 4]"),
                        (["--robot", "xarm6", "--reality", "mujoco"], "the xarm6 plays ball_drop in the pybullet"),
                        (["--out", "/proc/nope/x.mcap"], "cannot write /proc/nope/x.mcap: /proc/nope is not a folder")):
        r = twin("record", "synth", "--scenario", "ball_drop", "--seed", "1", "--out", out, *extra, timeout=60)
        assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, (extra, r.returncode, r.stderr)
    assert not Path(out).exists()


def test_check_says_that_bag_options_need_the_bag():
    """--remap and --joint-order without --recording were left out without a word: the check said all was well of
    options it never used."""
    r = twin("check", "scenes/ball_drop.yaml", "--remap", "/joint_states:=/foo", "--joint-order", "a,b", timeout=60)
    assert r.returncode == 2 and "--remap and --joint-order say how to read a bag: give it with --recording BAG" \
        in r.stderr, r.stderr


def test_twin_check_names_a_trigger_waiting_for_an_action_the_bag_never_has(tmp_path):
    """A misspelt action (relase) made a trigger that never fired, and twin check said the bag fits: it is now a
    warning with the action it is close to (exit 3); an action the bag simply does not have is a note."""
    text = (ROOT / "scenes" / "ball_drop.yaml").read_text()
    assert "{action: release, phase: start}" in text
    rec = str(ROOT / "recordings" / "ball_drop_00.mcap")
    typo, other = tmp_path / "typo.yaml", tmp_path / "other.yaml"
    typo.write_text(text.replace("{action: release, phase: start}", "{action: relase, phase: start}"))
    other.write_text(text.replace("{action: release, phase: start}", "{action: pour, phase: start}"))
    r = twin("check", str(typo), "--recording", rec)
    assert r.returncode == 3, r.stdout + r.stderr
    assert f"{rec}: trigger released waits for action 'relase', which the bag never has (did you mean 'release'?): " \
           "it will never fire" in r.stderr, r.stderr
    r = twin("check", str(other), "--recording", rec)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "note: " in r.stdout and "waits for action 'pour', which the bag never has (its actions: move_arm, " \
           "move_hand, release)" in r.stdout, r.stdout
    # twin run says the misspelling too, degraded (exit 3) as twin check said it would be; it ended complete
    summary = tmp_path / "s.json"
    r = twin("run", str(typo), "--recording", rec, "--run-dir", str(tmp_path / "run"), "--summary", str(summary))
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    s = json.loads(summary.read_text())
    assert s["status"] == "degraded" and any("trigger released waits for action 'relase'" in why
                                             for why in s["status_reasons"]), s


def test_a_trigger_call_whose_effect_failed_is_no_success():
    """twin trigger exited 0 with "fired": true when the trigger's service call failed (the run degraded by it):
    a problem or error anywhere in the answer makes it exit 1, saying what failed."""
    from conductor.cli.serve import _problems

    answer = [{"trigger": "bad_heat", "fired": True, "effects": [{"call": "mug.heat", "problem": "TypeError: by"}]},
              {"trigger": "ok", "fired": True, "effects": [{"transfer": "pose of ball to holder"}]}]
    assert _problems(answer) == ["TypeError: by"]
    assert _problems([{"trigger": "ok", "fired": True, "effects": []}]) == []


def test_an_agent_s_kind_is_found_after_its_flags(capsys):
    """``python -m agents --name ball trivial`` runs a trivial model named ball: the kind is the first word that is
    not a flag's value (it took ``ball`` for the kind and refused it)."""
    from agents.__main__ import main as agent_main
    for argv in (["--name", "ball", "trivial", "--describe"], ["trivial", "--name", "ball", "--describe"],
                 ["--mode", "peer", "--name=ball", "--describe", "trivial"]):
        assert agent_main(argv) == 0, argv
        desc = json.loads(capsys.readouterr().out)
        assert (desc["name"], desc["kind"]) == ("ball", "trivial"), (argv, desc)
    assert agent_main(["--name", "ball", "no_such_kind"]) == 2
    assert "no_such_kind" in capsys.readouterr().err


def test_a_bag_s_reading_options_or_a_replay_s_pace_elsewhere_are_refused():
    """``--from-log`` with ``--remap``/``--joint-order`` ran without a word of them (a run log is not a bag), and
    ``--rtf 4`` with ``--live`` paced the live twin at four times the robot's pace, its handovers four times late."""
    from conductor.cli.main import build_parser
    from conductor.cli.run import _usage_problem

    def problem(*argv: str) -> str | None:
        return _usage_problem(build_parser().parse_args(["run", *argv]))

    assert problem("--from-log", "run.mcap", "--remap", "/joint_states:=/arm") == \
        "--remap goes only with --recording FILE (a bag)"
    assert problem("--from-log", "run.mcap", "--joint-order", "a,b") == \
        "--joint-order goes only with --recording FILE (a bag)"
    assert problem("s.yaml", "--live", "--rtf", "4") == "--rtf paces a replay: a live run goes at the robot's pace"
    assert problem("s.yaml", "--ros2-domain", "0", "--rtf", "4") is not None
    assert problem("s.yaml", "--recording", "r.mcap", "--rtf", "4", "--remap", "/joint_states:=/arm") is None


def test_a_trigger_argument_in_base_60_is_refused_not_read_as_another_number():
    """YAML 1.1 reads 1:30 as 90 (base 60): ``--arg t=1:30`` gave the trigger 90. It is refused in one line now; a
    quoted '1:30' is the text, a plain number is the number."""
    from conductor.cli.serve import _arg

    r = twin("trigger", "hold", "--arg", "t=1:30", timeout=30)
    assert r.returncode == 2 and "base-60 number 90" in r.stderr, r.stderr
    assert _arg("t='1:30'") == ("t", "1:30") and _arg("t=90") == ("t", 90) and _arg("t=1.5") == ("t", 1.5)


def test_an_output_that_cannot_be_written_is_said_in_one_line(tmp_path):
    """twin acl --out a folder, or a file where nothing can be written, and twin certs into such a folder, were
    Python tracebacks (exit 1); each is now one line naming the path, exit 2."""
    (tmp_path / "blocker").write_text("a file where a folder is asked for")
    for args, said in [(("acl", "scenes/ball_drop.yaml", "--out", str(tmp_path)), f"cannot write {tmp_path}"),
                       (("acl", "scenes/ball_drop.yaml", "--out", str(tmp_path / "blocker" / "acl.json5")),
                        "cannot write"),
                       (("certs", str(tmp_path / "blocker" / "pki")), "cannot write the certificates into")]:
        r = twin(*args)
        assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)


def test_an_agent_without_endpoints_waits_for_the_default_router_and_can_be_stopped():
    """An agent given no --connect (a client: it joins tcp/127.0.0.1:7447) opened its session once, with Zenoh's
    connect timeout of for ever: with no router there it ignored --register-timeout and SIGTERM (found by a review:
    one was still waiting 11 minutes later). It now tries a second at a time like an agent with endpoints. Its name
    is checked first: one with a '$*' answered queries meant for other models."""
    import socket

    with socket.socket() as s:
        if s.connect_ex(("127.0.0.1", 7447)) == 0:
            pytest.skip("something listens on 127.0.0.1:7447 on this machine")
    r = twin("agent", "trivial", "--register-timeout", "1", timeout=60)
    assert r.returncode == 3 and "no Zenoh router answered at tcp/127.0.0.1:7447 within 1 s" in r.stderr, r.stderr
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "agent", "trivial"], env=ENV, cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(3)
        p.terminate()
        assert p.wait(timeout=20) == 0
    finally:
        p.kill()
        p.wait()
    for name in ("ph$*", "grip/left", "_conductor"):
        r = twin("agent", "trivial", "--name", name, timeout=60)
        assert r.returncode == 2 and "invalid agent name" in r.stderr, (name, r.stderr)


def test_the_demo_never_judges_an_earlier_run_s_summary(tmp_path):
    """``make demo`` after a run that failed before its summary: the earlier run's summary.json stays in
    runs/demo, and the demo printed its answer as this run's (CORRECT) under the failure."""
    demo = tmp_path / "runs" / "demo"
    demo.mkdir(parents=True)
    (demo / "summary.json").write_text(json.dumps({"status": "complete", "semantic_state": {
        "in(container, ball)": True}}))
    r = subprocess.run([sys.executable, "-m", "conductor.cli.demo"], capture_output=True, text=True, cwd=tmp_path,
                       timeout=120, env={**os.environ, "TWIN_ENSEMBLE": "bad/name", "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2, r.stdout + r.stderr
    assert "invalid ensemble name" in r.stderr and "interpretation" not in r.stdout, r.stdout
    # the run taken up so far left nothing behind: the bus's secrets (.zenoh-users, access.json) were not made
    assert sorted(p.name for p in demo.iterdir()) == ["summary.json"]
