"""Faults across hosts: an agent's cable pulled mid-run, and the router restarted mid-run.

::

    router ──┬── conductor      every box is its own network namespace (bench/netns.py), joined by
             ├── sim (main)     a bridge; the test process watches through its own link
             ├── holder   <──── its cable is pulled for a few seconds while it owns ball.pose
             ├── grip
             └── beat

The run replays tests/core_scene.yaml at real time so the faults land mid-run; each test ends by reading
the complete run log (MCAP) the conductor wrote.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from bench.netns import EventWatch, python_cmd, wait_exit, wait_tokens
from conductor.runlog import read_metadata, read_run_log
from conductor.scene import load_scene
from protocol.config import ZenohOptions
from protocol.keys import Keys
from recordings.simple import core_recording

from .test_integration import check_invariant, owner_timeline

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "tests" / "core_scene.yaml"
ENSEMBLE = "faults"
PORT = 7447


class Deployment:
    """Router, conductor and one host per model of SCENE, plus an observer session of the test."""

    def __init__(self, lan, tmp_path: Path, mode: str = "client", seconds: float = 9.0, live: bool = False):
        self.lan, self.tmp = lan, tmp_path
        self.scene = load_scene(SCENE)
        self.rec = core_recording(tmp_path / "rec.mcap", seconds=seconds, grip=(0.8, seconds - 2.5))
        self.router_host = lan.add_host("router")
        self.conductor_host = lan.add_host("conductor")
        self.model_hosts = {name: lan.add_host(name) for name in self.scene.models}
        robot_host = lan.add_host("robot") if live else None
        lan.attach_root()
        lan.wait_reachable(self.conductor_host, self.router_host)
        self.zen = ["--connect", f"tcp/router:{PORT}", "--ensemble", ENSEMBLE]
        if mode == "peer":  # direct links between processes; the router is only met for discovery
            self.zen += ["--mode", "peer", "--listen", "tcp/0.0.0.0:0"]
        self.routers = 0
        self.start_router()
        for name, spec in self.scene.models.items():
            self.model_hosts[name].spawn(name, python_cmd("agent", spec.kind, "--name", name, *self.zen))
        self.observer = ZenohOptions(mode="client", connect=[f"tcp/{self.router_host.ip}:{PORT}"]).open()
        self.events = EventWatch(self.observer, ENSEMBLE)
        self.keys = Keys(ENSEMBLE)
        wait_tokens(self.observer, self.keys.alive_all, self.scene.models, timeout=60)
        self.run_log = tmp_path / "run.mcap"
        self.summary_path = tmp_path / "summary.json"
        source = ["--live", "--idle-timeout", "3"] if live else ["--recording", str(self.rec), "--rtf", "1"]
        self.conductor = self.conductor_host.spawn("conductor", python_cmd(
            "-v", "conductor", str(SCENE), *source, "--run-log", str(self.run_log),
            "--summary", str(self.summary_path), *self.zen))
        if robot_host is not None:  # the robot as its own host, publishing the recording live once the twin is up
            robot_host.spawn("robot", python_cmd("robot", "play", str(self.rec), "--wait-twin", "60", *self.zen))

    def start_router(self):
        self.routers += 1
        return self.router_host.spawn(f"router-{self.routers}", python_cmd("router", "--listen", f"tcp/0.0.0.0:{PORT}"))

    def stop_router(self) -> None:
        p = self.lan.procs.procs[f"router-{self.routers}"]
        p.terminate()
        wait_exit(p, 10)

    def finish(self, timeout: float = 90.0) -> dict:
        rc = wait_exit(self.conductor, timeout, self.tmp / "hosts" / "agent-conductor.log")
        assert self.summary_path.exists(), f"conductor exited {rc} without a summary"
        return json.loads(self.summary_path.read_text())

    def log_events(self) -> list[tuple[str, dict]]:
        return [(k.rsplit("/", 1)[-1], m["data"]) for k, _, m in read_run_log(self.run_log)
                if isinstance(m, dict) and "/event/_conductor/" in k and not k.endswith("/trigger")]

    def close(self) -> None:
        self.events.close()
        self.observer.close()


@pytest.fixture
def deploy(lan, tmp_path):
    made = []

    def make(**kw):
        d = Deployment(lan, tmp_path, **kw)
        made.append(d)
        return d

    try:
        yield make
    finally:
        for d in made:
            d.close()


def assert_complete_log(d: Deployment, summary: dict) -> None:
    """The run log is closed (summary metadata), holds every tick of the main model and keeps one owner."""
    assert "twin.summary" in read_metadata(d.run_log)
    changes, states, _ = owner_timeline(d.run_log)
    check_invariant(d.scene, changes, states)
    sim_ticks = {s["tick"] for s in states if s["model"] == "sim"}
    assert sim_ticks == set(range(summary["ticks"])), "main-model states missing from the run log"
    assert summary["ticks"] >= 900  # the recording played to its end (9 s at 100 Hz)


@pytest.mark.slow
def test_cut_agent_link_falls_back_then_rejoins(deploy):
    """Pulling the holder's cable while it owns the ball hands the ball back to the main model; when the
    cable returns the holder registers again under its name; the run log shows both transitions."""
    d = deploy(mode="client", seconds=12.0)  # room for the 3 s lease, 2 s unplugged and the way back before the end
    d.events.wait_for("handover", lambda e: e["trigger"] == "pick", timeout=60)
    time.sleep(0.3)
    holder = d.model_hosts["holder"]
    holder.link(False)
    try:
        lost = d.events.wait_for("agent_lost", lambda e: e["model"] == "holder", timeout=15)
        time.sleep(2.0)  # stay unplugged a while after the loss was noticed
    finally:
        holder.link(True)
    rejoin = d.events.wait_for("rejoin", lambda e: e["model"] == "holder", timeout=30)
    s = d.finish()
    assert s["errors"] == [], s["errors"]
    assert rejoin["tick"] > lost["tick"]
    hs = [(h["from"], h["to"], h["trigger"]) for h in s["handovers"]]
    assert hs == [("sim", "holder", "pick"), ("holder", "sim", "fallback:holder lost")]
    assert s["semantic_state"] == {"in(bin, ball)": True}  # the ball fell from where the holder had it
    assert s["models"]["holder"]["alive"] is True
    kinds = [k for k, _ in d.log_events()]
    assert kinds == ["run_start", "handover", "agent_lost", "handover", "rejoin", "run_end"], kinds
    assert_complete_log(d, s)
    # after the rejoin the holder is stepped again: its outputs go on past the rejoin tick
    holder_ticks = [m["tick"] for k, _, m in read_run_log(d.run_log) if k.endswith("/out/holder/holding")]
    assert max(holder_ticks) > rejoin["tick"] and min(holder_ticks) < lost["tick"]


def _restart_router_mid_run(d: Deployment) -> None:
    d.events.wait_for("handover", lambda e: e["trigger"] == "pick", timeout=60)
    time.sleep(0.3)
    d.stop_router()
    time.sleep(1.5)
    d.start_router()
    # every process finds the new router by itself: a client of that router sees all their tokens again
    wait_tokens(d.observer, d.keys.alive_all, [*d.scene.models, "_conductor"], timeout=15)


def _run_through_router_restart(deploy, mode: str) -> list[str]:
    """Restart the router mid-run; the run completes as if nothing happened (same handovers and
    outcome, a complete run log). Returns the conductor's own events in the run log."""
    d = deploy(mode=mode)
    _restart_router_mid_run(d)
    s = d.finish()
    assert s["errors"] == [], s["errors"]
    hs = [(h["from"], h["to"], h["trigger"]) for h in s["handovers"]]
    assert hs == [("sim", "holder", "pick"), ("holder", "sim", "drop")]
    assert s["semantic_state"] == {"in(bin, ball)": True}
    assert_complete_log(d, s)
    if mode == "client":  # the pause is said: a replay loses nothing by it (a live robot's input would be lost)
        notes = [n for n in s.get("input_notes", []) if n.startswith("the conductor lost its network for")]
        assert len(notes) == 1 and notes[0].endswith("the replay paused meanwhile and went on where it was"), s
        assert s["status"] == "complete", s["status_reasons"]
    return [k for k, _ in d.log_events()]


@pytest.mark.slow
def test_router_restart_in_a_live_run_says_the_robot_s_input_was_lost(deploy):
    """A live run through the same restart: what the robot published while the conductor was cut off reached no
    one, and the summary only blamed the robot for its gap (or for going quiet). The outage is now a reason the
    run is degraded, in the conductor's words."""
    d = deploy(mode="client", live=True)
    _restart_router_mid_run(d)
    s = d.finish()
    assert s["status"] == "degraded", s
    said = [r for r in s["status_reasons"] if r.startswith("the conductor lost its network for")]
    assert len(said) == 1 and said[0].endswith("what the robot sent meanwhile did not reach the twin"), s


@pytest.mark.slow
def test_a_network_that_never_comes_back_fails_the_run(deploy):
    """The router gone for good under a client-mode conductor: it said "network restored ... missing: every agent"
    every 30 s while the network was still down, stepped a tick with nobody to answer, and waited again, until its
    deadline ended the run 'truncated' minutes later. The run now fails once the network has not come back within
    its timeout, and says so."""
    from bench.netns import wait_exit

    d = deploy(mode="client")
    d.events.wait_for("handover", lambda e: e["trigger"] == "pick", timeout=60)
    d.stop_router()
    rc = wait_exit(d.conductor, 120, d.tmp / "hosts" / "agent-conductor.log")
    s = json.loads(d.summary_path.read_text())
    assert rc == 1 and s["status"] == "failed", (rc, s["status"], s["status_reasons"])
    said = s["status_reasons"] + s["errors"]
    assert any("the conductor's network did not come back within 30 s" in r for r in said), s


@pytest.mark.slow
def test_router_restart_peer_mode_run_completes(deploy):
    """With processes in peer mode (direct links, the router for discovery, as rmw_zenoh deploys), a
    router restart loses nobody, every process reconnects to the new router, and the run completes."""
    kinds = _run_through_router_restart(deploy, "peer")
    assert "agent_lost" not in kinds and kinds[0] == "run_start" and kinds[-1] == "run_end", kinds


@pytest.mark.slow
def test_router_restart_client_mode_run_completes(deploy):
    """With every process a client of the router, a router restart cuts the conductor off from all agents
    at once: it waits for the network instead of declaring them dead, and the run completes."""
    kinds = _run_through_router_restart(deploy, "client")
    assert kinds == ["run_start", "handover", "network_lost", "network_restored", "handover", "run_end"], kinds
