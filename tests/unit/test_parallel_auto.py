"""``twin evaluate --parallel``: what it accepts, and how many recordings ``auto`` interprets at once."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import pytest

from bench.cli import parallel_arg
from bench.evaluate import SLOT_BYTES, idle_cores, parallel_auto


def test_parallel_takes_a_count_or_auto():
    assert parallel_arg("auto") == "auto" and parallel_arg("3") == 3
    for bad in ("0", "-1", "two", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            parallel_arg(bad)


def test_auto_is_at_least_one_and_at_most_the_recordings(monkeypatch):
    n, why = parallel_auto(1)
    assert n == 1 and "cores idle" in why
    monkeypatch.setattr("bench.evaluate.idle_cores", lambda cores, window=0.3: float(cores))
    monkeypatch.setattr("bench.evaluate._available_bytes", lambda: 64 * SLOT_BYTES)
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(range(8)))
    assert parallel_auto(3)[0] == 3 and parallel_auto(50)[0] == 8
    monkeypatch.setattr("bench.evaluate._available_bytes", lambda: 2 * SLOT_BYTES + 5)  # memory bounds it too
    assert parallel_auto(50)[0] == 2
    monkeypatch.setattr("bench.evaluate.idle_cores", lambda cores, window=0.3: 0.2)  # a busy machine: still one
    assert parallel_auto(50) == (1, "0 of 8 cores idle, 2 GiB available")


def test_a_busy_core_is_not_counted_idle():
    """A process spinning on one core: at most the other cores are idle (measured, not the load average)."""
    spin = subprocess.Popen([sys.executable, "-c", "while 1: pass"])
    try:
        time.sleep(0.5)
        busy = idle_cores(1, window=0.5)
    finally:
        spin.kill()
        spin.wait()
    assert 0.0 <= busy <= (os.cpu_count() or 1) - 0.5
