"""An engine's world keeps the clock's time: each model step runs the fixed substeps its time is due, the
fraction left carried to the next (a 1 ms MuJoCo world at 120 Hz ran round(8.33) = 8 a step and fell 4 % behind
the robot it was driven by)."""
from __future__ import annotations

import pytest

from agents.engines.bodies import Substeps


def test_a_second_of_steps_runs_a_second_of_substeps():
    mujoco = Substeps(0.001, 120.0)
    runs = [mujoco.take(1 / 120) for _ in range(120)]
    assert sum(runs) == 1000 and set(runs) == {8, 9}
    pybullet = Substeps(1 / 240, 120.0)  # (the shipped scenes: two a step, always, as before)
    assert [pybullet.take(1 / 120) for _ in range(10_000)] == [2] * 10_000
    odd = Substeps(0.006, 120.0)  # (round(1.39) = 1 a step: its world ran at 0.72 of the clock)
    assert sum(odd.take(1 / 120) for _ in range(720)) == 1000


def test_a_time_step_longer_than_the_step_period_is_refused():
    with pytest.raises(ValueError, match=r"time_step 1 s is longer than the model's step period 0.00833333 s"):
        Substeps(1.0, 120.0)
    with pytest.raises(ValueError, match="time_step must be positive"):
        Substeps(0.0, 120.0)
    assert Substeps(1 / 120, 120.0).take(1 / 120) == 1  # (the period itself is fine)


def test_an_idle_step_carries_nothing_over():
    s = Substeps(0.001, 120.0)
    assert [s.take(1 / 120) for _ in range(2)] == [8, 8] and s.carry > 0.0006  # (0.67 ms carried to the next)
    s.idle()
    assert s.carry == 0.0 and s.take(1 / 120) == 8  # (not 9: nothing was carried over the idle step)


def test_a_step_of_no_time_runs_no_substep():
    """A step of 0 s ran one substep (at least one, always): 120 such steps moved a falling ball 0.5 s of fall."""
    s = Substeps(1 / 240, 120.0)
    assert [s.take(0.0) for _ in range(120)] == [0] * 120 and s.carry == 0.0
    assert s.take(1 / 120) == 2  # (and the steps after go on as before)
