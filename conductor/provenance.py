"""What a run log carries so that it stands alone: the scene's text, the perception the run used, where the input
came from (path, sha256, topics), the twin's version; and reading a run back as a recording (``twin run
--from-log``: the joint states and actions the replay published, on their own clock)."""
from __future__ import annotations

import functools
import hashlib
import json
import platform
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

from protocol.errors import InputError

from .runlog import read_metadata, read_run_log
from .runlog.reader import LOG_INFO
from .scene import Scene
from .sources.recording import Recording, ended_short

SCENE_TEXT, PERCEPTION, VERSION = "twin.scene_text", "twin.perception", "twin.version"
EPOCH_STAMPS = 1e8
"""Telemetry stamps above this many seconds are a live robot's wall clock (since the epoch: 1973 on), not a
replay's time since its recording began."""


def sha256_of(path: str | Path) -> str:
    """The sha256 of a file, or of a directory's files (names and contents, in name order)."""
    p, h = Path(path), hashlib.sha256()
    for f in sorted(x for x in (p.rglob("*") if p.is_dir() else [p]) if x.is_file()):
        if p.is_dir():
            h.update(str(f.relative_to(p)).encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def scene_code(scene_text: str, scene_file: str) -> dict[str, str]:
    """The scene's own model code outside the twin's packages, each file's sha256 by what names it: an ``fmu:``
    unit by its path as the scene resolves it, a ``module:Class`` kind by its module (its file as this process
    imports it). A cluster worker compares them with its own (:func:`scene_code_differs`): the twin's fingerprint
    leaves them out, and a worker with another copy gave other answers, complete."""
    import importlib.util

    from .scene import parse_scene

    out: dict[str, str] = {}
    for m in parse_scene(scene_text, scene_file).models.values():
        kind = m.kind
        if kind.startswith("fmu:"):
            out[kind] = _sha256(Path(kind[4:]))
        elif ":" in kind:
            module = kind.split(":", 1)[0]
            try:
                spec = importlib.util.find_spec(module)
            except (ImportError, ValueError):
                spec = None
            if spec is not None and spec.origin and spec.origin not in ("built-in", "frozen"):
                out[f"module:{module}"] = _sha256(Path(spec.origin))
    return out


def scene_code_differs(expected: dict[str, str], scene_text: str, scene_file: str) -> str | None:
    """What of the scene's own model code (:func:`scene_code`) this process lacks or has otherwise, or None."""
    try:
        here = scene_code(scene_text, scene_file)
    except Exception as e:  # (a unit missing here: the scene does not load)
        return f"the scene's own model files cannot be read here ({type(e).__name__}: {str(e).splitlines()[0]})"
    off = sorted(k for k, sha in expected.items() if here.get(k) != sha)
    return None if not off else "its copy of " + ", ".join(off) + " is not the client's (or is missing)"


def _sha256(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return "unreadable"


@functools.lru_cache(maxsize=2)
def code_fingerprint(root: Path | None = None) -> str:
    """A short sha256 of this twin's own code, every ``.py`` file of ``agents/``, ``conductor/`` and ``protocol/``
    (names and contents): two processes with the same one run the same twin, whatever version either says (a
    checkout's version does not change with each edit). Computed once per process (``root``: another checkout's).
    """
    root, h = root or Path(__file__).resolve().parent.parent, hashlib.sha256()
    for package in ("agents", "conductor", "protocol"):
        for f in sorted((root / package).rglob("*.py")):
            if any(part.startswith(".") for part in f.relative_to(root).parts):  # (an editor's lock file: .#core.py)
                continue
            h.update(str(f.relative_to(root)).encode())
            try:
                h.update(f.read_bytes())
            except OSError:  # (a dangling link): its name counts, and that it cannot be read
                h.update(b"\0unreadable")
    return h.hexdigest()[:16]


def run_metadata(scene: Scene, scene_text: str, rec: Recording | None) -> dict[str, dict[str, str]]:
    """The metadata that makes a run log self-contained (written when the log is opened)."""
    perception = {"entities": {n: {"pose": list(e.pose), "shape": dict(e.shape),
                                   **{k: e.extra[k] for k in ("mass", "friction", "position_sigma") if k in e.extra}}
                               for n, e in scene.entities.items()}}
    try:
        version = importlib_metadata.version("twin")
    except importlib_metadata.PackageNotFoundError:
        version = "unknown"
    out = {SCENE_TEXT: {"file": scene.file, "yaml": scene_text},
           PERCEPTION: {"json": json.dumps(perception)},
           VERSION: {"twin": version, "code": code_fingerprint(), "python": platform.python_version(),
                     "host": platform.node()}}
    # what a recording carries, so that the log is itself a recording (twin run --recording, twin robot play)
    out["twin.scene"] = dict(out[PERCEPTION])
    if rec is not None:
        out["twin.recording"] = {"path": rec.path, "storage": rec.storage, "topics": json.dumps(rec.topics),
                                 "sha256": sha256_of(rec.path) if Path(rec.path).exists() else ""}
        if rec.metadata.get("twin.ground_truth"):
            out["twin.ground_truth"] = dict(rec.metadata["twin.ground_truth"])
    return out


def scene_of_log(path: str | Path) -> tuple[str, str, dict[str, Any]]:
    """(scene text, scene file name, perception) a run log carries; InputError naming the file if it does not."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such run log" if not p.exists() else f"{path}: a folder, not a run log")
    meta = read_metadata(path)
    if SCENE_TEXT not in meta:
        raise InputError(f"{path}: not a self-contained run log (no '{SCENE_TEXT}' metadata: a log of a twin run "
                        "before this version, a robot recording, or a log cut before its first records were written)")
    try:
        perception = json.loads(meta.get(PERCEPTION, {}).get("json", "{}"))
    except ValueError as e:
        raise InputError(f"{path}: metadata '{PERCEPTION}' is not valid JSON ({e})") from None
    return meta[SCENE_TEXT].get("yaml", ""), meta[SCENE_TEXT].get("file", str(path)), perception


def recording_of_log(path: str | Path) -> Recording:
    """The joint states and actions a run published (``telemetry/*``), as the recording they came from."""
    items: list[tuple[float, str, dict[str, Any]]] = []
    problems: list[str] = []
    for key, _, msg in read_run_log(path, problems=problems):
        if "/telemetry/" not in key or not isinstance(msg, dict) or not isinstance(msg.get("stamp"), (int, float)):
            continue
        kind = "joint_state" if key.endswith("/joint_states") else "action" if key.endswith("/action") else None
        if kind is not None:
            items.append((float(msg["stamp"]), kind, {k: v for k, v in msg.items() if k not in ("v", "type")}))
    if not items:
        raise InputError(f"{path}: the run log holds no telemetry to replay")
    items.sort(key=lambda x: x[0])
    if items[0][0] > EPOCH_STAMPS:  # a live run's: the robot's wall clock, from here on since its first message
        t0 = items[0][0]
        items = [(t - t0, k, {**m, "stamp": float(m["stamp"]) - t0}) for t, k, m in items]
    names = sorted({n for _, k, m in items if k == "joint_state" for n in m.get("name", [])})
    meta = read_metadata(path)
    info = meta.get(LOG_INFO, {})
    origin = int(info["origin_ns"]) if info.get("stamps") == "since origin" and info.get("origin_ns") else None
    cut = ended_short(meta) if "twin.summary" in meta else (
        f"a run log cut short (no summary at its end: its run did not finish); only its telemetry up to "
        f"{items[-1][0]:.2f} s is replayed")
    if problems and not cut:
        cut = f"a run log {problems[0]}; only its telemetry up to {items[-1][0]:.2f} s is replayed"
    return Recording(str(path), items, {}, storage="twin run log", topics={"telemetry": ["telemetry/*"]},
                     joint_names=names, origin_ns=origin, cut_short=cut)
