"""Screenshots of the Rerun web viewer showing a run of the twin (the pictures of the README, *Watching it*).

    python docs/screenshot.py RUN.mcap --until 1.5 --out docs/img/handover.png [--scene SCENE.yaml]
    python docs/screenshot.py --live scenes/ball_drop.yaml recordings/ball_drop_00.mcap --out docs/img/live.png

Serves the run (``twin view``'s code, serve mode) to the Rerun web viewer on local ports, opens it
in headless Chromium through playwright (``apt-get install chromium``, ``pip install playwright``;
no browser download), waits for the viewer to render, and saves a PNG. ``--until`` picks the moment:
the viewer opens on the last logged time. Without a run log, ``--core`` runs the framework's core
scene (tests/core_scene.yaml, test models, a synthetic recording) first and uses its run log.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]


def run_core(run_dir: Path, seconds: float = 3.0) -> Path:
    """Run tests/core_scene.yaml with its test models and return the run log."""
    from conductor.launch import run_embedded
    from conductor.scene import load_scene
    from conductor.sources.recording import load_recording
    from conductor.sources.replay import ReplaySource
    from recordings.simple import core_recording

    run_dir.mkdir(parents=True, exist_ok=True)
    rec = load_recording(core_recording(run_dir / "core.mcap", seconds=seconds))
    scene = load_scene(ROOT / "tests" / "core_scene.yaml")
    run_embedded(scene, ReplaySource(rec), run_dir=run_dir, rtf=4.0)
    return run_dir / "run.mcap"


def run_live(scene: str, recording: str, out: Path, *, width: int, height: int, wait_s: float,
             chromium: str, rtf: float) -> None:
    """`twin run SCENE --recording REC --rerun serve`: photograph its live web viewer once the run is
    over and the viewer keeps serving it, then stop it with SIGINT."""
    import os
    import signal
    import subprocess

    cmd = [sys.executable, "-m", "conductor.cli", "run", scene, "--recording", recording, "--rerun", "serve",
           "--rtf", str(rtf), "--run-dir", tempfile.mkdtemp(prefix="twin-shot-")]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    url = None
    try:
        deadline = time.monotonic() + 300
        for line in p.stdout:
            print(line, end="")
            if "Rerun web viewer (live):" in line:
                url = line.split(":", 1)[1].strip()
            if "goes on serving" in line or time.monotonic() > deadline:
                break
        if url is None:
            raise SystemExit("the run printed no web viewer address")
        shoot(url, out, width=width, height=height, wait_s=wait_s, chromium=chromium)
    finally:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()


def shoot(url: str, out: Path, *, width: int, height: int, wait_s: float, chromium: str) -> None:
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as profile, sync_playwright() as pw:
        browser = pw.chromium.launch_persistent_context(
            profile, executable_path=chromium, headless=True, args=CHROMIUM_ARGS,
            viewport={"width": width, "height": height})
        try:
            page = browser.new_page()
            page.goto(url)
            page.wait_for_timeout(int(wait_s * 1000))
            page.screenshot(path=str(out))
        finally:
            browser.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_log", nargs="?", help="run log (MCAP); omit with --core")
    ap.add_argument("--core", action="store_true", help="run the core scene first and show that run")
    ap.add_argument("--live", nargs=2, metavar=("SCENE", "RECORDING"),
                    help="photograph the live viewer of `twin run SCENE --recording RECORDING --rerun serve`")
    ap.add_argument("--rtf", type=float, default=2.0, help="--live: pace of the run")
    ap.add_argument("--scene", help="scene file of the run (default: found from the run's scene name)")
    ap.add_argument("--until", type=float, help="simulated time the picture shows (default: the end)")
    ap.add_argument("--out", default="docs/img/viewer.png")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--wait", type=float, default=25.0, help="seconds to let the web viewer render")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args(argv)

    from conductor.viewer import close_stream, log_run, scene_for_run_log

    if args.live:
        run_live(args.live[0], args.live[1], Path(args.out), width=args.width, height=args.height,
                 wait_s=args.wait, chromium=args.chromium, rtf=args.rtf)
        print(f"wrote {args.out}")
        return 0
    tmp = None
    if args.core:
        tmp = tempfile.TemporaryDirectory()
        run_log = run_core(Path(tmp.name) / "run")
    elif args.run_log:
        run_log = Path(args.run_log)
    else:
        ap.error("give a run log or --core")
    scene, note = scene_for_run_log(run_log, args.scene)
    print(note)
    with tempfile.TemporaryDirectory() as d:
        stream, logger = log_run(run_log, Path(d) / "shot.rrd", scene=scene, mode="serve", until=args.until)
        print(f"{logger.counts}; serving {stream.url}")
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        time.sleep(1.0)
        try:
            shoot(stream.url, out, width=args.width, height=args.height, wait_s=args.wait, chromium=args.chromium)
        finally:
            close_stream(stream)
    print(f"wrote {out} ({out.stat().st_size // 1024} KiB)")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
