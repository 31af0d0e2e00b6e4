"""Afterwards: a Rerun recording made from a run log (``twin view RUN.mcap``)."""
from __future__ import annotations

import json
import logging
import uuid
from pathlib import Path

from ..provenance import SCENE_TEXT, scene_of_log
from ..runlog import read_metadata, read_run_log
from ..runlog.reader import LOG_INFO
from ..scene import load_scene, parse_scene
from ..sources.recording import load_recording
from .logger import TwinLogger
from .stream import (
    DEFAULT_CONNECT_URL,
    Stream,
    ViewerError,
    _nobody_at,
    close_stream,
    no_display,
    open_stream,
    parse_mode,
)

log = logging.getLogger("twin.viewer")


# --------------------------------------------------------------------------- run logs
def scene_for_run_log(run_log: str | Path, scene_path: str | Path | None = None):
    """The scene a run log was made with: ``scene_path``; else the scene text and perception the log carries
    (a log of this version needs nothing else); else, for an older log, ``scenes/<name>.yaml`` if its entities
    match the run's, placed where the recording perceived them. Returns (scene or None, note)."""
    meta = read_metadata(run_log)
    if scene_path is None and SCENE_TEXT in meta:
        try:
            text, file, perceived = scene_of_log(run_log)
            carried = parse_scene(text, file)
            carried.apply_perception(perceived)
            return carried, f"scene {file} as the run log carries it, placed as the run perceived it"
        except Exception as e:  # a damaged scene in the log: fall back on finding it by name
            log.warning("the scene the run log carries cannot be read (%s): looking for it by name", e)
    summary = {}
    try:
        summary = json.loads(meta.get("twin.summary", {}).get("json", "{}"))
    except ValueError:
        pass
    name = summary.get("scene")
    scene, note = None, ""
    if scene_path is not None:
        scene = load_scene(scene_path)
        note = f"scene {scene_path}"
        ran = {str(k).split(".")[0] for k in summary.get("final_ownership") or {}}
        missing = sorted(ran - set(scene.entities))
        if missing:  # another scene's shapes would be drawn over this run's messages
            note += (f" (it has no {', '.join(missing)}, which the run had: is it this run's scene? its own is "
                     f"{name!r})")
            log.warning("%s", note)
    elif name:
        root = Path(__file__).resolve().parents[2]
        for cand in (Path("scenes") / f"{name}.yaml", root / "scenes" / f"{name}.yaml"):
            if not cand.is_file():
                continue
            try:
                s = load_scene(cand)
            except Exception:
                continue
            final = set(summary.get("final_ownership") or {})
            if s.name == name and (not final or final == {f"{e}.{a}" for e, a in s.initial_owners()}):
                scene, note = s, f"scene {cand} (found by the run's scene name; --scene chooses another)"
                break
    if scene is None:
        which = f" for {name!r}" if name else ""
        return None, f"no scene file{which}: drawing what the messages tell (--scene adds shapes)"
    rec_path = (meta.get("twin.recording") or {}).get("path")
    if rec_path and Path(rec_path).is_file():
        try:
            r = load_recording(rec_path)
            if "twin.scene" in r.metadata:
                scene.apply_perception(json.loads(r.metadata["twin.scene"].get("json", "{}")))
        except Exception as e:
            log.info("perception of %s not applied: %s", rec_path, e)
    return scene, note


def _robot_time_zero(run_log: str | Path) -> float:
    """The robot's stamp (s) of simulated time 0 in a run log: 0 where its stamps are since the log's origin (a
    replay), the origin where they are since the epoch (a live run)."""
    try:
        info = read_metadata(run_log).get(LOG_INFO) or {}
        return int(info["origin_ns"]) * 1e-9 if info.get("stamps") == "epoch" else 0.0
    except (OSError, ValueError, KeyError):  # (an older log, or one whose end is cut: its stamps as they are)
        return 0.0


def log_run(run_log: str | Path, out: str | Path | None = None, *, scene=None, mode: str = "save",
            pose_hz: float = 60.0, web_port: int | None = None, until: float | None = None,
            problems: list[str] | None = None) -> tuple[Stream, TwinLogger]:
    """Turn a run log (MCAP from conductor/runlog.py) into a Rerun recording with the live sink's code.

    ``until`` stops at that simulated time (the viewer then opens on that moment); a log cut short or damaged is
    shown up to there, and said in ``problems`` (see :func:`~conductor.runlog.read_run_log`). Returns the
    stream (closed, for mode save) and the logger (its ``counts``). In serve/spawn/connect modes the
    stream is left open for the caller to close with :func:`close_stream`.
    """
    run_log = Path(run_log)
    out = Path(out) if out is not None else run_log.with_suffix(".rrd")
    name = scene.name if scene is not None else run_log.parent.name or "run"
    kind, arg = parse_mode(mode)
    nobody = _nobody_at(arg or DEFAULT_CONNECT_URL) if kind == "connect" else no_display() if kind == "spawn" else None
    if nobody is not None:  # no viewer to take it: said before the file is opened (an .rrd already there is kept)
        ask = f"; is it running at the address given? ({mode})" if kind == "connect" else ""
        raise ViewerError(f"{nobody}{ask}; {out} is left as it was")
    stream = open_stream(mode, out, scene=scene, name=name, recording_id=f"{name}-{uuid.uuid4().hex[:12]}",
                         web_port=web_port)
    if stream.undelivered is not None:  # connect=URL with no viewer there: said at once, nothing read
        raise ViewerError(f"{stream.undelivered}; is it running at the address given? ({mode})")
    logger = TwinLogger(stream.rec, scene, pose_hz=pose_hz)
    logger.begin()
    n = 0
    # (the logger's health plots, the real-time factor, take the wall clock: each message's publish time)
    if until is None:
        for key, wall_ns, raw in read_run_log(run_log, decode=False, problems=problems, wall=True):
            logger.offer(key, raw, wall_ns)  # type: ignore[arg-type]  # raw bytes when decode=False
            n += 1
            if n % 4096 == 0:
                logger.flush()
    limit = until if until is not None else float("inf")
    robot_t0 = _robot_time_zero(run_log) if until is not None else 0.0
    for key, wall_ns, msg in (read_run_log(run_log, problems=problems, wall=True) if until is not None else ()):
        n += 1
        if isinstance(msg, dict):
            tt = msg["t"] if "t" in msg else msg.get("stamp")
            if isinstance(tt, (int, float)) and ("t" in msg and tt > limit or "t" not in msg and tt - robot_t0 > limit):
                continue
        logger.feed(key, msg, wall_ns)
        if n % 4096 == 0:
            logger.flush()
    logger.counts["records"] = n  # the run log's messages read (the same figure by either path)
    logger.finish()
    if parse_mode(mode)[0] == "save":
        close_stream(stream)
    else:
        try:
            stream.rec.flush(timeout_sec=10.0)
        except RuntimeError as e:  # a viewer that is not there (connect=URL): said in a line, not a traceback
            raise ViewerError(f"the Rerun viewer did not take the recording within 10 s ({e}); is it running at "
                              f"the address given? ({mode})") from None
    return stream, logger
