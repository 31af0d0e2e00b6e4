"""Many whole runs at once (``--samples``, ``twin evaluate --cluster``): where each ensemble runs.

A job is a plain dict (it crosses process boundaries as it is): the scene's text and file name, the recording
(a path where the job runs), the perception to apply, an ensemble name and a run folder. :func:`run_job` does one
job as ``twin run`` would: its own embedded router, its own agents, on loopback, so two jobs never share a bus.
The fleets place the jobs:

- :class:`LocalFleet`: ``jobs`` at a time on this machine (threads, each driving one ensemble of processes);
- :class:`WarmFleet`: through a ``twin serve`` service in this process (agents started once, reinitialised);
  :class:`WarmLocal` is one on an embedded router of its own (``twin run --samples``' default);
- :class:`DaskFleet`: on a Dask distributed cluster (``--cluster tcp://scheduler:8786``): one task per job, so
  each ensemble is placed whole on one worker; the workers need this project installed (or on ``PYTHONPATH``),
  nothing else: each recording travels with its jobs (:func:`parcel`, once per recording), and a worker that does
  not share the client's files sends each run's folder back with its summary (:data:`RUN_MARK`).

Dask distributed rather than Ray: it is pure Python, installs in seconds on a two-core CI machine, and its
scheduler and workers are ordinary processes one starts by hand (``dask scheduler``, ``dask worker ADDRESS``) on
the machines one has; Ray brings a large runtime of its own for features (actors, object store) a job per
ensemble does not need.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from protocol.errors import TwinError

from .record import unrun

if TYPE_CHECKING:
    from .launch import ClosedBus, Stopper
    from .service import Service

log = logging.getLogger("twin.fleet")

Job = dict[str, Any]
Progress = Callable[[int, dict[str, Any]], None]
WATCH_S = 0.5
"""How often a job on a cluster looks whether its fleet was stopped (seconds)."""
RUN_MARK = ".twin-client"
"""A file the client writes into each job's run folder before a cluster gets the job: a worker that reads the same
token there shares the client's files and writes the run there; one that does not runs in a folder of its own and
sends its files back with the summary."""


class Fleet(Protocol):
    """Where many whole runs go: every fleet below."""

    where: str

    def map(self, jobs: list[Job], progress: Progress | None = None) -> list[dict[str, Any]]:
        """Run every job; their summaries in the jobs' order (``progress`` told as each ends)."""

    def stop(self, reason: str) -> None:
        """End the runs going on (``truncated``) and start no more (thread-safe)."""

    def close(self) -> None:
        """Let go of what the fleet holds."""


def run_job(job: Job, stopper: Stopper | None = None) -> dict[str, Any]:
    """One whole run (see the module docstring); its summary. Never raises for a run that fails: the summary
    says ``failed`` and why (a cluster then still returns every sample). ``stopper`` can end it early."""
    from .launch import run_embedded
    from .provenance import run_metadata
    from .scene import parse_scene
    from .sources.recording import load_recording
    from .sources.replay import ReplaySource

    try:
        scene = parse_scene(job["scene_text"], job.get("scene_file", "<scene>"))
        at = job.get("recording_at") or job["recording"]  # (a worker's copy of the client's recording)
        rec = load_recording(at, remap=job.get("remap"), joint_order=job.get("joint_order"))
        if job.get("perception") is not None:
            scene.apply_perception(job["perception"])
        deadline = job.get("deadline") or 600.0 + 20.0 * rec.duration
        metadata = run_metadata(scene, job["scene_text"], rec)
        if at != job["recording"]:  # the log names the recording as the client does (its sha256 is the copy's)
            metadata["twin.recording"]["path"] = job["recording"]
        return run_embedded(scene, ReplaySource(rec), ensemble=job["ensemble"], run_dir=job["run_dir"],
                            deadline=deadline, metadata=metadata,
                            max_ticks=job.get("max_ticks"), rtf=job.get("rtf"), stopper=stopper)
    except Exception as e:  # the job's answer is its summary, whatever happened
        log.exception("job %s", job.get("ensemble"))
        return unrun(f"{type(e).__name__}: {e}")


def cluster_job(job: Job, signal: str) -> dict[str, Any]:
    """:func:`run_job` on a Dask worker, watching the cluster Variable ``signal`` that :meth:`DaskFleet.stop` sets
    (its value the reason): a job that has not begun then is not run, a run going on ends ``truncated``. A
    worker whose twin code is not the client's (``code``, :func:`~conductor.provenance.code_fingerprint`) runs
    nothing: its answers would be another twin's."""
    import socket

    from .provenance import code_fingerprint

    if job.get("code") is not None and job["code"] != code_fingerprint():
        return unrun(f"not run: the Dask worker on {socket.gethostname()} runs other twin code than the client "
                     f"(code {code_fingerprint()}, the client's {job['code']}): install the client's checkout "
                     "there, and start its workers again")
    from distributed import Variable

    from .launch import Stopper

    watched = Variable(signal)
    stopper, over = Stopper(), threading.Event()

    def reason(wait: float) -> str | None:
        try:
            return str(watched.get(timeout=wait))
        except TimeoutError:
            return None

    first = reason(0.0)
    if first is not None:
        return unrun(f"not run: stopped by {first}", "truncated")

    def watch() -> None:
        while not over.is_set():
            try:
                r = reason(WATCH_S)
            except Exception as e:  # the client let go of the signal (its map ended) or the scheduler went away
                log.debug("job %s: stop signal unreadable (%s)", job.get("ensemble"), e)
                return
            if r is not None:
                stopper.stop(r)
                return

    threading.Thread(target=watch, name="twin-cluster-stop", daemon=True).start()
    try:
        if job.get("recording_parcel") is not None:
            job = {**job, "recording_at": str(unpack(job["recording_parcel"]))}
        if _shares_files(job):
            return run_job(job, stopper)
        with tempfile.TemporaryDirectory(prefix="twin-job-") as tmp:  # the client's folder is not here
            here = Path(tmp) / "run"
            summary = run_job({**job, "run_dir": str(here)}, stopper)
            files = sorted(f for f in here.rglob("*") if f.is_file() and f.name != ".lock") if here.is_dir() else []
            back = {str(f.relative_to(here)): f.read_bytes() for f in files}
            return {**summary, "_ran_in": str(here), "_files": back}
    except Exception as e:  # (a recording that could not be unpacked, a run folder that could not be read back)
        log.exception("job %s", job.get("ensemble"))
        return unrun(f"on the Dask worker {socket.gethostname()}: {type(e).__name__}: {e}")
    finally:
        over.set()


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


def _carried(p: dict[str, Any]) -> dict[str, Any]:
    """A :func:`parcel` as a task's result on the cluster, passed from worker to worker to the jobs that read it."""
    return p


def _inside(root: Path, rel: str) -> Path:
    """``root / rel``, refusing a name that would leave ``root`` (ValueError)."""
    r = Path(rel)
    if r.is_absolute() or ".." in r.parts or not r.parts:
        raise ValueError(f"{rel!r}: not a file name inside a folder")
    return root / r


def unpack(p: dict[str, Any]) -> Path:
    """Where a :func:`parcel` is on this machine (unpacked once, in the temporary directory, under its sha256:
    the jobs of one recording on one worker share it)."""
    home = Path(tempfile.gettempdir()) / "twin-recordings" / str(p["sha256"])[:32]
    if not (home / ".complete").is_file():
        home.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=".unpacking-", dir=home.parent))
        try:
            for rel, data in p["files"].items():
                dest = _inside(work, rel)
                dest.parent.mkdir(parents=True, exist_ok=True)
                dest.write_bytes(data)
            (work / ".complete").touch()
            shutil.rmtree(home, ignore_errors=True)  # (a copy left half made by a worker killed while unpacking)
            os.rename(work, home)
        except OSError:
            if not (home / ".complete").is_file():  # (else another job of this worker unpacked it first)
                raise
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return _inside(home, p["open"])


def _shares_files(job: Job) -> bool:
    """Whether this worker sees the client's run folder for ``job`` (the client's :data:`RUN_MARK` token there)."""
    token = job.get("run_mark")
    if token is None:
        return True
    try:
        return (Path(job["run_dir"]) / RUN_MARK).read_text() == token
    except OSError:
        return False


def _land(summary: dict[str, Any], job: Job) -> dict[str, Any]:
    """A cluster job's summary on the client: a run folder sent back (the worker did not share the client's
    files) is written to the job's run folder, and the summary names it there."""
    from .launch import write_summary

    files, ran_in = summary.pop("_files", None), summary.pop("_ran_in", None)
    if files is None:
        return summary
    dest = Path(job["run_dir"])
    try:
        for rel, data in files.items():
            target = _inside(dest, rel)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
    except (OSError, ValueError) as e:  # the answer stands; its run log is not where it was to be
        why = f"the run folder the Dask worker sent back could not be written to {dest}: {e}"
        if summary.get("status") == "complete":
            summary["status"] = "degraded"
        summary["status_reasons"] = [*summary.get("status_reasons", []), why]
        return summary
    log_file = summary.get("run_log")
    if isinstance(log_file, str) and isinstance(ran_in, str) and log_file.startswith(ran_in):
        summary["run_log"] = str(dest) + log_file[len(ran_in):]
    if "summary.json" in files:
        write_summary(dest / "summary.json", summary)
    return summary


def _side_by_side(run: Callable[[Job], dict[str, Any]], jobs: list[Job], n: int, progress: Progress | None,
                  stopped: Callable[[], str | None]) -> list[dict[str, Any]]:
    """``run`` every job, ``n`` at a time, the summaries in the jobs' order (``progress`` told as each ends); a
    job that has not begun when ``stopped()`` names a reason is not run (its summary says so, ``truncated``)."""
    def one(ij: tuple[int, Job]) -> dict[str, Any]:
        reason = stopped()
        s = run(ij[1]) if reason is None else unrun(f"not run: stopped by {reason}", "truncated")
        if progress is not None:
            progress(ij[0], s)
        return s

    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(one, enumerate(jobs)))


class LocalFleet:
    """``jobs`` runs at a time on this machine."""

    def __init__(self, jobs: int = 1) -> None:
        from .launch import Stopper

        self.jobs = max(1, jobs)
        self.where = f"this machine, {self.jobs} at a time"
        self.stopper = Stopper()

    def stop(self, reason: str) -> None:
        """End the runs going on (``truncated``) and start no more (thread-safe)."""
        self.stopper.stop(reason)

    def map(self, jobs: list[Job], progress: Progress | None = None) -> list[dict[str, Any]]:
        return _side_by_side(lambda j: run_job(j, self.stopper), jobs, self.jobs, progress,
                             lambda: self.stopper.reason)

    def close(self) -> None:
        pass


class WarmFleet:
    """Through a warm :class:`~conductor.service.Service` in this process (its pools run ``parallel`` at once)."""

    def __init__(self, service: Any, parallel: int = 1) -> None:
        self.service, self.parallel = service, max(1, parallel)
        self.where = f"a warm service, {self.parallel} at a time"
        self._stopped: str | None = None

    def stop(self, reason: str) -> None:
        """End the runs going on (``truncated``) and start no more (thread-safe)."""
        self._stopped = reason
        self.service.stop_all(reason)

    def map(self, jobs: list[Job], progress: Progress | None = None) -> list[dict[str, Any]]:
        from .service import Job as ServiceJob

        def one(j: Job) -> dict[str, Any]:
            return dict(self.service.run(ServiceJob(
                scene_text=j["scene_text"], scene_file=j.get("scene_file", "<scene>"), recording=j["recording"],
                perception=j.get("perception"), max_ticks=j.get("max_ticks"), remap=j.get("remap"),
                joint_order=j.get("joint_order"), deadline=j.get("deadline"), rtf=j.get("rtf")), Path(j["run_dir"])))

        return _side_by_side(one, jobs, self.parallel, progress, lambda: self._stopped)

    def close(self) -> None:
        pass


class WarmLocal(WarmFleet):
    """``jobs`` at a time on this machine, on the warm agents of a service of its own (:func:`local_service`;
    its agents' logs under ``root``): each set of models is started once, not once per sample."""

    def __init__(self, root: Path, jobs: int = 1) -> None:
        self.session, service, self.bus = local_service(root, f"samples{os.getpid()}", max_pools=max(1, jobs))
        super().__init__(service, jobs)
        self.where = f"this machine, {self.parallel} at a time on warm agents"

    def close(self) -> None:
        self.service.close()
        self.session.close()
        self.bus.close()


def local_service(root: Path, ensemble: str, max_pools: int) -> tuple[Any, Service, ClosedBus]:
    """A :class:`~conductor.service.Service` on an embedded router of its own on loopback that admits only the
    service's own agents, as ``twin run``'s router does (:class:`~conductor.launch.ClosedBus`, its secrets in
    ``root``): (its session, the service, the bus)."""
    from protocol.config import ZenohOptions

    from .launch import ClosedBus, open_router, output_dir
    from .service import Service

    bus = ClosedBus(output_dir(root))
    opts = ZenohOptions(mode="router")
    opts.auth_dictionary = str(bus.dictionary)
    session, endpoint = open_router(options=opts)
    return session, Service(session, endpoint, ensemble, root, max_pools=max_pools, agent_env=bus.agent_env()), bus


class DaskFleet:
    """A Dask distributed cluster at ``address`` (``tcp://host:8786``): one task per job.

    A map does not wait for ever: once stopped, the jobs that have not come back within :attr:`STOP_GRACE_S`
    (those running end truncated at once; those never begun) are cancelled and reported ``truncated``; a
    cluster without a worker for :attr:`NO_WORKER_S` fails the jobs left, saying so."""

    STOP_GRACE_S = 15.0
    NO_WORKER_S = 60.0

    def __init__(self, address: str, timeout: float = 30.0) -> None:
        from distributed import Client

        try:
            self.client = Client(address, timeout=timeout)
        except (OSError, TimeoutError, ValueError) as e:  # nobody there, a bad address: one line, not a traceback
            raise TwinError(f"--cluster {address}: no Dask scheduler answered within {timeout:g} s ({e})") from None
        workers = self.client.scheduler_info().get("workers", {})
        self.where = f"the Dask cluster at {address} ({len(workers)} workers)"
        self._stopped: str | None = None
        self._stop_seen: float | None = None  # when a map first saw the stop
        self._no_worker_since: float | None = None
        self._signals: set[Any] = set()  # the cluster Variables the jobs of the maps going on watch (stop sets)
        self._lock = threading.Lock()

    def stop(self, reason: str) -> None:
        """End the runs going on (``truncated``, each with the summary of what it ran) and start no more
        (thread-safe): the reason goes to the cluster, where every job of this fleet watches for it
        (:func:`cluster_job`). The jobs not begun come back ``truncated``, not run."""
        with self._lock:
            self._stopped = reason
            signals = list(self._signals)
        for signal in signals:
            try:
                signal.set(reason)
            except Exception as e:  # the scheduler is gone: the jobs are lost anyway, and map says so
                log.warning("could not tell the cluster to stop: %s", e)

    def map(self, jobs: list[Job], progress: Progress | None = None) -> list[dict[str, Any]]:
        from distributed import Variable, wait

        from .provenance import code_fingerprint

        signal = Variable(f"twin-stop-{uuid.uuid4().hex}", client=self.client)
        with self._lock:  # (maps may go on side by side: twin evaluate --parallel N --samples K --cluster)
            stopped = self._stopped
            if stopped is None:
                self._signals.add(signal)
        if stopped is not None:
            return [unrun(f"not run: stopped by {stopped}", "truncated") for _ in jobs]
        try:  # each job a task: its ensemble whole on one worker, which runs the code this client runs
            code, mark = code_fingerprint(), uuid.uuid4().hex
            futures = self.client.map(cluster_job, self._ship(jobs, code, mark), signal=signal.name, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            out: list[dict[str, Any] | None] = [None] * len(jobs)
            pending = set(futures)
            while pending:
                try:
                    wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
                except TimeoutError:  # (a second without news: is it stopped, is there a worker?)
                    pass
                for fut in [f for f in pending if f.done()]:
                    pending.discard(fut)
                    i = index[fut.key]
                    try:
                        out[i] = fut.result()
                    except Exception as e:  # a worker lost, the task killed: that job's answer is not to be had
                        out[i] = unrun(f"the cluster lost the job: {type(e).__name__}: {e}")
                    out[i] = _land(out[i], jobs[i])  # type: ignore[arg-type]
                    if progress is not None:
                        progress(i, out[i])  # type: ignore[arg-type]
                given_up = self._give_up() if pending else None
                if given_up is not None:
                    why, status = given_up
                    self.client.cancel(list(pending))
                    for fut in pending:
                        out[index[fut.key]] = unrun(why, status)
                    pending = set()
            return [o if o is not None else unrun("the cluster returned nothing") for o in out]
        finally:
            for job in jobs:
                (Path(job["run_dir"]) / RUN_MARK).unlink(missing_ok=True)
            with self._lock:
                self._signals.discard(signal)
            try:
                signal.delete()
            except Exception:
                pass

    def _ship(self, jobs: list[Job], code: str, mark: str) -> list[Job]:
        """The jobs as they go to the cluster: each with the client's code fingerprint, its recording (sent once per
        recording, not once per job) and a :data:`RUN_MARK` token in its run folder (made here)."""
        parcels: dict[str, Any] = {}
        out = []
        for job in jobs:
            rec = str(job["recording"])
            if rec not in parcels:
                try:
                    packed = parcel(rec)
                except OSError as e:
                    raise TwinError(f"{rec}: cannot be read to send to the cluster ({e.strerror or e})") from None
                # a task of its own (not scattered: that needs a worker there now), which its jobs depend on
                parcels[rec] = self.client.submit(_carried, packed, pure=False)
            run_dir = Path(job["run_dir"])
            try:
                run_dir.mkdir(parents=True, exist_ok=True)
                (run_dir / RUN_MARK).write_text(mark)
            except OSError as e:
                raise TwinError(f"--run-dir {run_dir}: cannot be written ({e.strerror or e})") from None
            out.append({**job, "code": code, "recording_parcel": parcels[rec], "run_mark": mark})
        return out

    def _give_up(self) -> tuple[str, str] | None:
        """Why to stop waiting for the jobs left, and their status (None: wait on). Called about once a second
        while jobs are out."""
        now = time.monotonic()
        with self._lock:
            if self._stopped is not None:
                self._stop_seen = self._stop_seen or now
                if now - self._stop_seen > self.STOP_GRACE_S:
                    return (f"not run, or not returned within {self.STOP_GRACE_S:g} s: stopped by {self._stopped}",
                            "truncated")
        try:
            workers = len(self.client.nthreads())
        except Exception as e:  # the scheduler is gone
            return f"the Dask scheduler stopped answering ({type(e).__name__}: {e})", "failed"
        if workers:
            self._no_worker_since = None
            return None
        if self._no_worker_since is None:
            self._no_worker_since = now
            log.warning("the Dask cluster has no worker: its jobs wait (for at most %g s)", self.NO_WORKER_S)
        if now - self._no_worker_since > self.NO_WORKER_S:
            return f"the Dask cluster had no worker for {self.NO_WORKER_S:g} s: the job was not run", "failed"
        return None

    def close(self) -> None:
        self.client.close()
