"""``--samples K``: the variations drawn, the distribution reported, and the same samples on a real local Dask
cluster (a scheduler and two workers as processes on loopback) giving the same numbers as on this machine."""
from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from conductor.launch import free_port
from conductor.provenance import sha256_of
from conductor.record import exit_code, unrun
from conductor.runlog.reader import read_metadata
from conductor.sampling import distribution, unvaried, variations, wilson, worst_status
from conductor.scene import load_scene, parse_scene
from protocol.errors import SceneError
from tests.conftest import ctrl_c_when

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
BALL = (ROOT / "scenes" / "ball_drop.yaml").read_text()


def test_variations_are_reproducible_and_stay_within_what_is_stated():
    scene = parse_scene(BALL + "uncertain:\n  ball.mass: [0.050, 0.065]\n  ball.friction: [0.4, 0.9]\n", "b.yaml")
    perception = {"entities": {"container": {"pose": [0.5, 0.2, 0.0, 0, 0, 0, 1], "position_sigma": 0.01}}}
    scene.apply_perception(perception)
    a, b = variations(scene, perception, 16, seed=7), variations(scene, perception, 16, seed=7)
    assert a == b  # the same K and seed: the same draws
    assert variations(scene, perception, 16, seed=8) != a
    xs = [v["entities"]["container"]["pose"] for v in a]
    assert len({round(p[0], 9) for p in xs}) == 16  # every sample its own container position ...
    assert all(p[2] == 0.0 and p[3:] == [0, 0, 0, 1] for p in xs)  # ... moved on the table only
    dx = [p[0] - 0.5 for p in xs] + [p[1] - 0.2 for p in xs]
    assert 0.004 < (sum(d * d for d in dx) / len(dx)) ** 0.5 < 0.02  # about the stated 1 cm
    assert all(0.050 <= v["entities"]["ball"]["mass"] <= 0.065 and 0.4 <= v["entities"]["ball"]["friction"] <= 0.9
               for v in a)
    assert all(v["entities"]["ball"]["pose"] == list(scene.entities["ball"].pose) for v in a)  # no sigma: kept
    assert unvaried(a) is None
    # nothing stated as uncertain: K samples are one run K times, and that is said
    plain = parse_scene(BALL, "b.yaml")
    assert "nothing was varied" in (unvaried(variations(plain, {"entities": {}}, 4, seed=7)) or "")


def test_samples_of_a_perception_of_another_scene_say_so_as_its_run_does():
    """Each sample's perception held every scene entity at its scene pose beside the drawn ones, so a perception of
    another scene (the run: degraded, it did not start from what the robot perceived) made samples that all placed
    everything and ended complete. A sample now says what its run says; and with one sample, nothing varied is said
    too (it was said only by comparing two)."""
    for seen, missed in (({"cup": {"pose": [0.5, 0.0, 0.1]}}, True), ({"ball": {"pose": [0.5, 0.0, 0.1]}}, False)):
        nominal = parse_scene(BALL, "b.yaml")
        perception = {"entities": seen}
        nominal.apply_perception(perception)
        assert bool(nominal.perception_missed) == missed
        for v in variations(nominal, perception, 3, seed=5):
            sample = parse_scene(BALL, "b.yaml")
            sample.apply_perception(json.loads(json.dumps(v)))  # (as it travels to a service or a worker)
            assert (sample.perception_missed, sample.perception_notes) == \
                (nominal.perception_missed, nominal.perception_notes), v
    plain = parse_scene(BALL, "b.yaml")
    assert "the sample is the run itself" in (unvaried(variations(plain, {"entities": {}}, 1, seed=7)) or "")
    ranged = parse_scene(BALL + "uncertain:\n  ball.mass: [0.050, 0.065]\n", "b.yaml")
    assert unvaried(variations(ranged, {"entities": {}}, 1, seed=7)) is None


def test_a_perceived_entity_without_a_pose_is_kept_as_a_single_run_takes_it():
    """A perception may name an entity the scene has not (another scene's, or what a perceived_as points at)
    without a pose; a single run takes it, and --samples ended in a traceback (KeyError 'pose')."""
    scene = load_scene(ROOT / "scenes" / "coffee.yaml")
    perception = {"entities": {"ball": {"mass": 0.05, "position_sigma": 0.01}}}
    scene.apply_perception(perception)
    out = variations(scene, perception, 2, seed=3)
    assert [v["entities"]["ball"] for v in out] == [{"mass": 0.05}] * 2
    assert out == variations(scene, perception, 2, seed=3)


def test_a_samples_folder_used_again_keeps_nothing_of_the_run_before(tmp_path):
    """--run-dir of an earlier sampled run: a sample that was not run (a stop) kept the earlier run's summary and
    log as its own, complete, and the earlier run's samples beyond K stayed beside the new ones."""
    from conductor.fleet import LocalFleet
    from conductor.sampling import sample_dir, sample_jobs

    root = tmp_path / "runs"
    for i in range(5):  # an earlier run of 5 samples
        sample_dir(root, i).mkdir(parents=True)
        (sample_dir(root, i) / "summary.json").write_text('{"status": "complete"}')
        (sample_dir(root, i) / "run.mcap").write_bytes(b"old")
        (sample_dir(root, i) / "agent-physics.log").write_text("old")
    (sample_dir(root, 7)).mkdir()
    (sample_dir(root, 7) / "notes.txt").write_text("mine")  # (not a run's: kept)
    jobs, _ = sample_jobs(str(ROOT / "scenes" / "insertion.yaml"), str(ROOT / "recordings" / "insertion_00.mcap"),
                          2, 0, root, register_timeout=5.0)
    assert sorted(p.name for p in root.iterdir()) == ["sample-000", "sample-001", "sample-007"]
    assert all(not any(sample_dir(root, i).iterdir()) for i in range(2))
    assert all(j["register_timeout"] == 5.0 for j in jobs)
    # a run going on in one of them (its folder locked, as every run locks its own): its files are its own
    from conductor.launch import _lock, _unlock
    from protocol.errors import TwinError

    for busy in (sample_dir(root, 1), sample_dir(root, 5)):
        busy.mkdir(exist_ok=True)
        (busy / "run.mcap").write_bytes(b"going")
        _lock(busy)
    try:
        with pytest.raises(TwinError, match="sample-001: another run is using it"):
            sample_jobs(str(ROOT / "scenes" / "insertion.yaml"), str(ROOT / "recordings" / "insertion_00.mcap"), 2, 0,
                        root)
        assert (sample_dir(root, 1) / "run.mcap").read_bytes() == b"going"
        sample_jobs(str(ROOT / "scenes" / "insertion.yaml"), str(ROOT / "recordings" / "insertion_00.mcap"), 1, 0,
                    root)  # (K=1: sample-001 and sample-005 are beyond it, and kept while their runs go on)
        assert (sample_dir(root, 5) / "run.mcap").read_bytes() == b"going" and sample_dir(root, 1).is_dir()
    finally:
        _unlock(sample_dir(root, 1))
        _unlock(sample_dir(root, 5))
    jobs, _ = sample_jobs(str(ROOT / "scenes" / "insertion.yaml"), str(ROOT / "recordings" / "insertion_00.mcap"),
                          2, 0, root, register_timeout=5.0)
    assert not sample_dir(root, 5).exists()  # (its run over, it went as any earlier run's sample beyond K)
    fleet = LocalFleet(2)
    fleet.stop("Ctrl-C")
    out = fleet.map(jobs)
    assert [o["status"] for o in out] == ["truncated", "truncated"]
    for i in range(2):  # its folder says what the command says
        on_disk = json.loads((sample_dir(root, i) / "summary.json").read_text())
        assert on_disk["status"] == "truncated" and "not run: stopped by Ctrl-C" in on_disk["status_reasons"][0]


def test_options_of_one_run_that_samples_do_not_take_are_refused():
    """--idle-timeout, --ros2-namespace and --no-hold did nothing with --samples, without a word."""
    for extra in (["--idle-timeout", "5"], ["--ros2-namespace", "foo"], ["--no-hold"]):
        r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/insertion.yaml", "--recording",
                            str(ROOT / "recordings" / "insertion_00.mcap"), "--samples", "2", *extra],
                           capture_output=True, text=True, timeout=120, env=ENV, cwd=ROOT)
        assert r.returncode == 2 and f"{extra[0]} does not go with --samples K" in r.stderr, (extra, r.stderr)


def test_samples_that_did_not_complete_degrade_the_evaluation_and_merged_figures_keep_them(tmp_path):
    """``twin evaluate --samples``: 1 complete sample of 8 gave a perfect Brier score, exit 0, status complete. Samples
    that did not complete now make the evaluation degraded and are counted beside the Brier score, which is that of
    the probability itself (not of it rounded to 4 places). Merged figures (--render A --render B) kept neither the
    samples of configurations run later nor a part's status."""
    import bench.evaluate as ev

    class Fleet:  # stands in for the engine that runs the samples: their summaries, as the runs ended
        def map(self, jobs):
            states = [("complete", True), ("complete", False), ("complete", False), ("degraded", True)]
            return [{"status": st, "semantic_state": {"in(container, ball)": v}, "handovers": []} for st, v in states]

    class Rec:
        path = str(ROOT / "recordings" / "ball_drop_00.mcap")

    ev.SAMPLES = (4, 0, Fleet())
    try:
        sp = ev.sampled(ROOT / "scenes" / "ball_drop.yaml", Rec(), tmp_path, "in(container, ball)", True, "t")
    finally:
        ev.SAMPLES = None
    assert (sp["p"], sp["complete"], sp["samples"]) == (0.3333, 3, 4)
    assert sp["brier"] == pytest.approx((1 / 3 - 1) ** 2, abs=1e-12)
    run = {"recording": "ball_drop_00.mcap", "scenario": "ball_drop", "truth": True, "reality": "pybullet",
           "kind": "success", "status": {"ensemble": "complete"}, "correct": {"ensemble": False},
           "samples": {"ensemble": sp}}
    (why,) = ev.degraded_by([run])
    assert why.startswith("1 sample(s) did not end complete") and "ball_drop_00.mcap ensemble 1 of 4" in why
    assert ev.brier_scores([run])["ensemble"]["samples_not_complete"] == 1
    assert ev.degraded_by([{**run, "samples": {"ensemble": {**sp, "complete": 4}}}]) == []
    later = {**run, "status": {"baseline1": "failed"}, "correct": {"baseline1": False},
             "samples": {"baseline1": sp}}
    merged = ev.merge_results([{"runs": [run], "configs": ["ensemble"], "status": "complete"},
                               {"runs": [later], "configs": ["baseline1"], "status": "degraded",
                                "status_reasons": ["1 run(s) did not end complete"]}])
    assert set(merged["brier"]) == {"ensemble", "baseline1"} and merged["status"] == "degraded"
    assert merged["status_reasons"] == ["1 run(s) did not end complete"]
    # the figures of an evaluation that stopped are no table: said, with its exit code (it crashed on none at all)
    stopped = tmp_path / "stopped.json"
    stopped.write_text(json.dumps({"status": "truncated", "stopped": "stopped by SIGINT", "configs": [], "runs": []}))
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "evaluate", "--render", str(stopped), "--table",
                        str(tmp_path / "t.md")], capture_output=True, text=True, timeout=120, env=ENV, cwd=ROOT)
    assert r.returncode == 4 and "not written" in r.stderr and "stopped by SIGINT" in r.stderr, r.stdout + r.stderr
    assert not (tmp_path / "t.md").exists()


@pytest.mark.parametrize("block, problem", [
    ("  ghost.mass: [1, 2]", "unknown entity 'ghost'"),
    ("  ball.radius: [1, 2]", "'radius' cannot be uncertain"),
    ("  ball.mass: [2, 1]", "0 <= low <= high"),
    ("  ball.mass: 0.05", "[low, high]"),
])
def test_uncertain_ranges_are_checked(block, problem):
    with pytest.raises(SceneError) as e:
        parse_scene(BALL + "uncertain:\n" + block + "\n", "b.yaml")
    assert problem in str(e.value) and "b.yaml:" in str(e.value)


def test_the_distribution_counts_complete_samples_only():
    def s(status, v, t):
        return {"status": status, "semantic_state": {"in(c, b)": v},
                "handovers": [{"trigger": "grasp", "entity": "b", "attribute": "pose", "from": "p", "to": "h", "t": t}]}
    d = distribution([s("complete", True, 1.0), s("complete", True, 1.2), s("complete", False, 1.4),
                      s("degraded", True, 9.0)])
    p = d["predicates"]["in(c, b)"]
    assert (p["true"], p["of"], p["p"]) == (2, 3, 0.6667)
    assert p["interval95"] == [round(x, 4) for x in wilson(2, 3)]
    h = d["handovers"]["grasp: b.pose p -> h"]
    assert (h["in"], h["median_s"]) == (3, 1.2)
    assert d["not_complete"][0]["sample"] == 3 and d["statuses"] == {"complete": 3, "degraded": 1}
    assert worst_status([{"status": "complete"}, {"status": "truncated"}, {"status": "degraded"}]) == "truncated"
    # a semantic value that is a number (a temperature, particles spilled): its spread (it was "no complete sample
    # could evaluate it")
    d = distribution([{"status": "complete", "semantic_state": {"spilled(cup)": n}} for n in (3, 5, 4, 40, None)])
    assert d["predicates"]["spilled(cup)"] == {"p": None, "median": 4.5, "p10": 3.3, "p90": 29.5, "of": 4,
                                              "unknown": 1}


def test_a_sample_runs_the_scene_a_single_run_does():
    """A variation kept only each entity's pose: a sample ran the scene file's shapes and masses, not what the
    recording perceived (a stand 2 mm thinner, the DIP's mass). It is the whole perception with the drawn values
    changed; and an entity perceived as another (coffee's cup, perceived as a ball) moves with that one's draw (its
    own undrawn copy put it back)."""
    scene = parse_scene(BALL, "b.yaml")
    perception = {"entities": {"stand": {"pose": [0.3, 0.3, 0.05], "shape": {"type": "cylinder", "radius": 0.0226,
                                                                           "length": 0.1025}, "mass": 0.4},
                               "container": {"pose": [0.5, 0.2, 0.0], "position_sigma": 0.01}}}
    scene.apply_perception(perception)
    for v in variations(scene, perception, 3, seed=1):
        assert v["entities"]["stand"]["shape"] == perception["entities"]["stand"]["shape"]
        assert v["entities"]["stand"]["mass"] == 0.4
        fresh = parse_scene(BALL, "b.yaml")
        fresh.apply_perception(v)
        assert fresh.entities["stand"].shape == scene.entities["stand"].shape
    coffee = ROOT / "scenes" / "coffee.yaml"
    c = load_scene(coffee)
    perceived = {"entities": {"ball": {"pose": [0.4, 0.1, 0.1, 0, 0, 0, 1], "position_sigma": 0.05}}}
    c.apply_perception(perceived)
    for v in variations(c, perceived, 3, seed=0):
        fresh = load_scene(coffee)
        fresh.apply_perception(v)
        assert fresh.entities["cup"].pose[:2] == v["entities"]["ball"]["pose"][:2] != [0.4, 0.1]


def test_samples_that_all_failed_on_the_input_exit_2_as_one_run_does():
    """Every sample refused for the user's input (a misspelt model argument) makes the distribution bad input, so
    ``record.exit_code`` gives 2 for it as for one run; one sample that failed otherwise keeps it a failure (1)."""
    bad = {**unrun("models.physics.args.tme_step: unknown parameter"), "bad_input": True}
    d = {**distribution([bad, bad]), "status": "failed"}
    assert d["bad_input"] is True and exit_code(d) == 2
    d = {**distribution([bad, unrun("the main model 'physics' died")]), "status": "failed"}
    assert "bad_input" not in d and exit_code(d) == 1


def twin_samples(*args: str, timeout: float = 900, cwd: Path = ROOT) -> dict:
    out = Path(args[args.index("--summary") + 1])
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", *args], capture_output=True, text=True,
                       timeout=timeout, env=ENV, cwd=cwd)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "P[connected(dip, spu)]" in r.stdout
    return json.loads(out.read_text())


@contextlib.contextmanager
def local_cluster(tmp_path: Path, hide: Path | None = None, processes: list | None = None):
    """A real Dask cluster on loopback: a scheduler and two single-threaded workers, each a process. With ``hide``,
    the workers run in a mount namespace of their own where that folder is an empty tmpfs: they share none of the
    client's files there, as workers on other machines would not. ``processes`` is given the scheduler's
    process, then the workers'."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = [open(tmp_path / f"dask-{i}.log", "w") for i in range(3)]
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"], stdout=logs[0], stderr=subprocess.STDOUT,
                              env=ENV, cwd=ROOT, start_new_session=True)]
    if processes is not None:
        processes.append(procs[0])
    try:
        for i in (1, 2):
            worker = [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                      "--no-dashboard", "--name", f"w{i}"]
            if hide is not None:
                worker = ["unshare", "-m", "--propagation", "private", "sh", "-c",
                          f'mount -t tmpfs tmpfs "{hide}" && exec "$0" "$@"', *worker]
            procs.append(subprocess.Popen(worker, stdout=logs[i], stderr=subprocess.STDOUT, env=ENV, cwd=ROOT,
                                          start_new_session=True))
            if processes is not None:
                processes.append(procs[-1])
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=90)
        yield address
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 20
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        for f in logs:
            f.close()


@pytest.fixture
def dask_cluster(tmp_path):
    with local_cluster(tmp_path) as address:
        yield address


@pytest.mark.slow
def test_samples_on_a_local_cluster_give_the_same_numbers_as_here(tmp_path, dask_cluster):
    rec = str(ROOT / "recordings" / "insertion_pb_10mm.mcap")  # the SPU 10 mm off the robot's belief (sigma 5 mm)
    common = [str(ROOT / "scenes" / "insertion.yaml"), "--recording", rec, "--samples", "4", "--seed", "11"]
    here = twin_samples(*common, "--jobs", "2", "--run-dir", str(tmp_path / "here"),
                        "--summary", str(tmp_path / "here.json"))
    # a --run-dir relative to where the command runs, not to where the workers run (they wrote there)
    there = twin_samples(*common, "--cluster", dask_cluster, "--run-dir", "there",
                         "--summary", str(tmp_path / "there.json"), cwd=tmp_path)
    assert all((tmp_path / "there" / f"sample-{i:03d}" / "summary.json").is_file() for i in range(4))
    assert here["samples"] == there["samples"] == 4 and here["status"] == there["status"] == "complete"
    assert here["variations"] == there["variations"]  # the same draws ...
    assert here["predicates"] == there["predicates"]  # ... the same answers ...
    assert here["handovers"] == there["handovers"]    # ... and the same handover times
    assert "2 workers" in there["where"]
    assert "warm agents" in here["where"]  # here: each set of models started once (the cluster: fresh per job)
    # the SPU's believed position varied by its stated 5 mm, sample to sample
    spus = {tuple(v["entities"]["spu"]["pose"][:2]) for v in here["variations"]}
    assert len(spus) == 4
    assert load_scene(ROOT / "scenes" / "insertion.yaml").entities["spu"]  # the shipped scene needs no change


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="a mount namespace of the workers' own needs root (CI runs as root)")
def test_workers_that_share_no_files_with_the_client_get_the_recording_and_send_the_runs_back(tmp_path):
    """Workers on other machines have neither the client's recording nor its run folder: the recording travels
    with the jobs, and each run's folder comes back to where the client said, its log naming the client's file."""
    mine = tmp_path / "client"
    mine.mkdir()
    rec = mine / "my_insertion.mcap"
    shutil.copy(ROOT / "recordings" / "insertion_pb_10mm.mcap", rec)
    with local_cluster(tmp_path, hide=mine) as address:
        there = twin_samples(str(ROOT / "scenes" / "insertion.yaml"), "--recording", str(rec), "--samples", "2",
                             "--seed", "11", "--cluster", address, "--run-dir", str(mine / "runs"),
                             "--summary", str(mine / "there.json"))
    assert there["status"] == "complete" and there["samples"] == 2
    for i in range(2):
        folder = mine / "runs" / f"sample-{i:03d}"
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["status"] == "complete" and summary["run_log"] == str(folder / "run.mcap")
        meta = read_metadata(folder / "run.mcap")["twin.recording"]
        assert meta["path"] == str(rec) and meta["sha256"] == sha256_of(rec)
    assert not list(mine.rglob(".twin-client"))  # the client's marks are gone


@pytest.mark.slow
def test_evaluate_reports_the_brier_score_beside_the_hit_rate(tmp_path):
    recs = tmp_path / "recordings"
    recs.mkdir()
    (recs / "insertion_pb_10mm.mcap").symlink_to(ROOT / "recordings" / "insertion_pb_10mm.mcap")
    out = tmp_path / "t2.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "evaluate", "--recordings", str(recs), "--configs",
                        "ensemble", "--samples", "3", "--seed", "4", "--json", str(out), "--run-dir",
                        str(tmp_path / "runs")], capture_output=True, text=True, timeout=900, env=ENV, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads(out.read_text())
    (run,) = result["runs"]
    sp = run["samples"]["ensemble"]
    assert sp["samples"] == 3 and sp["complete"] == 3 and 0.0 <= sp["p"] <= 1.0
    assert sp["brier"] == pytest.approx((sp["p"] - float(run["truth"])) ** 2)
    b = result["brier"]["ensemble"]
    assert b["brier"] == pytest.approx(sp["brier"], abs=1e-4) and b["hit_rate"] in ("0/1", "1/1")
    assert b["unvaried"] == 0 and "Brier score" in r.stdout
    # what makes the figures again is in them: the command, each run's seed and its samples' draws
    assert result["produced_by"] == f"twin evaluate --recordings {recs} --configs ensemble --samples 3 --seed 4"
    assert sp["seed"] == 4 and len(sp["variations"]) == 3 and all("spu" in v["entities"] for v in sp["variations"])
    table = tmp_path / "t2.md"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "evaluate", "--render", str(out), "--table",
                        str(table)], capture_output=True, text=True, timeout=300, env=ENV, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    text = table.read_text()
    assert f"Produced by `{result['produced_by']} --table" in text and "## With samples: Brier score" in text


def test_samples_cut_short_say_so(tmp_path):
    """--max-ticks reaches every sample: none is complete, and the command's status and exit code say so."""
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/insertion.yaml", "--recording",
                        str(ROOT / "recordings" / "insertion_00.mcap"), "--samples", "2", "--max-ticks", "60",
                        "--run-dir", str(tmp_path / "runs"), "--summary", str(tmp_path / "s.json")],
                       capture_output=True, text=True, timeout=600, env=ENV, cwd=ROOT)
    assert r.returncode == 4, r.stdout + r.stderr
    d = json.loads((tmp_path / "s.json").read_text())
    assert d["status"] == "truncated" and d["complete"] == 0 and d["statuses"] == {"truncated": 2}
    assert d["predicates"] == {}  # no probability is made of samples that did not complete


@pytest.mark.slow
@pytest.mark.parametrize("where", [[], ["--cold", "--jobs", "2"]], ids=["warm", "cold"])
def test_ctrl_c_ends_the_samples_truncated_and_reports_the_rest(tmp_path, where):
    """Ctrl-C on ``twin run --samples`` (warm agents, or fresh processes per sample): the samples going on end
    truncated, those not begun are not run, and what did complete is still reported, with the worst status and its
    exit code."""
    out = tmp_path / "s.json"
    code, text = ctrl_c_when(["run", "scenes/insertion.yaml", "--recording",
                              str(ROOT / "recordings" / "insertion_pb_10mm.mcap"), "--samples", "6", "--run-dir",
                              str(tmp_path / "runs"), "--summary", str(out), *where],
                             lambda line: line.strip().startswith("sample   0:"))
    assert code == 4, text
    d = json.loads(out.read_text())
    assert d["status"] == "truncated" and d["samples"] == 6, text
    assert 1 <= d["complete"] < 6 and d["statuses"]["truncated"] == 6 - d["complete"], d["statuses"]
    assert all(s["status"] == "truncated" for s in d["not_complete"]), d["not_complete"]
    assert "stopped" in text and "P[connected(dip, spu)]" in text  # the complete ones are still reported


@pytest.mark.slow
def test_a_stopped_cluster_fleet_ends_the_runs_going_on_truncated(tmp_path, dask_cluster):
    """``DaskFleet.stop`` (Ctrl-C on ``--cluster``) reaches the workers: the runs going on there end ``truncated``,
    each with the summary of what it ran, and the jobs not begun come back not run; the map returns them all."""
    from conductor.fleet import DaskFleet
    from conductor.sampling import sample_jobs

    jobs, _ = sample_jobs("scenes/insertion.yaml", str(ROOT / "recordings" / "insertion_pb_10mm.mcap"), 6, 3,
                          tmp_path / "runs")
    logs = [Path(j["run_dir"]) / "run.mcap" for j in jobs]
    fleet = DaskFleet(dask_cluster)
    seen: list[Path] = []

    def stop_when_a_run_is_going_on() -> None:  # its run log growing: it is past its start, ticking
        deadline = time.monotonic() + 300
        while not seen and time.monotonic() < deadline:
            seen.extend(p for p in logs if p.exists() and p.stat().st_size > 300_000)
            time.sleep(0.05)
        fleet.stop("a test")

    stopper = threading.Thread(target=stop_when_a_run_is_going_on)
    stopper.start()
    try:
        summaries = fleet.map(jobs)
    finally:
        stopper.join(timeout=330)
        fleet.close()
    assert seen, "no run began on the cluster"
    assert len(summaries) == 6 and "complete" not in [s["status"] for s in summaries], summaries
    not_run = [s for s in summaries if s["status_reasons"] == ["not run: stopped by a test"]]
    cut = [s for s in summaries if s not in not_run]
    assert cut, "no run going on was reached"  # (before, a run going on went on to its end; its answer was dropped)
    for s in cut:
        assert s["status"] == "truncated" and any("a test" in r for r in s["status_reasons"]), s
    assert max(s["ticks"] for s in cut) > 0  # the one seen going on had ticked: it ended there, not at its end
    assert all(s["status"] == "truncated" for s in not_run)
    ran = {Path(s["run_log"]).parent for s in cut if s.get("run_log")}
    assert ran and ran <= {p.parent for p in logs}, (ran, cut)
    for d in ran:  # the run log of a run cut short is whole: closed with its summary
        assert "twin.summary" in read_metadata(d / "run.mcap"), d


def test_a_worker_with_other_twin_code_runs_nothing():
    """A Dask worker ran whatever twin it had installed: a client's fix not yet deployed there gave the old code's
    answers as the client's. Each job now carries the client's code fingerprint; a worker whose own differs runs
    nothing and says why (the job as the cluster gives it to the worker, without a cluster)."""
    from conductor.fleet import cluster_job
    from conductor.provenance import code_fingerprint

    s = cluster_job({"code": "0" * 16, "scene_text": "", "recording": "nowhere.mcap", "ensemble": "x",
                     "run_dir": "nowhere"}, signal="unused")
    assert s["status"] == "failed" and "runs other twin code than the client" in s["status_reasons"][0], s
    assert f"(code {code_fingerprint()}, the client's {'0' * 16})" in s["status_reasons"][0]
    assert len(code_fingerprint()) == 16 and code_fingerprint() == code_fingerprint()


def test_the_code_fingerprint_skips_an_editors_lock_file(tmp_path):
    """An editor's lock file (Emacs's dangling .#core.py link) beside the code crashed every run's metadata: it is
    not code, so it is left out; a changed source changes the fingerprint."""
    from conductor.provenance import code_fingerprint

    for package in ("agents", "conductor", "protocol"):
        (tmp_path / package).mkdir()
        (tmp_path / package / "m.py").write_text(f"X = {package!r}\n")
    before = code_fingerprint(tmp_path)
    (tmp_path / "conductor" / ".#m.py").symlink_to("root@host.1234:1700000000")  # (dangling, as Emacs makes it)
    code_fingerprint.cache_clear()
    assert code_fingerprint(tmp_path) == before
    (tmp_path / "protocol" / "m.py").write_text("X = 2\n")
    code_fingerprint.cache_clear()
    assert code_fingerprint(tmp_path) != before


def test_a_cluster_that_is_not_there_is_one_line():
    """--cluster at an address where no scheduler listens: a TwinError naming it (one line from twin), not
    distributed's traceback."""
    from conductor.fleet import DaskFleet
    from conductor.launch import free_port
    from protocol.errors import TwinError

    address = f"tcp://127.0.0.1:{free_port()}"
    with pytest.raises(TwinError, match=f"--cluster {address}: no Dask scheduler answered within 1 s"):
        DaskFleet(address, timeout=1.0)
    # an empty address (an unset $SCHED) ran on this machine; ucx:// and tls:// ended in a TypeError's traceback
    for bad, said in (("", "an empty address"), ("ucx://127.0.0.1:1", "not a tcp://host:port address"),
                      ("tls://127.0.0.1:1", "not a tcp://host:port address"),
                      ("tcp://127.0.0.1", "cannot connect to a Dask scheduler there (ValueError")):
        shown = bad or "''"
        with pytest.raises(TwinError, match=re.escape(f"--cluster {shown}: {said}")):
            DaskFleet(bad, timeout=1.0)
    # a port that takes the connection and never speaks held it for ever
    silent = socket.create_server(("127.0.0.1", 0))
    try:
        address = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
        with pytest.raises(TwinError, match=f"--cluster {address}: no Dask scheduler answered within 1 s"):
            DaskFleet(address, timeout=1.0)
    finally:
        silent.close()


@pytest.fixture
def lone_scheduler(tmp_path):
    """A real Dask scheduler without workers on a free loopback port, a process group of its own: (its address, its
    process). Ended however the test left it (stopped, killed or running)."""
    port = free_port()
    log = open(tmp_path / "scheduler.log", "w")
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                              "--port", str(port), "--no-dashboard"], stdout=log, stderr=subprocess.STDOUT, env=ENV,
                             cwd=ROOT, start_new_session=True)
    try:
        yield f"tcp://127.0.0.1:{port}", sched
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(sched.pid, signal.SIGKILL)
        sched.wait()
        log.close()


def test_a_cluster_without_workers_or_stopped_does_not_hold_its_jobs_for_ever(tmp_path, lone_scheduler):
    """A scheduler with no worker used to keep twin run --samples --cluster waiting for ever, deaf to Ctrl-C (its
    jobs were never run, and nothing cancelled them): the jobs left now fail, saying why, once it has had no worker
    for NO_WORKER_S; and after a stop, what has not come back within STOP_GRACE_S is cancelled, truncated."""
    from conductor.fleet import DaskFleet

    address, _ = lone_scheduler
    idle = DaskFleet(address, timeout=60)
    idle.NO_WORKER_S = 2.0
    assert "(0 workers)" in idle.where
    def job(n: int) -> dict:
        return {"recording": str(ROOT / "recordings" / "ball_drop_00.mcap"), "run_dir": str(tmp_path / f"r{n}")}

    out = idle.map([job(1), job(2)])
    assert [o["status"] for o in out] == ["failed", "failed"]
    assert out[0]["status_reasons"] == ["the Dask cluster had no worker for 2 s: the job was not run"]
    stopped = DaskFleet(address, timeout=60)
    stopped.STOP_GRACE_S, stopped.NO_WORKER_S = 1.0, 600.0
    threading.Timer(0.5, lambda: stopped.stop("Ctrl-C")).start()
    (one,) = stopped.map([job(1)])
    assert one["status"] == "truncated" and "stopped by Ctrl-C" in one["status_reasons"][0], one
    idle.close()
    stopped.close()


def test_a_scheduler_lost_mid_map_fails_the_jobs_left_and_keeps_the_rest(tmp_path, lone_scheduler):
    """The scheduler killed while a map waited: distributed cancels the futures, and its wait raised that
    (FuturesCancelledError) through twin evaluate --cluster as a traceback, every result already in lost. The jobs
    left now fail, saying the scheduler was lost."""
    from conductor.fleet import DaskFleet

    address, sched = lone_scheduler
    fleet = None
    try:
        fleet = DaskFleet(address, timeout=60)
        fleet.NO_WORKER_S = 600.0  # (no worker: the jobs wait, until the scheduler dies under them)
        threading.Timer(1.5, lambda: os.killpg(sched.pid, signal.SIGKILL)).start()
        jobs = [{"recording": str(ROOT / "recordings" / "ball_drop_00.mcap"), "run_dir": str(tmp_path / f"r{n}")}
                for n in (1, 2)]
        out = fleet.map(jobs)
        assert [o["status"] for o in out] == ["failed", "failed"], out
        assert all("scheduler" in o["status_reasons"][0] for o in out), out
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(sched.pid, signal.SIGKILL)  # (a frozen or dead scheduler: the client is let go of at once)
        if fleet is not None:
            with contextlib.suppress(Exception):
                fleet.close()


def test_a_scheduler_that_stops_answering_does_not_hold_the_map_or_its_stop(tmp_path, lone_scheduler):
    """A scheduler that keeps its connection but no longer answers (a frozen host; here a stopped process): the map
    waited inside its once-a-second question to the scheduler, and a stop (SIGTERM, Ctrl-C) inside its word to the
    jobs, both for ever. The jobs left now fail, saying so, and the stop returns."""
    from conductor.fleet import DaskFleet

    address, sched = lone_scheduler
    fleet = None
    try:
        fleet = DaskFleet(address, timeout=60)
        fleet.NO_WORKER_S, fleet.ANSWER_S, fleet.STOP_GRACE_S = 600.0, 2.0, 600.0  # (only the answers bound it)
        stop_took: list[float] = []

        def freeze_then_stop() -> None:
            os.killpg(sched.pid, signal.SIGSTOP)
            t0 = time.monotonic()
            fleet.stop("SIGTERM")
            stop_took.append(time.monotonic() - t0)

        threading.Timer(1.5, freeze_then_stop).start()
        t0 = time.monotonic()
        out = fleet.map([{"recording": str(ROOT / "recordings" / "ball_drop_00.mcap"), "run_dir": str(tmp_path / "r")}])
        assert time.monotonic() - t0 < 120, out
        assert [o["status"] for o in out] == ["failed"], out
        assert "the Dask scheduler stopped answering" in out[0]["status_reasons"][0], out
        deadline = time.monotonic() + 30
        while not stop_took and time.monotonic() < deadline:
            time.sleep(0.1)
        assert stop_took and stop_took[0] < 30, stop_took
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(sched.pid, signal.SIGKILL)  # (a frozen or dead scheduler: the client is let go of at once)
        if fleet is not None:
            with contextlib.suppress(Exception):
                fleet.close()


@pytest.mark.slow
def test_runs_whose_scheduler_died_stop_and_do_not_say_complete(tmp_path):
    """The scheduler killed mid-map: the client reports the jobs lost, while the workers' runs went on and wrote
    'complete' over the folders the client had said lost. A job whose stop signal is gone now stops its run,
    truncated, saying that no one waits for its answer (or, on a loaded machine, its worker gives up on the lost
    scheduler first and ends with its run: the client's word stands)."""
    from conductor.fleet import DaskFleet
    from conductor.sampling import sample_jobs

    processes: list = []
    with local_cluster(tmp_path, processes=processes) as address:
        jobs, _ = sample_jobs("scenes/insertion.yaml", str(ROOT / "recordings" / "insertion_pb_10mm.mcap"), 2, 5,
                              tmp_path / "runs", rtf=1.0)
        logs = [Path(j["run_dir"]) / "run.mcap" for j in jobs]
        fleet = DaskFleet(address)

        def kill_when_the_runs_go_on() -> None:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not all(p.exists() and p.stat().st_size > 200_000 for p in logs):
                time.sleep(0.05)
            processes[0].kill()

        killer = threading.Thread(target=kill_when_the_runs_go_on)
        killer.start()
        try:
            out = fleet.map(jobs)
        finally:
            killer.join(timeout=130)
            with contextlib.suppress(Exception):
                fleet.close()
        assert [o["status"] for o in out] == ["failed", "failed"], out
        workers = processes[1:]
        for log in logs:  # the workers' runs end soon after, truncated, each saying why (the file is theirs)
            summary = log.parent / "summary.json"
            deadline = time.monotonic() + 60  # (a run not stopped would end by then: its recording is 10 s)
            while time.monotonic() < deadline:
                s = json.loads(summary.read_text()) if summary.exists() else {}
                if s.get("status") in ("truncated", "complete") or all(w.poll() is not None for w in workers):
                    break
                time.sleep(0.2)
            s = json.loads(summary.read_text())
            assert s["status"] in ("truncated", "failed"), s
            if s["status"] == "truncated":
                assert any("its client no longer waits for it" in r for r in s["status_reasons"]), s
            else:  # the worker ended, and its run with it: the client's summary stands
                assert all(w.poll() is not None for w in workers), s
                assert "the cluster lost the job" in s["status_reasons"][0], s



def test_a_worker_without_the_scene_s_own_model_code_runs_nothing(tmp_path):
    """The twin's fingerprint covers its own packages only: a worker whose copy of the scene's FMI unit cooled ten
    times faster answered 69 degC for 83 complete, and one without it failed on a path it could not find. The jobs
    now carry the sha256 of the scene's own model files, and a worker whose copy differs, or lacks one, runs
    nothing and says what (the same files at the same paths are what it needs)."""
    from conductor.fleet import cluster_job
    from conductor.provenance import scene_code

    scene = tmp_path / "coffee.yaml"
    (tmp_path / "units").mkdir()
    unit = tmp_path / "units" / "cooling.py"
    unit.write_text((ROOT / "scenes" / "units" / "cooling.py").read_text())
    scene.write_text((ROOT / "scenes" / "coffee.yaml").read_text())
    text = scene.read_text()
    job = {"scene_text": text, "scene_file": str(scene), "scene_code": scene_code(text, str(scene))}
    assert list(job["scene_code"]) == [f"fmu:{unit}"]
    unit.write_text(unit.read_text().replace("self.tau = 1500.0", "self.tau = 150.0"))
    s = cluster_job(job, "unused")
    assert s["status"] == "failed" and f"its copy of fmu:{unit} is not the client's" in s["status_reasons"][0], s
    unit.unlink()
    s = cluster_job(job, "unused")
    assert s["status"] == "failed" and "the scene's own model files cannot be read here" in s["status_reasons"][0], s
