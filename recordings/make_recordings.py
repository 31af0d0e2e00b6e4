"""Regenerate the shipped recordings from manifest.yaml (run by `make recordings`)."""
import subprocess
import sys
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent


def main() -> int:
    manifest = yaml.safe_load((HERE / "manifest.yaml").read_text())
    only = set(sys.argv[1:])
    for name, spec in manifest.items():
        if only and name not in only:
            continue
        cmd = [sys.executable, "-m", "conductor.cli", "record", "synth", "--scenario", spec["scenario"],
               "--seed", str(spec["seed"]), "--out", str(HERE / f"{name}.mcap")]
        if "container" in spec:
            cmd += ["--container", spec["container"]]
        if "outcome" in spec:
            cmd += ["--outcome", spec["outcome"]]
        if "localization_error" in spec:
            cmd += ["--localization-error", str(spec["localization_error"])]
        print(" ".join(cmd[1:]), flush=True)
        subprocess.run(cmd, check=True, cwd=HERE.parent)
    return 0


if __name__ == "__main__":
    sys.exit(main())
