"""What every engine's world needs to know about the scene's bodies, whichever engine builds them: a default
mass for an entity that gives none, the velocity of a body carried from one pose to another, and the velocity of
a body another model carries, from the poses its owner sent."""
from __future__ import annotations

import math
from typing import Any

from ..robot.kinematics import quat_conj, quat_mul, rotation_vector

TENNIS_BALL = (0.033, 0.057)  # radius (m), mass (kg)


def default_mass(shape: dict[str, Any], density: float) -> float:
    """Mass (kg) of a dynamic entity without a ``mass``: a sphere is taken for a hollow ball with a tennis ball's
    areal density (0.057 kg at r = 0.033 m, scaling with r²), boxes and cylinders are solid at ``density``
    kg/m³ (at least 5 g); anything else 0.1 kg."""
    t = shape.get("type")
    if t == "sphere":
        r = float(shape["radius"])
        return TENNIS_BALL[1] * (r / TENNIS_BALL[0]) ** 2
    if t == "box":
        sx, sy, sz = map(float, shape["size"])
        return max(0.005, density * sx * sy * sz)
    if t == "cylinder":
        r, h = float(shape["radius"]), float(shape["length"])
        return max(0.005, density * math.pi * r * r * h)
    return 0.1


def velocity_between(a: Any, b: Any, dt: float) -> list[float]:
    """[vx, vy, vz, wx, wy, wz] of the motion from pose ``a`` to pose ``b`` (``[x, y, z, qx, qy, qz, qw]``) in
    ``dt`` seconds (zeros for ``dt <= 0``)."""
    if dt <= 0:
        return [0.0] * 6
    lin = [(b[i] - a[i]) / dt for i in range(3)]
    w = rotation_vector(quat_mul(b[3:7], quat_conj(a[3:7]))) / dt
    return lin + [float(w[0]), float(w[1]), float(w[2])]


def owner_velocity(hist: list[tuple[float, list[float]]], now: float, window: float) -> list[float]:
    """Velocity of a body another model carries, from the distinct poses its owner sent (``(time, pose)``, oldest
    first), over the last ``window`` seconds of them: the owner's motion over its own times, whatever this model's
    rate (over this model's step, an owner at half its rate gave 0 and twice the speed on alternate steps). Zero
    if the owner has sent nothing new at ``now`` for more than twice its usual interval (it stands still)."""
    if len(hist) < 2:
        return [0.0] * 6
    t1, p1 = hist[-1]
    if now - t1 > 2.0 * (t1 - hist[-2][0]) + 1e-9:
        return [0.0] * 6
    t0, p0 = hist[0]
    for tk, pk in reversed(hist[:-1]):
        if tk <= t1 - window + 1e-9:
            t0, p0 = tk, pk
            break
    return velocity_between(p0, p1, t1 - t0) if t1 > t0 else [0.0] * 6


class Substeps:
    """How many fixed engine steps of ``time_step`` each model step runs, so that the engine's time follows the
    clock's exactly: the fraction of a step left over is carried to the next. ``round(dt / time_step)`` did not:
    a 1 ms MuJoCo step at 120 Hz ran 8 substeps where 8.33 were due, and its world fell 4 % behind the robot.
    A ``time_step`` longer than the model's step period (``1 / rate``) is refused: some steps would move nothing.
    """

    def __init__(self, time_step: float, rate: float) -> None:
        if not time_step > 0:
            raise ValueError("time_step must be positive")
        if rate > 0 and time_step > 1.0 / rate * (1 + 1e-9):
            raise ValueError(f"time_step {time_step:g} s is longer than the model's step period {1.0 / rate:g} s "
                             f"(rate {rate:g} Hz): a step would run no substep; make it at most the period")
        self.time_step = time_step
        self.carry = 0.0  # seconds of the clock not yet stepped (less than one time_step)

    def take(self, dt: float) -> int:
        """The substeps that bring the engine to the end of a step of ``dt`` seconds: none for a step of no time
        (a step of 0 s ran one, and the world fell by a substep's worth ahead of the clock each time)."""
        self.carry += max(0.0, dt)
        n = int(self.carry / self.time_step + 1e-9)
        self.carry = max(0.0, self.carry - n * self.time_step)
        return n

    def idle(self) -> None:
        """A step the engine did not simulate (a kinematic model owning nothing): the next starts afresh."""
        self.carry = 0.0


class Followed:
    """The bodies a world model moves where other models, their owners, put them: each one's target (the last pose
    its owner sent) and the distinct poses its owner sent, over their own times, from which its velocity comes
    (:func:`owner_velocity` over ``window`` seconds). An owner's value that is not a pose leaves the target where it
    was and is reported once per body."""

    HISTORY = 32  # distinct poses kept per body

    def __init__(self, window: float) -> None:
        self.window = window
        self.targets: dict[str, list[float]] = {}
        self._history: dict[str, list[tuple[float, list[float]]]] = {}
        self._bad: set[str] = set()

    def __contains__(self, name: object) -> bool:
        return name in self.targets

    def follow(self, name: str, pose: list[float], t: float) -> None:
        """Follow ``name`` from ``pose`` at time ``t`` (the model gave it up, or never owned it)."""
        self.targets[name] = list(pose)
        self._history[name] = [(t, list(pose))]

    def stop(self, name: str, now: float) -> list[float]:
        """Stop following ``name`` (the model owns it now): the velocity its owner gave it, as of ``now``."""
        self.targets.pop(name, None)
        return owner_velocity(self._history.pop(name, []), now, self.window)

    def this_step(self, inputs: dict[str, Any], t: float, now: float,
                  bad: list[str]) -> list[tuple[str, list[float], list[float]]]:
        """(name, target, velocity) of each followed body after its owner's values in ``inputs`` (entity ->
        attribute -> value) at time ``t``; the velocity as of ``now``, the model's time before the step. The bodies
        whose owner sent a value that is not a 7-vector pose for the first time are added to ``bad``."""
        out = []
        for name, target in self.targets.items():
            attrs = inputs.get(name)
            if attrs is not None and attrs.get("pose") is not None:
                target = self._take(name, target, attrs["pose"], t, bad)
            out.append((name, target, owner_velocity(self._history.get(name, []), now, self.window)))
        return out

    def _take(self, name: str, target: list[float], value: Any, t: float, bad: list[str]) -> list[float]:
        try:
            new = [float(v) for v in value]
        except (TypeError, ValueError):
            new = []
        if len(new) != 7:
            if name not in self._bad:
                self._bad.add(name)
                bad.append(name)
            return target
        if new != target:
            hist = self._history.setdefault(name, [])
            hist.append((t, new))
            del hist[:-self.HISTORY]
            self.targets[name] = new
        return new
