"""End to end, as a user evaluates the twin: make one short recording per scenario with
`twin record synth` (a fresh seed, not one of the shipped recordings), then `twin evaluate` runs the
ensemble and a baseline on them (real agent processes, real pybullet, real Zenoh) and compares each
interpretation with the ground truth the reality run measured."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ctrl_c_when

ROOT = Path(__file__).resolve().parent.parent


def twin(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "conductor.cli", *args], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, f"twin {' '.join(args)}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


@pytest.mark.slow
def test_fresh_recordings_are_interpreted_end_to_end(tmp_path):
    recs = tmp_path / "recordings"  # (not made here: twin record synth makes the folder its --out names)
    twin("record", "synth", "--scenario", "ball_drop", "--seed", "1000", "--container", "bowl",
         "--outcome", "success", "--time-scale", "0.7", "--out", str(recs / "ball_drop_fresh.mcap"), "-q")
    twin("record", "synth", "--scenario", "insertion", "--seed", "1001", "--localization-error", "0.002",
         "--time-scale", "0.7", "--out", str(recs / "insertion_fresh.mcap"), "-q")
    out = tmp_path / "t2.json"
    r = twin("evaluate", "--recordings", str(recs), "--configs", "ensemble,baseline1", "--json", str(out),
             "--table", str(tmp_path / "t2.md"), "--run-dir", str(tmp_path / "runs"), timeout=600)
    result = json.loads(out.read_text())
    assert len(result["runs"]) == 2 and result["status"] == "complete", r.stdout
    by = {r["scenario"]: r for r in result["runs"]}
    assert set(by) == {"ball_drop", "insertion"}
    for scenario, predicate, truth_key in (("ball_drop", "in(container, ball)", "in_container"),
                                           ("insertion", "connected(dip, spu)", "connected")):
        run = by[scenario]
        assert run["errors"] == {} or not any(run["errors"].values()), run["errors"]
        truth = run["ground_truth"][truth_key]
        assert isinstance(truth, bool)
        got = run["interpretations"]["ensemble"][predicate]
        assert got == truth, f"{scenario}: ensemble says {predicate}={got}, the reality run measured {truth}"
        assert run["correct"]["ensemble"] is True
        assert run["handovers"]["ensemble"], f"{scenario}: the ensemble never moved a responsibility"
        assert run["rtf_by_config"]["ensemble"] > 0 and run["rtf_by_config"]["baseline1"] > 0
    table = (tmp_path / "t2.md").read_text()
    assert "| ball_drop |" in table and "| insertion |" in table
    # that ran through one warm service (each scene's agents started once); --cold starts fresh processes for
    # every run, as twin run does: the same interpretations and handovers, run by run
    cold = tmp_path / "cold.json"
    twin("evaluate", "--cold", "--recordings", str(recs), "--configs", "ensemble,baseline1", "--json", str(cold),
         "--run-dir", str(tmp_path / "cold"), timeout=600)
    for warm_run, cold_run in zip(result["runs"], json.loads(cold.read_text())["runs"], strict=True):
        for k in ("interpretations", "handovers", "status", "correct"):
            assert warm_run[k] == cold_run[k], (warm_run["recording"], k)


def test_what_cannot_be_evaluated_is_said_before_anything_runs(tmp_path):
    """A folder with a file that is not a recording it can evaluate, or a configuration that does not exist:
    every file at fault named, exit 2 (a bad command line), nothing run, no figures written as if complete."""
    recs = tmp_path / "recordings"
    recs.mkdir()
    (recs / "ball_drop_00.mcap").symlink_to(ROOT / "recordings" / "ball_drop_00.mcap")
    (recs / "garbage.mcap").write_bytes(b"not mcap\n")
    (recs / "gone.mcap").symlink_to(tmp_path / "nowhere.mcap")
    whole = (ROOT / "recordings" / "ball_drop_00.mcap").read_bytes()
    (recs / "notes.mcap").write_bytes(whole[:8])  # cut short after the magic
    (recs / "half.mcap").write_bytes(whole[: len(whole) // 2])  # the recorder killed: no ground truth yet
    from recordings.rosbag import RecordingWriter
    with RecordingWriter(recs / "ball_drop_nogt.mcap") as w:  # a ball_drop by its name, without ground truth
        w.joint_state(0.0, ["j1"], [0.0], [0.0], [0.0])
    # the log of a run cut short by --max-ticks: the recording's metadata, its ground truth too, but part of it
    part = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/ball_drop.yaml", "--recording",
                           str(ROOT / "recordings" / "ball_drop_00.mcap"), "--max-ticks", "60", "--run-dir",
                           str(tmp_path / "part")], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert part.returncode == 4, part.stdout + part.stderr
    (tmp_path / "part" / "run.mcap").rename(recs / "ball_drop_partial.mcap")
    # the log of a whole run, named as a recording: it holds the robot's telemetry, not what the robot's run was
    whole_run = subprocess.run([sys.executable, "-m", "conductor.cli", "run", "scenes/ball_drop_baseline1.yaml",
                                "--recording", str(ROOT / "recordings" / "ball_drop_00.mcap"), "--run-dir",
                                str(tmp_path / "whole")], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert whole_run.returncode == 0, whole_run.stdout + whole_run.stderr
    (tmp_path / "whole" / "run.mcap").rename(recs / "ball_drop_log.mcap")
    out = tmp_path / "t2.json"
    argv = [sys.executable, "-m", "conductor.cli", "evaluate", "--recordings", str(recs), "--json", str(out),
            "--run-dir", str(tmp_path / "runs")]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 2, r.stdout + r.stderr
    for name, why in (("garbage.mcap", "not a recording: not an MCAP file"), ("gone.mcap", "link to nothing"),
                      ("notes.mcap", "cut short"), ("half.mcap", "cut short"),
                      ("ball_drop_nogt.mcap", "no ground truth to score against ('in_container'"),
                      ("ball_drop_partial.mcap", "a twin run log, not a robot recording"),
                      ("ball_drop_partial.mcap", "; and the log of a run that ended truncated"),
                      ("ball_drop_log.mcap", "a twin run log, not a robot recording: evaluate the recording it "
                                             f"replayed ({ROOT / 'recordings' / 'ball_drop_00.mcap'})")):
        assert any(name in line and why in line for line in r.stderr.splitlines()), r.stderr
    assert f"{recs / 'ball_drop_00.mcap'}:" not in r.stderr and not out.exists() and not (tmp_path / "runs").exists()
    # damage inside a file whose header and metadata are whole: found by reading it, before any run (it used to
    # end the evaluation at that recording, after the runs before it, with no figures written)
    inside = tmp_path / "inside"
    inside.mkdir()
    (inside / "ball_drop_00.mcap").symlink_to(ROOT / "recordings" / "ball_drop_00.mcap")
    (inside / "ball_drop_05.mcap").write_bytes(whole[:150_000] + b"\xaa" * 20_000 + whole[170_000:])
    r = subprocess.run([*argv[:5], str(inside), *argv[6:]], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"{inside / 'ball_drop_05.mcap'}: a chunk of its messages" in r.stderr, r.stderr
    assert "cannot be read" in r.stderr and "twin evaluate takes whole recordings only" in r.stderr, r.stderr
    assert "ball_drop_00" not in r.stderr and not out.exists() and not (tmp_path / "runs").exists()
    r = subprocess.run([*argv[:5], str(tmp_path / "nowhere.mcap"), *argv[6:]], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert r.returncode == 2 and "nowhere.mcap: no such file or folder" in r.stderr, r.stdout + r.stderr
    r = subprocess.run([*argv[:-4], "--configs", "ensemble,ensembl"], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 2 and "unknown configuration 'ensembl'" in r.stderr and "baseline1" in r.stderr
    # options of samples without --samples: said, not one plain run each on this machine
    r = subprocess.run([*argv, "--seed", "3", "--cluster", "tcp://127.0.0.1:1"], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert r.returncode == 2 and "--seed, --cluster go only with --samples K" in r.stderr, r.stdout + r.stderr


def test_an_evaluation_with_a_run_that_could_not_do_its_work_is_degraded(tmp_path):
    """Every recording run, but one run failed (its joints are not the scene's robot's): counted not correct, and
    the evaluation says it is degraded (exit 3), not complete."""
    from recordings.rosbag import RecordingWriter

    recs = tmp_path / "recordings"
    recs.mkdir()
    with RecordingWriter(recs / "ball_drop_other_robot.mcap") as w:
        for i in range(50):
            w.joint_state(i * 0.01, ["j1", "finger"], [0.0, 1.0], [0.0, 0.0], [0.0, 0.0])
        w.metadata("twin.ground_truth", {"in_container": "true"})
    out = tmp_path / "t2.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "evaluate", "--recordings", str(recs), "--configs",
                        "baseline1", "--json", str(out), "--run-dir", str(tmp_path / "runs")], capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 3, r.stdout + r.stderr
    assert "not complete (never counted correct): ball_drop_other_robot.mcap baseline1: failed" in r.stdout, r.stdout
    assert "status: degraded: 1 run(s) did not end complete" in r.stdout, r.stdout
    result = json.loads(out.read_text())
    assert result["status"] == "degraded" and result["overall"]["all"]["baseline1"] == [0, 1], result


# one short recording per reality and failure kind, seeds 8001.. (used nowhere else): ball_drop's six outcomes
# and insertion's four bands of localization error (slides in, guided by the chamfer, on the rim, beside)
KINDS = [("ball_drop", outcome, None) for outcome in ("success", "released_early", "missed", "empty_grasp",
                                                       "slipped", "knocked")] + \
        [("insertion", None, err) for err in (0.003, 0.009, 0.02, 0.045)]


@pytest.mark.slow
def test_every_reality_and_failure_kind_end_to_end(tmp_path):
    """Generate one short recording per reality (pybullet, MuJoCo) and failure kind, and interpret each with
    the ensemble and signal binding through `twin evaluate`: the ensemble is right on every one; on a slipped
    ball (the gripper signal still says closed) signal binding is wrong, the ensemble right."""
    recs = tmp_path / "recordings"
    recs.mkdir()
    seed = 8000
    for reality in ("pybullet", "mujoco"):
        for scenario, outcome, err in KINDS:
            seed += 1
            name = f"{reality}_{outcome or f'ins{round(err * 1000)}mm'}.mcap"
            argv = ["--scenario", scenario, "--seed", str(seed), "--reality", reality, "--time-scale", "0.7"]
            argv += ["--outcome", outcome, "--container", ("bin", "cup")[seed % 2]] if outcome else \
                ["--localization-error", str(err)]
            twin("record", "synth", *argv, "--out", str(recs / name), "-q")
    out = tmp_path / "t2.json"
    r = twin("evaluate", "--recordings", str(recs), "--configs", "ensemble,baseline2", "--json", str(out),
             "--run-dir", str(tmp_path / "runs"), timeout=1500)
    result = json.loads(out.read_text())
    runs = result["runs"]
    assert len(runs) == 2 * len(KINDS), r.stdout
    assert not list(tmp_path.glob("*.md")) and not list(tmp_path.glob("*.png"))  # --json writes only the JSON
    kinds = {(run["reality"], run["kind"]) for run in runs}
    assert len(kinds) == 2 * len(KINDS), sorted(kinds)  # one of each reality and kind
    wrong = [(run["recording"], run["kind"], run["truth"], run["interpretations"]["ensemble"], run["status"])
             for run in runs if not run["correct"]["ensemble"]]
    assert not wrong, wrong
    for run in runs:
        assert run["status"]["ensemble"] == "complete", (run["recording"], run["status"])
        if run["kind"] == "slipped":
            assert run["truth"] is False and run["correct"]["baseline2"] is False, run["recording"]
            assert any("grasp_lost" in h for h in run["handovers"]["ensemble"]), run["handovers"]["ensemble"]


@pytest.mark.slow
@pytest.mark.parametrize("where,times", [(["--parallel", "1"], 1), (["--cold"], 1), (["--parallel", "2"], 1),
                                         (["--parallel", "1"], 2)],
                         ids=["warm", "cold", "warm-two-at-a-time", "warm-signal-delivered-twice"])
def test_ctrl_c_ends_an_evaluation_truncated_with_what_it_evaluated(tmp_path, where, times):
    """Ctrl-C on ``twin evaluate``: the runs going on end truncated, no recording after them begins, the figures of
    what was evaluated are still written (status truncated, the recordings not run named, the cut runs counted
    neither right nor wrong), the table is not, and the exit code is a truncated run's. Two at a time, both
    recordings are going on when the first run's line is printed: neither is named not run. The same Ctrl-C
    delivered twice (a process group's signal that a wrapper passes on too) is one stop, not an interrupt."""
    recs = tmp_path / "recordings"
    recs.mkdir()
    for name in ("ball_drop_00.mcap", "ball_drop_01.mcap"):
        (recs / name).symlink_to(ROOT / "recordings" / name)
    out, table = tmp_path / "t2.json", tmp_path / "t2.md"
    code, text = ctrl_c_when(["evaluate", "--recordings", str(recs), "--configs", "ensemble,baseline1,baseline2",
                              "--json", str(out), "--table", str(table), "--run-dir", str(tmp_path / "runs"), *where],
                             lambda line: line.startswith(("[1/2]", "[2/2]")), times=times)
    assert code == 4, text
    result = json.loads(out.read_text())
    assert result["status"] == "truncated" and result["stopped"] == "stopped by Ctrl-C", text
    two = "2" in where
    assert result["not_run"] == ([] if two else [str(recs / "ball_drop_01.mcap")])
    assert len(result["runs"]) == (2 if two else 1), text
    assert not table.exists() and "not written" in text
    for run in result["runs"]:
        cut = [c for c, st in run["status"].items() if st != "complete"]
        assert all(run["status"][c] == "truncated" and c not in run["correct"] for c in cut), run
        assert all(c in run["correct"] for c in run["status"] if c not in cut), run
    assert any(st == "truncated" for run in result["runs"] for st in run["status"].values()), text
    cut_n = sum(st == "truncated" for run in result["runs"] for st in run["status"].values())
    assert f"{len(result['not_run'])} of 2 recordings not begun, {cut_n} run{'s' if cut_n != 1 else ''} cut short" \
        in text, text
    assert sum(n for _, n in result["overall"]["all"].values()) == sum(
        st == "complete" for run in result["runs"] for st in run["status"].values())
    # every configuration is in the last line of figures, those never run too (they used to vanish from it)
    # (said to be of the runs that ended before the stop: the configurations reached different recordings)
    shown = next(line for line in text.splitlines() if line.startswith("correct, of the runs that ended before "))
    assert all(f"{c} " in shown for c in ("ensemble", "baseline1", "baseline2")), shown
    if not two:
        (run,) = result["runs"]
        assert run["status"]["ensemble"] == "complete" and run["correct"]["ensemble"] is True


@pytest.mark.slow
def test_table1_runs_are_complete_measured_in_rounds_and_compared_round_by_round(tmp_path):
    """Table 1 replays a ball drop through the fluid scenes: the recording's perception names none of their entities,
    so every run ended degraded, and each setup's runs went one after another, all counted. The recording now drives
    the robot only (the cup where the scene puts it), each round runs every setup, and a run that is not complete
    would be left out and said (exit 3)."""
    out = tmp_path / "t1.json"
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "evaluate", "rtf", "--repeat", "2", "--json", str(out),
                        "--table", str(tmp_path / "t1.md"), "--run-dir", str(tmp_path / "runs")],
                       capture_output=True, text=True, timeout=1200, env={**os.environ, "PYTHONPATH": str(ROOT)},
                       cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    d = json.loads(out.read_text())
    assert d["status"] == "complete" and d["left_out"] == [] and d["order"] == "rounds, setups alternating"
    assert all(s["rounds"] == [0, 1] and len(s["rtf_all"]) == 2 for s in d["setups"])
    rounds = [line.split(":")[0] for line in r.stdout.splitlines() if line.startswith("round ")]
    assert rounds == ["round 1"] * 5 + ["round 2"] * 5  # (every setup in a round before the next round)
    one = d["setups"][1]
    assert one["vs_one_world_50"] == 0.0 and d["setups"][2]["vs_one_world_50"] is not None
    assert "rounds" in (tmp_path / "t1.md").read_text()


def test_tables_name_the_machine_their_figures_were_measured_on():
    """Table 1 and Table 2 said 'this 2-core machine' whatever machine ran them (and a render on another machine):
    the figures keep their cores, the tables say them, older figures say no number."""
    from bench.evaluate import machine_cores, merge_results, on_machine, summarise

    fresh = summarise([], ["ensemble"], "recordings/", 0.0)
    assert fresh["cores"] == machine_cores() >= 1
    assert on_machine({"cores": 2}) == "a 2-core machine" and on_machine({}) == "the machine it ran on"
    assert merge_results([{**fresh, "cores": 4}, {**fresh, "cores": 4}])["cores"] == 4
    assert merge_results([{**fresh, "cores": 4}, {**fresh, "cores": 2}])["cores"] is None
