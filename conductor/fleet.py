"""Many whole runs at once (``--samples``, ``twin evaluate --cluster``): where each ensemble runs.

A job is a plain dict (it crosses process boundaries as it is): the scene's text and file name, the recording
(a path where the job runs), the perception to apply, an ensemble name and a run folder. :func:`run_job` does one
job as ``twin run`` would: its own embedded router, its own agents, on loopback, so two jobs never share a bus.
The fleets place the jobs:

- :class:`LocalFleet`: ``jobs`` at a time on this machine (threads, each driving one ensemble of processes);
- :class:`WarmFleet`: through a ``twin serve`` service in this process (agents started once, reinitialised);
  :class:`WarmLocal` is one on an embedded router of its own (``twin run --samples``' default);
- :class:`DaskFleet`: on a Dask distributed cluster (``--cluster tcp://scheduler:8786``): one task per job, so
  each ensemble is placed whole on one worker; the workers need this project installed (or on ``PYTHONPATH``)
  and the recordings at the same path.

Dask distributed rather than Ray: it is pure Python, installs in seconds on a two-core CI machine, and its
scheduler and workers are ordinary processes one starts by hand (``dask scheduler``, ``dask worker ADDRESS``) on
the machines one has; Ray brings a large runtime of its own for features (actors, object store) a job per
ensemble does not need.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable
from concurrent.futures import CancelledError, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from .record import unrun

if TYPE_CHECKING:
    from .launch import ClosedBus, Stopper
    from .service import Service

log = logging.getLogger("twin.fleet")

Job = dict[str, Any]
Progress = Callable[[int, dict[str, Any]], None]


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
        rec = load_recording(job["recording"], remap=job.get("remap"), joint_order=job.get("joint_order"))
        if job.get("perception") is not None:
            scene.apply_perception(job["perception"])
        deadline = job.get("deadline") or 600.0 + 20.0 * rec.duration
        return run_embedded(scene, ReplaySource(rec), ensemble=job["ensemble"], run_dir=job["run_dir"],
                            deadline=deadline, metadata=run_metadata(scene, job["scene_text"], rec),
                            max_ticks=job.get("max_ticks"), stopper=stopper)
    except Exception as e:  # the job's answer is its summary, whatever happened
        log.exception("job %s", job.get("ensemble"))
        return unrun(f"{type(e).__name__}: {e}")


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
                joint_order=j.get("joint_order"), deadline=j.get("deadline")), Path(j["run_dir"])))

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

    from .launch import ClosedBus, open_router
    from .service import Service

    root.mkdir(parents=True, exist_ok=True)
    bus = ClosedBus(root)
    opts = ZenohOptions(mode="router")
    opts.auth_dictionary = str(bus.dictionary)
    session, endpoint = open_router(options=opts)
    return session, Service(session, endpoint, ensemble, root, max_pools=max_pools, agent_env=bus.agent_env()), bus


class DaskFleet:
    """A Dask distributed cluster at ``address`` (``tcp://host:8786``): one task per job."""

    def __init__(self, address: str, timeout: float = 30.0) -> None:
        from distributed import Client

        self.client = Client(address, timeout=timeout)
        workers = self.client.scheduler_info().get("workers", {})
        self.where = f"the Dask cluster at {address} ({len(workers)} workers)"
        self._stopped: str | None = None
        self._futures: list[Any] = []

    def stop(self, reason: str) -> None:
        """Cancel the jobs (thread-safe): they are reported ``truncated``, not run. A run already going on on a
        worker cannot be reached from here: it goes on there to its end, and its answer is dropped."""
        self._stopped = reason
        waiting = [f for f in self._futures if not f.done()]  # the answers already there are kept
        if waiting:
            self.client.cancel(waiting)

    def map(self, jobs: list[Job], progress: Progress | None = None) -> list[dict[str, Any]]:
        from distributed import as_completed

        if self._stopped is not None:
            return [unrun(f"not run: stopped by {self._stopped}", "truncated") for _ in jobs]
        # each job a task: its ensemble whole on one worker
        futures = self._futures = self.client.map(run_job, jobs, pure=False)
        if self._stopped is not None:  # stopped while they were submitted
            self.client.cancel(futures)
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[dict[str, Any] | None] = [None] * len(jobs)
        for fut in as_completed(futures):
            i = index[fut.key]
            try:
                out[i] = fut.result()
            except CancelledError:  # (also a job that ended as it was cancelled: its answer is not to be had)
                out[i] = unrun(f"not run: stopped by {self._stopped}", "truncated")
            if progress is not None:
                progress(i, out[i] or {})
        return [s or {} for s in out]

    def close(self) -> None:
        self.client.close()
