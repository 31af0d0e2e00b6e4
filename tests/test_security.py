"""A twin on a shared network: mutual TLS on every link, access control generated from the scene.

::

    router (mTLS + twin acl) ── conductor, sim, holder, grip, beat     each with its own certificate
                             ── viewer                                 read-only identity (the test)
                             ── rogue: a valid certificate of model "grip" trying to write sim's keys
                             ── mallory: a certificate of the right CA but an identity the scene never names
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.netns import EventWatch, wait_exit, wait_tokens
from conductor.launch import AgentProcs, agent_command, free_port
from conductor.runlog import read_run_log
from conductor.scene import load_scene
from protocol import codec
from protocol.config import ZenohOptions
from protocol.keys import Keys
from protocol.security import acl_config, make_certs

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
SCENE = ROOT / "tests" / "core_scene.yaml"
ENSEMBLE = "sec"
FORGED_POSE = [9.0, 9.0, 9.0, 0.0, 0.0, 0.0, 1.0]
ROUTER = [sys.executable, "-m", "conductor.cli", "router"]  # with access control it logs every denial


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """A CA with certificates for the scene's identities (+ mallory), and a foreign CA's certificate."""
    d = tmp_path_factory.mktemp("pki")
    scene = load_scene(SCENE)
    names = ["router", "conductor", "robot", "viewer", "mallory", *scene.models]
    certs = make_certs(d / "ours", names)
    foreign = make_certs(d / "foreign", ["viewer"])
    return {"ca": str(d / "ours" / "ca.pem"), "certs": {n: (str(c), str(k)) for n, (c, k) in certs.items()},
            "foreign": {n: (str(c), str(k)) for n, (c, k) in foreign.items()}}


def tls_args(pki, name: str) -> list[str]:
    cert, key = pki["certs"][name]
    return ["--tls-ca", pki["ca"], "--tls-cert", cert, "--tls-key", key]


def client(endpoint: str, ca: str | None, cert_key: tuple[str, str] | None, wait_ms: int = 1500):
    """A client session that gives up after ``wait_ms`` instead of retrying forever (raises then)."""
    opts = ZenohOptions(mode="client", connect=[endpoint], tls_ca=ca,
                        tls_cert=cert_key[0] if cert_key else None, tls_key=cert_key[1] if cert_key else None,
                        extra={"connect/timeout_ms": wait_ms, "connect/exit_on_failure": True})
    return opts.open()


def start_router(procs: AgentProcs, pki, port: int, acl: Path | None = None):
    args = ["--listen", f"tls/127.0.0.1:{port}", *tls_args(pki, "router")] + (["--config", str(acl)] if acl else [])
    return procs.spawn("router", ROUTER + args)


def wait_router(pki, endpoint: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            client(endpoint, pki["ca"], pki["certs"]["viewer"], wait_ms=500).close()
            return
        except Exception:
            if time.monotonic() > deadline:
                raise


@pytest.mark.slow
def test_only_clients_with_ca_signed_certificates_connect(tmp_path, pki):
    """With mutual TLS on the router, a client connects only with a certificate signed by the twin's CA."""
    procs = AgentProcs(tmp_path / "logs")
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    try:
        start_router(procs, pki, port)
        wait_router(pki, endpoint)
        ok = client(endpoint, pki["ca"], pki["certs"]["viewer"])  # the positive control
        assert len(list(ok.info.routers_zid())) == 1
        ok.close()
        with pytest.raises(Exception):  # noqa: B017 (any refusal of the link will do)  server-authenticated TLS only: sends no client certificate
            client(endpoint, pki["ca"], None)
        with pytest.raises(Exception):  # noqa: B017  a certificate of another CA
            client(endpoint, pki["ca"], pki["foreign"]["viewer"])
        with pytest.raises(Exception):  # noqa: B017  trusting another CA: the router's certificate is refused
            client(endpoint, str(Path(pki["foreign"]["viewer"][0]).parent / "ca.pem"), pki["foreign"]["viewer"])
        with pytest.raises(Exception):  # noqa: B017  plain TCP to the TLS port
            client(f"tcp/127.0.0.1:{port}", None, None)
    finally:
        procs.stop()
    log = (tmp_path / "logs" / "agent-router.log").read_text(errors="replace")
    assert "no certificates" in log or "certificate" in log.lower(), log[-2000:]


def test_acl_generated_from_the_scene():
    """Only model <id> may write state/<id> (and done, out, event of <id>); only the conductor ownership."""
    acl = acl_config(load_scene(SCENE).models, ENSEMBLE)
    k = Keys(ENSEMBLE)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    pol = {p["id"]: p for p in acl["policies"]}
    subj = {s["id"]: s for s in acl["subjects"]}

    def writes(policy: str) -> set[str]:
        return {ke for rid in pol[policy]["rules"] for ke in rules[rid]["key_exprs"]
                if "put" in rules[rid]["messages"] and rules[rid]["flows"] == ["ingress"]}

    assert k.ownership in writes("conductor") and k.clock in writes("conductor")
    for m in ("sim", "holder", "grip", "beat"):
        assert subj[f"model-{m}"]["cert_common_names"] == [m]
        w = writes(f"model-{m}")
        assert k.state(m) in w and k.done(m) in w
        assert not any(k.state(o) in w or k.done(o) in w for o in ("sim", "holder", "grip", "beat") if o != m)
        assert k.ownership not in w and k.clock not in w
    assert writes("viewer") == set()

    def asks(policy: str) -> set[str]:
        return {ke for rid in pol[policy]["rules"] for ke in rules[rid]["key_exprs"]
                if rules[rid]["messages"] == ["query"] and rules[rid]["flows"] == ["ingress"]}

    # the robot's program may fire the scene's service triggers; a viewer and the models may not
    assert k.conductor("trigger/*") in asks("robot")
    assert not any("trigger" in ke for p in ("viewer", "model-sim") for ke in asks(p))


def test_twin_certs_checks_everything_before_writing_and_says_what_it_replaced(tmp_path):
    """A bad name or SAN leaves no folder half written (a new CA and four certificates were there, exit 2); a SAN
    that looks like an address but is none is refused (999.1.1.1 went in as a DNS name); certificates made again
    say so; after --new-ca the ones the old CA signed, which no longer verify, are named."""
    from cryptography import x509

    def certs(*args):
        return subprocess.run([sys.executable, "-m", "conductor.cli", "certs", *args], capture_output=True, text=True,
                              timeout=60, env=ENV, cwd=ROOT)

    for bad, said in ((["--names", "../evil"], "invalid certificate name '../evil'"),
                      (["--san", "999.1.1.1"], "--san '999.1.1.1': neither an IP address nor a DNS name")):
        r = certs(str(tmp_path / "bad"), *bad)
        assert r.returncode == 2 and said in r.stderr, r.stderr
        assert not (tmp_path / "bad").exists()
    d = tmp_path / "pki"
    r = certs(str(d), "--names", "grip", "--san", "10.0.0.5,robot.lab")
    assert r.returncode == 0 and "(replaced)" not in r.stdout, r.stdout + r.stderr
    san = x509.load_pem_x509_certificate((d / "grip.pem").read_bytes()).extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert "robot.lab" in san.get_values_for_type(x509.DNSName)
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1", "10.0.0.5"]
    r = certs(str(d), "--new-ca")
    assert r.returncode == 0 and "replacing the one there" in r.stdout and "(replaced)" in r.stdout, r.stdout
    assert "grip.pem in" in r.stderr and "no longer verify" in r.stderr, r.stderr


def test_a_model_named_as_a_part_of_the_deployment_gets_no_certificate_or_rights():
    """A model named robot shared the robot's certificate name: the access control gave that name both subjects'
    rights, so the model could publish telemetry (and one named conductor, ownership and steps). The names are
    refused by the scene checker, acl_config and default_identities; a key chunk ending in a newline too (``$``
    matched before it)."""
    from protocol.keys import check_name
    from protocol.security import default_identities

    for name in ("robot", "conductor", "viewer", "router"):
        with pytest.raises(ValueError, match="would share its rights"):
            acl_config(["physics", name], ENSEMBLE)
        with pytest.raises(ValueError, match="would share its rights"):
            default_identities(["physics", name])
    with pytest.raises(ValueError, match="would share its rights"):  # (a conductor given another certificate name)
        acl_config(["physics", "boss"], ENSEMBLE, conductor="boss")
    for name in ("physics\n", "lab\n"):
        with pytest.raises(ValueError, match="invalid"):
            check_name("model", name)


@pytest.mark.slow
def test_rogue_with_valid_certificate_cannot_write_other_models_keys(tmp_path, pki):
    """Under TLS + the scene's access control, a client holding model grip's valid certificate cannot
    publish sim's state or step results, the ownership map, nor answer sim's queries or stop the run;
    an unknown identity cannot even listen. The run's map and outcome stay intact; the router logs the
    denials, and the rogue's writes to its own keys do arrive (it was connected all along)."""
    scene = load_scene(SCENE)
    acl = tmp_path / "acl.json5"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "acl", str(SCENE), "--out", str(acl),
                        "--ensemble", ENSEMBLE], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=60)
    assert r.returncode == 0, r.stderr
    from recordings.simple import core_recording

    rec = core_recording(tmp_path / "rec.mcap", seconds=3.0)
    procs = AgentProcs(tmp_path / "logs")
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    keys = Keys(ENSEMBLE)
    sessions = []
    try:
        start_router(procs, pki, port, acl)
        wait_router(pki, endpoint)
        for name, spec in scene.models.items():
            procs.spawn(name, agent_command(spec.kind, name, endpoint, ENSEMBLE, tls_args(pki, name)))
        viewer = client(endpoint, pki["ca"], pki["certs"]["viewer"])
        sessions.append(viewer)
        seen = []
        viewer_sub = viewer.declare_subscriber(keys.everything, lambda s: seen.append(
            (str(s.key_expr), s.payload.to_bytes())))
        events = EventWatch(viewer, ENSEMBLE)
        wait_tokens(viewer, keys.alive_all, scene.models, timeout=60)
        summary = tmp_path / "summary.json"
        conductor = procs.spawn("conductor", [sys.executable, "-m", "conductor.cli", "conductor", str(SCENE),
                                              "--recording", str(rec), "--rtf", "1", "--run-log",
                                              str(tmp_path / "run.mcap"), "--summary", str(summary),
                                              "--connect", endpoint, "--ensemble", ENSEMBLE,
                                              *tls_args(pki, "conductor")])
        rogue = client(endpoint, pki["ca"], pki["certs"]["grip"])
        mallory = client(endpoint, pki["ca"], pki["certs"]["mallory"])
        sessions += [rogue, mallory]
        mallory_zid = str(mallory.info.zid())
        mallory_seen = []
        mallory.declare_subscriber(keys.everything, lambda s: mallory_seen.append(codec.unpack(s.payload.to_bytes())))
        ticks = []
        for key in (keys.step_all, f"{keys.step_all}/**"):  # the broadcast, and the messages addressed to models
            rogue.declare_subscriber(key, lambda s: ticks.append(codec.unpack(s.payload.to_bytes())["tick"]))

        def impersonate(query):  # answers sim's queries if the router let this queryable through
            with query:
                query.reply(query.key_expr, b"forged")

        rogue.declare_queryable(keys.model_all("sim"), impersonate)
        events.wait_for("run_start", timeout=60)
        stop_replies = []
        deadline = time.monotonic() + 1.5
        n = 0
        while time.monotonic() < deadline:
            tick = ticks[-1] + 1 if ticks else 0
            rogue.put(keys.state("sim"), codec.encode("state", model="sim", tick=tick, t=tick / 100,
                                                      values={"ball": {"pose": FORGED_POSE}}))
            rogue.put(keys.done("sim"), codec.pack({"v": 1, "type": "step_reply", "tick": tick, "status": "ok",
                                                    "state": {"ball": {"pose": FORGED_POSE}}, "outputs": {},
                                                    "events": []}))
            rogue.put(keys.ownership, codec.encode("ownership", version=99, tick=tick, t=0.0, change=None,
                                                   owners={"ball": {"pose": "grip"}, "bin": {"pose": "grip"}}))
            rogue.put(keys.out("grip", "rogue_marker"), codec.encode("out", model="grip", name="rogue_marker",
                                                                      tick=tick, t=0.0, value=n))
            mallory.put(keys.state("sim"), codec.encode("state", model="sim", tick=tick, t=0.0,
                                                        values={"ball": {"pose": FORGED_POSE}}))
            n += 1
            time.sleep(0.02)
        for reply in rogue.get(keys.conductor("stop"), payload=codec.encode("stop", reason="rogue"), timeout=1.0):
            stop_replies.append(reply.ok is not None)
        # grip's certificate registers as model sim: on sim's key the router denies the query, on its own key the
        # conductor refuses a registration that names another model
        impostor = codec.encode("register", name="sim", kind="tests.models.simple:BallSim", role="simulation",
                                step_modes=["service"], params={}, attributes=["pose"], outputs=[], events=[],
                                evaluators=[], services=[])
        as_sim = [r for r in rogue.get(keys.register_as("sim"), payload=impostor, timeout=1.0)]
        as_grip = [codec.decode("r", r.ok.payload, "register_reply")
                   for r in rogue.get(keys.register_as("grip"), payload=impostor, timeout=2.0) if r.ok is not None]
        # exit 3: what grip's certificate wrote on grip's own keys, an output grip never declared, was seen
        assert wait_exit(conductor, 90, tmp_path / "logs" / "agent-conductor.log") == 3
        viewer_sub.undeclare()
        events.close()
    finally:
        for s in sessions:
            s.close()
        procs.stop()
    s = json.loads(summary.read_text())
    # the run was neither stopped nor disturbed: same story as without the rogue, but for what grip's certificate
    # could write, on grip's own keys, which is said (left out: nothing of the scene reads an undeclared output)
    assert s["errors"] == [] and s["malformed_messages"] == 0 and s["unauthorized_writes"] == 0
    assert s["status"] == "degraded" and len(s["status_reasons"]) == 1, s["status_reasons"]
    assert s["status_reasons"][0].startswith("models sent what they never declared, left out: grip: output "
                                             "rogue_marker ("), s["status_reasons"]
    assert [(h["from"], h["to"], h["trigger"]) for h in s["handovers"]] == [("sim", "holder", "pick"),
                                                                            ("holder", "sim", "drop")]
    assert s["final_ownership"] == {"ball.pose": "sim", "bin.pose": "sim"}
    assert s["semantic_state"] == {"in(bin, ball)": True}
    assert s["ticks"] >= 300 and not any(stop_replies)
    assert as_sim == []
    assert len(as_grip) == 1 and not as_grip[0].accepted and "names model 'sim'" in as_grip[0].reason
    # nothing forged reached the run log or the viewer; the rogue's own key did (it was connected)
    forged = json.dumps(FORGED_POSE)[1:-1].replace(" ", "")
    log = list(read_run_log(s["run_log"]))
    owners = [m for k, _, m in log if k == keys.ownership]
    assert [m["version"] for m in owners] == [0, 1, 2]
    assert all("grip" not in json.dumps(m["owners"]) for m in owners)
    assert not any(forged in json.dumps(m).replace(" ", "") for _, _, m in log)
    markers = [m for k, _, m in log if k == keys.out("grip", "rogue_marker")]
    assert len(markers) >= n // 2
    assert not any(forged in json.dumps(codec.unpack(p)).replace(" ", "") for k, p in seen if "/telemetry/" not in k)
    # an identity the scene does not name cannot even listen: it only hears its own (local) publications
    assert mallory_seen and all(m["values"]["ball"]["pose"] == FORGED_POSE for m in mallory_seen)
    # the router saw and refused the attempts, naming the certificate
    rlog = (tmp_path / "logs" / "agent-router.log").read_text(errors="replace")
    for what in (keys.state("sim"), keys.ownership, keys.done("sim")):
        assert any("CertCommonName(grip)" in line and f"unauthorized to Put (ingress) on {what}" in line
                   for line in rlog.splitlines()), what
    assert any("CertCommonName(grip)" in line and f"unauthorized to Query (ingress) on {keys.register_as('sim')}"
               in line for line in rlog.splitlines())
    assert f"{mallory_zid} did not match any configured ACL subject" in rlog


def test_tls_files_that_cannot_make_a_link_are_said_at_once(tmp_path, pki):
    """A missing certificate, a key that is not the certificate's, a key given as the CA: Zenoh took each for a
    router not up yet, and the conductor waited silently for ever (an agent, till its register timeout, then blamed
    the bus's credentials). Each is now one line and exit 2, before any session opens."""
    cert, key = pki["certs"]["sim"]
    other_key = pki["certs"]["conductor"][1]
    cases = [(["--tls-ca", pki["ca"], "--tls-cert", str(tmp_path / "none.pem"), "--tls-key", key],
              f"--tls-cert {tmp_path / 'none.pem'}: no such file"),
             (["--tls-ca", pki["ca"], "--tls-cert", cert, "--tls-key", other_key],
              f"--tls-key {other_key} is not the key of --tls-cert {cert}"),
             (["--tls-ca", key], f"--tls-ca {key}: not a PEM certificate"),
             (["--tls-ca", pki["ca"], "--tls-cert", cert], "--tls-cert and --tls-key go together")]
    for flags, said in cases:
        for argv in (["conductor", str(SCENE), "--max-ticks", "5", "--connect", "tls/127.0.0.1:9"],
                     ["agent", "trivial", "--name", "a", "--connect", "tls/127.0.0.1:9"]):
            r = subprocess.run([sys.executable, "-m", "conductor.cli", *argv, *flags], capture_output=True, text=True,
                               env=ENV, cwd=ROOT, timeout=60)
            assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, (argv, flags, r.stderr)
