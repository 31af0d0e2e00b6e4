"""The speed limit (bench/limit.py) gives the twin's answers: the same models in one process, without Zenoh
or agent processes, hand over the same responsibilities and end in the same semantic state as a real
``twin run`` of the same scene and recording. No timing is asserted: the figures are the benchmark's."""
from __future__ import annotations

from pathlib import Path

from bench.limit import SCENARIOS, differences, limit_once, run_limit, twin_once

ROOT = Path(__file__).resolve().parent.parent


def test_limit_answers_as_twin_run_does(tmp_path: Path) -> None:
    scene, recording = SCENARIOS["baseline"]
    twin = twin_once(scene, recording, tmp_path)
    assert twin["status"] == "complete"
    limit = run_limit(ROOT / scene, ROOT / recording)
    assert limit["ticks"] == twin["ticks"]
    assert limit["handovers"] == twin["handovers"]
    assert limit["semantic_state"] == twin["semantic_state"]
    assert limit["final_ownership"] == twin["final_ownership"]
    assert not limit["errors"] and not limit["failed_steps"]
    assert differences(twin, limit) == []
    assert limit["rtf"] is not None and limit["init_s"] > 0


def test_differences_are_listed_never_hidden() -> None:
    twin = {"handovers": [{"tick": 400, "entity": "ball", "attribute": "pose", "from": "physics", "to": "in_hand",
                           "trigger": "grasp", "variables": {"near": {"distance": 0.1}}}],
            "semantic_state": {"in(container, ball)": True}, "final_ownership": {"ball.pose": "physics"}}
    same = {**twin, "handovers": [{**twin["handovers"][0], "tick": 401}]}
    assert differences(twin, same) == []  # a tick apart is the same answer
    other = {"handovers": [{**twin["handovers"][0], "tick": 403, "trigger": "grasp_confirmed",
                            "variables": {"near": {"distance": 0.2}}}],
             "semantic_state": {"in(container, ball)": False}, "final_ownership": {"ball.pose": "in_hand"}}
    found = differences(twin, other)
    assert len(found) == 5
    assert any("trigger" in d for d in found) and any("tick 400" in d for d in found)
    assert any("variables" in d for d in found) and any("semantics" in d for d in found)
    assert any("final owner" in d for d in found)


def test_the_limit_runs_as_its_own_process(tmp_path: Path) -> None:
    scene, recording = SCENARIOS["baseline"]
    res = limit_once(scene, recording, tmp_path)
    assert res["process_s"] > 0 and res["ticks"] > 0
    assert res["semantic_state"] == {"in(container, ball)": True}


def test_a_round_with_a_fault_is_left_out_of_the_figures_and_said() -> None:
    """A twin run that did not end complete, or a limit whose models failed steps, went into the ratio's median
    and spread (an unrun twin's RTF of 0 raised ZeroDivisionError), and the benchmark exited 0."""
    from bench.limit import scenario_result

    def rnd(twin_rtf: float, status: str = "complete", failed: dict | None = None) -> dict:
        twin = {"rtf": twin_rtf, "status": status, "process_s": 2.0, "setup_s": 1.0, "ticks": 500, "handovers": []}
        limit = {"rtf": 12.0, "process_s": 1.0, "init_s": 0.3, "errors": [], "failed_steps": failed or {},
                 "invariant_violations": 0}
        return {"twin": twin, "limit": limit, "differences": [], "order": "twin first"}

    r = scenario_result("ball_drop", [rnd(10.0), rnd(0.0, "failed"), rnd(2.0, failed={"physics": 500}), rnd(8.0)])
    assert r["rounds"] == 2 and r["ratio_max"] == 1.5 and r["ratio_min"] == 1.2  # (12/10 and 12/8 only)
    assert r["faulty_rounds"] == {1: ["twin run failed"], 2: ["limit: physics failed 500 steps"]}
    assert r["twin_status"] == ["complete", "failed"]
    none = scenario_result("ball_drop", [rnd(0.0, "failed")])
    assert none["rounds"] == 0 and not none["same_answers"]
