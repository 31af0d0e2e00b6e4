"""What travels between a client and a Dask worker besides the job (:mod:`conductor.fleet`): the recording a job
reads, and the run folder it wrote when the worker does not share the client's files.

- :func:`parcel` packs a recording (a file, or a rosbag2 folder whole) on the client; :func:`unpack` puts it on
  the worker once per recording, in a folder of the worker's user (:func:`cache_root`) under its sha256, where
  copies unused for :data:`KEEP_DAYS` are removed.
- The client writes a token (:data:`RUN_MARK`) into each job's run folder; a worker that reads it back and may
  write there (:func:`shares_files`) runs there, one that does not runs in a folder of its own and sends the
  folder's files back with the summary, which :func:`land` writes where the client said.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from protocol.errors import TwinError

RUN_MARK = ".twin-client"
"""A file the client writes into each job's run folder before a cluster gets the job: a worker that reads the same
token there (and may write there) shares the client's files and writes the run there; one that does not runs in a
folder of its own and sends its files back with the summary."""
KEEP_DAYS = 7.0
"""Days an unpacked recording nobody used is kept on a worker (a folder left by a killed job: one day)."""
STALE = ("run.mcap", "summary.json", "run.rrd")
"""What an earlier run left in a run folder, besides its agents' logs (``agent-*.log``)."""


def parcel(path: str | Path) -> dict[str, Any]:
    """A recording's bytes, to travel with the jobs that read it, so that a worker needs neither the file nor the
    client's path for it: the file, or a rosbag2 folder's files (``open``: what to read, relative to where they are
    unpacked; ``sha256``: of the names and contents, which names the unpacked copy)."""
    p = Path(path)
    folder = p if p.is_dir() else p.parent if p.suffix == ".db3" and (p.parent / "metadata.yaml").is_file() else None
    if folder is None:
        files, opens = {p.name: p.read_bytes()}, p.name
    else:
        files = {str(f.relative_to(folder.parent)): f.read_bytes() for f in sorted(folder.rglob("*")) if f.is_file()}
        opens = str(p.relative_to(folder.parent))
    digest = hashlib.sha256()
    for name in sorted(files):
        digest.update(name.encode() + b"\0")
        digest.update(files[name])
    return {"files": files, "open": opens, "sha256": digest.hexdigest()}


def inside(root: Path, rel: str) -> Path:
    """``root / rel``, refusing a name that would leave ``root`` (ValueError)."""
    r = Path(rel)
    if r.is_absolute() or ".." in r.parts or not r.parts:
        raise ValueError(f"{rel!r}: not a file name inside a folder")
    return root / r


def cache_root() -> Path:
    """This user's folder for what cluster jobs unpack and run in (made private: another user of the machine can
    neither read it nor plant a copy in it)."""
    root = Path(tempfile.gettempdir()) / f"twin-cluster-{os.getuid()}"
    root.mkdir(mode=0o700, exist_ok=True)
    if root.stat().st_uid != os.getuid() or root.is_symlink():
        raise PermissionError(f"{root} is not this user's own folder")
    return root


def unpack(p: dict[str, Any]) -> Path:
    """Where a :func:`parcel` is on this machine: unpacked once under its sha256 (the jobs of one recording on
    one worker share it; two unpacking at once each make a whole copy, and the first one in place is kept)."""
    root = cache_root()
    home = root / str(p["sha256"])[:32]
    if not (home / ".complete").is_file():
        work = Path(tempfile.mkdtemp(prefix=".unpacking-", dir=root))
        try:
            for rel, data in p["files"].items():
                dest = inside(work, rel)
                dest.parent.mkdir(parents=True, exist_ok=True)
                dest.write_bytes(data)
            (work / ".complete").touch()
            try:
                os.rename(work, home)  # (atomic: a copy in place is always whole, and never replaced)
            except OSError:
                if not (home / ".complete").is_file():
                    raise
        finally:
            shutil.rmtree(work, ignore_errors=True)
    os.utime(home / ".complete")  # (used now: kept another KEEP_DAYS)
    _evict(root, keep=home)
    return inside(home, p["open"])


def _evict(root: Path, keep: Path) -> None:
    """Remove the copies unused for :data:`KEEP_DAYS` and what killed jobs left (unpacking, running) a day ago."""
    now = time.time()
    for entry in root.iterdir():
        if entry == keep or not entry.is_dir():
            continue
        try:
            done = entry / ".complete"
            age = now - (done.stat().st_mtime if done.is_file() else entry.stat().st_mtime)
        except OSError:
            continue
        if age > (KEEP_DAYS if done.is_file() else 1.0) * 86400:
            shutil.rmtree(entry, ignore_errors=True)


def job_folder() -> tempfile.TemporaryDirectory[str]:
    """A folder of its own for a job whose worker does not share the client's files (removed after it)."""
    return tempfile.TemporaryDirectory(prefix="job-", dir=cache_root())


def in_use(run_dir: Path) -> str | None:
    """The pid of the run that holds ``run_dir`` now (its ``.lock``, as :func:`conductor.launch` takes it), "?"
    when it does not say, or None when none holds it."""
    import fcntl

    try:
        fd = os.open(run_dir / ".lock", os.O_RDONLY)
    except OSError:
        return None  # (no lock file: no run has it)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None
    except OSError:
        return os.read(fd, 32).decode(errors="replace").strip() or "?"
    finally:
        os.close(fd)


def clear(run_dir: Path) -> None:
    """Make ``run_dir`` for a run: what an earlier run left there goes (else a job that fails or is not run before
    it writes anything leaves the earlier run's summary and log there as its own). TwinError when a run going on
    holds it (its files are its own)."""
    holder = in_use(run_dir)
    if holder is not None:
        raise TwinError(f"--run-dir {run_dir}: another run is using it (pid {holder}): give each run its own folder")
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in [*(run_dir / n for n in STALE), *run_dir.glob("agent-*.log")]:
        stale.unlink(missing_ok=True)


def only_run_files(folder: Path) -> bool:
    """Whether ``folder`` holds nothing but what a run writes (its log, summary, stream, agents' logs, marks), and
    no run going on holds it."""
    return folder.is_dir() and in_use(folder) is None and all(
        f.is_file() and (f.name in STALE or f.name in (RUN_MARK, ".lock") or
                         (f.name.startswith("agent-") and f.name.endswith(".log"))) for f in folder.iterdir())


def mark(run_dir: Path, token: str) -> None:
    """Make ``run_dir`` on the client for a cluster job (:func:`clear`), its token written."""
    clear(run_dir)
    (run_dir / RUN_MARK).write_text(token)


def shares_files(run_dir: Path, token: str | None) -> bool:
    """Whether this worker sees the client's ``run_dir`` (its token there) and may write there."""
    if token is None:
        return True
    try:
        return (run_dir / RUN_MARK).read_text() == token and os.access(run_dir, os.W_OK)
    except OSError:
        return False


def files_of(folder: Path) -> dict[str, bytes]:
    """A run folder's files, to send back (not its lock)."""
    if not folder.is_dir():
        return {}
    return {str(f.relative_to(folder)): f.read_bytes() for f in sorted(folder.rglob("*"))
            if f.is_file() and f.name != ".lock"}


def renamed(value: Any, old: str, new: str) -> Any:
    """``value`` with ``old`` replaced by ``new`` in every string in it (a worker's paths, as the client knows
    them)."""
    if isinstance(value, str):
        return value.replace(old, new)
    if isinstance(value, list):
        return [renamed(v, old, new) for v in value]
    if isinstance(value, dict):
        return {k: renamed(v, old, new) for k, v in value.items()}
    return value


def land(summary: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    """A cluster job's summary on the client: a run folder sent back (``_files``, from a worker that does not share
    the client's files) is written to ``run_dir``; the summary is written there in every case (a job that failed or
    was lost has one too). A folder that cannot be written makes a complete run degraded, said."""
    from .launch import write_summary

    files = summary.pop("_files", None) or {}
    try:
        for rel, data in files.items():
            target = inside(run_dir, rel)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        write_summary(run_dir / "summary.json", summary)
    except (OSError, ValueError) as e:  # the answer stands; its run folder is not where it was to be
        why = f"the run folder could not be written to {run_dir}: {e}"
        if summary.get("status") == "complete":
            summary["status"] = "degraded"
        summary["status_reasons"] = [*summary.get("status_reasons", []), why]
    return summary
