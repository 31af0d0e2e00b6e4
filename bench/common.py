"""What every benchmark shares: the machine it ran on, and the raw Zenoh rounds the twin is measured against."""
from __future__ import annotations

import os
import platform
import time
from importlib.metadata import version
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def machine_info() -> dict[str, Any]:
    """The machine a benchmark ran on: Python, platform, CPUs, memory and the versions compared."""
    info: dict[str, Any] = {"python": platform.python_version(), "platform": platform.platform(),
                            "cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()}
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                info["cpu"] = line.split(":", 1)[1].strip()
                break
        with open("/proc/meminfo") as f:
            info["mem_gib"] = round(int(f.readline().split()[1]) / 2**20, 1)
    except OSError:
        pass
    try:
        info["eclipse_zenoh"] = version("eclipse-zenoh")
        info["mosaik"] = version("mosaik")
    except Exception:
        pass
    return info


def wait_tokens(session, key: str, n: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = sum(1 for r in session.liveliness().get(key, timeout=1.0) if r.ok is not None)
        if got >= n:
            return
        time.sleep(0.05)
    raise RuntimeError(f"only {got} of {n} processes came up")


PAYLOAD = b"\x86" + b"y" * 60  # a small msgpack-like request, the same for every raw baseline


def query_rounds(session, keys: list[str], ticks: int, warmup: int = 50) -> float:
    """Rounds per second of one get to each of ``keys`` at once (bare queryables answering)."""
    def rounds(count):
        for _ in range(count):
            pending = [session.get(k, payload=PAYLOAD, timeout=10.0) for k in keys]
            for r in pending:
                for reply in r:
                    _ = reply.ok  # touch it, as a real client would

    rounds(min(warmup, ticks))
    t0 = time.perf_counter()
    rounds(ticks)
    return ticks / (time.perf_counter() - t0)


def pubsub_rounds(session, n: int, ticks: int, warmup: int = 50) -> float:
    """Rounds per second of one put on bench/ps/step answered by a put from each of ``n`` bare
    subscribers (bench/raw_subscriber.py) on bench/ps/done/*: the shape of the step broadcast."""
    import queue

    q: queue.SimpleQueue = queue.SimpleQueue()
    sub = session.declare_subscriber("bench/ps/done/*", lambda s: q.put(None))
    pub = session.declare_publisher("bench/ps/step")
    time.sleep(0.3)  # let the subscribers' interest arrive

    def rounds(count):
        for _ in range(count):
            pub.put(PAYLOAD)
            for _ in range(n):
                q.get(timeout=10)

    try:
        rounds(min(warmup, ticks))
        t0 = time.perf_counter()
        rounds(ticks)
        return ticks / (time.perf_counter() - t0)
    finally:
        sub.undeclare()
        pub.undeclare()


