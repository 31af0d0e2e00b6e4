"""Regenerate the shipped recordings from manifest.yaml (run by `make recordings`).

    python recordings/make_recordings.py [NAME ...] [--out DIR]

Without names, every entry; ``--out`` writes into another folder (default: this one). Each file is
made by ``twin record synth`` with the entry's arguments; one line per file says what the reality
measured, the file's size and how long it took, and a last line the totals.
"""
import argparse
import subprocess
import sys
import time
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent


def command(name: str, spec: dict, out_dir: Path) -> list[str]:
    """The ``twin record synth`` command line of one manifest entry."""
    cmd = [sys.executable, "-m", "conductor.cli", "record", "synth", "--scenario", spec["scenario"],
           "--seed", str(spec["seed"]), "--out", str(out_dir / f"{name}.mcap"), "--quiet"]
    for key in ("container", "outcome", "localization_error", "reality", "robot"):
        if key in spec:
            cmd += [f"--{key.replace('_', '-')}", str(spec[key])]
    return cmd


def main(argv: list[str] | None = None) -> int:
    """Make the named manifest entries (default: all); 0 made, 1 a generation failed, 2 a name not in it."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="entries of manifest.yaml to make (default: all)")
    ap.add_argument("--out", type=Path, default=HERE, help="folder to write into (default: recordings/)")
    args = ap.parse_args(argv)
    manifest = yaml.safe_load((HERE / "manifest.yaml").read_text())
    unknown = set(args.names) - set(manifest)
    if unknown:
        print(f"make_recordings: not in manifest.yaml: {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    args.out = args.out.resolve()  # (the child runs in the repository: a relative --out is the caller's)
    args.out.mkdir(parents=True, exist_ok=True)
    total_t, total_bytes, made = time.perf_counter(), 0, 0
    for name, spec in manifest.items():
        if args.names and name not in args.names:
            continue
        t0 = time.perf_counter()
        r = subprocess.run(command(name, spec, args.out), cwd=HERE.parent, capture_output=True, text=True)
        if r.returncode != 0:
            print(f"{name}: failed\n{r.stderr[-2000:]}", file=sys.stderr, flush=True)
            return 1
        size = (args.out / f"{name}.mcap").stat().st_size
        total_bytes += size
        made += 1
        print(f"{name}: {r.stdout.strip().split(': ', 1)[-1]} [{size / 1e6:.2f} MB, {time.perf_counter() - t0:.1f} s]",
              flush=True)
    print(f"{made} recordings, {total_bytes / 1e6:.1f} MB in {time.perf_counter() - total_t:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
