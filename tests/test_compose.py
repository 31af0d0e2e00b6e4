"""compose.yaml, proved without a container engine: every service runs its own ``command`` with its own
``environment`` in its own network namespace (bench/netns.py), reaching the others only over the emulated
LAN by their service names, and the twin's interpretation equals the single-host run's.

::

    router ── conductor ── robot ── <one host per model>        (>= 4 hosts, one bridge)

Also here: two twins with different ``--ensemble`` names share one router without seeing each other.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import pytest
import yaml

from bench.netns import python_cmd, wait_exit
from conductor.runlog import read_run_log
from conductor.scene import load_scene
from recordings.simple import core_recording

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "compose.yaml"

# The scene and recording this test deploys: compose.yaml's own ball_drop deployment (its model services
# physics, grasp_monitor and in_hand run verbatim). With another scene, each of its models gets a copy of
# the first model service (load_services).
SCENE = "scenes/ball_drop.yaml"
RECORDING: str | None = "recordings/ball_drop_00.mcap"

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")


def interpolate(value, env: dict):
    """Compose's variable substitution: ``${VAR}``, ``${VAR:-default}`` (recursively in lists/maps)."""
    if isinstance(value, str):
        return _VAR.sub(lambda m: env.get(m.group(1)) or (m.group(2) or ""), value)
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    return value


def service_env(svc: dict) -> dict:
    env = svc.get("environment") or {}
    if isinstance(env, list):  # ["KEY=value", ...]
        env = dict(item.split("=", 1) for item in env)
    return {str(k): str(v) for k, v in env.items()}


def command_line(svc: dict) -> list[str]:
    cmd = svc["command"]
    cmd = cmd.split() if isinstance(cmd, str) else list(cmd)
    assert cmd[0] == "twin", f"service command must run the image's `twin` program: {cmd}"
    return python_cmd(*cmd[1:])


def load_services(variables: dict, scene) -> dict[str, dict]:
    """compose.yaml's services after substitution, with the model services matched to ``scene``.

    A model service is one whose command is ``twin agent KIND --name NAME``. If their names are the
    scene's models they run as written; otherwise (the core scene) each scene model gets a copy of the
    first model service with its KIND and NAME, everything else unchanged.
    """
    doc = yaml.safe_load(COMPOSE.read_text())
    services = {name: interpolate(svc, variables) for name, svc in doc["services"].items()}
    models = {n: s for n, s in services.items() if list(s["command"][:2]) == ["twin", "agent"]}
    assert models, "compose.yaml has no `twin agent` service"
    if set(models) != set(scene.models):
        template = next(iter(models.values()))
        for n in models:
            del services[n]
        for name, spec in scene.models.items():
            svc = json.loads(json.dumps(template))
            cmd = svc["command"]
            cmd[2] = spec.kind
            cmd[cmd.index("--name") + 1] = name
            services[name] = svc
    return services


def start_order(services: dict) -> list[str]:
    """Dependencies first (compose's depends_on), then the file's order."""
    done: list[str] = []

    def visit(n, stack=()):
        if n in done:
            return
        assert n not in stack, f"depends_on cycle through {n}"
        deps = services[n].get("depends_on") or []
        for d in (deps if isinstance(deps, list) else list(deps)):
            visit(d, stack + (n,))
        done.append(n)

    for n in services:
        visit(n)
    return done


def single_host_reference(tmp_path: Path, scene: str, rec: Path) -> dict:
    """The same scene and recording replayed by `twin run` on one host (loopback, embedded router)."""
    out = tmp_path / "reference.json"
    r = subprocess.run(python_cmd("run", scene, "--recording", str(rec), "--summary", str(out),
                                  "--run-dir", str(tmp_path / "reference")),
                       capture_output=True, text=True, timeout=180, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    summary = json.loads(out.read_text()) if out.exists() else {}
    # (on a loaded machine the free-running heartbeat, which no handover reads, may fall behind its 20 Hz: the
    # reference is then rightly degraded for that alone, and its interpretation is still the reference)
    beat_only = [w for w in summary.get("status_reasons", []) if w.startswith("model beat (free-running")]
    assert r.returncode == 0 or (r.returncode == 3 and beat_only and summary["status_reasons"] == beat_only), \
        r.stdout[-2000:] + r.stderr[-2000:]
    return summary


def handover_story(summary: dict) -> list[tuple]:
    return [(h["entity"], h["attribute"], h["from"], h["to"], h["trigger"]) for h in summary["handovers"]]


def explain(*summaries: dict) -> list[dict]:
    """What to print when two runs disagree: each run's outcome, handovers (with ticks), errors and models."""
    return [{k: s.get(k) for k in ("semantic_state", "ticks", "rtf", "errors", "models")}
            | {"handovers": [(h["tick"], h["trigger"], h["from"], h["to"]) for h in s["handovers"]]}
            for s in summaries]


@pytest.mark.slow
def test_compose_services_run_the_scene_across_hosts(lan, tmp_path):
    """Each compose service on its own namespace host: the live twin's outcome equals the replay's."""
    rec = ROOT / RECORDING if RECORDING else core_recording(tmp_path / "rec.mcap", seconds=3.0)
    run_dir = tmp_path / "runs"
    run_dir.mkdir()
    variables = {"TWIN_SCENE": SCENE, "TWIN_RECORDING": str(rec), "TWIN_RUN_DIR": str(run_dir),
                 "TWIN_ENSEMBLE": "compose"}
    scene = load_scene(ROOT / SCENE)
    services = load_services(variables, scene)
    assert {"router", "conductor", "robot"} <= set(services)
    hosts = {name: lan.add_host(name) for name in services}
    assert len(hosts) >= 4
    procs = {}
    for name in start_order(services):
        svc = services[name]
        procs[name] = hosts[name].spawn(name, command_line(svc), env=service_env(svc), cwd=str(ROOT))
        if name == "router":
            lan.wait_reachable(hosts["conductor"], hosts["router"])
    logs = lan.logdir
    rc = wait_exit(procs["conductor"], 150, logs / "agent-conductor.log")
    conductor_log = (logs / "agent-conductor.log").read_text(errors="replace")
    assert rc == 0, conductor_log[-3000:]
    assert wait_exit(procs["robot"], 30, logs / "agent-robot.log") == 0
    robot_log = (logs / "agent-robot.log").read_text()
    assert "sent " in robot_log and " 0 joint states" not in robot_log, robot_log
    live = json.loads((run_dir / "compose" / "summary.json").read_text())  # (runs/<ensemble>/)
    assert live["errors"] == [], live["errors"]
    assert live["ensemble"] == "compose"
    # the robot's stream reached the twin across the LAN: lag figures in the summary
    lag = live["lag"]
    print(f"\nlive lag (ball_drop, compose services on namespace hosts): {lag}, rtf {live['rtf']}")
    assert lag["samples"] > 100 and lag["p50_ms"] >= 0 and lag["p99_ms"] >= lag["p50_ms"]
    # every model worked from its own host: service models through their steps, the others through outputs
    service = {n for n, spec in scene.models.items() if spec.step == "service"}
    assert all(live["models"][n]["steps"] > 0 for n in service), live["models"]
    publishers = {k.split("/")[3] for k, _, _ in read_run_log(run_dir / "compose" / "run.mcap") if "/out/" in k}
    assert set(scene.models) <= publishers | service, publishers
    # the same interpretation as a single-host replay
    ref = single_host_reference(tmp_path, SCENE, rec)
    assert live["semantic_state"] == ref["semantic_state"], explain(live, ref)
    assert handover_story(live) == handover_story(ref)
    assert handover_story(live), "the scenario hands the ball over: an empty story proves nothing"
    assert (run_dir / "compose" / "run.mcap").stat().st_size > 0


@pytest.mark.slow
def test_two_ensembles_share_a_router_without_crosstalk(lan, tmp_path):
    """Two twins with the same model names but different --ensemble names run at once on one router; each
    sees only its own traffic (its run log holds only its own keys and its own models' outputs)."""
    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    base = (ROOT / "tests" / "core_scene.yaml").read_text()
    scenes = {"alpha": tmp_path / "alpha.yaml", "beta": tmp_path / "beta.yaml"}
    for ens, path in scenes.items():  # identical scenes but for a label the sim model echoes
        text = base.replace("label: hello", f"label: from-{ens}")
        assert text != base
        path.write_text(text)
    router = lan.add_host("router")
    sites = {ens: lan.add_host(f"site-{ens}") for ens in scenes}
    router.spawn("router", python_cmd("router", "--listen", "tcp/0.0.0.0:7447"))
    lan.wait_reachable(sites["alpha"], router)
    scene = load_scene(scenes["alpha"])
    conductors = {}
    for ens, host in sites.items():
        zen = ["--connect", "tcp/router:7447", "--ensemble", ens]
        for name, spec in scene.models.items():
            host.spawn(f"{ens}-{name}", python_cmd("agent", spec.kind, "--name", name, *zen))
        conductors[ens] = host.spawn(f"{ens}-conductor", python_cmd(
            "conductor", str(scenes[ens]), "--recording", str(rec), "--rtf", "1", "--run-log",
            str(tmp_path / f"{ens}.mcap"), "--summary", str(tmp_path / f"{ens}.json"), *zen))
    windows = {}
    for ens, p in conductors.items():
        assert wait_exit(p, 120, lan.logdir / f"agent-{ens}-conductor.log") == 0
        s = json.loads((tmp_path / f"{ens}.json").read_text())
        assert s["errors"] == [] and s["semantic_state"] == {"in(bin, ball)": True}
        assert [h[4] for h in handover_story(s)] == ["pick", "drop"]
        # no model was stepped by the other twin's step broadcasts
        assert s["models"]["sim"]["steps"] == s["ticks"]
        assert s["models"]["holder"]["steps"] == (s["ticks"] + 1) // 2
        keys, labels, stamps = set(), set(), []
        for key, t_ns, msg in read_run_log(tmp_path / f"{ens}.mcap"):
            keys.add(key)
            stamps.append(t_ns)
            if key.endswith("/out/sim/label"):
                labels.add(msg["value"])
        assert all(k.startswith(f"twin/{ens}/") for k in keys), sorted(keys)[:5]
        assert labels == {f"from-{ens}"}
        windows[ens] = (min(stamps), max(stamps))
    # the two runs overlapped in time on the same router
    (a0, a1), (b0, b1) = windows.values()
    assert a0 < b1 and b0 < a1


def test_a_second_twin_of_the_file_joins_the_first_router_and_writes_its_own_log():
    """The recipe for a second twin (docs/deployment.md): its services join the router TWIN_ROUTER names, on their
    own ensemble, and its conductor writes under runs/<ensemble>/ (both twins wrote /runs/run.mcap, and every
    service joined the file's own router, whatever was set)."""
    doc = yaml.safe_load(COMPOSE.read_text())
    # (TWIN_CONNECT exported on the host, for the twin's own commands there, is not what the containers join)
    first = {n: interpolate(s, {"TWIN_CONNECT": "tcp/127.0.0.1:7447"}) for n, s in doc["services"].items()}
    second = {n: interpolate(s, {"TWIN_ENSEMBLE": "lab2", "TWIN_ROUTER": "tcp/10.0.0.7:7447"})
              for n, s in doc["services"].items()}
    for name, svc in second.items():
        if name != "router":
            assert service_env(svc)["TWIN_CONNECT"] == "tcp/10.0.0.7:7447", name
            assert service_env(svc)["TWIN_ENSEMBLE"] == "lab2"
            assert service_env(first[name])["TWIN_CONNECT"] == "tcp/router:7447"
    logs = [next(c for c in s["conductor"]["command"] if c.endswith("run.mcap")) for s in (first, second)]
    assert logs == ["/runs/ball_drop/run.mcap", "/runs/lab2/run.mcap"]
