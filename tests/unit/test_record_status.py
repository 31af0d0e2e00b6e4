"""A run's status and its reasons: cut short (stopped, interrupted) it is truncated or interrupted, and what went
wrong before the cut is still listed after the cut's reason; a failure is said alone."""
from __future__ import annotations

from conductor.record import RunRecord
from conductor.scene import load_scene


def test_a_cut_short_run_keeps_what_went_wrong_before():
    rec = RunRecord(load_scene("scenes/ball_drop.yaml"))
    rec.degraded.append("the main model physics was unreachable at tick 9 (its token vanished) and came back")
    assert rec.status({"in(container, ball)": True}, 0, []) == ("degraded", [rec.degraded[0]])
    rec.stopped = "stopped at max_ticks 60"
    status, reasons = rec.status({"in(container, ball)": True}, 2, ["3 joint states left out"])
    assert status == "truncated" and reasons == ["stopped at max_ticks 60", rec.degraded[0],
                                                 "2 malformed messages were dropped", "input: 3 joint states left out"]
    rec.interrupted = "SIGTERM"
    assert rec.status({"in(container, ball)": None}, 0, [])[1] == [
        "SIGTERM", rec.degraded[0], "the predicate 'in(container, ball)' could not be evaluated"]
    rec.failure = "the main model 'physics' died at tick 12"
    assert rec.status({}, 5, []) == ("failed", ["the main model 'physics' died at tick 12"])


def test_a_value_dropped_because_its_model_did_not_own_it_makes_the_run_degraded():
    """A model's value of an attribute it does not own is dropped: the run said complete, 'nothing dropped', with
    the count in a field nobody reads. It is a reason now, naming the model."""
    from conductor.responsibility import Responsibilities

    from .fakes import ready_registry

    scene = load_scene("scenes/ball_drop.yaml")
    rec, rmap = RunRecord(scene), Responsibilities(scene)
    registry = ready_registry({"physics": ["pose"], "in_hand": ["pose"], "grasp_monitor": []})

    def summary():
        return rec.summary(ticks=10, dt=scene.rate ** -1, loop_wall=1.0, wall=2.0, rmap=rmap, registry=registry,
                           semantic_state={"in(container, ball)": True}, malformed=0, ensemble="e", run_log=None,
                           input_warnings=[], log_dropped={})

    assert summary()["status"] == "complete"
    rmap.absorb_state("in_hand", {"ball": {"pose": [0.0, 0.0, 0.1, 0, 0, 0, 1]}})  # physics owns it
    s = summary()
    assert s["status"] == "degraded" and s["unauthorized_writes"] == 1 and s["status_reasons"] == [
        "1 value reported for an attribute its model did not own was dropped (in_hand: 1)"], s["status_reasons"]


def test_a_models_step_warnings_are_in_the_summary_and_printed(capsys):
    """A StepWarning (e.g. the SPU told it has no pose of the part to classify) was counted in the model's errors
    and said nowhere a person reads: the summary now lists it, and the printed summary shows it."""
    from conductor.cli.run import print_summary
    from conductor.responsibility import Responsibilities

    from .fakes import ready_registry

    scene = load_scene("scenes/ball_drop.yaml")
    rec, rmap = RunRecord(scene), Responsibilities(scene)
    registry = ready_registry({"physics": ["pose"], "in_hand": ["pose"], "grasp_monitor": []})
    ok = {"status": "ok", "state": {}, "outputs": {}, "events": []}
    for tick in range(4):
        rec.stats("physics").count("physics", tick, ok)
        rec.stats("grasp_monitor").count("grasp_monitor", tick, dict(ok, status="warning", message=f"no hand {tick}")
                                         if tick >= 2 else ok)
    s = rec.summary(ticks=4, dt=scene.rate ** -1, loop_wall=1.0, wall=2.0, rmap=rmap, registry=registry,
                    semantic_state={"in(container, ball)": True}, malformed=0, ensemble="e", run_log=None,
                    input_warnings=[], log_dropped={})
    assert s["status"] == "complete", s["status_reasons"]  # a warning alone does not degrade the run
    assert s["step_warnings"] == ["model grasp_monitor: 2 of 4 steps warned (last: no hand 3)"]
    assert s["models"]["grasp_monitor"]["warned_steps"] == 2 and s["models"]["physics"]["warned_steps"] == 0
    print_summary(s)
    assert "warning: model grasp_monitor: 2 of 4 steps warned (last: no hand 3)" in capsys.readouterr().out


def test_a_run_log_whose_end_could_not_be_written_fails_the_run():
    """The run log is closed after the summary is made (the summary goes into it): a disk full then, or a writer
    that did not finish, left a cut log behind a summary that said complete, exit 0. The summary returned is now
    failed, saying why; one that had failed already stays as it was."""
    rec = RunRecord(load_scene("scenes/ball_drop.yaml"))
    summary = {"status": "complete", "status_reasons": [], "errors": []}
    assert rec.unfinished_log(summary, None) is summary
    why = "run log /x/run.mcap: writing failed (OSError: [Errno 28] No space left on device)"
    s = rec.unfinished_log(summary, why)
    assert s["status"] == "failed" and s["status_reasons"] == [why] and s["errors"] == [why] and rec.failure == why
    failed = {"status": "failed", "status_reasons": ["agent lost: physics"], "errors": []}
    assert rec.unfinished_log(failed, why) is failed


def test_a_new_process_under_a_name_whose_token_vanished_is_admitted():
    """A supervisor restarting the main model's agent after a kill: the conductor still held the dead process as
    live (its token's loss not yet taken in by the tick loop) and refused the new one, which exited for good, so
    the next run waited for it and failed. A name whose token vanished since it registered is free to take; a
    second live process under a taken name is still refused."""
    from protocol.messages import Message

    from .fakes import ready_registry

    registry = ready_registry({"physics": ["pose"]})
    registry.agents["physics"].desc.update(pid=100, host="h")
    new = Message({"name": "physics", "kind": "physics", "role": "simulation", "attributes": ["pose"], "pid": 200,
                   "host": "h"})
    assert "a live agent already holds the name 'physics'" in (registry.admit(new) or "")
    assert registry.admit(new, lapsed=True) is None
