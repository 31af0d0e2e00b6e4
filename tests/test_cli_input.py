"""Bad input to `twin evaluate`, `twin bench overhead`, `twin record synth`, `twin robot play` and
recordings/make_recordings.py is refused up front in one line (exit 2), never with a traceback or after the work."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def twin(*args: str, cwd: Path = ROOT, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=ENV, cwd=cwd)


def refused(r: subprocess.CompletedProcess, said: str) -> None:
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-2000:]
    assert "Traceback" not in r.stderr and said in r.stderr, r.stderr[-2000:]


@pytest.mark.parametrize("what", ["table2", "rtf"])
def test_render_of_figures_it_cannot_read_says_so(tmp_path, what):
    """A missing file was a FileNotFoundError traceback; '{}' a KeyError ('runs', or 'setups' for rtf)."""
    empty = tmp_path / "empty.json"
    empty.write_text("{}")
    table = tmp_path / "t.md"
    refused(twin("evaluate", what, "--render", str(tmp_path / "missing.json"), "--table", str(table)),
            f"cannot read {tmp_path / 'missing.json'}: ")
    refused(twin("evaluate", what, "--render", str(empty), "--table", str(table)), f"cannot read {empty}: not the "
            "figures of twin evaluate")
    assert not table.exists()


def test_rtf_without_a_ball_drop_recording_or_repeats_is_refused(tmp_path):
    """A folder without ball_drop*.mcap was an IndexError traceback; --repeat 0 'no median for empty data'."""
    refused(twin("evaluate", "rtf", "--recordings", str(tmp_path)), f"no ball_drop*.mcap recording in {tmp_path}")
    refused(twin("evaluate", "rtf", "--repeat", "0"), "argument --repeat: at least 1, not 0")
    refused(twin("bench", "overhead", "--repeat", "0"), "argument --repeat: at least 1, not 0")


@pytest.mark.parametrize("flag, value", [("--recording", "recordings/ball_drop_00.mcap"), ("--repeat", "2")])
def test_table2_refuses_the_options_of_rtf(tmp_path, flag, value):
    """They were accepted and ignored (the whole evaluation ran)."""
    refused(twin("evaluate", "--recordings", str(tmp_path), flag, value), f"{flag} goes only with 'twin evaluate rtf'")


def test_record_synth_refuses_a_folder_and_a_negative_seed(tmp_path):
    """--out FOLDER simulated the whole task, then failed (exit 1); --seed -3 said numpy's words, not the option."""
    refused(twin("record", "synth", "--scenario", "ball_drop", "--seed", "1", "--out", str(tmp_path), "-q",
                 timeout=30), f"cannot write {tmp_path}: it is a folder")
    refused(twin("record", "synth", "--scenario", "ball_drop", "--seed", "-3", "--out", str(tmp_path / "x.mcap")),
            "argument --seed: seed must be a whole number from 0")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, said", [(["--loops", "-1"], "argument --loops: at least 1, not -1"),
                                        (["--ros2-domain", "-7"], "argument --ros2-domain: a ROS 2 domain id from 0"),
                                        (["--ros2-domain", "233"], "to 232, not 233")])
def test_robot_play_refuses_impossible_counts_and_domains(args, said):
    refused(twin("robot", "play", "recordings/ball_drop_00.mcap", *args), said)


@pytest.mark.parametrize("command", [["run", "scenes/ball_drop.yaml"], ["conductor", "scenes/ball_drop.yaml"],
                                     ["submit", "scenes/ball_drop.yaml"]])
def test_a_ros2_domain_out_of_range_is_refused_by_every_command_that_takes_one(command):
    refused(twin(*command, "--ros2-domain", "-7"), "argument --ros2-domain: a ROS 2 domain id from 0 to 232, not -7")


@pytest.mark.parametrize("command", [["run", "scenes/ball_drop.yaml"], ["conductor", "scenes/ball_drop.yaml"],
                                     ["submit", "scenes/ball_drop.yaml"],
                                     ["robot", "play", "recordings/ball_drop_00.mcap"]])
def test_a_ros2_namespace_that_is_none_is_refused_by_every_command_that_takes_one(command):
    """'a//b' or 'a*b' failed once the run had begun (Zenoh refused the key expression: exit 1, no summary), and
    'robot 1' was published where no ROS 2 node could be."""
    for namespace in ("a//b", "a*b", "robot 1"):
        refused(twin(*command, "--ros2-domain", "3", "--ros2-namespace", namespace),
                f"argument --ros2-namespace: not a ROS 2 namespace: {namespace!r}")


def test_robot_play_refuses_what_would_play_nothing_a_twin_can_use(tmp_path):
    """--ros2-namespace without --ros2-domain played on the twin's keys, the namespace ignored; a recording without
    joint states was played (its actions alone: the twin's robot never moved), exit 0. twin run refuses both."""
    from recordings.rosbag import RecordingWriter

    refused(twin("robot", "play", "recordings/ball_drop_00.mcap", "--ros2-namespace", "robot1"),
            "--ros2-namespace goes only with --ros2-domain N")
    rec = tmp_path / "actions.mcap"
    with RecordingWriter(rec) as w:
        w.action(0.0, "move_arm", "start")
        w.action(0.5, "move_arm", "end")
    refused(twin("robot", "play", str(rec)), f"{rec}: it has no joint states with joint names")


def test_robot_play_loops_implies_loop(tmp_path):
    """--loops 2 without --loop played once, silently."""
    from conductor.launch import free_port
    from recordings.simple import core_recording

    rec = tmp_path / "short.mcap"
    core_recording(rec, seconds=0.4)
    r = twin("robot", "play", str(rec), "--loops", "2", "--speed", "4", "--lead-in", "0", "--mode", "peer",
             "--listen", f"tcp/127.0.0.1:{free_port()}", "--ensemble", f"loops{os.getpid()}")
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "2 times" in r.stdout and "in 2 whole pass(es)" in r.stdout, r.stdout


def _play(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "conductor.cli", "robot", "play", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)


def test_robot_play_stops_when_told_and_says_it_did_not_finish(tmp_path):
    """Ctrl-C (SIGINT) or SIGTERM while the player waits for a router, in its lead-in or halfway through the
    recording: it stops within a second or two and exits 5, saying the play did not end (it waited out the
    router's 40 s deaf to them, slept its lead-in out, and a play stopped halfway exited 0 as one pass)."""
    import signal
    import time

    from conductor.launch import free_port

    cases = [(["--connect", f"tcp/127.0.0.1:{free_port()}", "--wait-twin", "40"], signal.SIGINT,
              "stopped before the play began"),
             (["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--lead-in", "30"], signal.SIGTERM,
              "stopped after 0 whole pass(es) of 1"),
             (["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--lead-in", "0"], signal.SIGINT,
              "stopped after 0 whole pass(es) of 1")]
    for args, sig, said in cases:
        p = _play("recordings/ball_drop_00.mcap", "--ensemble", f"stop{os.getpid()}", *args)
        try:
            time.sleep(3.0)  # (the router's wait has begun / the lead-in / the play, 9.9 s long, is under way)
            assert p.poll() is None, p.communicate()
            p.send_signal(sig)
            out, err = p.communicate(timeout=8)
        finally:
            p.kill()
            p.wait()
        assert p.returncode == 5 and said in err, (args, p.returncode, out, err)


def test_robot_play_with_a_configuration_file_and_no_router_gives_up(tmp_path):
    """The router named by --config is not there: the player gives up after its join time (exit 1), as with
    --connect (an open of a configuration file's endpoints is not retried a second at a time: it waited for ever)."""
    from conductor.launch import free_port

    port = free_port()
    conf = tmp_path / "z.json5"
    conf.write_text(f'{{mode: "client", connect: {{endpoints: ["tcp/127.0.0.1:{port}"]}}}}\n')
    r = twin("robot", "play", "recordings/ball_drop_00.mcap", "--config", str(conf), timeout=60)
    assert r.returncode == 1 and "no Zenoh router answered" in r.stderr, r.stdout + r.stderr


def test_robot_play_says_the_flaws_of_what_it_plays(tmp_path):
    """A recording with malformed joint states is played as it is (a robot's stream has what it has), its flaws
    said as twin check says them, exit 3 (it exited 0 without a word)."""
    from conductor.launch import free_port
    from recordings.rosbag import RecordingWriter

    rec = tmp_path / "nan.mcap"
    names = [f"panda_joint{i}" for i in range(1, 8)]
    with RecordingWriter(rec) as w:
        for k in range(50):
            q = [float("nan") if k % 5 == 0 else 0.1] * 7
            w.joint_state(k * 0.01, names, q, [0.0] * 7, [0.0] * 7)
    r = twin("robot", "play", str(rec), "--lead-in", "0", "--mode", "peer", "--listen",
             f"tcp/127.0.0.1:{free_port()}", "--ensemble", f"flaw{os.getpid()}")
    assert r.returncode == 3, r.stdout + r.stderr
    assert "warning: " in r.stderr and "left out" in r.stderr and "sent 40 joint states" in r.stdout, r.stderr


def test_a_recording_written_halfway_is_never_left_as_one(tmp_path):
    """A recording whose writing is stopped (an exception, Ctrl-C in twin record synth) is not left at its name
    reading as whole (it was: a footer was written on the way out), and one already there stays as it was."""
    from conductor.sources.recording import load_recording
    from recordings.rosbag import RecordingWriter
    from recordings.simple import core_recording

    rec = core_recording(tmp_path / "rec.mcap", seconds=0.5)
    before = rec.read_bytes()
    with pytest.raises(KeyboardInterrupt), RecordingWriter(rec) as w:
        for k in range(300):
            w.joint_state(k * 0.004, ["panda_joint1"], [0.0], [0.0], [0.0])
            if k == 200:
                raise KeyboardInterrupt
    assert rec.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap"]
    with RecordingWriter(tmp_path / "new.mcap") as w:
        w.joint_state(0.0, ["panda_joint1"], [0.0], [0.0], [0.0])
    assert len(load_recording(tmp_path / "new.mcap").items) == 1


@pytest.mark.parametrize("args, said", [([], "nothing to run on: give --recording FILE, --live or --ros2-domain N"),
                                        (["--recording", "recordings/ball_drop_00.mcap", "--live"],
                                         "--recording and --live are each a source of the run: give one"),
                                        (["--live", "--rtf", "2"], "--rtf paces a replay"),
                                        (["--max-ticks", "5", "--idle-timeout", "2"], "--idle-timeout goes only with")])
def test_twin_conductor_refuses_what_twin_run_refuses(args, said):
    """No source ended twin conductor in a TypeError traceback; two sources, a pace for a live robot, an idle
    timeout without one were ignored without a word (the recording dropped, the run then failed on no telemetry)."""
    r = twin("conductor", "scenes/ball_drop.yaml", "--connect", "tcp/127.0.0.1:9", *args)
    refused(r, f"twin conductor: {said}")


def test_twin_conductor_waiting_for_its_router_hears_ctrl_c(tmp_path):
    """No router at --connect: twin conductor says it is waiting, and Ctrl-C ends the wait (it waited for ever,
    deaf to it, printing nothing), its summary saying the run was interrupted before it began."""
    import json
    import signal
    import time

    from conductor.launch import free_port

    port = free_port()
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "conductor", "scenes/ball_drop.yaml", "--recording",
                          "recordings/ball_drop_00.mcap", "--connect", f"tcp/127.0.0.1:{port}", "--run-log",
                          str(tmp_path / "run.mcap"), "--summary", str(tmp_path / "s.json")], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    try:
        time.sleep(4.0)
        assert p.poll() is None, p.communicate()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=8)
    finally:
        p.kill()
        p.wait()
    assert p.returncode == 5, (out, err)
    assert f"no Zenoh router answered at tcp/127.0.0.1:{port}" in err and "waiting (Ctrl-C stops)" in err, err
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["status"] == "interrupted" and "while waiting for the Zenoh router" in summary["status_reasons"][0]


def test_make_recordings_writes_a_relative_out_where_the_caller_is(tmp_path):
    """The child ran in the repository with the relative folder, the size check looked in the caller's: it wrote
    into the repository, then FileNotFoundError."""
    r = subprocess.run([sys.executable, str(ROOT / "recordings" / "make_recordings.py"), "insertion_00", "--out",
                        "made"], capture_output=True, text=True, timeout=300, env=ENV, cwd=tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert (tmp_path / "made" / "insertion_00.mcap").stat().st_size > 100_000
    assert not (ROOT / "made").exists()


def test_check_says_a_suggested_map_joins_a_revolute_and_a_prismatic_joint():
    """The xArm's drive_joint (rad) was suggested for the Panda's panda_finger_joint1 (m) without a word."""
    r = twin("check", "scenes/ball_drop.yaml", "--recording", "recordings/ball_drop_xarm_success_bin.mcap")
    refused(r, "drive_joint: panda_finger_joint1")
    assert "drive_joint is revolute (rad), panda_finger_joint1 prismatic (m)" in r.stderr, r.stderr
    assert "robot: {use: xarm6}" in r.stderr


def test_a_run_zenoh_refuses_to_start_still_writes_its_summary(tmp_path):
    """A port already in use: twin run said Zenoh's words and exited 1, but wrote no --summary, which a script
    waiting for one then found missing (a scene or recording it refused had one)."""
    from conductor.launch import open_router

    session, endpoint = open_router()
    try:
        r = twin("run", "scenes/ball_drop.yaml", "--live", "--listen", endpoint, "--summary", str(tmp_path / "s.json"),
                 "--run-dir", str(tmp_path / "run"), timeout=60)
    finally:
        session.close()
    assert r.returncode == 1 and "Address already in use" in r.stderr and "Traceback" not in r.stderr, r.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["status"] == "failed" and s["status_reasons"][0].startswith("zenoh: ") and s["ticks"] == 0, s


def test_twin_run_refuses_options_of_an_embedded_router_when_it_joins_one():
    """--connect joins a router already there, so --listen (the embedded router's endpoint) was ignored without a
    word, and a robot told to use it never reached the twin; so was --open-bus."""
    for flag in (["--listen", "tcp/127.0.0.1:7999"], ["--open-bus"]):
        refused(twin("run", "scenes/ball_drop.yaml", "--live", "--connect", "tcp/127.0.0.1:7998", *flag),
                f"twin run: {flag[0]} ")


def test_twin_run_joining_a_router_that_is_not_there_says_so_in_time(tmp_path):
    """twin run --connect to no router waited for ever, deaf to Ctrl-C, with no summary; and a TWIN_LISTEN in the
    environment, which --connect leaves alone, was still checked and failed the run. It now says after 10 s that no
    router answered (exit 1), with its summary."""
    from conductor.launch import free_port

    port = free_port()
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/ball_drop.yaml", "--live", "--connect",
                        f"tcp/127.0.0.1:{port}", "--summary", str(tmp_path / "s.json"), "--run-dir",
                        str(tmp_path / "run")], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "TWIN_LISTEN": "127.0.0.1:7447"})
    said = f"no Zenoh router answered at tcp/127.0.0.1:{port} within 10 s"
    assert r.returncode == 1 and said in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert json.loads((tmp_path / "s.json").read_text())["status_reasons"] == [said]
