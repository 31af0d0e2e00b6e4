"""The fluid model over the real protocol: two fluid agents (one per cup) and a scripted owner of the
cups' poses as subprocesses, driven by a Conductor through tests/scenes/fluid_tip.yaml; and its
particle-set geometry in-process.

    script ──state: cup_up.pose, cup_tip.pose──▶ conductor ──inputs──▶ fluid_up, fluid_tip
    fluid_* ──state: water_*.pose (N×3), out: particles, spilled, in_cup──▶ conductor, run log
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agents.models.fluid import fill_points, interior_mask, rim_top
from conductor.core import Conductor, RunOptions
from conductor.runlog import read_run_log
from conductor.scene import load_scene
from protocol.geometry import inside_container, quat_from_axis_angle
from protocol.keys import Keys

from .conftest import spawn_agents

HERE = Path(__file__).parent
N = 50


@pytest.mark.slow
def test_tipped_cup_spills_most_upright_cup_none(router, procs, tmp_path):
    """Tipping a cup by 120° within a second spills most of its particles onto the table; the cup
    that stays upright spills none; the owned pose of the particle set is the N×3 positions."""
    session, endpoint = router
    scene = load_scene(HERE / "scenes" / "fluid_tip.yaml")
    spawn_agents(procs, scene, endpoint)
    c = Conductor(scene, session, Keys("default"), None, RunOptions(run_log=str(tmp_path / "run.mcap"), max_ticks=150,
                                                                    register_timeout=60))
    try:
        s = c.run()
    finally:
        c.close()
    assert s["errors"] == [] and s["unauthorized_writes"] == 0, s["errors"]
    assert s["models"]["fluid_tip"]["steps"] == 150 and s["models"]["fluid_tip"]["errors"] == 0
    sem = s["semantic_state"]
    assert sem["spilled(cup_up)"] == 0
    assert sem["spilled(cup_tip)"] >= 0.8 * N, sem

    spilled = {"fluid_up": [], "fluid_tip": []}
    particles, states, events = {}, {}, []
    for key, _, msg in read_run_log(s["run_log"]):
        if not isinstance(msg, dict):
            continue
        if "/out/" in key and msg["name"] == "spilled":
            spilled[msg["model"]].append((msg["tick"], msg["value"]))
        elif "/out/" in key and msg["name"] == "particles" and msg["model"] == "fluid_tip":
            particles[msg["tick"]] = msg["value"]
        elif key.endswith("/state/fluid_tip"):
            states[msg["tick"]] = msg["values"]["water_tip"]["pose"]
        elif "/event/" in key:
            events.append((msg["tick"], msg["model"], msg["name"]))
    assert len(spilled["fluid_up"]) == 150 and all(v == 0 for _, v in spilled["fluid_up"])
    # nothing spills before the tipping starts (t = 0.5 s = tick 30); the count only grows after
    assert all(v == 0 for tick, v in spilled["fluid_tip"] if tick < 30)
    started = [e for e in events if e[2] == "spill_started"]
    assert len(started) == 1 and started[0][1] == "fluid_tip" and 30 <= started[0][0] <= 90, events
    # the particle set travels as an (N, 3) array in both the owned state and the output
    last = max(states)
    pts = np.asarray(states[last])
    assert pts.shape == (N, 3) and np.array_equal(pts, np.asarray(particles[last]))
    # the spilled particles lie on the table (z = radius) far below the tipped cup
    cup_pose = [0.5, 0.25, 0.25, *quat_from_axis_angle([1, 0, 0], math.radians(120))]
    out = [p for p in pts if not inside_container(scene.entities["cup_tip"].shape, cup_pose, p, margin=0.008)]
    assert len(out) >= 0.8 * N
    assert sum(1 for p in out if p[2] < 0.02) >= 0.7 * N


def _cup_of_water(**params):
    """A fluid model owning the water in a cup at x = 0.35 m, stepped at 120 Hz with a 1/240 s time step."""
    from agents.models.fluid import Fluid

    scene = {"entities": {"cup": {"shape": {"type": "container", "style": "cup"}, "pose": [0.35, 0, 0, 0, 0, 0, 1]},
                          "water": {"shape": {"type": "sphere", "radius": 0.008}, "pose": [0.35, 0, 0],
                                    "tags": ["virtual"]}}}
    m = Fluid()
    m.owned, m.rate = {("water", "pose")}, 120.0
    m.init({k: p.default for k, p in Fluid.params.items()} | {"cup": "cup", "entity": "water", "time_step": 1 / 240}
           | params, scene)
    return m


@pytest.mark.parametrize("speed", [0.3, 0.5])
def test_a_cup_carried_level_keeps_its_water(speed):
    """Water 4 cm deep in a 13 cm cup carried level at walking pace does not spill. The cup was moved by resetting
    its pose, which the contacts took for a cup standing still: its trailing wall slid through the particles
    (33 of 50 spilled at 0.3 m/s, all at 0.5)."""
    m = _cup_of_water(particles=50)
    a, x, v = speed / 0.25, 0.35, 0.0  # 0.25 s to speed up, 1 s at it, 0.25 s to stop
    try:
        for k in range(int(2.0 * 120)):
            t = (k + 1) / 120
            v = max(0.0, min(speed, v + (a if t <= 0.25 else -a if 1.25 < t <= 1.5 else 0.0) / 120))
            x += v / 120
            m._outputs, m._events = {}, []
            m.step(k, t, 1 / 120, {}, {"cup": {"pose": [x, 0, 0, 0, 0, 0, 1]}})
        assert x > 0.35 + speed  # it went
        assert (m.spilled, m.in_cup) == (0, 50)
        assert np.all(np.abs(m.positions[:, 0] - x) < 0.05)  # the water went with the cup
    finally:
        m.close()


def test_a_released_and_reacquired_water_moves_on_as_it_was():
    """The particles' velocities go with their positions (a fallback round trip froze any sloshing)."""
    m = _cup_of_water(particles=20, settle=0.0)
    try:
        m.step(0, 1 / 120, 1 / 120, {}, {"cup": {"pose": [0.35, 0, 0, 0, 0, 0, 1]}})
        value, extra = m.release("water", "pose")
        assert extra["velocity"].shape == (20, 3) and np.abs(extra["velocity"]).max() > 0.01  # settling
        m.acquire("water", "pose", value, extra)
        again = np.array([m.pb.getBaseVelocity(b, physicsClientId=m.client)[0] for b in m.bodies])
        np.testing.assert_allclose(again, extra["velocity"], atol=1e-9)
    finally:
        m.close()


def test_particle_geometry_helpers_match_protocol_geometry():
    """The vectorized interior test agrees with protocol.geometry.inside_container, the lattice fill
    lies inside the cup below its rim, and the rim height follows the cup's tilt."""
    shape = {"type": "container", "style": "cup"}
    rng = np.random.default_rng(0)
    for angle in (0.0, 0.7, 2.1):
        pose = [0.4, -0.1, 0.3, *quat_from_axis_angle([1, 0.3, 0], angle)]
        pts = np.asarray(pose[:3]) + rng.uniform(-0.15, 0.15, size=(400, 3))
        ref = np.array([inside_container(shape, pose, p, margin=0.008) for p in pts])
        assert ref.any() and not ref.all()
        assert np.array_equal(interior_mask(shape, pose, pts, margin=0.008), ref)
    box = {"type": "container", "style": "box"}
    pose = [0, 0, 0, *quat_from_axis_angle([0, 1, 0], 0.4)]
    pts = rng.uniform(-0.2, 0.2, size=(400, 3))
    assert np.array_equal(interior_mask(box, pose, pts), [inside_container(box, pose, p) for p in pts])
    fill = fill_points(shape, 100, 0.008)
    assert fill.shape == (100, 3)
    assert all(inside_container(shape, [0, 0, 0, 0, 0, 0, 1], p, margin=-0.008) for p in fill)
    d = np.linalg.norm(fill[:, None] - fill[None], axis=-1) + np.eye(100)
    assert d.min() >= 2 * 0.008  # no two particles overlap at the start
    with pytest.raises(ValueError):
        fill_points(shape, 2000, 0.008)
    assert rim_top(shape, [0, 0, 0, 0, 0, 0, 1]) == pytest.approx(0.13)
    # tipped by 90° about x: the rim's highest point is the rim radius above the origin
    assert rim_top(shape, [0, 0, 0, *quat_from_axis_angle([1, 0, 0], math.pi / 2)]) == pytest.approx(0.055)


def test_a_fluid_substep_longer_than_its_step_period_is_refused(tmp_path):
    """A step that runs no substep moves the cup by resetting its pose, its walls through the water: the fluid
    model at 240 Hz with its 1/160 s substep spilled 27 of 50 particles from a cup carried at 0.3 m/s (none at
    120 Hz). Its time_step is now held to the step period, as physics' and MuJoCo's are, before anything starts."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    text = (root / "scenes" / "fluid_split_50.yaml").read_text()
    bad = tmp_path / "fluid.yaml"
    bad.write_text(text.replace("particles: 50, time_step: 0.004166666666666667", "particles: 50, time_step: 0.01"))
    r = subprocess.run([sys.executable, "-m", "conductor.cli", "check", str(bad)], capture_output=True, text=True,
                       cwd=root, timeout=120)
    line = 1 + next(i for i, row in enumerate(bad.read_text().splitlines()) if row.startswith("  fluid:"))
    assert r.returncode == 2 and f"{bad}:{line}: models.fluid.args.time_step: parameter 'time_step' of fluid is " \
        "0.01 s, longer than the model's step period" in r.stderr, r.stdout + r.stderr


def test_a_bowl_s_interior_narrows_to_its_floor_as_its_wall_flares():
    """The interior of a round container was a cylinder of the rim's radius: a bowl's wall flares out (0.35 rad), so a
    particle on the table 11 cm from its axis, outside the wall (9.7 cm from the axis there), counted in the bowl, not
    spilled. Both tests (the model's and the semantics') follow the wall now; a cup's (no flare) is as it was."""
    bowl, cup, at = {"type": "container", "style": "bowl"}, {"type": "container", "style": "cup"}, [0, 0, 0, 0, 0, 0, 1]
    for shape, point, inside in ((bowl, [0.110, 0, 0.008], False), (bowl, [0.090, 0, 0.008], True),
                                 (bowl, [0.112, 0, 0.068], True), (bowl, [0.115, 0, 0.068], False),
                                 (cup, [0.049, 0, 0.01], True), (cup, [0.051, 0, 0.01], False)):
        assert inside_container(shape, at, point) is inside, (shape, point)
        assert bool(interior_mask(shape, at, np.array([point]))[0]) is inside, (shape, point)
