"""What travels between a client and a Dask worker (conductor/parcels.py), without a cluster: the recording's copy
on a worker, and the run folder on the client. The real cluster is in tests/test_samples.py."""
from __future__ import annotations

import json
import threading
from pathlib import Path

from conductor.parcels import RUN_MARK, land, mark, parcel, renamed, shares_files, unpack
from conductor.record import unrun


def test_jobs_of_one_recording_unpacking_at_once_all_read_a_whole_copy(tmp_path, monkeypatch):
    """A worker with several threads gets the jobs of one recording at once: each unpacked a copy, and the last to
    finish removed the copy in place before putting its own there, while the others read it (FileNotFoundError)."""
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    bag = tmp_path / "client" / "bag"
    bag.mkdir(parents=True)
    for i in range(40):
        (bag / f"f{i:03d}.bin").write_bytes(bytes([i]) * 20000)
    p = parcel(bag)
    seen, failed = [], []
    start = threading.Barrier(8)

    def job() -> None:
        start.wait()
        try:
            there = unpack(p)
            seen.append(sum(len(f.read_bytes()) for f in sorted(there.iterdir()) if f.suffix == ".bin"))
        except Exception as e:  # noqa: BLE001 (what the test looks for)
            failed.append(repr(e))

    threads = [threading.Thread(target=job) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert failed == [] and seen == [40 * 20000] * 8
    root = unpack(p).parent.parent
    assert [e.name for e in root.iterdir() if e.name.startswith(".unpacking-")] == []  # no half copies left
    assert root.stat().st_mode & 0o077 == 0  # the worker's user's alone


def test_a_run_folder_on_the_client_never_shows_an_earlier_runs_answer(tmp_path):
    """A job that failed, was lost or was given up wrote nothing on the client: its folder kept the earlier run's
    summary and log, which read as this run's (complete, perhaps). The client clears them when it marks the folder,
    and every job's summary is written there."""
    folder = tmp_path / "sample-001"
    folder.mkdir()
    for name in ("run.mcap", "summary.json", "run.rrd", "agent-holder.log"):
        (folder / name).write_text("an earlier run's")
    (folder / "notes.txt").write_text("the user's")
    mark(folder, "token")
    assert sorted(f.name for f in folder.iterdir()) == sorted([RUN_MARK, "notes.txt"])
    assert shares_files(folder, "token") and not shares_files(folder, "another") and shares_files(folder, None)
    s = land(unrun("the cluster lost the job: KilledWorker"), folder)
    assert json.loads((folder / "summary.json").read_text())["status"] == s["status"] == "failed"
    back = {"status": "complete", "status_reasons": [], "run_log": str(folder / "run.mcap"),
            "_files": {"run.mcap": b"log", "summary.json": b"{}", "../outside": b"x"}}
    s = land(back, folder)  # a name that would leave the folder: the answer stands, degraded, said
    assert s["status"] == "degraded" and "could not be written to" in s["status_reasons"][0]
    assert not (tmp_path / "outside").exists()


def test_a_workers_paths_are_the_clients_in_what_is_said():
    s = {"status_reasons": ["/w/copy/r.mcap: 3 joint states left out"], "run_log": "/w/job/run/run.mcap", "ticks": 4}
    out = renamed(renamed(s, "/w/job/run", "/c/runs/s0"), "/w/copy/r.mcap", "/c/r.mcap")
    assert out == {"status_reasons": ["/c/r.mcap: 3 joint states left out"], "run_log": "/c/runs/s0/run.mcap",
                   "ticks": 4}
    assert Path(out["run_log"]).name == "run.mcap"


def test_a_sample_that_could_not_run_here_leaves_its_summary_in_its_folder(tmp_path):
    """--cold samples (conductor.fleet.run_job): one that failed before its run (a recording gone) wrote no summary,
    so its folder, listed as the sample's, held nothing or an earlier run's."""
    from conductor.fleet import run_job

    folder = tmp_path / "sample-000"
    s = run_job({"scene_text": "name: x\n", "scene_file": "x.yaml", "recording": str(tmp_path / "gone.mcap"),
                 "ensemble": "x", "run_dir": str(folder)})
    assert s["status"] == "failed"
    assert json.loads((folder / "summary.json").read_text())["status_reasons"] == s["status_reasons"]
