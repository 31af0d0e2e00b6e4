"""The Rerun stream: a real run of the core scene with the sink in save mode, read back with Rerun's
own reader; ``twin view`` on the same run log; the colour and decimation rules."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from conductor.core import Conductor, RunOptions
from conductor.scene import load_scene
from conductor.sources.recording import load_recording
from conductor.sources.replay import ReplaySource
from conductor.viewer import (
    FIXED_COLOURS,
    Colours,
    TwinLogger,
    ViewerError,
    ViewerSink,
    close_stream,
    open_stream,
    parse_mode,
    start_sink,
)
from protocol import codec
from protocol.config import ZenohOptions
from protocol.keys import Keys
from recordings.simple import core_recording

from .conftest import spawn_agents

HERE = Path(__file__).parent
ROOT = HERE.parent
RERUN = str(Path(sys.executable).with_name("rerun"))


def read_rrd(path) -> dict[str, list[dict]]:
    """Rows of every entity of the recording in an .rrd: {entity_path: [{column: value}]}, with
    ``tick`` (int) and ``sim_time`` (float seconds) when the row is on those timelines."""
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict]] = {}
    for chunk in RrdReader(str(path)).stream():
        rb = chunk.to_record_batch()
        cols = {}
        for name in rb.schema.names:
            if name.startswith("rerun.controls") or name == "log_time":
                continue
            col = rb.column(name)
            if name == "sim_time":
                cols[name] = [None if v is None else v * 1e-9 for v in col.cast(pa.int64()).to_pylist()]
            else:
                cols[name] = col.to_pylist()
        n = rb.num_rows
        rows.setdefault(chunk.entity_path, []).extend({k: v[i] for k, v in cols.items()} for i in range(n))
    for r in rows.values():
        r.sort(key=lambda x: (x.get("tick") is not None, x.get("tick") or 0))
    return rows


def verify(path) -> None:
    out = subprocess.run([RERUN, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr


def state_at(rows: list[dict], tick: int) -> str | None:
    """The ownership lane's state in force at ``tick`` (the last change at or before it)."""
    cur = None
    for r in rows:
        if "StateChange:state" in r and r.get("tick") is not None and r["tick"] <= tick:
            cur = r["StateChange:state"][0]
    return cur


def check_handovers(rows: dict, handovers: list[dict], colours: Colours) -> None:
    """Every handover is in the recording at its tick and simulated time: the lane switches from the
    old owner to the new one, a text log entry names trigger, variables and both owners, and the
    entity's shape takes the new owner's colour."""
    assert handovers
    for h in handovers:
        lane = rows[f"/ownership/{h['entity']}/{h['attribute']}"]
        at = [r for r in lane if r.get("tick") == h["tick"] and "StateChange:state" in r]
        assert [r["StateChange:state"] for r in at] == [[h["to"]]], (h, lane)
        assert at[0]["sim_time"] == pytest.approx(h["t"], abs=1e-6)
        assert state_at(lane, h["tick"] - 1) == h["from"]
        texts = [r for r in rows["/log/handovers"] if r.get("tick") == h["tick"]]
        assert len(texts) == 1, texts
        text = texts[0]["TextLog:text"]
        assert f"{h['from']} → {h['to']}" in text[0] and f"trigger {h['trigger']}" in text[0]
        for k, v in h["variables"].items():
            assert f"{k} = {v}" in text[0]
        assert texts[0]["sim_time"] == pytest.approx(h["t"], abs=1e-6)
        if h["attribute"] == "pose":
            shape = [r for r in rows[f"/world/{h['entity']}/shape"] if r.get("tick") == h["tick"]]
            rgb = colours.rgb(h["to"])
            packed = (rgb[0] << 24) | (rgb[1] << 16) | (rgb[2] << 8) | 0xFF
            assert any(packed in (r.get("Ellipsoids3D:colors") or []) for r in shape), shape
    assert len(rows["/log/handovers"]) == len(handovers)


def run_with_sink(router, procs, tmp_path, mode="save", tapped=True, **sink_kw):
    """A run with the sink fed from the run log in the conductor's process (as ``twin run`` does), or
    (``tapped=False``) from its own subscriptions in a session of its own, as a viewer elsewhere would be."""
    session, endpoint = router
    scene = load_scene(HERE / "core_scene.yaml")
    rec = load_recording(core_recording(tmp_path / "rec.mcap"))
    spawn_agents(procs, scene, endpoint)
    keys = Keys("default")
    c = Conductor(scene, session, keys, ReplaySource(rec), RunOptions(run_log=str(tmp_path / "run.mcap"),
                                                                      register_timeout=60))
    own = None if tapped else ZenohOptions(mode="client", connect=[endpoint]).open()
    try:
        sink = start_sink(own or session, keys, scene, mode, tmp_path, tap=c.run_log if tapped else None, **sink_kw)
        try:
            summary = c.run()
        finally:
            c.close()
            hint = sink.close() if sink is not None else ""
    finally:
        if own is not None:
            own.close()
    return scene, summary, sink, hint


@pytest.mark.slow
@pytest.mark.parametrize("tapped", [True, False], ids=["tapping the run log", "own session"])
def test_live_sink_shows_every_handover_and_twin_view_agrees(router, procs, tmp_path, tapped):
    """A run of the core scene with the sink in save mode: the .rrd verifies, holds both handovers at
    their simulated times with the right owners, the poses decimated to the sink's pose_hz, health series and the
    blueprint; ``twin view`` on the run log writes an .rrd with the same responsibility lanes."""
    scene, s, sink, hint = run_with_sink(router, procs, tmp_path, tapped=tapped)
    rrd = tmp_path / "run.rrd"
    assert f"rerun {rrd}" in hint
    verify(rrd)
    rows = read_rrd(rrd)
    colours = Colours(scene.models)
    hs = [(h["from"], h["to"], h["trigger"]) for h in s["handovers"]]
    assert hs == [("sim", "holder", "pick"), ("holder", "sim", "drop")]
    check_handovers(rows, s["handovers"], colours)
    assert sink.logger.counts["bad"] == 0
    # poses: at most one per 1/pose_hz s of simulated time (plus the ones forced at handovers and the end)
    ball = [r for r in rows["/world/ball"] if "Transform3D:translation" in r and r.get("tick") is not None]
    sim_s, hz = s["sim_s"], sink.pose_hz
    assert 0.5 * hz * sim_s <= len(ball) <= hz * sim_s + 2 * len(s["handovers"]) + 3
    assert ball[-1]["Transform3D:translation"][0][2] == pytest.approx(0.0, abs=1e-6)  # came to rest in the bin
    held = [r for r in ball if s["handovers"][0]["tick"] < r["tick"] <= s["handovers"][1]["tick"]]
    assert held and all(r["Transform3D:translation"][0][2] == pytest.approx(0.8) for r in held)
    # health: real-time factor, and a step rate per model that stepped
    assert len(rows["/health/rtf"]) >= 1
    for m in ("sim", "holder"):
        assert any("Scalars:scalars" in r for r in rows[f"/health/step_rate/{m}"])
    # the trigger that fired and the action that caused it are in the log
    assert any("trigger pick fired" in r["TextLog:text"][0] for r in rows["/log/triggers"] if "TextLog:text" in r)
    assert any("move_hand end" in r["TextLog:text"][0] for r in rows["/log/actions"])
    # the layout travels with the recording
    from rerun.chunk import RrdReader

    assert len(RrdReader(str(rrd)).blueprints()) == 1

    # twin view turns the run log into an .rrd drawn by the same code
    out = tmp_path / "view.rrd"
    p = subprocess.run([sys.executable, "-m", "conductor.cli", "view", s["run_log"], "--out", str(out),
                        "--scene", str(HERE / "core_scene.yaml")], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "2 handovers" in p.stdout
    verify(out)
    view = read_rrd(out)
    check_handovers(view, s["handovers"], colours)
    lanes = {k: [(r["tick"], r["StateChange:state"]) for r in v if "StateChange:state" in r]
             for k, v in rows.items() if k.startswith("/ownership/")}
    assert lanes == {k: [(r["tick"], r["StateChange:state"]) for r in v if "StateChange:state" in r]
                     for k, v in view.items() if k.startswith("/ownership/")}
    # its real-time factor is the run's, timed by the wall clock (the messages' publish times): it took their log
    # times, the simulated clock, and always showed about 1 (a review's finding)
    rtf = sorted(r["Scalars:scalars"][0] for r in view["/health/rtf"] if r.get("Scalars:scalars"))
    assert rtf and 0.33 < rtf[len(rtf) // 2] / s["rtf"] < 3, (rtf, s["rtf"])


def test_twin_view_without_scene_draws_from_messages(tmp_path):
    """Without a scene file, ``twin view`` still shows ownership, handovers and poses (as markers),
    and loads the Panda when the joint states are the Panda's."""
    from conductor.runlog import RunLog
    from conductor.viewer import log_run

    keys = Keys("default")
    log_path = tmp_path / "run.mcap"
    rl = RunLog(log_path)
    own = {"cube": {"pose": "physics"}}
    rl.record(keys.ownership, codec.encode("ownership", version=0, tick=0, t=0.0, owners=own, change=None), 1)
    names = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]
    for tick in range(240):
        t = tick / 240
        q = [0.0, -0.3 + t, 0.0, -2.0, 0.0, 2.0, 0.8, 0.04, 0.04]
        rl.record(keys.telemetry("joint_states"), codec.encode("joint_state", stamp=t, name=names, position=q,
                                                                velocity=[0.0] * 9, effort=[0.0] * 9), 10 + tick)
        owner = "physics" if tick <= 120 else "in_hand"
        rl.record(keys.state(owner), codec.encode("state", model=owner, tick=tick, t=t,
                                                  values={"cube": {"pose": [0.4, 0.0, 0.02 + t, 0, 0, 0, 1]}}),
                  10 + tick)
        if tick == 120:
            change = {"tick": 120, "t": 0.5, "entity": "cube", "attribute": "pose", "from": "physics",
                      "to": "in_hand", "trigger": "grasp", "variables": {"near": {"entity": "cube"}}}
            rl.record(keys.ownership, codec.encode("ownership", version=1, tick=120, t=0.5,
                                                   owners={"cube": {"pose": "in_hand"}}, change=change), 10 + tick)
            rl.record(keys.event("_conductor", "handover"),
                      codec.encode("event", model="_conductor", name="handover", tick=120, t=0.5,
                                   data=change), 10 + tick)
    rl.close()
    stream, logger = log_run(log_path, tmp_path / "x.rrd")
    verify(tmp_path / "x.rrd")
    rows = read_rrd(tmp_path / "x.rrd")
    lane = rows["/ownership/cube/pose"]
    assert [(r["tick"], r["StateChange:state"][0]) for r in lane if "StateChange:state" in r] == \
        [(0, "physics"), (120, "in_hand")]
    assert "physics → in_hand" in rows["/log/handovers"][0]["TextLog:text"][0]
    assert FIXED_COLOURS["in_hand"][1] == Colours(["in_hand"]).rgb("in_hand")
    # the Panda: visual meshes logged, its moving joints follow the telemetry, decimated to 60 Hz
    assert any(p.startswith("/world/panda/visual_geometries/") for p in rows)
    j2 = [r for r in rows["/world/robot_joints/panda_joint2"] if r.get("tick") is not None]
    assert 50 <= len(j2) <= 61
    assert not any(p.startswith("/world/panda/collision_geometries/") for p in rows)


def test_twin_view_until_keeps_a_live_robot_s_joints_up_to_that_time(tmp_path):
    """A live run's log stamps the robot's messages since the epoch: ``--until`` compared those stamps with the
    simulated time and left out every joint state and action, even with a limit past the run's end (a review's
    finding). They are now timed from the log's origin, the robot's first stamp."""
    from conductor.runlog import RunLog
    from conductor.viewer import log_run

    keys, t0 = Keys("default"), 1.8e9  # (seconds since the epoch, as a robot stamps)
    log_path = tmp_path / "live.mcap"
    rl = RunLog(log_path)  # (no origin given: a live run's log)
    rl.set_origin(round(t0 * 1e9))
    names = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]
    rl.record(keys.ownership, codec.encode("ownership", version=0, tick=0, t=0.0, owners={}, change=None), 1)
    for tick in range(240):
        t = tick / 120
        rl.record(keys.telemetry("joint_states"), codec.encode(
            "joint_state", stamp=t0 + t, name=names, position=[0.0, t, 0.0, -2.0, 0.0, 2.0, 0.8, 0.04, 0.04],
            velocity=[], effort=[]), 10 + tick)
        rl.record(keys.clock, codec.encode("clock", tick=tick, t=t, dt=1 / 120), 10 + tick)
        if tick in (30, 200):
            rl.record(keys.telemetry("action"), codec.encode("action", stamp=t0 + t, operation="grip",
                                                               phase="start", params={}), 10 + tick)
    rl.close()
    # (without --until the high-rate keys are sampled by count, with it every message is read: 60 Hz of 2 s)
    for until, joints, actions in ((None, (20, 60), 2), (100.0, (110, 121), 2), (1.0, (55, 61), 1)):
        log_run(log_path, tmp_path / "x.rrd", until=until)
        rows = read_rrd(tmp_path / "x.rrd")
        j2 = [r for r in rows.get("/world/robot_joints/panda_joint2", []) if r.get("tick") is not None]
        assert joints[0] <= len(j2) <= joints[1], (until, len(j2))
        assert len(rows.get("/log/actions", [])) == actions, (until, rows.get("/log/actions"))


def test_a_run_log_cut_short_is_shown_up_to_the_cut_and_said(tmp_path):
    """A run log whose writer was killed has no end: ``twin view`` shows what it holds, says that it is cut short
    and exits 4 (truncated); a whole one exits 0. One damaged in the middle (a chunk's length, a flipped byte that
    its checksum finds) is shown up to the damage and said the same way. A run log is never its own output."""
    from mcap.reader import make_reader

    from conductor.runlog import RunLog, cut_short

    keys = Keys("default")
    whole = tmp_path / "run.mcap"
    rl = RunLog(whole)
    for tick in range(1200):
        rl.record(keys.state("physics"), codec.encode("state", model="physics", tick=tick, t=tick / 120,
                                                      values={"cube": {"pose": [0.4, 0.0, 0.02, 0, 0, 0, 1]}}), tick)
    rl.close()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    assert not cut_short(whole) and cut_short(cut) and cut_short(tmp_path / "nothing.mcap")
    with open(whole, "rb") as f:
        chunks = sorted(c.chunk_start_offset for c in make_reader(f).get_summary().chunk_indexes)
    assert len(chunks) >= 3, chunks
    data = whole.read_bytes()
    middle = chunks[len(chunks) // 2]
    lost_length, flipped = tmp_path / "length.mcap", tmp_path / "flipped.mcap"
    lost_length.write_bytes(data[:middle + 1] + b"\xff" * 8 + data[middle + 9:])  # (opcode, then its length)
    flipped.write_bytes(data[:middle + 200] + bytes([data[middle + 200] ^ 0x55]) + data[middle + 201:])
    for path, code, said in ((whole, 0, None), (cut, 4, "is cut short"), (lost_length, 4, "is damaged near byte"),
                             (flipped, 4, "is damaged near byte")):
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "view", str(path)], capture_output=True, text=True,
                           cwd=ROOT, timeout=120)
        assert r.returncode == code, r.stdout + r.stderr
        assert said is None and not r.stderr.strip() or said in r.stderr, r.stderr
        assert path.with_suffix(".rrd").stat().st_size > 0  # shown either way, up to the cut
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "view", str(whole), "--out", str(whole)],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "is also the output named" in r.stderr and whole.read_bytes() == data, r.stderr


def test_colours_are_fixed_for_builtins_and_distinct_in_a_scene():
    """Built-in model names keep their colour; other names hash into the palette, never clashing with
    another model of the same scene, and get the same colour in every run."""
    names = ["physics", "in_hand", "grasp_monitor", "spu", "fluid"] + [f"m{i}" for i in range(7)]
    c = Colours(names)
    assert {n: c.rgb(n) for n in FIXED_COLOURS} == {n: rgb for n, (_, rgb) in FIXED_COLOURS.items()}
    assert len({c.rgb(n) for n in names}) == len(names)
    assert Colours(list(reversed(names))).assigned == c.assigned
    assert Colours(["holder"]).rgb("holder") == Colours(["holder", "physics"]).rgb("holder")


def test_logger_decimates_poses_but_never_handovers(tmp_path):
    """At 1 kHz of state messages the viewer gets at most 60 poses per simulated second, and the pose
    at a handover tick is logged even between two samples; malformed messages are counted, not raised."""
    stream = open_stream("save", tmp_path / "d.rrd")
    lg = TwinLogger(stream.rec, None, pose_hz=60)
    lg.begin()
    k = Keys("e")
    lg.feed(k.ownership, {"version": 0, "tick": 0, "t": 0.0, "owners": {"b": {"pose": "physics"}}}, 0)
    for tick in range(1000):
        t = tick / 1000
        lg.feed(k.state("physics" if tick <= 503 else "in_hand"),
                {"model": "physics" if tick <= 503 else "in_hand", "tick": tick, "t": t,
                 "values": {"b": {"pose": [0.0, 0.0, t, 0, 0, 0, 1]}}}, tick * 1_000_000)
        if tick == 503:
            lg.feed(k.ownership, {"version": 1, "tick": 503, "t": 0.503, "owners": {"b": {"pose": "in_hand"}}}, 0)
    lg.feed(k.state("x"), {"model": "x"}, 0)        # lacks fields
    lg.feed(k.out("x", "y"), b"\x00", 0)             # not a map
    lg.finish()
    close_stream(stream)
    assert lg.counts["bad"] == 2
    rows = read_rrd(tmp_path / "d.rrd")
    ticks = [r["tick"] for r in rows["/world/b"]]
    assert 503 in ticks and 504 in ticks and 999 in ticks
    assert len(ticks) <= 60 + 3
    assert np.all(np.diff(ticks) > 0)


def test_modes():
    """Mode strings parse; 'none' starts no sink; an unknown mode is refused with the allowed list."""
    assert parse_mode("connect=rerun+http://h:9876/proxy") == ("connect", "rerun+http://h:9876/proxy")
    assert parse_mode("serve=9090") == ("serve", "9090")
    assert parse_mode(None) == ("none", None)
    assert start_sink(None, Keys("default"), None, "none", "/nonexistent") is None
    with pytest.raises(ViewerError, match="use none, save, spawn"):
        parse_mode("bogus")
    assert ViewerSink.LOW == ("ownership", "event/*/*")


def test_connect_says_whether_a_viewer_took_the_stream(tmp_path):
    """--rerun connect=URL: with a viewer there (a real Rerun gRPC server in its own process) the stream is sent
    and said so; with nobody there it is said at once, the .rrd is still written, and ``twin view --connect``
    is a one-line error (exit 1), not a traceback or a claim that it was sent."""
    import rerun as rr

    from conductor.launch import free_port

    port = free_port()
    viewer = subprocess.Popen([sys.executable, "-c", "import rerun as rr, time; rr.init('viewer'); "
                               f"rr.serve_grpc(grpc_port={port}); time.sleep(120)"])
    try:
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        stream = None
        for _ in range(100):  # until the server listens (bounded: 20 s)
            stream = open_stream(f"connect={url}", tmp_path / "there.rrd")
            if stream.undelivered is None:
                break
            close_stream(stream)
            assert viewer.poll() is None, "the viewer stand-in exited"
            time.sleep(0.2)
        assert stream is not None and stream.undelivered is None, stream and stream.undelivered
        stream.rec.log("x", rr.Points3D([[0, 0, 0]]))
        close_stream(stream)
        assert stream.undelivered is None and stream.hint().startswith(f"Rerun stream sent to {url}")
        assert stream.facts() == {"mode": "connect", "rrd": str(tmp_path / "there.rrd"), "url": url,
                                  "delivered": True}  # (the summary's rerun_stream: for a program)
    finally:
        viewer.kill()
        viewer.wait()
    nobody = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    stream = open_stream(f"connect={nobody}", tmp_path / "nobody.rrd")
    stream.rec.log("x", rr.Points3D([[0, 0, 0]]))
    close_stream(stream)
    assert "no Rerun viewer answers at 127.0.0.1:" in (stream.undelivered or "")
    assert stream.hint().startswith("warning: the Rerun stream reached no viewer: ") and "sent" not in stream.hint()
    assert (tmp_path / "nobody.rrd").stat().st_size > 0
    facts = stream.facts()
    assert facts["delivered"] is False and facts["url"] == nobody and "no Rerun viewer answers" in facts["undelivered"]
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    run = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(HERE / "core_scene.yaml"), "--recording",
                          str(rec), "--run-dir", str(tmp_path / "run")], capture_output=True, text=True, cwd=ROOT,
                         timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    saved = subprocess.run([sys.executable, "-m", "conductor.cli", "view", str(tmp_path / "run" / "run.mcap")],
                           capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert saved.returncode == 0, saved.stdout + saved.stderr
    rrd = tmp_path / "run" / "run.rrd"
    whole = rrd.read_bytes()
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "view", str(tmp_path / "run" / "run.mcap"), "--connect",
                        nobody], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "no Rerun viewer answers at" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert rrd.read_bytes() == whole, "the recording already there is kept (it was cut to a stub)"


def test_twin_view_refuses_what_it_would_overwrite_or_ignore(tmp_path):
    """``twin view``: an --out that exists and is not a Rerun recording (another run's log, by a slip) is kept,
    exit 2; --foxglove-layout with a flag it would ignore, and a --serve port that is not one, exit 2 naming them;
    --spawn with no display says so (exit 1), and the viewer is really started when there is one (rr.spawn was
    called without the recording stream, asked the global one, and started nothing)."""
    import os

    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")}
    run = subprocess.run([sys.executable, "-m", "conductor.cli", "run", str(HERE / "core_scene.yaml"), "--recording",
                          str(rec), "--run-dir", str(tmp_path / "run"), "--rerun", "spawn"], capture_output=True,
                         text=True, cwd=ROOT, timeout=120, env=headless)
    assert run.returncode == 0, run.stdout + run.stderr
    # no display for a viewer: said, and the recording is written all the same (the stream was dropped whole)
    assert "no display here" in run.stdout + run.stderr and (tmp_path / "run" / "run.rrd").stat().st_size > 0
    log = str(tmp_path / "run" / "run.mcap")
    other = tmp_path / "other.mcap"
    other.write_bytes((tmp_path / "run" / "run.mcap").read_bytes())

    def view(*args, env=None):
        import os

        return subprocess.run([sys.executable, "-m", "conductor.cli", "view", log, *args], capture_output=True,
                              text=True, cwd=ROOT, timeout=60, env={**os.environ, **(env or {})})

    counted = []
    for extra in ((), ("--until", "1000")):  # the log's messages, counted alike whichever way it is read
        r = view("--out", str(tmp_path / "all.rrd"), *extra)
        assert r.returncode == 0, r.stderr
        counted.append(next(ln.split(" messages read")[0] for ln in r.stdout.splitlines() if "messages read" in ln))
    assert counted[0] == counted[1] and int(counted[0]) > 100, counted
    empty = tmp_path / "empty.rrd"
    empty.write_bytes(b"")
    for out in (str(empty), "/dev/null"):  # an empty file, no regular file: written to as they are
        assert view("--out", out).returncode == 0
    piped = subprocess.run(f"{sys.executable} -m conductor.cli view {log} --out /dev/stdout | wc -c", shell=True,
                           capture_output=True, text=True, cwd=ROOT, timeout=60)  # (it read its own pipe, for ever)
    assert int(piped.stdout.split()[-1]) > 100_000, piped.stdout + piped.stderr
    r = view("--out", str(other))
    assert r.returncode == 2 and "exists and is not a Rerun recording: it is kept" in r.stderr, r.stderr
    assert other.read_bytes() == (tmp_path / "run" / "run.mcap").read_bytes()
    r = view("--foxglove-layout", str(tmp_path / "l.json"), "--serve")
    assert r.returncode == 2 and "--serve cannot go with it" in r.stderr and not (tmp_path / "l.json").exists()
    for port in ("abc", "99999"):
        r = view("--serve", port)
        assert r.returncode == 2 and "argument --serve: the web viewer's port must be a number from 1 to 65535" \
            in r.stderr, r.stderr
    r = view("--out", str(tmp_path / "s.rrd"), "--spawn", env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    assert r.returncode == 1 and "no display here" in r.stderr, r.stderr
    assert not (tmp_path / "s.rrd").exists()
    from conductor.launch import free_port

    port = free_port()  # a display that is not there: the viewer starts and ends at once, but it is started
    r = subprocess.run([sys.executable, "-c", "from conductor.viewer.stream import open_stream, close_stream\n"
                        f"s = open_stream('spawn', {str(tmp_path / 's.rrd')!r}, spawn_port={port})\n"
                        "close_stream(s)"], capture_output=True, text=True, cwd=ROOT, timeout=60,
                       env={**__import__("os").environ, "DISPLAY": ":97", "RUST_LOG": "warn"})
    assert "spawn() call ignored" not in r.stdout + r.stderr, r.stderr


def test_a_live_sink_that_falls_behind_drops_samples_never_a_handover(tmp_path):
    """The sink fed from the run log queued every message in one deque of ``capacity`` that dropped its oldest when
    full: a worker far behind lost ownership changes too, and the .rrd showed no handover (a review's suspicion,
    reproduced with a small capacity). High-rate samples are now left out and counted; ownership, events (those in
    a step answer too) and robot actions never."""
    from conductor.runlog import RunLog
    from conductor.viewer.sink import ViewerSink

    scene = load_scene(HERE / "core_scene.yaml")
    keys = Keys("default")
    rl = RunLog(tmp_path / "run.mcap")
    sink = ViewerSink(None, keys, scene, mode="save", path=tmp_path / "run.rrd", capacity=50, period=60.0,
                      tap=rl).start()
    try:
        deadline = time.monotonic() + 30  # (its worker's first drain is done: the next one is a minute away)
        while sink.worker_cpu_s == 0.0 and time.monotonic() < deadline:
            time.sleep(0.01)
        owners = {"ball": {"pose": "sim"}}
        rl.take(keys.ownership, codec.encode("ownership", version=0, tick=0, t=0.0, owners=owners, change=None))
        for tick in range(1, 400):
            t = tick / 100
            rl.take(keys.state("sim"), codec.encode("state", model="sim", tick=tick, t=t,
                                                    values={"ball": {"pose": [0.5, 0, 0.3, 0, 0, 0, 1]}}))
            if tick == 200:
                change = {"tick": 200, "t": t, "entity": "ball", "attribute": "pose", "from": "sim",
                          "to": "holder", "trigger": "pick", "variables": {}}
                rl.take(keys.ownership, codec.encode("ownership", version=1, tick=200, t=t,
                                                     owners={"ball": {"pose": "holder"}}, change=change))
            if tick == 300:  # a service-stepped model's event comes in its step answer; a robot's action
                rl.take(keys.done("sim"), codec.encode("step_reply", tick=tick, status="ok", state={}, outputs={},
                                                       events=[{"name": "grasped", "data": {"by": "holder"}}]))
                rl.take(keys.telemetry("action"), codec.encode("action", stamp=t, operation="grip", phase="end",
                                                               params={}))
    finally:
        sink.close()
        rl.close()
    assert sink.dropped > 300
    rows = read_rrd(tmp_path / "run.rrd")
    lane = rows["/ownership/ball/pose"]
    assert [(r["tick"], r["StateChange:state"][0]) for r in lane if "StateChange:state" in r] == \
        [(0, "sim"), (200, "holder")]
    assert any("grasped" in r["TextLog:text"][0] for r in rows["/log/events/sim"] if "TextLog:text" in r)
    assert any("grip end" in r["TextLog:text"][0] for r in rows["/log/actions"] if "TextLog:text" in r)
