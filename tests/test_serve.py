"""``twin serve`` and ``twin submit`` as a user runs them: a real service process with its embedded router, its warm
agents as processes, clients as processes."""
from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from conductor.launch import AgentProcs, free_port
from conductor.service import ASKING_S
from recordings.simple import core_recording

from .conftest import wait_until

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
CORE = str(ROOT / "tests" / "core_scene.yaml")


def twin(*args, timeout=180):
    return subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=ENV, cwd=ROOT)


@pytest.fixture
def service(tmp_path):
    """A ``twin serve`` process on a free loopback port: yields (client flags, run dir)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "serve"
    log = open(tmp_path / "serve.log", "w")
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "serve", "--listen", endpoint, "--run-dir",
                          str(run_dir), "--ensemble", "svc"], stdout=log, stderr=subprocess.STDOUT, env=ENV, cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while "clients: " not in (tmp_path / "serve.log").read_text():
            assert p.poll() is None, (tmp_path / "serve.log").read_text()
            assert time.monotonic() < deadline, "twin serve did not come up within 60 s"
            time.sleep(0.1)
        flags = ["--connect", endpoint, "--ensemble", "svc", "--credentials", str(run_dir / "access.json")]
        # it says every option a client needs (it said only --credentials: a client asked the default endpoint)
        assert f"clients: twin submit SCENE --recording R {' '.join(flags)}" in (tmp_path / "serve.log").read_text()
        yield flags, run_dir
    finally:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        log.close()


def ask(flags: list[str], key: str, args: dict, timeout: float = 20) -> list[tuple[str, Any]]:
    """A query to the service from a client session of this process: its replies, ("ok", message) or ("err",
    the error's message)."""
    from protocol import codec
    from protocol.config import ZenohOptions

    access = json.loads(Path(flags[flags.index("--credentials") + 1]).read_text())
    session = ZenohOptions(mode="client", connect=[flags[flags.index("--connect") + 1]], user=access["user"],
                           password=access["password"]).open()
    try:
        return [("ok", codec.decode(key, r.ok.payload, None)) if r.ok is not None else
                ("err", codec.decode(key, r.err.payload, "error").message)
                for r in session.get(key, payload=codec.encode("control", args=args), timeout=timeout)]
    finally:
        session.close()


def status(flags: list[str]) -> dict:
    r = twin("status", *flags, timeout=30)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def ctrl_c(p: subprocess.Popen, timeout: float = 120) -> str:
    """Ctrl-C to a client process, then its output; killed if it does not end within ``timeout``."""
    try:
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=timeout)
        return out
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def wait_serving(p: subprocess.Popen, log: Path) -> None:
    """Until twin serve ``p`` says it serves (its log, ``log``), within 60 s; it must not exit meanwhile."""
    deadline = time.monotonic() + 60
    while "; Ctrl-C stops" not in log.read_text():
        assert p.poll() is None and time.monotonic() < deadline, log.read_text()
        time.sleep(0.1)


def stop_service(p: subprocess.Popen, log: Any = None) -> None:
    """Ctrl-C to twin serve ``p`` (started in a session of its own), killed with its agents if it does not end
    within 30 s; its log file closed."""
    p.send_signal(signal.SIGINT)
    try:
        p.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    if log is not None:
        log.close()


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"


@pytest.mark.slow
def test_two_runs_back_to_back_on_the_same_agents_one_killed_between(service, tmp_path):
    flags, run_dir = service
    rec = str(ROOT / "recordings" / "ball_drop_00.mcap")
    first = twin("submit", "scenes/ball_drop.yaml", "--recording", rec, "--summary", str(tmp_path / "1.json"), *flags)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "COMPLETE" in first.stdout and "handover  ball.pose: physics -> in_hand" in first.stdout
    pools = status(flags)["pools"]
    assert len(pools) == 1
    (pool,) = pools.values()
    pids = pool["pids"]
    os.kill(pids["in_hand"], signal.SIGKILL)  # a model dies between two runs: the service starts it again

    second = twin("submit", "scenes/ball_drop.yaml", "--recording", rec, "--summary", str(tmp_path / "2.json"), *flags)
    assert second.returncode == 0, second.stdout + second.stderr
    s1, s2 = (json.loads((tmp_path / f"{i}.json").read_text()) for i in (1, 2))
    assert s2["service"]["pool"] == s1["service"]["pool"] and s2["service"]["restarted"] == 1
    after = status(flags)["pools"][s1["service"]["pool"]]["pids"]
    assert after["physics"] == pids["physics"] and after["grasp_monitor"] == pids["grasp_monitor"]  # warm: same
    assert after["in_hand"] != pids["in_hand"] and alive(after["in_hand"])
    # the same run on re-initialised agents gives the same answer and the same handovers as the first
    assert s2["status"] == s1["status"] == "complete"
    assert s2["semantic_state"] == s1["semantic_state"] and s1["semantic_state"]["in(container, ball)"] is True
    assert [(h["t"], h["entity"], h["to"]) for h in s2["handovers"]] == \
           [(h["t"], h["entity"], h["to"]) for h in s1["handovers"]]
    assert (run_dir / "2" / "run.mcap").stat().st_size > 0


def test_submit_errors_and_a_stopped_run(service, tmp_path):
    flags, _ = service
    rec = core_recording(tmp_path / "rec.mcap", seconds=120.0)  # (paced below, and stopped long before its end)
    bad = tmp_path / "bad.yaml"
    bad.write_text(Path(CORE).read_text().replace("main: sim", "main: nobody"))
    r = twin("submit", str(bad), "--recording", str(rec), *flags)
    assert r.returncode == 2 and "bad.yaml" in r.stderr and "main" in r.stderr  # said here, nothing sent
    r = twin("submit", CORE, "--recording", "/nowhere/rec.mcap", *flags)
    assert r.returncode == 2 and "no such recording on the service's machine" in r.stderr, r.stderr  # bad input
    # a file there that is no recording is bad input too, as twin run says it (the run failed, and exited 1)
    r = twin("submit", CORE, "--recording", CORE, *flags)
    assert r.returncode == 2 and "FAILED" in r.stdout and "core_scene.yaml" in r.stdout, r.stdout + r.stderr
    r = twin("submit", CORE, "--recording", str(rec), "--connect", f"tcp/127.0.0.1:{free_port()}",
             "--timeout", "2")
    assert r.returncode == 1 and "no Zenoh router answered" in r.stderr
    # the service's own router, without its access file: said as such, not as a router that is not there
    r = twin("submit", CORE, "--recording", str(rec), *flags[:4], "--timeout", "2")
    assert r.returncode == 1 and "did not let this session in" in r.stderr and "--credentials" in r.stderr, r.stderr

    # a paced run, stopped from the client with Ctrl-C: the service ends it, the summary says truncated
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec), "--rtf",
                          "1", *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
    try:
        assert p.stdout is not None
        line = p.stdout.readline()
        assert "started on the service" in line, line  # nothing else was running
        deadline = time.monotonic() + 60
        while not status(flags)["running"]:
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.2)
        running = status(flags)["running"][0]
        # a run submitted now waits for the paced one: the client says behind which
        q = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec),
                              "--max-ticks", "5", *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             env=ENV, cwd=ROOT)
        try:
            assert q.stdout is not None
            queued = q.stdout.readline()
        finally:
            q.kill()  # the client only: the run stays queued on the service, and runs after the paced one
            q.communicate(timeout=30)
        assert f"queued on the service behind run {running} (1 at a time)" in queued, queued
        # a service trigger called on the service is passed on to the running run's conductor (this scene has
        # none by that name: the run's conductor says so)
        r = twin("trigger", "hold", "--arg", "target=ball", *flags, timeout=60)
        assert r.returncode == 1 and "listens to service 'hold'" in r.stderr and "core_demo" in r.stderr, r.stderr
        # the run is chosen by --run (in the selector); an argument named run goes to the trigger as it is
        r = twin("trigger", "hold", "--arg", "run=999", *flags, timeout=60)
        assert r.returncode == 1 and "listens to service 'hold'" in r.stderr, r.stderr
        r = twin("trigger", "hold", "--run", "999", *flags, timeout=60)
        assert r.returncode == 1 and "no run '999' on this service" in r.stderr, r.stderr
        waiting = status(flags)["queued"][0]  # (the one submitted behind the paced run)
        r = twin("trigger", "hold", "--run", waiting, *flags, timeout=60)
        assert r.returncode == 1 and f"run {waiting} is queued" in r.stderr, r.stderr
        r = twin("trigger", "hold", "--run", running, *flags, timeout=60)
        assert r.returncode == 1 and "listens to service 'hold'" in r.stderr, r.stderr
        # a wildcard query (a generic Zenoh tool reading the service) reached start, status and stop, each of which
        # took it for a stop: the run it read was ended. Refused now, by each, and the run goes on
        said = ask(flags, "twin/svc/conductor/*", {"run": running})
        assert len(said) == 3 and all(k == "err" and "by its own name" in m for k, m in said), said
        said = ask(flags, "twin/svc/conductor/trigger/*", {})  # (it was passed on as a trigger named '*')
        assert len(said) == 1 and said[0][0] == "err" and "name one trigger" in said[0][1], said
        # (and a pattern over ensembles was passed on to the run as well: the run's own conductor answers it itself)
        said = ask(flags, "twin/*/conductor/trigger/hold", {})
        assert ("err", "twin/*/conductor/trigger/hold: name one trigger of this service (conductor/trigger/NAME), "
                "not a pattern") in said, said
        assert running in status(flags)["running"]
        # a start prepared after its client stopped waiting (?timeout=) is not queued: the client had said it failed
        scene = Path(CORE).read_text()
        said = ask(flags, "twin/svc/conductor/start?timeout=0.0001", {"scene": scene, "recording": str(rec)})
        assert said[0][0] == "err" and "its client waits: not queued" in said[0][1], said
        assert status(flags)["queued"] == [waiting]
    finally:
        out = ctrl_c(p)
    assert p.returncode == 4, out
    assert "TRUNCATED" in out and "conductor/stop" in out

    # a second service on the same run directory is refused (it would write its access file over this one's and
    # number its runs over them); this one's clients still get in
    _, run_dir = service
    r = twin("serve", "--listen", f"tcp/127.0.0.1:{free_port()}", "--run-dir", str(run_dir), timeout=60)
    assert r.returncode == 1 and "another twin serve uses this run directory" in r.stderr, r.stdout + r.stderr
    assert status(flags)["finished"] >= 1


def test_a_service_started_again_numbers_its_runs_after_those_there(tmp_path):
    from conductor.service import first_free_id

    assert first_free_id(tmp_path / "nothing yet") == 1 and first_free_id(tmp_path) == 1
    for name in ("1", "2", "7", "agents", "x9", "access.json"):
        (tmp_path / name).mkdir()
    assert first_free_id(tmp_path) == 8


@pytest.mark.slow
def test_samples_through_the_service_equal_samples_run_here(service, tmp_path):
    flags, _ = service
    rec = str(ROOT / "recordings" / "insertion_pb_10mm.mcap")
    common = ["scenes/insertion.yaml", "--recording", rec, "--samples", "3", "--seed", "5"]
    r = twin("submit", *common, "--summary", str(tmp_path / "served.json"), *flags, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "P[connected(dip, spu)]" in r.stdout
    # where the samples are and how long they took, as twin run --samples says it
    last = r.stdout.strip().splitlines()[-2]  # (the last line says where the summary went)
    assert last.startswith("status: complete (the worst sample's); ") and " s in all; runs in " in last, r.stdout
    folders = json.loads((tmp_path / "served.json").read_text())["runs"]
    assert len(folders) == 3 and all((Path(f) / "summary.json").is_file() for f in folders), folders
    served_lines = sorted(line for line in r.stdout.splitlines() if line.startswith("  sample "))
    r = twin("run", *common, "--jobs", "2", "--run-dir", str(tmp_path / "here"), "--summary",
             str(tmp_path / "here.json"), timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    # each sample is said as it ends, on the service as here (it said nothing until the last one)
    here_lines = sorted(line for line in r.stdout.splitlines() if line.startswith("  sample "))
    assert len(served_lines) == 3 and served_lines == here_lines, (served_lines, here_lines)
    served, here = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("served", "here"))
    assert served["samples"] == here["samples"] == 3 and served["status"] == "complete"
    for k in ("variations", "predicates", "handovers"):
        assert served[k] == here[k], k
    # the samples' agents outlive the sampled run's threads: the next run finds them all warm
    r = twin("submit", "scenes/insertion.yaml", "--recording", rec, "--summary", str(tmp_path / "after.json"), *flags,
             timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    after = json.loads((tmp_path / "after.json").read_text())
    assert after["status"] == "complete" and after["service"]["warm_runs"] == 3, after["service"]
    assert after["service"]["restarted"] == 0, after["service"]


def test_agents_outlive_the_thread_that_started_them(tmp_path):
    """An agent gets SIGTERM when its launcher dies (Linux's parent-death signal, which follows the thread that
    started the process): a warm pool started from a run's worker thread must not die when that thread ends."""
    procs = AgentProcs(tmp_path / "agents")
    try:
        sleeper = [sys.executable, "-c", "import time; time.sleep(60)"]
        t = threading.Thread(target=procs.spawn, args=("sleeper", sleeper))
        t.start()
        t.join()
        p = procs.procs["sleeper"]
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:  # bounded: a SIGTERM would end it at once
            assert p.poll() is None, f"the agent died with its starting thread (exit {p.returncode})"
            time.sleep(0.05)
    finally:
        procs.stop()


def test_an_agent_started_again_leaves_no_file_open_here(tmp_path):
    """A warm service restarts an agent that died (its pool's process spawned again under the same name): each spawn
    kept the log file it handed the child open in the service, one more for every restart, until spawning failed
    for want of file descriptors. The child writes its log on its own copy; the service keeps none."""
    procs = AgentProcs(tmp_path / "agents")
    quick = [sys.executable, "-c", "print('started')"]
    try:
        procs.spawn("flaky", quick).wait(timeout=30)
        before = len(os.listdir("/proc/self/fd"))
        for _ in range(10):
            procs.spawn("flaky", quick).wait(timeout=30)
        assert len(os.listdir("/proc/self/fd")) <= before
        assert (tmp_path / "agents" / "agent-flaky.log").read_text().count("started") == 11
    finally:
        procs.stop()


@pytest.mark.slow
def test_a_sampled_run_stops_midway(service, tmp_path):
    """Ctrl-C on a sampled submit: the sample running ends truncated, the ones not begun are not run, and the
    distribution says truncated (exit 4), not complete."""
    flags, _ = service
    rec = str(ROOT / "recordings" / "insertion_pb_10mm.mcap")
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", "scenes/insertion.yaml", "--recording", rec,
                          "--samples", "3", "--rtf", "1", "--summary", str(tmp_path / "s.json"), *flags],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
    try:
        deadline = time.monotonic() + 120
        while not status(flags)["running"]:
            assert p.poll() is None and time.monotonic() < deadline, "the sampled run never started"
            time.sleep(0.2)
        time.sleep(1.0)  # into the first sample (paced: it lasts the recording's length)
        # a trigger with no --run while only the sampled run runs: said so (it said "no run is running")
        r = twin("trigger", "letgo", *flags, timeout=60)
        assert r.returncode == 1 and "only sampled runs are running" in r.stderr, r.stderr
    finally:
        out = ctrl_c(p)
    assert p.returncode == 4, out
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["status"] == "truncated", s["status"]
    assert s["samples"] == 3 and s.get("complete", 0) < 3, s


def test_a_service_stopping_gives_its_clients_their_runs_ends(tmp_path):
    """SIGTERM to twin serve while one run goes on and one waits: each client still gets its run's summary (the
    running one truncated by the service closing, the queued one never started) and exits 4; the queued run's
    folder keeps its summary, so a service started again there never gives its id to another run. A client killed
    while it waited is not waited for: the service says so, and that run's summary is in its folder."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "serve"
    log = open(tmp_path / "serve.log", "w")
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "serve", "--listen", endpoint, "--run-dir",
                          str(run_dir), "--ensemble", "closing"], stdout=log, stderr=subprocess.STDOUT, env=ENV,
                         cwd=ROOT)
    flags = ["--connect", endpoint, "--ensemble", "closing", "--credentials", str(run_dir / "access.json")]
    rec = core_recording(tmp_path / "rec.mcap", seconds=60.0)
    clients: list[subprocess.Popen] = []
    try:
        wait_serving(p, tmp_path / "serve.log")
        for i in (1, 2, 3):  # the first paced (it runs a minute), the others queued behind it
            clients.append(subprocess.Popen(
                [sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec), "--rtf", "1",
                 "--summary", str(tmp_path / f"{i}.json"), *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                text=True, env=ENV, cwd=ROOT))
            assert clients[-1].stdout is not None
            line = clients[-1].stdout.readline()
            assert ("started" if i == 1 else "queued") in line, line
        deadline = time.monotonic() + 60
        while not status(flags)["running"]:
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.2)
        clients[2].kill()  # its client dies: the service no longer hears it ask
        clients[2].wait()
        time.sleep(ASKING_S + 0.5)
        p.send_signal(signal.SIGTERM)
        outs = [c.communicate(timeout=90)[0] for c in clients[:2]]
        assert p.wait(timeout=60) == 0
    finally:
        for c in [*clients, p]:
            if c.poll() is None:
                c.kill()
                c.wait()
        log.close()
    assert [c.returncode for c in clients[:2]] == [4, 4], outs
    first, second = (json.loads((tmp_path / f"{i}.json").read_text()) for i in (1, 2))
    assert first["status"] == "truncated" and "the service closing" in " ".join(first["status_reasons"]), first
    assert second["status"] == "truncated" and "stopped before it started" in " ".join(second["status_reasons"])
    assert json.loads((run_dir / "2" / "summary.json").read_text())["status"] == "truncated"
    assert json.loads((run_dir / "3" / "summary.json").read_text())["status"] == "truncated"
    said = (tmp_path / "serve.log").read_text()
    assert "the client of run 3 did not take the summary" in said, said


def test_a_client_whose_service_died_says_so_and_does_not_spin(tmp_path):
    """twin serve killed (SIGKILL) while a client follows its run: the client said "nothing answered ... no twin
    serve of that ensemble there", as if it had never been, after asking again as fast as Zenoh answered for its
    whole timeout. It now asks once a poll, and says that the service stopped answering about its run, and where
    what the run wrote is."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "serve"
    log = open(tmp_path / "serve.log", "w")
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "serve", "--listen", endpoint, "--run-dir",
                          str(run_dir), "--ensemble", "dying"], stdout=log, stderr=subprocess.STDOUT, env=ENV,
                         cwd=ROOT, start_new_session=True)  # (its agents are killed with it, as a group)
    flags = ["--connect", endpoint, "--ensemble", "dying", "--credentials", str(run_dir / "access.json")]
    rec = core_recording(tmp_path / "rec.mcap", seconds=60.0)
    client = queued = None
    try:
        wait_serving(p, tmp_path / "serve.log")
        client = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec),
                                   "--rtf", "1", "--timeout", "3", *flags], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
        assert client.stdout is not None
        line = client.stdout.readline()
        assert "started on the service" in line, line
        queued = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec),
                                   "--timeout", "3", *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, env=ENV, cwd=ROOT)
        assert queued.stdout is not None
        line = queued.stdout.readline()
        assert "run 2" in line and "queued" in line, line
        deadline = time.monotonic() + 60
        while not status(flags)["running"]:
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.2)
        time.sleep(1.5)  # (its run log has ticks to show by then)
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        out, err = client.communicate(timeout=60)
        queued.communicate(timeout=60)
    finally:
        for c in (client, queued, p):
            if c is not None and c.poll() is None:
                c.kill()
                c.wait()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        log.close()
    assert client.returncode == 1, out + err
    assert "the service stopped answering about run 1 (3 s without an answer after it took the run)" in err, err
    assert "Traceback" not in err
    # a service started again on the folder answered "no run '1' on this service": it now says it was cut short
    log = open(tmp_path / "serve2.log", "w")
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "serve", "--listen", endpoint, "--run-dir",
                          str(run_dir), "--ensemble", "dying"], stdout=log, stderr=subprocess.STDOUT, env=ENV,
                         cwd=ROOT, start_new_session=True)
    try:
        wait_serving(p, tmp_path / "serve2.log")
        r = twin("status", "--run", "1", "--wait", *flags, timeout=60)
    finally:
        stop_service(p, log)
    assert r.returncode == 5 and "INTERRUPTED" in r.stdout, r.stdout + r.stderr
    assert "run 1 was cut short: the service that ran it stopped before it ended" in r.stdout, r.stdout
    s = json.loads((run_dir / "1" / "summary.json").read_text())
    assert s["status"] == "interrupted" and s["cut_short"] and s["run_log"] == str(run_dir / "1" / "run.mcap")
    # and what its run log holds up to the cut (it said scene '?', 0 ticks, no handovers)
    assert s["scene"] == "core_demo" and s["ticks"] > 0 and s["sim_s"] > 0, s
    assert f"its run log reaches tick {s['ticks'] - 1}" in s["status_reasons"][0], s["status_reasons"]
    assert f"{s['ticks']} ticks, {s['sim_s']:.2f} s simulated (cut short: its wall time is unknown)" in r.stdout, \
        r.stdout
    # the run that waited behind it: its id was in no folder, and the service started again gave it to another run
    s = json.loads((run_dir / "2" / "summary.json").read_text())
    assert s["status"] == "interrupted" and "run 2 never started" in s["status_reasons"][0], s
    assert not (run_dir / "2" / "queued").exists()


@pytest.mark.slow
def test_a_service_on_a_router_of_its_own_waits_out_the_routers_restart(tmp_path):
    """twin serve --connect (a client of a router it does not own) took a router restart for every agent dying:
    the main model waited for, the others lost, their handovers to the main model, degraded. twin conductor on the
    same router waited for the network and went on. The service's runs now know their session's mode and do the
    same: the run ends complete, with both handovers and the network's loss and return among its events. Started
    before its router, the service said nothing while it waited: it now says so, and serves once one comes."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"

    def router() -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "conductor.cli", "router", "--listen", endpoint],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV, cwd=ROOT)

    routers: list[subprocess.Popen] = []
    log = open(tmp_path / "serve.log", "w")
    svc = subprocess.Popen([sys.executable, "-m", "conductor.cli", "serve", "--connect", endpoint, "--run-dir",
                            str(tmp_path / "serve"), "--ensemble", "lab"], stdout=log, stderr=subprocess.STDOUT,
                           env=ENV, cwd=ROOT, start_new_session=True)
    rec = core_recording(tmp_path / "rec.mcap", seconds=9.0, grip=(0.8, 6.5))
    client = None
    try:
        # started before its router, it says what it waits for (it said nothing), then serves once one is there
        deadline = time.monotonic() + 60
        while "trying again every second (Ctrl-C gives up)" not in (tmp_path / "serve.log").read_text():
            assert svc.poll() is None and time.monotonic() < deadline, (tmp_path / "serve.log").read_text()
            time.sleep(0.1)
        assert f"no Zenoh router answered at {endpoint}; trying again" in (tmp_path / "serve.log").read_text()
        routers.append(router())
        wait_serving(svc, tmp_path / "serve.log")
        client = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec),
                                   "--rtf", "1", "--timeout", "30", "--connect", endpoint, "--ensemble", "lab",
                                   "--summary", str(tmp_path / "s.json")], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
        assert client.stdout is not None
        seen = []
        deadline = time.monotonic() + 90
        while not any("handover" in line and "(pick)" in line for line in seen):
            assert time.monotonic() < deadline, "".join(seen)
            seen.append(client.stdout.readline())
        time.sleep(0.3)
        routers[0].kill()
        routers[0].wait()
        time.sleep(1.5)
        routers.append(router())
        out, _ = client.communicate(timeout=120)
    finally:
        for p in [client, *routers]:
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        stop_service(svc, log)
    s = json.loads((tmp_path / "s.json").read_text())
    assert client.returncode == 0 and s["status"] == "complete", "".join(seen) + out
    assert [(h["from"], h["to"], h["trigger"]) for h in s["handovers"]] == [("sim", "holder", "pick"),
                                                                            ("holder", "sim", "drop")]
    assert s["semantic_state"] == {"in(bin, ball)": True}


def test_ctrl_c_while_the_service_waits_for_its_router_is_a_stop_not_a_failure(tmp_path):
    """twin serve --connect before its router: Ctrl-C there exited 1, where Ctrl-C while it serves exits 0; the user
    asked for the stop, and nothing had run. It now exits 0 and says that nothing was served."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    svc = subprocess.Popen([sys.executable, "-m", "conductor.cli", "serve", "--connect", endpoint, "--run-dir",
                            str(tmp_path / "serve")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=ENV, cwd=ROOT)
    assert svc.stdout is not None
    try:
        ready, _, _ = select.select([svc.stdout], [], [], 60)  # (said after its first try)
        first = svc.stdout.readline() if ready else "(nothing within 60 s)"
        assert "trying again every second (Ctrl-C gives up)" in first, first
        out = ctrl_c(svc, timeout=30)
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait()
    assert svc.returncode == 0, first + out
    assert "stopped before a router answered (nothing was served)" in out, out


def test_a_refusal_for_bad_input_is_a_bad_request():
    """A service that refuses a job for a bad input file (InputError, e.g. a perception out of shape sent by a
    client of its own) refuses a bad request: twin submit exits 2 for it, as for a bad scene."""
    from conductor.cli.serve import Refused

    assert all(Refused("x", kind).bad_request for kind in ("ValueError", "SceneError", "InputError", "ProtocolError"))
    assert not Refused("x", "TwinError").bad_request and not Refused("x").bad_request
    # a seed the samples cannot be drawn with is refused with the job (it failed in the service's worker)
    from conductor.service import Job

    for bad in (-5, 2**64, 1.5, "3"):
        with pytest.raises(ValueError, match="start: seed must be a whole number from 0 to 4294967295"):
            Job.from_args({"scene": "name: x", "recording": "r.mcap", "samples": 2, "seed": bad})
    # each argument is what the command line's types allow: a samples of -2 ran none and said nothing, 2.5 ran 2,
    # a max_ticks of 'x' failed at tick 0 as the conductor's own failure, a deadline of 'x' as the service's
    for key, bad, said in (("samples", -2, "a whole number from 1 to 10000"), ("samples", 2.5, "a whole number"),
                           ("samples", True, "a whole number"), ("max_ticks", "x", "a whole number from 1"),
                           ("max_ticks", -5, "a whole number from 1"), ("deadline", "x", "a finite number above 0"),
                           ("rtf", 0, "a finite number above 0"), ("idle_timeout", -1, "a finite number above 0"),
                           ("joint_order", "finger", "a list of strings"), ("recording", 5, "a string")):
        with pytest.raises(ValueError, match=f"start: '{key}' must be {said}"):
            Job.from_args({"scene": "name: x", "recording": "r.mcap", key: bad})
    for key, bad, said in (("rtf", 2, "'rtf' paces a replay"), ("remap", ["/a:=/b"], "say how to read a bag")):
        with pytest.raises(ValueError, match=said):
            Job.from_args({"scene": "name: x", "live": "robot", key: bad})
    # a ROS 2 domain as the command line bounds it (233 or 10**12 waited 30 s, then failed as the service's own)
    for bad in (233, 10**12, -1):
        with pytest.raises(ValueError, match="start: 'ros2_domain' must be a whole number from 0 to 232"):
            Job.from_args({"scene": "name: x", "ros2_domain": bad})
    for bad in ("a//b", "a*b", 5):  # (a key expression Zenoh refuses, once the run had begun)
        with pytest.raises(ValueError, match="start: 'ros2_namespace' must be a ROS 2 namespace"):
            Job.from_args({"scene": "name: x", "ros2_domain": 3, "ros2_namespace": bad})
    assert Job.from_args({"scene": "name: x", "ros2_domain": 3, "ros2_namespace": "/lab/arm_2"}).ros2_namespace


def test_a_request_larger_than_a_message_is_refused_before_it_is_sent(tmp_path):
    """Zenoh drops a query larger than a message unsent: twin submit waited out its timeout and blamed a busy
    service (which never saw it). It is refused here, saying the size; a scene file that large before it is read."""
    from conductor.cli.serve import Refused, _ask
    from conductor.launch import open_router
    from protocol.config import MAX_MESSAGE_SIZE

    session, _ = open_router()
    try:
        t0 = time.monotonic()
        with pytest.raises(Refused, match=r"the request is 17\.0 MiB, more than the 16 MiB") as e:
            _ask(session, "twin/x/conductor/start", {"scene": "x" * (17 * 2**20)}, "value_reply", 30.0)
        assert e.value.bad_request and time.monotonic() - t0 < 10  # (not the timeout waited out)
    finally:
        session.close()
    big = tmp_path / "big.yaml"
    big.write_text(Path(CORE).read_text() + ("# " + "x" * 1000 + "\n") * (MAX_MESSAGE_SIZE // 1000 + 10))
    r = twin("submit", str(big), "--recording", "r.mcap", "--connect", f"tcp/127.0.0.1:{free_port()}", timeout=60)
    assert r.returncode == 2 and "big.yaml" in r.stderr and "MiB" in r.stderr, r.stderr


def test_a_run_asked_of_a_stopped_service_does_not_start(tmp_path):
    """twin evaluate's Ctrl-C stops the runs going on; a run asked for just after (its caller had looked before the
    stop) was not among them and ran to its deadline. The caller's stop is now looked at as the run is taken."""
    from conductor.launch import open_router
    from conductor.service import Job, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=2.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "halt", tmp_path / "serve")
    try:
        reason: list[str] = []
        job = Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec), max_ticks=3)
        assert svc.run(job, tmp_path / "r0", lambda: reason[0] if reason else None)["ticks"] == 3
        reason.append("Ctrl-C")  # (as twin evaluate sets it, then stops the service's runs)
        svc.stop_all("Ctrl-C")
        t0 = time.monotonic()
        s = svc.run(job, tmp_path / "r", lambda: reason[0] if reason else None)
        assert s["status"] == "truncated" and "stopped by Ctrl-C" in " ".join(s["status_reasons"]), s
        assert time.monotonic() - t0 < 5  # (no agent was started for it), and its folder says so
        assert json.loads((tmp_path / "r" / "summary.json").read_text())["status_reasons"] == s["status_reasons"]
    finally:
        svc.close()
        session.close()


def test_a_run_stopped_as_it_is_taken_ends_once(tmp_path):
    """A stop right after the submit, while a worker was preparing the run: the stop finished it ("stopped before it
    started") and the client was told so, then the worker ran it anyway and wrote another summary over the first
    ("stopped at tick 0"). A run now ends once, with one summary, the client's and the folder's alike."""
    from conductor.launch import open_router
    from conductor.service import Job, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=2.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "race", tmp_path / "serve").serve()
    finished: dict[str, int] = {}
    finish = svc._finish

    def counted(entry, summary, run_dir=None):
        finished[entry.id] = finished.get(entry.id, 0) + 1
        finish(entry, summary, run_dir)

    svc._finish = counted  # type: ignore[method-assign]
    try:
        for delay in (0.0, 0.002, 0.01, 0.03, 0.06, 0.1):
            entry = svc.submit(Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec)))
            time.sleep(delay)
            svc.stop_all("the test")
            assert entry.done.wait(60), delay
            told = entry.summary
            time.sleep(0.5)  # (the second end came a little later)
            assert finished[entry.id] == 1, (delay, entry.summary["status_reasons"], told["status_reasons"])
            on_disk = json.loads((tmp_path / "serve" / entry.id / "summary.json").read_text())
            assert on_disk["status_reasons"] == told["status_reasons"] == entry.summary["status_reasons"], delay
            assert told["status"] == "truncated" and entry.state == "finished", (delay, told["status_reasons"])
    finally:
        svc.close()
        session.close()


def test_a_warm_agent_whose_model_file_changed_is_started_again(tmp_path):
    """A researcher edits their model between two runs on twin serve: the warm agent kept the code it imported, and
    the second run gave the old model's answer without a word. The pool now starts an agent again when its model's
    file changed since it started (and leaves the others, and an unchanged one, warm)."""
    from conductor.launch import open_router
    from conductor.service import Pool, kind_file

    mods = tmp_path / "mods"
    mods.mkdir()
    (mods / "labelled.py").write_text("from tests.models.simple import BallSim\n\n\nclass Labelled(BallSim):\n"
                                      "    kind = 'labelled'\n")
    env = {"PYTHONPATH": f"{mods}{os.pathsep}{ROOT}"}
    assert kind_file("labelled:Labelled", env) == mods / "labelled.py"
    assert kind_file("physics", env) is None and kind_file("nowhere:X", env) is None
    session, endpoint = open_router()
    pool = Pool("warmedit", {"sim": "labelled:Labelled", "other": "tests.models.simple:BallSim"}, endpoint,
                tmp_path / "logs", env=env)
    try:
        pids = {n: p.pid for n, p in pool.procs.procs.items()}
        assert pool.revive() == [] and {n: p.pid for n, p in pool.procs.procs.items()} == pids  # nothing changed
        stamp = (mods / "labelled.py").stat().st_mtime + 5
        os.utime(mods / "labelled.py", (stamp, stamp))  # (edited)
        assert pool.revive() == ["sim"] and pool.restarts == 1
        now = {n: p.pid for n, p in pool.procs.procs.items()}
        assert now["sim"] != pids["sim"] and now["other"] == pids["other"]
        assert not alive(pids["sim"]) and pool.procs.procs["sim"].poll() is None
        assert pool.revive() == []  # and once started again, it is warm again
    finally:
        pool.close()
        session.close()


def test_a_summary_too_large_for_one_reply_comes_trimmed_and_says_where_it_is(tmp_path):
    """A sampled run of many thousand samples: its summary (each sample's variation and folder) was over what one
    Zenoh reply carries, the reply never arrived, and the client said that nothing answered. It now comes without
    those two lists, saying where the whole summary is."""
    from conductor.launch import open_router
    from conductor.service import REPLY_LIMIT, Job, RunEntry, Service
    from protocol import codec

    session, endpoint = open_router()
    svc = Service(session, endpoint, "big", tmp_path / "serve")
    try:
        k = 90_000
        summary = {"status": "complete", "status_reasons": [], "predicates": {"in(bin, ball)": {"p": 0.5}},
                   "variations": [{"entities": {"ball": {"pose": [0.1 * i, 0.2, 0.3, 0, 0, 0, 1]}}, "sample": i,
                                   "seed": i} for i in range(k)],
                   "runs": [f"/somewhere/runs/serve/7/sample-{i:06d}" for i in range(k)]}
        svc.runs["7"] = RunEntry(id="7", job=Job(scene_text="x"), state="finished", summary=summary)
        assert len(codec.encode("status", {"fields": svc.status("7")})) > REPLY_LIMIT
        payload = svc._status_reply("7")
        assert len(payload) <= REPLY_LIMIT
        got = codec.decode("t", payload, "status").fields["summary"]
        assert got["status"] == "complete" and got["predicates"] == summary["predicates"]
        assert "variations" not in got and "runs" not in got
        assert str(tmp_path / "serve" / "7" / "summary.json") in got["trimmed"], got["trimmed"]
        svc.runs["8"] = RunEntry(id="8", job=Job(scene_text="x"), state="finished",
                                 summary={"status": "complete", "runs": ["a"]})
        assert "trimmed" not in codec.decode("t", svc._status_reply("8"), "status").fields["summary"]  # (small)
    finally:
        session.close()


@pytest.mark.slow
def test_parallel_bounds_the_runs_going_on_with_a_sampled_run_among_them(tmp_path):
    """twin serve --parallel 2: a sampled run took `parallel` ensembles of its own beside the other run's, three
    at once on a machine sized for two. Its samples now wait for a slot like any run."""
    from conductor.launch import open_router
    from conductor.service import Job, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=1.5)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "slots", tmp_path / "serve", parallel=2, max_pools=1).serve()
    text = Path(CORE).read_text()
    most = 0
    try:
        sampled = svc.submit(Job(scene_text=text, scene_file=CORE, recording=str(rec), rtf=1.0, samples=3))
        plain = svc.submit(Job(scene_text=text, scene_file=CORE, recording=str(rec), rtf=1.0))
        deadline = time.monotonic() + 180
        while not (sampled.done.is_set() and plain.done.is_set()):
            assert time.monotonic() < deadline, "the runs did not end within 180 s"
            most = max(most, sum(p.busy for ps in list(svc.pools.values()) for p in ps))
            time.sleep(0.02)
        assert plain.summary["status"] == "complete", plain.summary["status_reasons"]
        assert sampled.summary["status"] == "complete", sampled.summary.get("status_reasons")
        assert most == 2, most  # two at once (never three), and both slots used
        # --max-pools 1: one set of agents kept warm after them (the other set was kept idle too: two, each 4
        # processes, however small max_pools was)
        kept = [p for ps in svc.pools.values() for p in ps]
        assert len(kept) == 1 and not kept[0].busy, [(p.ensemble, p.busy) for p in kept]
    finally:
        svc.close()
        session.close()


def test_one_run_s_status_and_stop_from_the_command_line(service, tmp_path):
    """``twin status --run`` and ``twin stop`` address one run of a service (they were only queries a client had to
    write itself): its state while it runs, a wait for its summary from another client that Ctrl-C does not stop,
    a stop of a queued run and of the running one, and what is said for a run that is over or not there."""
    flags, run_dir = service
    rec = core_recording(tmp_path / "rec.mcap", seconds=300.0)  # (paced: it runs until it is stopped, even when
    # the clients below take seconds each on a loaded machine)
    p = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec), "--rtf",
                          "1", *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
    waiters: list[subprocess.Popen] = []
    try:
        assert p.stdout is not None
        run = p.stdout.readline().split()[1]  # "run 1 of core_scene.yaml started on the service"
        deadline = time.monotonic() + 60
        while status(flags)["running"] != [run]:
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.2)
        view = json.loads(twin("status", "--run", run, *flags, timeout=30).stdout)
        assert view["state"] == "running" and view["live"]["running"] and "summary" not in view, view
        assert json.loads(twin("status", "--run", f"0{run}", *flags, timeout=30).stdout)["run"] == run  # (03 is 3)
        r = twin("stop", *flags, timeout=30)  # a service runs many: which is said
        assert r.returncode == 2 and f"is a twin serve: name the runs to stop (running: {run})" in r.stderr, r.stderr
        queued = subprocess.Popen([sys.executable, "-m", "conductor.cli", "submit", CORE, "--recording", str(rec),
                                   *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV,
                                  cwd=ROOT)
        waiters.append(queued)
        assert queued.stdout is not None
        second = queued.stdout.readline().split()[1]
        view = json.loads(twin("status", "--run", second, *flags, timeout=30).stdout)
        assert view["state"] == "queued" and view["scene"] == "core_demo", view  # (it said "?" until it ran)
        # another client waits for the running run; Ctrl-C leaves it (the run goes on), a second one stays
        for _ in range(2):
            w = subprocess.Popen([sys.executable, "-m", "conductor.cli", "status", "--run", run, "--wait", *flags],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV, cwd=ROOT)
            waiters.append(w)
            assert w.stdout is not None and w.stdout.readline().startswith(f"run {run} of core_demo: running")
        left = ctrl_c(waiters[1], timeout=60)
        assert waiters[1].returncode == 130 and f"left run {run} going (twin stop {run} ends it)" in left, left
        assert status(flags)["running"] == [run]

        r = twin("stop", second, run, second, *flags, timeout=30)
        assert r.returncode == 0, r.stdout + r.stderr
        assert r.stdout.splitlines() == [f"run {second}: taken off the queue: it will not start",
                                         f"run {run}: stopping: it ends truncated"], r.stdout
        out, _ = waiters[2].communicate(timeout=120)
        assert waiters[2].returncode == 4 and "TRUNCATED" in out and "conductor/stop" in out, out
        out, _ = queued.communicate(timeout=120)
        assert queued.returncode == 4 and "stopped before it started" in out, out
        out, _ = p.communicate(timeout=120)
        assert p.returncode == 4 and "TRUNCATED" in out, out
    finally:
        for q in [p, *waiters]:
            if q.poll() is None:
                q.kill()
                q.communicate()
    r = twin("stop", run, *flags, timeout=30)
    assert r.returncode == 1 and f"run {run} has already finished (truncated)" in r.stderr, r.stderr
    r = twin("status", "--run", "999", *flags, timeout=30)
    assert r.returncode == 2 and "no run '999' on this service" in r.stderr, r.stderr
    r = twin("stop", "999", *flags, timeout=30)  # (no such run: bad input, as for status; it exited 1)
    assert r.returncode == 2 and "no run '999' on this service" in r.stderr, r.stderr
    for bad in ("1.0", "x", "-1"):  # (a sample's id, a word: no run of the service)
        r = twin("status", "--run", bad, *flags, timeout=30)
        assert r.returncode == 2 and "a run id is the number twin submit printed" in r.stderr, r.stderr
    r = twin("status", "--timeout", "inf", *flags, timeout=30)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr

    view = json.loads(twin("status", "--run", run, *flags, timeout=30).stdout)
    assert view["state"] == "finished" and view["summary"]["status"] == "truncated"
    assert view["summary"] == json.loads((run_dir / run / "summary.json").read_text())


def test_finished_runs_are_let_go_of_and_read_back_from_their_folder(tmp_path, monkeypatch):
    """A long-lived service held every run it had done, with its summary and events (a sampled run's samples too),
    and grew without bound. It now holds the last KEEP_FINISHED; an older one's status comes from its folder."""
    import conductor.service as service
    from conductor.launch import open_router

    monkeypatch.setattr(service, "KEEP_FINISHED", 2)
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    session, endpoint = open_router()
    svc = service.Service(session, endpoint, "letgo", tmp_path / "serve").serve()
    try:
        job = service.Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec), max_ticks=5)
        entries = []
        for i in range(4):
            entries.append(svc.submit(job))
            assert entries[-1].done.wait(120)
            if i < 2:  # the first one's client asked, then went (its summary never taken): the second's still asks
                entries[-1].followed, entries[-1].fetched = True, False
                entries[-1].asked = time.monotonic() + (-10.0 if i == 0 else 3600.0)
        sampled = svc.submit(service.Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec),
                                         max_ticks=5, samples=3))
        assert sampled.done.wait(240)
        assert sampled.samples == [] and sampled.summary["samples"] == 3  # (each sample's summary is in its folder)
        held = [e.id for e in svc.runs.values()]
        assert held == [entries[1].id, sampled.id], held
        assert svc.status()["finished"] == 5 and svc.status()["statuses"] == {entries[1].id: "truncated",
                                                                               sampled.id: "truncated"}
        old = svc.status(entries[0].id)
        assert old["state"] == "finished" and old["read_from"] == str(tmp_path / "serve" / entries[0].id /
                                                                      "summary.json")
        assert old["summary"]["ticks"] == 5 and old["summary"]["status"] == "truncated"
        with pytest.raises(ValueError, match="no run '77' on this service"):
            svc.status("77")
    finally:
        svc.close()
        session.close()


@pytest.mark.slow
def test_a_warm_agent_that_does_not_answer_is_started_again_after_its_run(tmp_path, monkeypatch):
    """A warm agent stopped (SIGSTOP) or stuck in its model kept its place in the pool: every run after failed at
    the wait for its agents, until someone resumed it. The pool now starts again, after the run, each agent the run
    found not answering (never registered, a query that timed out, taken out of the run), and the next run goes;
    one it sees stopped before a run is started again before it (the run waited out the register timeout and
    failed)."""
    from conductor.launch import open_router
    from conductor.service import Job, Pool, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=120.0)  # (the paced run below is stopped long before)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "hung", tmp_path / "serve", register_timeout=20.0).serve()
    stopped: list[int] = []
    try:
        job = Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec), max_ticks=5)
        first = svc.run(job)
        (pool,) = [p for ps in svc.pools.values() for p in ps]
        pids = {n: p.pid for n, p in pool.procs.procs.items()}
        assert first["ticks"] == 5 and first["service"]["replaced_after"] == []
        os.kill(pids["holder"], signal.SIGSTOP)  # before a run: the run waited out the register timeout for it,
        stopped.append(pids["holder"])  # and failed; the pool now sees it stopped and starts it again first
        second = svc.run(job)
        assert second["ticks"] == 5 and second["status"] != "failed", second["status_reasons"]
        assert second["service"]["restarted_agents"] == ["holder"]  # (a new process in this run)
        assert second["service"]["replaced_after"] == []
        third = svc.run(job)
        assert third["ticks"] == 5 and third["service"]["replaced_after"] == [], third["status_reasons"]
        assert third["service"]["restarted_agents"] == []
        now = {n: p.pid for n, p in pool.procs.procs.items()}
        assert now["holder"] != pids["holder"] and not alive(pids["holder"])
        assert {n: now[n] for n in now if n != "holder"} == {n: pids[n] for n in pids if n != "holder"}  # warm

        # stopped in the middle of a run: taken out of it for not answering a step, then started again
        paced = svc.submit(Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec), rtf=1.0))
        deadline = time.monotonic() + 60
        while paced.state != "running" or not any(e["kind"] == "tick" or e["kind"] == "run_start"
                                                  for e in paced.events):
            assert time.monotonic() < deadline, "the paced run never started"
            time.sleep(0.1)
        os.kill(now["holder"], signal.SIGSTOP)
        stopped.append(now["holder"])
        while not any(e["kind"] == "agent_lost" for e in paced.events):
            assert time.monotonic() < deadline + 30, paced.events[-5:]
            time.sleep(0.2)
        svc.stop_all("the test")
        assert paced.done.wait(60)
        assert paced.summary["service"]["replaced_after"] == ["holder"], paced.summary["service"]
        assert not alive(now["holder"]) and pool.procs.procs["holder"].poll() is None

        # stalled in the middle of a run, and going again before the run is over: slow, not stuck, so kept (a
        # healthy agent that missed the run's closing stop on a loaded machine was started again for nothing)
        stalled = pool.procs.procs["holder"].pid
        paced = svc.submit(Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec), rtf=1.0))
        deadline = time.monotonic() + 60
        while paced.state != "running" or not any(e["kind"] == "run_start" for e in paced.events):
            assert time.monotonic() < deadline, "the paced run never started"
            time.sleep(0.1)
        os.kill(stalled, signal.SIGSTOP)
        stopped.append(stalled)
        while not any(e["kind"] == "agent_lost" for e in paced.events):
            assert time.monotonic() < deadline + 30, paced.events[-5:]
            time.sleep(0.2)
        os.kill(stalled, signal.SIGCONT)
        svc.stop_all("the test")
        assert paced.done.wait(60)
        assert paced.summary["service"]["replaced_after"] == [], paced.summary["service"]
        again = svc.run(job)
        assert again["ticks"] == 5 and again["status_reasons"] == [
            "stopped at max_ticks 5: the source goes on (to 119.99 s)"], again["status_reasons"]
        assert again["service"]["restarted_agents"] == [] and pool.procs.procs["holder"].pid == stalled

        # stopped before a run that is itself stopped while it waits for its agents: started again all the same
        # (stopped after the pool looked at its agents for the run, or the pool would start it again first)
        stuck = pool.procs.procs["holder"].pid
        os.kill(stuck, signal.SIGSTOP)
        stopped.append(stuck)
        deadline = time.monotonic() + 60
        while svc.status()["pools"][pool.ensemble]["stopped"] != ["holder"]:  # (said in the pool's status)
            assert time.monotonic() < deadline, svc.status()["pools"]
            time.sleep(0.05)
        os.kill(stuck, signal.SIGCONT)
        revive = Pool.revive

        def revive_then_stop(self: Pool) -> list[str]:
            out = revive(self)
            os.kill(self.procs.procs["holder"].pid, signal.SIGSTOP)
            stopped.append(self.procs.procs["holder"].pid)
            return out

        monkeypatch.setattr(Pool, "revive", revive_then_stop)
        waiting = svc.submit(job)
        while waiting.state != "running":
            assert time.monotonic() < deadline, "the run never began to wait for its agents"
            time.sleep(0.05)
        # (within the 20 s it waits; the one it waits for is named, not only those that came)
        assert wait_until(lambda: svc.status(waiting.id)["live"]["agents"]["sim"]["registered"], timeout=15), \
            svc.status(waiting.id)["live"]
        live = svc.status(waiting.id)["live"]["agents"]
        assert live["holder"]["registered"] is False and live["sim"]["registered"] is True, live
        svc.stop_all("the test")
        assert waiting.done.wait(60)
        assert waiting.summary["status"] == "truncated", waiting.summary["status_reasons"]
        assert waiting.summary["service"]["replaced_after"] == ["holder"], waiting.summary["service"]
        monkeypatch.setattr(Pool, "revive", revive)
        assert svc.run(job)["ticks"] == 5
    finally:
        for pid in stopped:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        svc.close()
        session.close()


def test_a_robot_waiting_for_its_twin_finds_a_live_run_on_the_service(tmp_path):
    """`twin robot play --wait-twin` asks its ensemble's conductor whether the twin is ready; a live run submitted
    to twin serve (`--live-ensemble robot1`) has its conductor on the pool's ensemble, so the robot never found it
    and gave up (exit 1). While such a run lasts, the service answers on the robot's ensemble with the run's
    status: the robot waits until the run's agents are ready, plays, and the run interprets it."""
    from conductor.launch import open_router
    from conductor.service import Job, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "lab", tmp_path / "serve").serve()
    try:
        entry = svc.submit(Job(scene_text=Path(CORE).read_text(), scene_file=CORE, live="robot1",
                               idle_timeout=1.5))
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "robot", "play", str(rec), "--connect", endpoint,
                            "--ensemble", "robot1", "--wait-twin", "60"], capture_output=True, text=True,
                           timeout=120, env=ENV, cwd=ROOT)
        assert r.returncode == 0, r.stdout + r.stderr
        assert "sent 300 joint states" in r.stdout, r.stdout
        assert entry.done.wait(60)
    finally:
        svc.close()
        session.close()
    s = entry.summary
    assert s["status"] == "complete", s["status_reasons"]
    assert [(h["from"], h["to"], h["trigger"]) for h in s["handovers"]] == [("sim", "holder", "pick"),
                                                                            ("holder", "sim", "drop")], json.dumps(s)
    assert s["semantic_state"] == {"in(bin, ball)": True}


def test_a_robot_sees_a_live_run_on_the_service_end_early(tmp_path):
    """A live run on twin serve holds no conductor token on the robot's ensemble (that would refuse a twin of the
    robot's own there), so `twin robot play --wait-twin` never saw such a run end early and exited 0, as if the
    twin had heard the whole play. The run holds a listener token there now: cut short by its --max-ticks, the
    play goes on to its end, says that the rest reached no twin, and exits 3."""
    from conductor.launch import open_router
    from conductor.service import Job, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "lab2", tmp_path / "serve").serve()
    try:
        entry = svc.submit(Job(scene_text=Path(CORE).read_text(), scene_file=CORE, live="robot2",
                               idle_timeout=1.5, max_ticks=50))
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "robot", "play", str(rec), "--connect", endpoint,
                            "--ensemble", "robot2", "--wait-twin", "60"], capture_output=True, text=True,
                           timeout=120, env=ENV, cwd=ROOT)
        assert entry.done.wait(60)
    finally:
        svc.close()
        session.close()
    assert entry.summary["status"] == "truncated", entry.summary["status_reasons"]
    assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
    assert "sent 300 joint states" in r.stdout, r.stdout  # it played to the end
    assert "the twin of ensemble 'robot2' went away" in r.stderr and "reached no twin" in r.stderr, r.stderr


def test_a_model_the_service_cannot_find_is_the_scenes_problem(tmp_path):
    """A scene checked on the client (which has its model's module) named a module that the service's machine
    lacks: the agent exited at once and the run failed, exit 1, as if the service were at fault. It is now the
    scene's problem, at its line, exit 2, and no agent is started for it."""
    from conductor.launch import open_router
    from conductor.record import exit_code
    from conductor.service import Job, Service

    text = Path(CORE).read_text().replace('"tests.models.simple:Holder"', '"only_on_my_laptop.models:Holder"')
    assert "only_on_my_laptop" in text
    rec = core_recording(tmp_path / "rec.mcap", seconds=1.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "lost", tmp_path / "serve").serve()
    try:
        s = svc.run(Job(scene_text=text, scene_file="core_scene.yaml", recording=str(rec)))
        assert not svc.pools  # (nothing started for it)
    finally:
        svc.close()
        session.close()
    assert s["status"] == "failed" and s["bad_input"] and exit_code(s) == 2, s["status_reasons"]
    why = "\n".join(s["status_reasons"])
    assert "core_scene.yaml:6: models.holder.kind: module 'only_on_my_laptop.models' is not on the service's" in why


def test_a_compiled_model_module_on_the_service_is_found(tmp_path, monkeypatch):
    """The service looked for a model's module as a .py file only: a compiled one (a sourceless .pyc, an
    extension module) that its agents import was refused as missing. Any file or folder an import would take
    counts; a module that is nowhere is still the scene's problem."""
    from conductor.scene import parse_scene
    from conductor.service import unfound_kinds

    monkeypatch.chdir(tmp_path)
    (tmp_path / "fastarm.pyc").write_bytes(b"")
    (tmp_path / "gripkit").mkdir()  # (a namespace package: a folder without __init__.py)
    text = Path(CORE).read_text().replace('"tests.models.simple:Holder"', '"fastarm:Holder"')
    scene = parse_scene(text.replace('"tests.models.simple:Heartbeat"', '"gripkit.beat:Heartbeat"'), "s.yaml")
    assert unfound_kinds(scene) == []
    scene = parse_scene(text.replace('"fastarm:Holder"', '"fastarm_gone:Holder"'), "s.yaml")
    assert [p.key for p in unfound_kinds(scene)] == ["models.holder.kind"]


def test_serve_with_a_bad_zenoh_config_says_so_at_once(tmp_path):
    """twin serve --connect with a Zenoh setting Zenoh refuses waited for ever, taking it for a router not yet
    there; it fails at once, saying what Zenoh refused (exit 1)."""
    bad = tmp_path / "bad.json5"
    bad.write_text('{ "nonsense_key": { "x": 1 } }\n')
    r = twin("serve", "--connect", f"tcp/127.0.0.1:{free_port()}", "--config", str(bad), "--run-dir",
             str(tmp_path / "serve"), timeout=60)
    assert r.returncode == 1 and "unknown field `nonsense_key`" in r.stderr, r.stdout + r.stderr
    assert "trying again" not in r.stdout
    # an agent given the same: one line and exit 2 (a traceback; before that, a silent wait for ever)
    a = subprocess.run([sys.executable, "-m", "agents", "trivial", "--name", "x", "--connect",
                        f"tcp/127.0.0.1:{free_port()}", "--config", str(bad)], capture_output=True, text=True,
                       timeout=60, env=ENV, cwd=ROOT)
    assert a.returncode == 2 and "Zenoh refused this agent's settings" in a.stderr, a.stderr
    assert "Traceback" not in a.stderr


def test_a_warm_run_whose_agent_is_lost_before_its_first_tick_runs_again_once(tmp_path, monkeypatch):
    """A warm agent registered for a run and was gone when the run initialised it (CI, a loaded machine: one of 4
    samples failed, "model physics at tick 0: ... Lost"). Nothing of the recording had been read: the service now
    runs it again once on its pool's agents, the lost one started again, and the summary says so."""
    from conductor.core import Conductor
    from conductor.launch import open_router
    from conductor.service import Job, Service

    rec = core_recording(tmp_path / "rec.mcap", seconds=2.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "lostinit", tmp_path / "serve", register_timeout=30.0).serve()
    init = Conductor._init_model
    killed: list[int] = []

    def kill_holder_first(self: Conductor, name: str, *args: Any, **kwargs: Any) -> None:
        if name == "holder" and not killed:  # registered, and gone before it is initialised
            (pool,) = [p for ps in svc.pools.values() for p in ps]
            proc = pool.procs.procs["holder"]
            proc.kill()
            proc.wait(10)
            killed.append(proc.pid)
        init(self, name, *args, **kwargs)

    monkeypatch.setattr(Conductor, "_init_model", kill_holder_first)
    try:
        job = Job(scene_text=Path(CORE).read_text(), scene_file=CORE, recording=str(rec), max_ticks=5)
        summary = svc.run(job)
        assert killed, "the agent was never initialised"
        assert summary["status"] != "failed" and summary["ticks"] == 5, summary["status_reasons"]
        assert "Lost" in summary["service"]["first_attempt"], summary["service"]
        assert summary["service"]["restarted_agents"] == ["holder"], summary["service"]
        (pool,) = [p for ps in svc.pools.values() for p in ps]
        assert pool.procs.procs["holder"].pid != killed[0] and pool.runs == 1  # (a run taken again is one run)

        again = svc.run(job)  # (and the pool is warm again: no second try, nothing started again)
        assert again["ticks"] == 5 and "first_attempt" not in again["service"], again["service"]
        assert again["service"]["warm_runs"] == 1, again["service"]
        assert again["service"]["restarted_agents"] == [], again["service"]
    finally:
        svc.close()
        session.close()


def test_a_warm_agent_whose_link_lapsed_is_kept_once_it_is_back(tmp_path):
    """After a run, the pool asks each agent the run found not answering for its health, and keeps one that answers
    (slow, not stuck). One stopped longer than its link's 3 s lease is dropped by the router and connects again
    when it goes on: asked once, as it went on, nothing served its key, and the pool started it again for nothing.
    It is now asked again until it is back (within the probe's 5 s)."""
    from conductor.launch import open_router
    from conductor.service import Pool

    session, endpoint = open_router()
    pool = Pool("lapse", {"sim": "tests.models.simple:BallSim"}, endpoint, tmp_path / "logs")
    pid = pool.procs.procs["sim"].pid
    try:
        deadline = time.monotonic() + 60
        while pool.answering(session, {"sim"}) != {"sim"}:  # (started, and serving its keys)
            assert time.monotonic() < deadline and pool.procs.procs["sim"].poll() is None, "the agent never answered"
            time.sleep(0.2)
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(4.5)  # (past the 3 s lease: the router drops its link and what it served)
        finally:
            os.kill(pid, signal.SIGCONT)
        assert pool.answering(session, {"sim"}) == {"sim"}
        assert pool.replace({"sim"}, session) == [] and pool.procs.procs["sim"].pid == pid
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
        pool.close()
        session.close()


def test_the_recordings_a_service_keeps_are_bounded_by_their_messages(tmp_path, monkeypatch):
    """A service keeps what its runs read for the next runs: 64 recordings whatever their size, the oldest read
    first to go. It keeps the most recently used within a bound on their messages too, and a hit counts as a use."""
    from conductor import service as service_mod

    recs = [core_recording(tmp_path / f"r{i}.mcap", seconds=1.0) for i in range(3)]
    svc = object.__new__(service_mod.Service)
    svc._lock, svc._recordings = threading.Lock(), {}
    size = len(svc.recording(str(recs[0])).items)
    monkeypatch.setattr(service_mod, "KEPT_MESSAGES", 2 * size)
    first = svc.recording(str(recs[0]))
    svc.recording(str(recs[1]))
    assert svc.recording(str(recs[0])) is first  # a hit: now the most recently used
    svc.recording(str(recs[2]))  # three would pass the bound: the least recently used (r1) goes
    kept = [json.loads(k)[0] for k in svc._recordings]
    assert kept == [str(recs[0]), str(recs[2])], kept


def test_a_start_is_not_held_behind_another_starts_preparation(tmp_path, monkeypatch):
    """Zenoh runs a queryable's callbacks one at a time: a start waited while another's long scene was parsed, its
    client gave up ("no answer"), and it was queued all the same. Each start is now prepared in a thread of its
    own; a scene longer than MAX_SCENE_CHARS is refused before it is parsed."""
    from conductor.cli.serve import _ask
    from conductor.launch import open_router
    from conductor.service import MAX_SCENE_CHARS, Job, Service
    from protocol.config import ZenohOptions

    with pytest.raises(ValueError, match="a scene may be at most 1 MiB"):
        Job.from_args({"scene": "x" * (MAX_SCENE_CHARS + 1), "max_ticks": 5})
    monkeypatch.setattr(Service, "_work", lambda self: None)  # (no worker: a queued run stays queued)
    rec = core_recording(tmp_path / "rec.mcap", seconds=2.0)
    session, endpoint = open_router()
    svc = Service(session, endpoint, "svc", tmp_path / "serve").serve()
    clients = [ZenohOptions(mode="client", connect=[endpoint]).open() for _ in range(2)]
    try:
        text = Path(CORE).read_text()
        slow = text + "\nx_pad:\n" + "\n".join(f"  - [{i}, {i}, {i}]" for i in range(12000)) + "\n"  # (seconds)
        refused: list[str] = []

        def first() -> None:
            try:
                _ask(clients[0], "twin/svc/conductor/start", {"scene": slow, "recording": str(rec)}, "value_reply",
                     120.0, selector="?timeout=120")
            except Exception as e:  # (its unknown key: refused, after the parse)
                refused.append(str(e))

        t = threading.Thread(target=first)
        t.start()
        time.sleep(0.2)  # (its parse going on)
        t0 = time.monotonic()
        answer = _ask(clients[1], "twin/svc/conductor/start", {"scene": text, "recording": str(rec)}, "value_reply",
                      20.0, selector="?timeout=20").value
        took = time.monotonic() - t0
        t.join(120)
        assert refused and "x_pad" in refused[0], refused
        assert svc.runs[str(answer["run"])].state == "queued"
        assert took < 0.5 * svc_parse_s(slow), took  # (it did not wait for the other's parse to end)
    finally:
        for c in clients:
            c.close()
        svc.close()
        session.close()


def svc_parse_s(text: str) -> float:
    """How long parsing ``text`` as a scene takes here, now (it is refused: only the time counts)."""
    from conductor.scene import parse_scene

    t0 = time.monotonic()
    with contextlib.suppress(Exception):
        parse_scene(text, "x.yaml")
    return time.monotonic() - t0
