"""A robot as data: the scene's ``robot:`` block, resolved against the shipped robot descriptions.

Every robot fact a model needs (the URDF, its base pose, the arm joints, the gripper's joints, finger
links, hand and tip, its open and closed positions, force limits, a resting posture) lives in a
:class:`Robot`; the models read nothing robot-specific from code. The shipped descriptions are YAML
files beside this module (``robots/panda.yaml``, ``robots/xarm6.yaml``); a scene names one with ``use:``
and may override any key, or describes its own URDF arm and parallel gripper in full::

    robot: {use: xarm6, base: [0, 0, 0]}
    robot:
      urdf: my_arm/arm.urdf                       # relative to the scene, the working directory or pybullet_data
      arm: [j1, j2, j3, j4, j5, j6]
      gripper: {joints: [finger], fingers: [left_pad, right_pad], hand: flange, tip: flange,
                tip_offset: [0, 0, 0.15], open: [0.0], closed: [0.8], force: 40}
      joints: {arm_joint_1: j1, ...}              # recording name -> URDF name (identity by default)

:func:`check_robot` lists every problem of a block (key path, problem) so the scene check reports them with
file and line; :func:`resolve_robot` turns a valid block into a :class:`Robot`, and :meth:`Robot.as_dict`
back into the full block the conductor hands every model (``scene["robot"]`` at init).

The URDF is read here only as XML (joint and link names, limits, ``<mimic>``): no physics engine needed.
"""
from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path
from typing import Any, TypeGuard

import yaml

from .geometry import full_pose, pose_problem, valid_pose

DESCRIPTIONS = Path(__file__).with_name("robots")
DEFAULT = "panda"
BLOCK_KEYS = frozenset({"use", "urdf", "base", "arm", "arm_force", "arm_inertia", "gripper", "ready", "joints"})
GRIPPER_KEYS = frozenset({"joints", "fingers", "hand", "tip", "tip_offset", "open", "closed", "force"})

Problems = list[tuple[tuple[str, ...], str]]

__all__ = ["BLOCK_KEYS", "DEFAULT", "DESCRIPTIONS", "GRIPPER_KEYS", "Gripper", "Problems", "Robot", "Urdf",
           "check_robot", "description", "read_urdf", "resolve_robot", "shipped", "urdf_path"]


def shipped() -> list[str]:
    """Names of the shipped robot descriptions (``use:`` values)."""
    return sorted(p.stem for p in DESCRIPTIONS.glob("*.yaml"))


@cache
def description(name: str) -> dict[str, Any]:
    """A shipped description as loaded (KeyError naming the shipped ones when unknown)."""
    path = DESCRIPTIONS / f"{name}.yaml"
    if not path.is_file():
        raise KeyError(f"no shipped robot description {name!r} (shipped: {', '.join(shipped())})")
    data: dict[str, Any] = yaml.safe_load(path.read_text(encoding="utf-8"))
    return data


def urdf_path(name: str, base_dir: str | Path | None = None) -> str:
    """Absolute path of a robot URDF: ``name`` as given if absolute, else relative to ``base_dir`` (the
    scene's folder), the working directory or ``pybullet_data``. FileNotFoundError otherwise."""
    if os.path.isabs(name):
        if os.path.exists(name):
            return name
        raise FileNotFoundError(f"robot URDF {name!r} not found")
    bases = [Path(base_dir)] if base_dir else []
    bases.append(Path.cwd())
    try:
        import pybullet_data  # a data folder only (no engine is loaded)

        bases.append(Path(pybullet_data.getDataPath()))
    except ImportError:  # pragma: no cover - pybullet is a dependency
        pass
    for b in bases:
        cand = b / name
        try:
            found = cand.is_file()
        except (OSError, ValueError):  # a name too long for the file system, or with a NUL byte in it
            found = False
        if found:
            return str(cand.resolve())
    raise FileNotFoundError(f"robot URDF {name!r} not found (absolute, relative to the scene, the working "
                            "directory or pybullet_data)")


@dataclass(frozen=True)
class Urdf:
    """What the robot's URDF names: movable joints (with type, limits, effort), links, mimic joints."""

    joints: dict[str, dict[str, Any]]  # movable joint -> {type, lower, upper, effort, velocity}
    links: tuple[str, ...]
    mimic: dict[str, tuple[str, float, float]]  # follower -> (leader, multiplier, offset)
    # every joint, fixed ones too -> (parent link, child link, length of its origin's offset from the parent, m)
    tree: dict[str, tuple[str, str, float]] = field(default_factory=dict)


@lru_cache(maxsize=32)
def read_urdf(path: str) -> Urdf:
    """Parse a URDF's joints, links and ``<mimic>`` tags (ValueError when it is not URDF XML)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise ValueError(f"{path}: not a readable URDF ({e})") from None
    if root.tag != "robot":
        raise ValueError(f"{path}: not a URDF (root element <{root.tag}>, not <robot>)")
    joints: dict[str, dict[str, Any]] = {}
    mimic: dict[str, tuple[str, float, float]] = {}
    tree: dict[str, tuple[str, str, float]] = {}
    for j in root.findall("joint"):  # (the robot's own: a <transmission> names its joints too, with no type)
        kind = j.get("type", "")
        name = j.get("name", "")
        parent, child, origin = j.find("parent"), j.find("child"), j.find("origin")
        if name and parent is not None and child is not None:
            try:
                xyz = [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
            except ValueError:
                xyz = [math.inf]
            tree[name] = (str(parent.get("link")), str(child.get("link")), math.sqrt(sum(v * v for v in xyz)))
        if kind in ("fixed", "floating", "planar") or not name:
            continue
        lim = j.find("limit")
        attrs = dict(lim.attrib) if lim is not None else {}
        joints[name] = {"type": kind, "lower": float(attrs.get("lower", -math.inf)),
                        "upper": float(attrs.get("upper", math.inf)), "effort": float(attrs.get("effort", math.inf)),
                        "velocity": float(attrs.get("velocity", math.inf))}
        m = j.find("mimic")
        if m is not None and m.get("joint"):
            mimic[name] = (str(m.get("joint")), float(m.get("multiplier", 1.0)), float(m.get("offset", 0.0)))
    links = tuple(str(link.get("name")) for link in root.iter("link") if link.get("name"))
    return Urdf(joints, links, mimic, tree)


@dataclass(frozen=True)
class Gripper:
    """A parallel gripper: one or two actuated joints moving two finger links.

    ``joints``: the actuated gripper joints as the URDF names them (two for fingers on their own joints
    like the Panda's, one for a linkage like the xArm's); ``open`` / ``closed``: their positions fully open
    and fully closed; ``fingers``: the two finger (pad) links; ``hand``: the link whose frame the in-hand
    model holds objects in; ``tip`` + ``tip_offset``: the point between the fingertips (in ``tip``'s frame);
    ``force``: the actuator's limit per joint (N for prismatic fingers, N m for a revolute drive).
    ``mimic``: joints of the URDF that follow a gripper joint (follower -> (leader, multiplier, offset)).
    """

    joints: tuple[str, ...]
    fingers: tuple[str, str]
    hand: str
    tip: str
    tip_offset: tuple[float, ...]  # (x, y, z)
    open: tuple[float, ...]
    closed: tuple[float, ...]
    force: float
    mimic: dict[str, tuple[str, float, float]] = field(default_factory=dict)

    def driver(self, finger: int) -> str:
        """The actuated joint that moves finger 0 or 1."""
        return self.joints[finger] if len(self.joints) == 2 else self.joints[0]


@dataclass(frozen=True)
class Robot:
    """A resolved robot block (see the module docstring). ``joint_map``: recording name -> URDF name."""

    name: str
    urdf: str  # as written (relative to pybullet_data, the scene or the working directory, or absolute)
    urdf_file: str  # resolved absolute path
    base: tuple[float, ...]
    arm: tuple[str, ...]
    arm_force: tuple[float, ...]
    gripper: Gripper
    ready: tuple[float, ...]  # arm joints, then gripper joints
    joint_map: dict[str, str]
    arm_inertia: tuple[float, ...] = ()  # joint-space inertia diagonal (kg m^2) for servo gains; () = compute

    @property
    def joints(self) -> tuple[str, ...]:
        """The joints the telemetry should report (URDF names): the arm's, then the gripper's."""
        return self.arm + self.gripper.joints

    def posture(self, values: Sequence[float]) -> tuple[float, ...]:
        """A model's ``initial_joints`` as a full posture (arm, then gripper): the arm's values alone leave the
        gripper open, none give the ready posture; any other count is a ValueError naming the joints."""
        q = tuple(float(v) for v in values)
        if not q:
            return self.ready
        if len(q) == len(self.arm):
            return q + tuple(self.gripper.open)
        if len(q) == len(self.joints):
            return q
        raise ValueError(f"initial_joints: {len(q)} values; {self.name} takes {len(self.arm)} (its arm: "
                         f"{', '.join(self.arm)}) or {len(self.joints)} (the arm, then its gripper: "
                         f"{', '.join(self.gripper.joints)})")

    def ready_positions(self) -> dict[str, float]:
        """The resting posture by joint name, mimic joints included."""
        q = dict(zip(self.joints, self.ready, strict=True))
        return self.with_mimic(q)

    def with_mimic(self, q: Mapping[str, float]) -> dict[str, float]:
        """``q`` plus the positions of the URDF's mimic joints whose leader is in ``q``."""
        out = dict(q)
        for follower, (leader, mult, off) in self.gripper.mimic.items():
            if leader in q and follower not in q:
                out[follower] = mult * float(q[leader]) + off
        return out

    def as_dict(self) -> dict[str, Any]:
        """The full block (every key given), which resolves to this same robot wherever the URDF is found the
        same way: its path as written when it does not depend on the scene's folder (a pybullet_data robot
        resolves on every machine), else the absolute path."""
        g = self.gripper
        extra = {"arm_inertia": list(self.arm_inertia)} if self.arm_inertia else {}
        try:
            urdf = self.urdf if urdf_path(self.urdf) == self.urdf_file else self.urdf_file
        except FileNotFoundError:
            urdf = self.urdf_file
        return {"name": self.name, "urdf": urdf, "base": list(self.base), "arm": list(self.arm),
                "arm_force": list(self.arm_force), **extra, "ready": list(self.ready), "joints": dict(self.joint_map),
                "gripper": {"joints": list(g.joints), "fingers": list(g.fingers), "hand": g.hand, "tip": g.tip,
                            "tip_offset": list(g.tip_offset), "open": list(g.open), "closed": list(g.closed),
                            "force": g.force}}

    # ------------------------------------------------------------- telemetry names
    def rename(self, names: list[str]) -> list[str]:
        """Recording joint names as the URDF's (names the map does not mention stay as they are)."""
        m = self.joint_map
        return [m.get(n, n) for n in names] if m else list(names)

    def fit(self, recorded: set[str] | list[str]) -> tuple[set[str], list[str]]:
        """(the robot joints the recording reports after the map, the arm and gripper joints it misses)."""
        have = set(self.rename(list(recorded)))
        return have & set(self.joints), [j for j in self.joints if j not in have]


# ------------------------------------------------------------------------------ checking
def _merged(block: Mapping[str, Any]) -> tuple[dict[str, Any], str]:
    """The block over the description it uses (``use:``, or the one whose URDF it names, else the
    default when it names no URDF): (merged dict, description name or '')."""
    use = block.get("use")
    if use is None:
        urdf = block.get("urdf")
        if urdf is None:
            use = DEFAULT
        else:
            use = next((n for n in shipped() if description(n)["urdf"] == urdf), None)
    if use is None:
        return dict(block), ""
    base = dict(description(str(use)))
    merged = {**base, **{k: v for k, v in block.items() if v is not None and k != "gripper"}}
    if isinstance(block.get("gripper"), Mapping):
        merged["gripper"] = {**base.get("gripper", {}), **block["gripper"]}
    elif block.get("gripper") is not None:
        merged["gripper"] = block["gripper"]
    return merged, str(use)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _names(v: Any) -> TypeGuard[list[str] | tuple[str, ...]]:
    return isinstance(v, (list, tuple)) and all(isinstance(x, str) and x for x in v)


def _nums(v: Any, n: int | None = None) -> TypeGuard[list[float] | tuple[float, ...]]:
    return isinstance(v, (list, tuple)) and all(_is_num(x) for x in v) and (n is None or len(v) == n)


def check_robot(block: Any, base_dir: str | Path | None = None) -> Problems:
    """Every problem of a scene's ``robot:`` block, as (key path, problem); empty when it resolves."""
    if block is None:
        block = {}
    if not isinstance(block, Mapping):
        return [(("robot",), f"robot must be a map like {{use: panda, base: [x, y, z]}} "
                             f"(shipped robots: {', '.join(shipped())})")]
    out: Problems = [(("robot", str(k)), f"unknown key {k!r} (allowed: {', '.join(sorted(BLOCK_KEYS))})")
                     for k in block if k not in BLOCK_KEYS and k != "name"]
    use = block.get("use")
    if use is not None and (not isinstance(use, str) or use not in shipped()):
        return out + [(("robot", "use"), f"use must name a shipped robot description ({', '.join(shipped())}), "
                                         f"got {use!r}")]
    if block.get("urdf") is not None and not isinstance(block.get("urdf"), str):
        return out + [(("robot", "urdf"), "urdf must be the robot's URDF file (a string)")]
    data, used = _merged(block)
    if data.get("base") is not None and not valid_pose(list(data["base"]) if _nums(data["base"]) else None):
        out.append((("robot", "base"), pose_problem(data["base"], "base")))
    if data.get("name") is not None and not (isinstance(data["name"], str) and data["name"]):
        out.append((("robot", "name"), f"name must be a string, got {data['name']!r}"))
    try:
        urdf = read_urdf(urdf_path(str(data.get("urdf")), base_dir))
    except (FileNotFoundError, ValueError) as e:  # (a misspelt shipped URDF: its arm and gripper follow from it)
        return out + [(("robot", "urdf"), str(e))]
    if not used:
        out += [(("robot", k), f"{k} is required for a URDF without a shipped description (give it, or "
                               f"use: {'|'.join(shipped())})") for k in ("arm", "gripper") if data.get(k) is None]
    if out:
        return out
    return _check_against(data, urdf)


def _joints_in(path: tuple[str, ...], v: Any, urdf: Urdf) -> Problems:
    if not _names(v) or not v:
        return [(path, "must be a list of joint names")]
    bad = [j for j in v if j not in urdf.joints]
    if not bad:
        return []
    return [(path, f"{', '.join(bad)}: not movable joints of the URDF (it has: {', '.join(urdf.joints)})")]


def _check_gripper(g: Mapping[str, Any], urdf: Urdf) -> tuple[Problems, int]:
    """The gripper block's problems, and how many actuated joints it names."""
    out: Problems = [(("robot", "gripper", str(k)), f"unknown key {k!r} (allowed: {', '.join(sorted(GRIPPER_KEYS))})")
                     for k in g if k not in GRIPPER_KEYS]
    gj = g.get("joints")
    out += _joints_in(("robot", "gripper", "joints"), gj, urdf)
    n_g = len(gj) if _names(gj) else 0
    if n_g not in (1, 2):
        out.append((("robot", "gripper", "joints"), "a parallel gripper has one or two actuated joints"))
    fingers = g.get("fingers")
    if not _names(fingers) or len(fingers) != 2:
        out.append((("robot", "gripper", "fingers"), "fingers must name the two finger links"))
    else:
        out += [(("robot", "gripper", "fingers"), f"{f}: not a link of the URDF") for f in fingers
                if f not in urdf.links]
    for k in ("hand", "tip"):
        v = g.get(k, g.get("hand") if k == "tip" else None)
        if not isinstance(v, str) or v not in urdf.links:
            out.append((("robot", "gripper", k), f"{k} must name a link of the URDF, got {v!r}"))
    out += [(("robot", "gripper", k), f"{k} must list the gripper joints' positions ({n_g} numbers)")
            for k in ("open", "closed") if not _nums(g.get(k), n_g or None)]
    if g.get("tip_offset") is not None and not _nums(g["tip_offset"], 3):
        out.append((("robot", "gripper", "tip_offset"), "tip_offset must be [x, y, z] (m, in the tip link's frame)"))
    if not (_is_num(g.get("force")) and g["force"] > 0):
        out.append((("robot", "gripper", "force"), "force must be a positive number (N, or N m for a revolute drive)"))
    return out, n_g


def _check_against(data: dict[str, Any], urdf: Urdf) -> Problems:
    """The names and numbers of a merged block against its URDF."""
    arm = data.get("arm")
    out = _joints_in(("robot", "arm"), arm, urdf)
    g = data.get("gripper")
    if not isinstance(g, Mapping):
        return out + [(("robot", "gripper"), "gripper must be a map with joints, fingers, hand, tip, open, closed, "
                                             "force")]
    problems, n_g = _check_gripper(g, urdf)
    out += problems + _check_values(data, g, n_g, urdf)
    jm = data.get("joints")
    if jm is not None:
        if not isinstance(jm, Mapping) or not all(isinstance(k, str) and isinstance(v, str) for k, v in jm.items()):
            out.append((("robot", "joints"), "joints must map recorded joint names to the URDF's ({name: urdf_name})"))
        else:
            out += [(("robot", "joints", k), f"{v}: not a movable joint of the URDF") for k, v in jm.items()
                    if v not in urdf.joints]
            to = list(jm.values())
            out += [(("robot", "joints", k), f"{v}: the URDF joint of another recorded name too (which is it?)")
                    for k, v in jm.items() if to.count(v) > 1]
    return out


def _check_values(data: dict[str, Any], g: Mapping[str, Any], n_g: int, urdf: Urdf) -> Problems:
    """The arm's numbers, the joints named twice, and postures against the URDF's limits."""
    out: Problems = []
    arm = data.get("arm")
    n_arm = len(arm) if _names(arm) else None
    for key, what, zero in (("arm_force", "one torque limit per arm joint, each above 0 (N m, or N)", False),
                            ("arm_inertia", "one inertia per arm joint, each 0 or more (kg m^2)", True)):
        v = data.get(key)
        if v is not None and not (_nums(v, n_arm) and all(x > 0 or (zero and x == 0) for x in v)):
            out.append((("robot", key), f"{key} must list {what}, got {v!r}"))
    gj = g.get("joints")
    named = [*(arm if _names(arm) else ()), *(gj if _names(gj) else ())]
    twice = sorted({j for j in named if named.count(j) > 1})
    if twice:
        out.append((("robot", "arm" if _names(arm) and any(arm.count(j) > 1 for j in twice) else "gripper"),
                    f"{', '.join(twice)}: named twice among the arm's and the gripper's joints"))
    n = (n_arm or 0) + n_g
    if data.get("ready") is not None and not _nums(data["ready"], n):
        out.append((("robot", "ready"), f"ready must list {n} joint positions (the arm's, then the gripper's)"))
    elif not twice and len(named) == n:
        for path, values, joints in ((("robot", "ready"), data.get("ready"), named),
                                     (("robot", "gripper", "open"), g.get("open"), named[n_arm or 0:]),
                                     (("robot", "gripper", "closed"), g.get("closed"), named[n_arm or 0:])):
            out += _within_limits(path, values, joints, urdf)
    return out


def _within_limits(path: tuple[str, ...], values: Any, joints: list[str], urdf: Urdf) -> Problems:
    """Positions of ``joints`` outside the URDF's limits (none when ``values`` is not a list of as many numbers)."""
    if not _nums(values, len(joints)):
        return []
    out = []
    for j, v in zip(joints, values, strict=True):
        limits = urdf.joints.get(j, {})  # (a joint the URDF lacks is said by _joints_in)
        lo, hi = limits.get("lower"), limits.get("upper")
        if lo is not None and hi is not None and hi > lo and not lo - 1e-6 <= v <= hi + 1e-6:
            out.append((path, f"{j} at {v:g} is outside its URDF limits [{lo:g}, {hi:g}]"))
    return out


def resolve_robot(block: Any, base_dir: str | Path | None = None) -> Robot:
    """The :class:`Robot` of a scene's ``robot:`` block (ValueError listing its problems when it has some)."""
    problems = check_robot(block, base_dir)
    if problems:
        raise ValueError("; ".join(f"{'.'.join(p)}: {m}" for p, m in problems))
    data, used = _merged(block or {})
    path = urdf_path(str(data["urdf"]), base_dir)
    urdf = read_urdf(path)
    g = data["gripper"]
    arm = tuple(data["arm"])
    gj = tuple(g["joints"])
    base = full_pose(data.get("base") or [0, 0, 0])
    arm_force = tuple(float(v) for v in data.get("arm_force") or [urdf.joints[j]["effort"] for j in arm])
    ready = data.get("ready") or [0.0] * len(arm) + list(g["open"])
    mimic = {f: m for f, m in urdf.mimic.items() if m[0] in gj and f not in gj}  # actuated joints lead
    gripper = Gripper(joints=gj, fingers=(g["fingers"][0], g["fingers"][1]), hand=g["hand"],
                      tip=g.get("tip") or g["hand"],
                      tip_offset=tuple(float(v) for v in g.get("tip_offset") or (0, 0, 0)),
                      open=tuple(float(v) for v in g["open"]), closed=tuple(float(v) for v in g["closed"]),
                      force=float(g["force"]), mimic=mimic)
    return Robot(name=str(data.get("name") or used or Path(path).stem), urdf=str(data["urdf"]), urdf_file=path,
                 base=tuple(base), arm=arm, arm_force=arm_force, gripper=gripper,
                 ready=tuple(float(v) for v in ready), joint_map=dict(data.get("joints") or {}),
                 arm_inertia=tuple(float(v) for v in data.get("arm_inertia") or ()))
