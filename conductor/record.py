"""What a run did, counted as it goes, and the run summary made from it at the end."""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .registry import Registry
from .responsibility import Responsibilities
from .runlog import MAX_MESSAGE
from .scene import Scene

log = logging.getLogger("twin.conductor")

MAX_ERRORS = 50  # the summary lists at most this many problems

STATUSES = ("complete", "degraded", "truncated", "interrupted", "failed")
"""How far a run's answer can be trusted:

- ``complete``: every model answered every step, nothing was lost, dropped or refused; the whole source ran;
- ``degraded``: the run went to its end, but something the answer may depend on went wrong (a model lost and
  its responsibilities taken over by the main model, a step that failed or was given up, a trigger that could
  not do what it said, input messages left out or dropped, a predicate that could not be evaluated);
- ``truncated``: stopped before the end of its source (a stop request, ``max_ticks``, the run's deadline);
- ``interrupted``: stopped by a signal (SIGINT, SIGTERM);
- ``failed``: it could not run or could not go on (no agents, the main model died, the run log failed)."""
EXIT_CODES = {"complete": 0, "failed": 1, "degraded": 3, "truncated": 4, "interrupted": 5}
"""The process exit code of a run by its status (2 stays the code of a bad command line or scene)."""


def exit_code(summary: dict[str, Any]) -> int:
    """A run's exit code: :data:`EXIT_CODES` by its status, 2 when it failed on the user's input (``bad_input``:
    a scene that does not fit what its agents declared when they registered, as ``twin check`` exits)."""
    return 2 if summary.get("bad_input") else EXIT_CODES.get(summary.get("status", "failed"), 1)


def unrun(reason: str, status: str = "failed", scene: str = "?") -> dict[str, Any]:
    """The summary of a run that stepped no tick (it could not start, or was stopped before it began)."""
    return {"scene": scene, "status": status, "status_reasons": [reason], "errors": [reason], "ticks": 0,
            "sim_s": 0.0, "wall_s": 0.0, "rtf": 0.0, "handovers": [], "malformed_messages": 0, "semantic_state": {},
            "run_log": None}


@dataclass
class ModelStats:
    """One model's steps in this run (kept across a rejoin: the model is the same, its process is new)."""

    steps: int = 0
    step_s: float = 0.0
    errors: int = 0
    failed: int = 0  # steps that raised (status "error"); warnings count in errors only
    gone: int = 0  # steps not answered in time, answered for the wrong ticks, clock ticks given up on
    warned: int = 0  # steps that raised a StepWarning (the run goes on; the summary's step_warnings say it)
    last_error: str = ""
    last_warning: str = ""
    clock: dict[str, Any] = field(default_factory=dict)  # clock-driven: max_lag_ticks, waited_s

    def count(self, name: str, tick: int, reply: dict[str, Any]) -> None:
        """Count one step reply."""
        self.steps += 1
        self.step_s += reply.get("step_s", 0.0) or 0.0
        if reply["status"] != "ok":
            self.errors += 1
            if reply["status"] == "error":
                self.failed += 1
            elif reply["status"] == "warning":
                self.warned += 1
                self.last_warning = reply.get("message", "warning")
            self.last_error = reply.get("message", reply["status"])
            if self.errors <= 5:
                log.warning("%s step %d: %s: %s", name, tick, reply["status"], self.last_error)

    def problem(self, name: str, text: str) -> None:
        """A problem that is not a step reply (no answer in time, a wrong answer)."""
        self.errors += 1
        self.gone += 1
        self.last_error = text
        log.warning("%s: %s", name, text)


class RunRecord:
    """Counters, problems and the trigger log of one run."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.failure: str | None = None  # why the run could not go on
        self.bad_input = False  # ... and that was the user's input (abort)
        self.stopped: str | None = None  # why it stopped before the end of its source
        self.interrupted: str | None = None  # the signal that stopped it
        self.degraded: list[str] = list(scene.perception_missed)  # what went wrong (besides the counters)
        self.notes: list[str] = []  # what bears on the answer and is no defect (the summary's input_notes)
        self.errors: list[str] = []
        self.trigger_log: list[dict[str, Any]] = []
        self.invariant_violations = 0
        self.step_messages = 0  # step broadcasts sent (a window of ticks each)
        self.schedule = "one per tick"  # how the ticks went into step messages (Conductor.loop)
        self.pace: dict[str, Any] | None = None  # a paced replay: how far it fell behind its pace (stepping.Pacer)
        self.models: dict[str, ModelStats] = {}

    def stats(self, name: str) -> ModelStats:
        st = self.models.get(name)
        if st is None:
            st = self.models[name] = ModelStats()
        return st

    def error(self, text: str) -> None:
        self.errors.append(text)

    def abort(self, reason: str, bad_input: bool = False) -> None:
        """The run ended early for ``reason``: a failure, unless a stop was asked for before (then the run is
        truncated or interrupted, and ``reason`` one of its errors: e.g. stopped while waiting for its agents).
        ``bad_input``: the reason is the user's input (a scene that does not fit what its agents declare), which
        the summary says (``bad_input``: the command exits 2, as for a scene it refuses before it starts)."""
        self.errors.append(reason)
        if not (self.stopped or self.interrupted):
            self.failure = self.failure or reason
            self.bad_input = self.bad_input or bad_input

    def status(self, semantic_state: dict[str, Any], malformed: int,
               input_warnings: list[str]) -> tuple[str, list[str]]:
        """The run's status (:data:`STATUSES`) and the reasons for it, most serious first."""
        if self.failure:
            return "failed", [self.failure]
        reasons = list(self.degraded)
        for name, st in sorted(self.models.items()):  # a StepWarning alone does not degrade a run
            if st.failed or st.gone:
                reasons.append(f"model {name}: {st.failed} steps failed, {st.gone} not answered "
                               f"(last: {st.last_error})")
        trigger_errors = [e for e in self.errors if e.startswith("tick ")]
        if trigger_errors:
            reasons.append(f"{len(trigger_errors)} trigger or clock problems (first: {trigger_errors[0]})")
        if malformed:
            reasons.append(f"{malformed} malformed messages were dropped")
        reasons += [f"input: {w}" for w in input_warnings]
        reasons += [f"the predicate {label!r} could not be evaluated"
                    for label, v in semantic_state.items() if v is None]
        cut = self.interrupted or self.stopped
        if cut:  # cut short; and what went wrong before, which the cut does not hide
            return ("interrupted" if self.interrupted else "truncated"), [cut, *reasons]
        return ("degraded", reasons) if reasons else ("complete", [])

    def summary(self, *, ticks: int, dt: float, loop_wall: float, wall: float, rmap: Responsibilities,
                registry: Registry, semantic_state: dict[str, Any], malformed: int, ensemble: str,
                run_log: str | None, input_warnings: list[str], log_dropped: dict[str, int],
                input_notes: Sequence[str] = ()) -> dict[str, Any]:
        """The run summary (README, *Command line*)."""
        for e, d in sorted(rmap.static_moved.items()):
            self.degraded.append(f"entity {e} is tagged static but its pose moved {d * 1000:.1f} mm (its readers "
                                 "were stepped in batches that assumed it fixed)")
        if rmap.unauthorized_writes:  # a value dropped: what the model computed is not in the answer
            by = _by_model(rmap.unauthorized_by)
            count = rmap.unauthorized_writes
            self.degraded.append((f"{count} values reported for attributes their model did not own were dropped"
                                  if count > 1
                                  else "1 value reported for an attribute its model did not own was dropped")
                                 + f" ({by})")
        if rmap.bad_values:  # a NaN pose handed on to physics, a None the next owner failed on: the model's fault
            self.degraded.append(f"{sum(rmap.bad_values.values())} values from models were no values and were left "
                                 f"out ({_by_model(rmap.bad_values)}; first: {'; '.join(rmap.bad_examples)})")
        if rmap.undeclared:  # nothing of the scene can use them (twin check refuses that): the model broke its word
            self.degraded.append("models sent what they never declared, left out: " + "; ".join(
                f"{m}: " + ", ".join(f"{w} ({k}x)" for w, k in sorted(seen.items()))
                for m, seen in sorted(rmap.undeclared.items())))
        self.degraded += stalled(self.scene, self.models, loop_wall)
        if self.invariant_violations:
            self.degraded.append(f"the one-owner invariant was broken {self.invariant_violations} times")
        if log_dropped:
            self.degraded.append(f"run log: {sum(log_dropped.values())} messages left out, over {MAX_MESSAGE} bytes "
                                 f"or not writable ({', '.join(sorted(log_dropped))})")
        sim_s = ticks * dt
        models = {}
        for n, info in registry.agents.items():
            st = self.stats(n)
            models[n] = {"steps": st.steps, "mean_step_ms": round(1e3 * st.step_s / st.steps, 4) if st.steps else None,
                         "rate_hz": self.scene.models[n].rate if n in self.scene.models else None,
                         "achieved_hz": round(st.steps / loop_wall, 2) if loop_wall > 0 else None,
                         "alive": info.alive, "errors": st.errors, "failed_steps": st.failed,
                         "warned_steps": st.warned,
                         "last_error": st.last_error or None, **st.clock}
        failed = [f"model {n}: {self.stats(n).failed} of {self.stats(n).steps} steps failed "
                  f"(last: {self.stats(n).last_error})" for n in registry.agents if self.stats(n).failed]
        warned = [f"model {n}: {st.warned} of {st.steps} steps warned (last: {st.last_warning})"
                  for n in registry.agents if (st := self.stats(n)).warned]
        status, reasons = self.status(semantic_state, malformed, input_warnings)
        return {
            "status": status,
            "status_reasons": reasons,
            "scene": self.scene.name,
            "ensemble": ensemble,
            "ticks": ticks,
            "sim_s": round(sim_s, 6),
            "wall_s": round(loop_wall, 4),
            "setup_s": round(wall - loop_wall, 4),
            "rtf": round(sim_s / loop_wall, 4) if loop_wall > 0 else None,
            "step_messages": self.step_messages,
            "schedule": self.schedule,
            "handovers": [h.as_dict() for h in rmap.handovers],
            "final_ownership": {f"{e}.{a}": m for (e, a), m in sorted(rmap.owners.items())},
            "semantic_state": semantic_state,
            "malformed_messages": malformed,
            "unauthorized_writes": rmap.unauthorized_writes,
            "late_writes": rmap.late_writes,
            "bad_values": sum(rmap.bad_values.values()),
            "invariant_violations": self.invariant_violations,
            "triggers_fired": sum(1 for r in self.trigger_log if r.get("fired")),
            "models": models,
            "errors": (self.errors + failed)[:MAX_ERRORS],
            "run_log": run_log,
            **({"input_warnings": input_warnings} if input_warnings else {}),
            # a model's StepWarning: a recoverable problem it reported; the run is not degraded by it alone
            **({"step_warnings": warned} if warned else {}),
            **({"bad_input": True} if self.bad_input and status == "failed" else {}),
            **({"pace": self.pace} if self.pace is not None else {}),
            # what the run did not start from or replay that is no defect (the status stays complete)
            **({"input_notes": notes} if (notes := [*self.scene.perception_notes, *self.notes, *input_notes,
                                                    *self._pace_note()]) else {}),
        }


    def _pace_note(self) -> list[str]:
        """A paced replay that fell more than a second behind its pace (a pause of the network or a process, or
        models too slow for it) and then went as fast as they allowed: no defect (a replay steps every tick
        whatever its pace), but what is watched at that pace was not at it."""
        if self.pace is None or self.pace["behind_max_s"] <= 1.0:
            return []
        return [f"the replay fell up to {self.pace['behind_max_s']:g} s behind its --rtf {self.pace['rtf']:g} pace "
                f"(at t={self.pace['at_t']:g} s: a pause, or models too slow for that pace) and went as fast as the "
                "models allowed until it caught up"]

    def unfinished_log(self, summary: dict[str, Any], problem: str | None) -> dict[str, Any]:
        """``summary`` as it stands once the run log is closed: failed, if the log could not be finished (its end
        is written after the summary was made)."""
        if problem is None or summary["status"] == "failed":
            return summary
        self.abort(problem)
        return {**summary, "status": "failed", "status_reasons": [problem, *summary["status_reasons"]],
                "errors": [*summary["errors"], problem]}


def stalled(scene: Scene, models: dict[str, ModelStats], loop_wall: float) -> list[str]:
    """The free-running models that stepped fewer than half the times their rate gives over the run (each step says
    so on done/<id>): one that hung with its liveliness token alive was never noticed. Only over at least ten of
    its periods, with two steps to spare (the last ones may still be on the way)."""
    out = []
    for name, spec in scene.models.items():
        expected = (spec.rate or 0.0) * loop_wall
        steps = models[name].steps if name in models else 0
        if spec.step == "free" and expected >= 10 and steps < expected / 2 - 2:
            out.append(f"model {name} (free-running at {spec.rate:g} Hz) stepped {steps} times in the "
                       f"{loop_wall:.1f} s of the run, where about {expected:.0f} were due: it stalled or fell behind")
    return out


def _by_model(counts: dict[str, int]) -> str:
    return ", ".join(f"{m}: {k}" for m, k in sorted(counts.items()))


def input_report(source: Any) -> dict[str, list[str]]:
    """What the run's source says of its input for the summary (a replay, of its recording; a live source, of the
    robot's telemetry; None or a source that says nothing: nothing): ``input_warnings``, what was left out, cut or
    missed (the run is then degraded), and ``input_notes``, what is not a defect."""
    if source is None or not hasattr(source, "warnings"):
        return {"input_warnings": []}
    return {"input_warnings": source.warnings(), "input_notes": source.notes()}


def plain(v: Any) -> Any:
    """``v`` as plain JSON-able data (numpy arrays and scalars unpacked, NaN as None)."""
    if isinstance(v, dict):
        return {str(k): plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return plain(v.tolist())  # (its NaN too, as None)
    if isinstance(v, np.generic):
        return plain(v.item())
    if isinstance(v, float) and math.isnan(v):
        return None
    return v
