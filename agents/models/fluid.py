"""A fluid in a cup, as particles in a pybullet world of its own (paper §4.2, Table 1).

The paper's point: a general physics world that simulates the robot *and* a fluid pays for every
collision check between the particles and the robot's many non-convex links. Splitting the fluid
into its own small world (particles + cup + table plane, no robot) is much cheaper, and the
ensemble stays coupled through the cup's pose.

The model keeps a private pybullet ``DIRECT`` client holding:

- the table, a static plane at z = 0;
- the cup, a compound body built from ``protocol.geometry.container_parts`` of the scene's
  container entity (``cup`` param; any container style works, a ``cup`` is the intended one),
  held by a stiff fixed constraint to the pose the main physics publishes for it (it does not touch
  the table). Each step the constraint's target travels from the cup's previous pose to the new one
  in as many small moves as there are substeps (lerp + slerp), and the cup follows it as a moving
  body, so its walls carry and push the particles (a cup moved by resetting its pose stood still
  for the contacts: carried at 0.3 m/s its trailing wall slid through two thirds of the water).
  Spilling is judged against where the walls are (a few mm behind a fast-moving target);
- ``particles`` spheres of ``radius`` and ``particle_mass``, low friction, no restitution, filled
  into the cup's interior on a lattice at init and let settle for ``settle`` seconds.

Every step it runs ``floor((dt + carry) / time_step)`` substeps of ``time_step`` (default 1.5 ×
1/240 s, the paper's coarser fluid step) with ``solver_iterations`` solver iterations.

*What it owns.* One entity (param ``entity``, default ``fluid``) stands for the whole particle
set, so a scene of 100 particles does not need 100 entities. Its ``pose`` value is **an N × 3
array of particle centres** (world frame, metres), not a 7-vector: the Rerun stream draws it as
points. In the scene it is declared with the particle shape, e.g.
``water: {shape: {type: sphere, radius: 0.008}, pose: [0.5, 0, 0], tags: [virtual], attributes: {pose: fluid}}``
(the ``virtual`` tag keeps the main physics from building a body for it)
(its scene pose is unused: the particles start in the cup). Do not give this entity to a model
that expects a 7-vector pose.

*Spilling.* A particle has spilled when it is outside the container's interior
(``protocol.geometry.inside_container``, with ``margin`` = one particle radius) and below the
rim's highest point; particles above the rim (a splash) are not counted.

Params: see :attr:`Fluid.params`. Reads: ``cup.pose``, ``container.pose`` (add
``reads: [<name>.pose]`` to the scene's model entry for another name). Outputs (every step):
``particles`` (N × 3 float array, same as the owned pose), ``spilled`` (int), ``in_cup`` (int).
Events: ``spill_started`` {spilled} the first time a particle spills. Evaluators: ``spilled()``,
``in_cup()``.
"""
from __future__ import annotations

import math

import numpy as np

from protocol.geometry import container_params, container_parts, inside_container, wall_radius

from ..model import Model, Param, StepWarning, evaluator
from ..robot.kinematics import as_pose, quat_matrix, quat_slerp

DEFAULT_TIME_STEP = 1.5 / 240.0
CUP_MASS, CUP_FORCE = 1.0, 5000.0
"""The cup's mass (kg) and the force (N) its constraint may use to hold it where its owner says: a thousandfold
the water's weight, so the particles never push it off its path."""


def interior_mask(shape: dict, pose, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Vectorized :func:`protocol.geometry.inside_container` over an (N, 3) array of points."""
    p = container_params(shape)
    pose = as_pose(pose)
    local = (np.asarray(points, float) - pose[:3]) @ quat_matrix(pose[3:])  # rows: Rᵀ (x - t)
    x, y, z = local[:, 0], local[:, 1], local[:, 2]
    w = float(p["wall"])
    if p["style"] in ("bin", "box"):
        sx, sy, h = map(float, p["size"])
        return ((np.abs(x) <= sx / 2 - w + margin) & (np.abs(y) <= sy / 2 - w + margin)
                & (z >= -margin) & (z <= h + margin))
    h = float(p["height"])
    return (np.hypot(x, y) <= wall_radius(p, z) - w + margin) & (z >= -margin) & (z <= h + margin)


def rim_top(shape: dict, pose) -> float:
    """World height of the highest point of the container's rim."""
    p = container_params(shape)
    pose = as_pose(pose)
    R = quat_matrix(pose[3:])
    if p["style"] in ("bin", "box"):
        sx, sy, h = map(float, p["size"])
        corners = np.array([[sx / 2 * i, sy / 2 * j, h] for i in (-1, 1) for j in (-1, 1)])
        return float(np.max(pose[2] + corners @ R[2]))
    r, h = float(p["radius"]), float(p["height"])
    # z(θ) = t_z + R[2,2] h + r (R[2,0] cos θ + R[2,1] sin θ): its maximum over θ
    return float(pose[2] + R[2, 2] * h + r * math.hypot(R[2, 0], R[2, 1]))


def fill_points(shape: dict, n: int, radius: float, gap: float = 1.05) -> np.ndarray:
    """``n`` sphere centres on a hexagonal lattice inside the container's interior, bottom up,
    in the container's frame. Raises ValueError when they do not fit below the rim."""
    p = container_params(shape)
    w = float(p["wall"])
    d = 2 * radius * gap
    if p["style"] in ("bin", "box"):
        sx, sy, h = map(float, p["size"])
        hx, hy = sx / 2 - w - radius, sy / 2 - w - radius
    else:
        r, h = float(p["radius"]), float(p["height"])
        rb = r - h * math.tan(float(p["flare"])) if p["flare"] else r
        hx = hy = min(r, rb) - w - radius
    out: list[tuple[float, float, float]] = []
    layer = 0
    z = w + radius * gap
    while len(out) < n:
        if z > h - radius:
            raise ValueError(f"{n} particles of radius {radius} m do not fit in the container below its rim "
                             f"(room for {len(out)})")
        # hexagonal close packing: every other layer sits in the hollows of the one below
        sx, sy = (d / 2) * (layer % 2), (d * math.sqrt(3) / 6) * (layer % 2)
        row = 0
        y = -hy + sy
        while y <= hy + 1e-12 and len(out) < n:
            x = -hx + sx + (d / 2) * (row % 2)
            while x <= hx + 1e-12 and len(out) < n:
                pt = np.array([x, y, z])
                if interior_mask(shape, [0, 0, 0, 0, 0, 0, 1], pt[None], margin=-radius)[0]:
                    out.append((x, y, z))
                x += d
            y += d * math.sqrt(3) / 2
            row += 1
        z += d * math.sqrt(2.0 / 3.0)
        layer += 1
    return np.array(out)


class Fluid(Model):
    """Particles in a cup, in a pybullet world of their own (see the module docstring)."""

    kind = "fluid"
    role = "simulation"
    params = {
        "entity": Param(str, "fluid", "the entity standing for the particle set (its pose = N×3 positions)"),
        "cup": Param(str, None, "the container entity (default: the first container of style cup)"),
        "particles": Param(int, 50, "number of particles", positive=True),
        "radius": Param(float, None, "particle radius (m); default: the entity's sphere radius, else 0.008"),
        "particle_mass": Param(float, 0.002, "mass of one particle (kg; pybullet fixes a body of mass 0 in place)",
                               positive=True),
        "time_step": Param(float, DEFAULT_TIME_STEP, "substep (s), at most the step period (a step without a substep "
                           "moved the cup through the water); default 1.5 × 1/240", positive=True, within_period=True),
        "solver_iterations": Param(int, 10, "constraint solver iterations per substep"),
        "friction": Param(float, 0.05, "particle friction coefficient"),
        "settle": Param(float, 0.5, "seconds simulated at init so the particles come to rest"),
        "table": Param(bool, True, "a static table plane at z = 0 catches spilled particles"),
        "gravity": Param(float, -9.81, "m/s^2 along z"),
    }
    attributes = ("pose",)
    outputs = ("particles", "spilled", "in_cup")
    events = ("spill_started",)
    reads = ("cup.pose", "container.pose")

    def init(self, params: dict, scene: dict) -> None:
        import pybullet as pb

        self.p = params
        self.pb = pb
        ents = scene.get("entities", {})
        self.entity = params["entity"]
        cup = params["cup"]
        if cup is None:
            cups = [n for n, e in ents.items() if e["shape"].get("type") == "container"
                    and e["shape"].get("style") == "cup"]
            if not cups:
                raise KeyError("fluid model: no 'cup' param and no container of style cup in the scene")
            cup = cups[0]
        if cup not in ents or ents[cup]["shape"].get("type") != "container":
            raise KeyError(f"fluid model: {cup!r} is not a container entity of the scene")
        self.cup = cup
        self.cup_shape = ents[cup]["shape"]
        radius = params["radius"]
        if radius is None:
            shape = ents.get(self.entity, {}).get("shape", {})
            radius = float(shape["radius"]) if shape.get("type") == "sphere" else 0.008
        self.radius = float(radius)
        self.n = int(params["particles"])
        if self.n <= 0:
            raise ValueError("fluid model: particles must be positive")
        self.ts = float(params["time_step"])
        self.cup_pose = self.wall_pose = as_pose(ents[cup]["pose"])
        self.carry = 0.0
        self.substeps = 0

        c = self.client = pb.connect(pb.DIRECT)
        pb.setGravity(0, 0, params["gravity"], physicsClientId=c)
        # contacts are kept only within a quarter radius (pybullet's default 2 cm is larger than a
        # particle) and friction uses the pyramid approximation: together about 1.5x faster
        pb.setPhysicsEngineParameter(fixedTimeStep=self.ts, numSolverIterations=int(params["solver_iterations"]),
                                     contactBreakingThreshold=0.25 * self.radius, enableConeFriction=0,
                                     physicsClientId=c)
        if params["table"]:
            plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
            self.table = pb.createMultiBody(0, plane, physicsClientId=c)
            pb.changeDynamics(self.table, -1, lateralFriction=0.3, physicsClientId=c)
        else:
            self.table = None
        parts = container_parts(self.cup_shape)
        col = pb.createCollisionShapeArray(
            [pb.GEOM_BOX] * len(parts), halfExtents=[[s / 2 for s in q["size"]] for q in parts],
            collisionFramePositions=[q["pos"] for q in parts],
            collisionFrameOrientations=[q["quat"] for q in parts], physicsClientId=c)
        self.cup_body = pb.createMultiBody(CUP_MASS, col, basePosition=self.cup_pose[:3].tolist(),
                                           baseOrientation=self.cup_pose[3:].tolist(), physicsClientId=c)
        self.cup_hold = pb.createConstraint(self.cup_body, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                            self.cup_pose[:3].tolist(),
                                            childFrameOrientation=self.cup_pose[3:].tolist(), physicsClientId=c)
        self._hold_cup(self.cup_pose[:3], self.cup_pose[3:])
        pb.changeDynamics(self.cup_body, -1, lateralFriction=0.1, restitution=0.0, physicsClientId=c)
        if self.table is not None:
            pb.setCollisionFilterPair(self.table, self.cup_body, -1, -1, 0, physicsClientId=c)
        local = fill_points(self.cup_shape, self.n, self.radius)
        R = quat_matrix(self.cup_pose[3:])
        world = self.cup_pose[:3] + local @ R.T
        sphere = pb.createCollisionShape(pb.GEOM_SPHERE, radius=self.radius, physicsClientId=c)
        self.bodies = []
        for pt in world:
            b = pb.createMultiBody(params["particle_mass"], sphere, basePosition=pt.tolist(), physicsClientId=c)
            pb.changeDynamics(b, -1, lateralFriction=params["friction"], rollingFriction=0.0, spinningFriction=0.0,
                              restitution=0.0, linearDamping=0.05, angularDamping=0.05, physicsClientId=c)
            self.bodies.append(b)
        for _ in range(max(0, int(round(params["settle"] / self.ts)))):
            pb.stepSimulation(physicsClientId=c)
        self.positions = self._read_positions()
        self.spilled = self._count_spilled()
        self.spill_reported = self.spilled > 0
        self._warned = False

    # ------------------------------------------------------------------ step
    def step(self, tick: int, t: float, dt: float, telemetry: dict, inputs: dict) -> None:
        pb, c = self.pb, self.client
        target = self.cup_pose
        cup_in = inputs.get(self.cup, {}).get("pose")
        warn = None
        if cup_in is not None:
            target = as_pose(cup_in)
        elif not self.owns(self.cup, "pose") and not self._warned:
            self._warned = True
            warn = f"no pose of {self.cup!r} in the inputs: add 'reads: [{self.cup}.pose]' to this model's scene entry"
        self.carry += dt
        n = int(self.carry / self.ts + 1e-9)
        self.carry -= n * self.ts
        start = self.cup_pose
        for i in range(1, n + 1):
            s = i / n
            pos = start[:3] + s * (target[:3] - start[:3])
            quat = quat_slerp(start[3:], target[3:], s)
            self._hold_cup(pos, quat)
            pb.stepSimulation(physicsClientId=c)
        if n == 0:  # (no substep this step: the cup goes there, held there)
            pb.resetBasePositionAndOrientation(self.cup_body, target[:3].tolist(), target[3:].tolist(),
                                               physicsClientId=c)
            self._hold_cup(target[:3], target[3:])
        self.cup_pose = target
        self.substeps += n
        pos, quat = pb.getBasePositionAndOrientation(self.cup_body, physicsClientId=c)
        self.wall_pose = np.array([*pos, *quat])  # (where the walls are: a few mm behind a fast cup)
        self.positions = self._read_positions()
        self.spilled = self._count_spilled()
        if self.spilled and not self.spill_reported:
            self.spill_reported = True
            self.emit("spill_started", spilled=self.spilled)
        self.output("particles", self.positions)
        self.output("spilled", self.spilled)
        self.output("in_cup", self.in_cup)
        if warn:
            raise StepWarning(warn)

    def _hold_cup(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Where the cup's constraint holds it now (the cup follows over the next substep)."""
        self.pb.changeConstraint(self.cup_hold, jointChildPivot=list(map(float, pos)),
                                 jointChildFrameOrientation=list(map(float, quat)), maxForce=CUP_FORCE, erp=0.9,
                                 physicsClientId=self.client)

    def _read_positions(self) -> np.ndarray:
        get = self.pb.getBasePositionAndOrientation
        c = self.client
        return np.array([get(b, physicsClientId=c)[0] for b in self.bodies], dtype=float)

    def _inside(self) -> np.ndarray:
        return interior_mask(self.cup_shape, self.wall_pose, self.positions, margin=self.radius)

    def _count_spilled(self) -> int:
        inside = self._inside()
        below = self.positions[:, 2] < rim_top(self.cup_shape, self.wall_pose)
        self.in_cup = int(inside.sum())
        return int((~inside & below).sum())

    def check_geometry(self) -> bool:
        """Does the vectorized interior test agree with ``protocol.geometry.inside_container``?"""
        ref = [inside_container(self.cup_shape, list(self.wall_pose), p, margin=self.radius) for p in self.positions]
        return bool(np.array_equal(np.array(ref), self._inside()))

    # ------------------------------------------------------------- ownership
    def read(self, entity: str, attribute: str):
        if entity == self.entity and attribute == "pose":
            return self.positions
        raise KeyError(f"fluid model owns only {self.entity}.pose, not {entity}.{attribute}")

    def acquire(self, entity: str, attribute: str, value, extra: dict) -> None:
        if entity != self.entity:
            raise KeyError(f"fluid model can only own {self.entity}.pose")
        arr = np.asarray(value, float) if value is not None else None
        if arr is not None and arr.shape == (self.n, 3):
            # handed back the particle set (e.g. after a fallback round trip): place the particles there, moving
            # as they were released (a round trip froze any sloshing)
            vel = np.asarray((extra or {}).get("velocity", np.zeros((self.n, 3))), float)
            if vel.shape != (self.n, 3) or not np.isfinite(vel).all():
                vel = np.zeros((self.n, 3))
            for b, pt, v in zip(self.bodies, arr, vel, strict=True):  # arr.shape == (n, 3) was checked
                self.pb.resetBasePositionAndOrientation(b, pt.tolist(), [0, 0, 0, 1], physicsClientId=self.client)
                self.pb.resetBaseVelocity(b, v.tolist(), [0, 0, 0], physicsClientId=self.client)
            self.positions = arr.copy()

    def release(self, entity: str, attribute: str):
        get, c = self.pb.getBaseVelocity, self.client
        velocity = np.array([get(b, physicsClientId=c)[0] for b in self.bodies], dtype=float)
        return self.read(entity, attribute), {"velocity": velocity}

    def close(self) -> None:
        c = getattr(self, "client", None)
        if c is not None:
            try:
                self.pb.disconnect(physicsClientId=c)
            except Exception:
                pass
            self.client = None

    # ------------------------------------------------------------ evaluators
    @evaluator("spilled")
    def spilled_count(self) -> int:
        return self.spilled

    @evaluator("in_cup")
    def in_cup_count(self) -> int:
        return self.in_cup
