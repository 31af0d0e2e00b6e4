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
  nothing else: each recording travels with its jobs (once per recording), and a worker that does not share the
  client's files sends each run's folder back with its summary (:mod:`conductor.parcels`).

Dask distributed rather than Ray: it is pure Python, installs in seconds on a two-core CI machine, and its
scheduler and workers are ordinary processes one starts by hand (``dask scheduler``, ``dask worker ADDRESS``) on
the machines one has; Ray brings a large runtime of its own for features (actors, object store) a job per
ensemble does not need.
"""
from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from protocol.errors import TwinError

from . import parcels
from .record import unrun

if TYPE_CHECKING:
    from .launch import ClosedBus, Stopper
    from .service import Service

log = logging.getLogger("twin.fleet")

Job = dict[str, Any]
Progress = Callable[[int, dict[str, Any]], None]
WATCH_S = 0.5
"""How often a job on a cluster looks whether its fleet was stopped (seconds)."""


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
                            max_ticks=job.get("max_ticks"), rtf=job.get("rtf"), stopper=stopper,
                            register_timeout=job.get("register_timeout") or 60.0)
    except Exception as e:  # the job's answer is its summary, whatever happened (in its folder too)
        log.exception("job %s", job.get("ensemble"))
        summary = unrun(f"{type(e).__name__}: {e}")
        with contextlib.suppress(Exception):
            from .launch import write_summary

            write_summary(Path(job["run_dir"]) / "summary.json", summary)
        return summary


def cluster_job(job: Job, signal: str) -> dict[str, Any]:
    """:func:`run_job` on a Dask worker, watching the cluster Variable ``signal`` that :meth:`DaskFleet.stop` sets
    (its value the reason): a job that has not begun then is not run, a run going on ends ``truncated``. A
    worker whose twin code is not the client's (``code``, :func:`~conductor.provenance.code_fingerprint`) runs
    nothing: its answers would be another twin's."""
    import socket

    from .provenance import code_fingerprint, scene_code_differs

    if job.get("code") is not None and job["code"] != code_fingerprint():
        return unrun(f"not run: the Dask worker on {socket.gethostname()} runs other twin code than the client "
                     f"(code {code_fingerprint()}, the client's {job['code']}): install the client's checkout "
                     "there, and start its workers again")
    off = scene_code_differs(job["scene_code"], job["scene_text"], job.get("scene_file", "<scene>")) \
        if job.get("scene_code") else None
    if off is not None:  # (the scene's own FMI unit or model module: another copy gave other answers, complete)
        return unrun(f"not run: the Dask worker on {socket.gethostname()} has not the scene's own model code: {off}; "
                     "put the same files at the same paths there")
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
            except Exception as e:  # the client let go of the signal (its map ended) or the scheduler went away:
                # no one waits for this run's answer, and a run left going wrote 'complete' over the folder the
                # client had said lost; it ends here, truncated, saying why
                log.warning("job %s: its stop signal is gone (%s): the run stops", job.get("ensemble"), e)
                stopper.stop("its client no longer waits for it (the Dask scheduler was lost, or the client's map "
                             "ended): what it ran is in its folder, its answer reached no one")
                return
            if r is not None:
                stopper.stop(r)
                return

    threading.Thread(target=watch, name="twin-cluster-stop", daemon=True).start()
    try:
        copy = None
        if job.get("recording_parcel") is not None:
            copy = str(parcels.unpack(job["recording_parcel"]))
            job = {**job, "recording_at": copy}
        if parcels.shares_files(Path(job["run_dir"]), job.get("run_mark")):
            summary = run_job(job, stopper)
        else:
            with parcels.job_folder() as tmp:  # the client's folder is not here: the run's files go back
                here = Path(tmp) / "run"
                summary = parcels.renamed(run_job({**job, "run_dir": str(here)}, stopper), str(here), job["run_dir"])
                summary["_files"] = parcels.files_of(here)
        return parcels.renamed(summary, copy, job["recording"]) if copy else summary  # (the client's path)
    except Exception as e:  # (a recording that could not be unpacked, a run folder that could not be read back)
        log.exception("job %s", job.get("ensemble"))
        return unrun(f"on the Dask worker {socket.gethostname()}: {type(e).__name__}: {e}")
    finally:
        over.set()


def _carried(p: dict[str, Any]) -> dict[str, Any]:
    """A :func:`~conductor.parcels.parcel` as a task's result on the cluster, passed from worker to worker to the
    jobs that read it."""
    return p


def _side_by_side(run: Callable[[Job], dict[str, Any]], jobs: list[Job], n: int, progress: Progress | None,
                  stopped: Callable[[], str | None]) -> list[dict[str, Any]]:
    """``run`` every job, ``n`` at a time, the summaries in the jobs' order (``progress`` told as each ends); a
    job that has not begun when ``stopped()`` names a reason is not run (its summary says so, ``truncated``)."""
    def one(ij: tuple[int, Job]) -> dict[str, Any]:
        reason = stopped()
        if reason is None:
            s = run(ij[1])
        else:  # (its folder says so too: an earlier run's summary there is not taken for its own)
            s = unrun(f"not run: stopped by {reason}", "truncated")
            if ij[1].get("run_dir"):
                parcels.land(s, Path(ij[1]["run_dir"]))
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
                joint_order=j.get("joint_order"), deadline=j.get("deadline"), rtf=j.get("rtf")), Path(j["run_dir"]),
                lambda: self._stopped))

        return _side_by_side(one, jobs, self.parallel, progress, lambda: self._stopped)

    def close(self) -> None:
        pass


class WarmLocal(WarmFleet):
    """``jobs`` at a time on this machine, on the warm agents of a service of its own (:func:`local_service`;
    its agents' logs under ``root``): each set of models is started once, not once per sample."""

    def __init__(self, root: Path, jobs: int = 1, register_timeout: float = 60.0) -> None:
        self.session, service, self.bus = local_service(root, f"samples{os.getpid()}", max_pools=max(1, jobs),
                                                        register_timeout=register_timeout)
        super().__init__(service, jobs)
        self.where = f"this machine, {self.parallel} at a time on warm agents"

    def close(self) -> None:
        self.service.close()
        self.session.close()
        self.bus.close()


def local_service(root: Path, ensemble: str, max_pools: int,
                  register_timeout: float = 60.0) -> tuple[Any, Service, ClosedBus]:
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
    return session, Service(session, endpoint, ensemble, root, max_pools=max_pools, agent_env=bus.agent_env(),
                            register_timeout=register_timeout), bus


def connect_cluster(address: str, timeout: float) -> Any:
    """A Dask ``Client`` of the scheduler at ``address``; TwinError in one line when there is none, the address is
    not a ``tcp://`` one (an empty one: an unset variable), or what answers there does not speak as a scheduler.
    The address is tried first on a loop of this call's own, bounded by ``timeout`` (distributed's own timeout does
    not bound a port that takes the connection and never speaks, and a Client left hanging in a thread blocks every
    Client after it in the process)."""
    import asyncio

    if not address.strip():
        raise TwinError("--cluster '': an empty address (an unset variable?): give the Dask scheduler's, "
                        "e.g. tcp://host:8786")
    if "://" not in address:  # (host:port: Dask's own default is tcp)
        address = "tcp://" + address.strip()
    if not address.startswith("tcp://"):
        raise TwinError(f"--cluster {address}: not a tcp://host:port address (the twin's jobs reach their scheduler "
                        "over plain TCP; tls://, ucx:// and others need a configuration it does not make)")
    from distributed import Client
    from distributed.comm import connect

    async def probe() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=timeout), timeout)
        try:
            await asyncio.wait_for(comm.write({"op": "identity", "reply": True}), timeout)
            answer = await asyncio.wait_for(comm.read(), timeout)
        finally:
            comm.abort()
        if not (isinstance(answer, dict) and answer.get("type") == "Scheduler"):
            raise ValueError(f"what answers there is no scheduler ({str(answer)[:80]})")

    try:
        asyncio.run(probe())
    except (OSError, TimeoutError) as e:  # nobody there, or nothing that speaks
        raise TwinError(f"--cluster {address}: no Dask scheduler answered within {timeout:g} s "
                        f"({type(e).__name__}{': ' + str(e).splitlines()[0] if str(e) else ''})") from None
    except Exception as e:  # a bad address, a peer that is not a scheduler
        raise TwinError(f"--cluster {address}: cannot connect to a Dask scheduler there ({type(e).__name__}: "
                        f"{str(e).splitlines()[0] if str(e) else ''})") from None
    try:
        return Client(address, timeout=timeout)
    except Exception as e:  # (it answered a moment ago: gone since)
        raise TwinError(f"--cluster {address}: the Dask scheduler stopped answering ({type(e).__name__}: {e})") \
            from None


class DaskFleet:
    """A Dask distributed cluster at ``address`` (``tcp://host:8786``): one task per job.

    A map does not wait for ever: once stopped, the jobs that have not come back within :attr:`STOP_GRACE_S`
    (those running end truncated at once; those never begun) are cancelled and reported ``truncated``; a
    cluster without a worker for :attr:`NO_WORKER_S` fails the jobs left, saying so."""

    STOP_GRACE_S = 15.0
    NO_WORKER_S = 60.0
    ANSWER_S = 10.0
    """Longest a request to the scheduler may go unanswered during a map or a stop: one that holds its connection
    but no longer answers (a frozen host, a stopped process) held the command for ever, deaf to SIGTERM."""

    def __init__(self, address: str, timeout: float = 30.0) -> None:
        self.client = connect_cluster(address, timeout)
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
                _within(self.ANSWER_S, signal.set, reason)
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
            del futures  # (each is let go of once its result is in)
            lost: str | None = None  # why the cluster cannot give the jobs left back
            while pending:
                try:
                    wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
                except TimeoutError:  # (a second without news: is it stopped, is there a worker?)
                    pass
                except Exception as e:  # the scheduler gone: its futures cancelled (the jobs that ended are kept)
                    lost = f"the Dask scheduler was lost ({type(e).__name__}: {e})"
                for fut in [f for f in pending if f.done()]:
                    pending.discard(fut)
                    i = index[fut.key]
                    try:
                        out[i] = fut.result()
                    except Exception as e:  # a worker lost, the task killed: that job's answer is not to be had
                        out[i] = unrun(f"the cluster lost the job: {type(e).__name__}: {e}")
                    out[i] = parcels.land(out[i], Path(jobs[i]["run_dir"]))  # type: ignore[arg-type]
                    fut.release()  # (its result, a run folder perhaps, need not stay on the cluster)
                    if progress is not None:
                        progress(i, out[i])  # type: ignore[arg-type]
                given_up = (lost, "failed") if pending and lost is not None else self._give_up() if pending else None
                if given_up is not None:
                    why, status = given_up
                    with contextlib.suppress(Exception):  # (a scheduler that does not answer: the jobs are lost)
                        _within(self.ANSWER_S, self.client.cancel, list(pending))
                    for fut in pending:
                        i = index[fut.key]
                        out[i] = parcels.land(unrun(why, status), Path(jobs[i]["run_dir"]))
                    pending = set()
            return [o if o is not None else unrun("the cluster returned nothing") for o in out]
        finally:
            for job in jobs:
                (Path(job["run_dir"]) / parcels.RUN_MARK).unlink(missing_ok=True)
            with self._lock:
                self._signals.discard(signal)
            with contextlib.suppress(Exception):
                _within(self.ANSWER_S, signal.delete)

    def _ship(self, jobs: list[Job], code: str, token: str) -> list[Job]:
        """The jobs as they go to the cluster: each with the client's code fingerprint, its recording (sent once per
        recording, not once per job) and a :data:`~conductor.parcels.RUN_MARK` token in its run folder (made here,
        what an earlier run left there removed)."""
        from .provenance import scene_code

        sent: dict[str, Any] = {}
        scenes: dict[str, dict[str, str]] = {}  # scene text -> its own model code (checked by each worker)
        out = []
        for job in jobs:
            rec = str(job["recording"])
            if rec not in sent:
                try:
                    packed = parcels.parcel(rec)
                except OSError as e:
                    raise TwinError(f"{rec}: cannot be read to send to the cluster ({e.strerror or e})") from None
                # a task of its own (not scattered: that needs a worker there now), which its jobs depend on
                sent[rec] = self.client.submit(_carried, packed, pure=False)
            run_dir = Path(job["run_dir"])
            try:
                parcels.mark(run_dir, token)
            except OSError as e:
                raise TwinError(f"--run-dir {run_dir}: cannot be written ({e.strerror or e})") from None
            text = job.get("scene_text")
            if isinstance(text, str) and text not in scenes:
                scenes[text] = scene_code(text, job.get("scene_file", "<scene>"))
            own = scenes.get(text, {}) if isinstance(text, str) else {}
            out.append({**job, "code": code, "recording_parcel": sent[rec], "run_mark": token, "scene_code": own})
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
            workers = len(_within(self.ANSWER_S, self.client.nthreads))
        except Exception as e:  # the scheduler is gone, or does not answer
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
        with contextlib.suppress(Exception):  # (a scheduler that does not answer: nothing more to say to it)
            _within(self.ANSWER_S, self.client.close)


def _within(seconds: float, call: Callable[..., Any], *args: Any) -> Any:
    """``call(*args)``, in a thread of its own so that a scheduler that never answers cannot hold this one:
    TimeoutError when it has not returned within ``seconds`` (it is left to end, or not, on its own)."""
    done: list[Any] = []

    def go() -> None:
        try:
            done.append((True, call(*args)))
        except BaseException as e:  # noqa: BLE001 (raised again in the caller's thread)
            done.append((False, e))

    t = threading.Thread(target=go, name="twin-dask-call", daemon=True)
    t.start()
    t.join(seconds)
    if not done:
        raise TimeoutError(f"no answer within {seconds:g} s")
    ok, value = done[0]
    if not ok:
        raise value
    return value
