"""What a run did, counted as it goes, and the run summary made from it at the end."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .registry import Registry
from .responsibility import Responsibilities
from .scene import Scene

log = logging.getLogger("twin.conductor")

MAX_ERRORS = 50  # the summary lists at most this many problems


@dataclass
class ModelStats:
    """One model's steps in this run (kept across a rejoin: the model is the same, its process is new)."""

    steps: int = 0
    step_s: float = 0.0
    errors: int = 0
    failed: int = 0  # steps that raised (status "error"); warnings count in errors only
    last_error: str = ""
    clock: dict[str, Any] = field(default_factory=dict)  # clock-driven: max_lag_ticks, waited_s

    def count(self, name: str, tick: int, reply: dict[str, Any]) -> None:
        """Count one step reply."""
        self.steps += 1
        self.step_s += reply.get("step_s", 0.0) or 0.0
        if reply["status"] != "ok":
            self.errors += 1
            if reply["status"] == "error":
                self.failed += 1
            self.last_error = reply.get("message", reply["status"])
            if self.errors <= 5:
                log.warning("%s step %d: %s: %s", name, tick, reply["status"], self.last_error)

    def problem(self, name: str, text: str) -> None:
        """A problem that is not a step reply (no answer in time, a wrong answer)."""
        self.errors += 1
        self.last_error = text
        log.warning("%s: %s", name, text)


class RunRecord:
    """Counters, problems and the trigger log of one run."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.errors: list[str] = []
        self.trigger_log: list[dict[str, Any]] = []
        self.invariant_violations = 0
        self.models: dict[str, ModelStats] = {}

    def stats(self, name: str) -> ModelStats:
        st = self.models.get(name)
        if st is None:
            st = self.models[name] = ModelStats()
        return st

    def error(self, text: str) -> None:
        self.errors.append(text)

    def summary(self, *, ticks: int, dt: float, loop_wall: float, wall: float, rmap: Responsibilities,
                registry: Registry, semantic_state: dict[str, Any], malformed: int, ensemble: str,
                run_log: str | None) -> dict[str, Any]:
        """The run summary (README, *Command line*)."""
        sim_s = ticks * dt
        models = {}
        for n, info in registry.agents.items():
            st = self.stats(n)
            models[n] = {"steps": st.steps, "mean_step_ms": round(1e3 * st.step_s / st.steps, 4) if st.steps else None,
                         "rate_hz": self.scene.models[n].rate if n in self.scene.models else None,
                         "achieved_hz": round(st.steps / loop_wall, 2) if loop_wall > 0 else None,
                         "alive": info.alive, "errors": st.errors, "failed_steps": st.failed,
                         "last_error": st.last_error or None, **st.clock}
        failed = [f"model {n}: {self.stats(n).failed} of {self.stats(n).steps} steps failed "
                  f"(last: {self.stats(n).last_error})" for n in registry.agents if self.stats(n).failed]
        return {
            "scene": self.scene.name,
            "ensemble": ensemble,
            "ticks": ticks,
            "sim_s": round(sim_s, 6),
            "wall_s": round(loop_wall, 4),
            "setup_s": round(wall - loop_wall, 4),
            "rtf": round(sim_s / loop_wall, 4) if loop_wall > 0 else None,
            "handovers": [h.as_dict() for h in rmap.handovers],
            "final_ownership": {f"{e}.{a}": m for (e, a), m in sorted(rmap.owners.items())},
            "semantic_state": semantic_state,
            "malformed_messages": malformed,
            "unauthorized_writes": rmap.unauthorized_writes,
            "invariant_violations": self.invariant_violations,
            "triggers_fired": sum(1 for r in self.trigger_log if r.get("fired")),
            "models": models,
            "errors": (self.errors + failed)[:MAX_ERRORS],
            "run_log": run_log,
        }


def plain(v: Any) -> Any:
    """``v`` as plain JSON-able data (numpy arrays and scalars unpacked, NaN as None)."""
    if isinstance(v, dict):
        return {str(k): plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and math.isnan(v):
        return None
    return v
