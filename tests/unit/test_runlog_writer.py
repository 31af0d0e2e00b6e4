"""The run log's writer thread alone: it must not depend on how soon the thread that creates the log runs again.

On a loaded machine the creating thread can lose the CPU for longer than the writer's first wait; a writer that
then read state the constructor had not set yet failed, and the run stopped as failed before its agents were in
(seen once in CI with two CPU burners beside it)."""
from __future__ import annotations

import threading
import time

from conductor.runlog import writer
from conductor.runlog.reader import read_run_log
from protocol import codec


def test_a_slow_constructor_does_not_break_the_writer(tmp_path, monkeypatch):
    start = threading.Thread.start

    def start_then_stall(self):  # the creating thread descheduled right after the writer started
        start(self)
        time.sleep(10 * writer.WAKE_S)

    monkeypatch.setattr(threading.Thread, "start", start_then_stall)
    log = writer.RunLog(tmp_path / "run.mcap", {}, dt=0.01, prefix="twin/t")
    monkeypatch.setattr(threading.Thread, "start", start)
    log.record("twin/t/ownership", codec.encode("ownership", version=1, tick=3, t=0.03, change=None, owners={}))
    time.sleep(3 * writer.WAKE_S)
    log.close()
    assert log.error is None
    got = [(k, m["tick"]) for k, _, m in read_run_log(tmp_path / "run.mcap")]
    assert got == [("twin/t/ownership", 3)]


def _ownership(tick: int) -> bytes:
    return codec.encode("ownership", version=1, tick=tick, t=tick * 0.01, change=None, owners={})


def test_settle_waits_for_a_quiet_bus_but_no_longer_than_its_limit(tmp_path):
    """At a run's end the log waits for what is still on its way: while messages keep coming, up to its limit;
    a message that comes while it waits starts the quiet time again. (Lower bounds only: a loaded machine can
    only make the waits longer; the upper bound is generous for the same reason.)"""
    log = writer.RunLog(tmp_path / "run.mcap", {}, dt=0.01, prefix="twin/t")
    try:
        t0 = time.perf_counter()
        log.settle(quiet=0.01, limit=30.0)  # nothing comes: done after the quiet time, far from the limit
        assert time.perf_counter() - t0 < 15.0

        stop = threading.Event()

        def chatter() -> None:  # a message every 2 ms: the bus never goes quiet for 100 ms
            tick = 0
            while not stop.is_set() and tick < 5000:
                log.take("twin/t/ownership", _ownership(tick))
                tick += 1
                time.sleep(0.002)
        th = threading.Thread(target=chatter)
        th.start()
        t0 = time.perf_counter()
        log.settle(quiet=0.1, limit=0.2)
        assert time.perf_counter() - t0 >= 0.2
        stop.set()
        th.join()

        late = threading.Timer(0.05, lambda: log.take("twin/t/ownership", _ownership(9999)))
        t0 = time.perf_counter()
        late.start()
        log.settle(quiet=0.08, limit=5.0)  # the late message at 50 ms starts the 80 ms again
        assert time.perf_counter() - t0 >= 0.13
        late.join()
    finally:
        log.close()
    assert log.error is None
    assert any(m["tick"] == 9999 for _, _, m in read_run_log(tmp_path / "run.mcap"))


def test_an_event_whose_data_the_log_view_cannot_sort_is_written_and_not_counted_lost(tmp_path):
    """An event whose data has an int key beside a str key (msgpack allows it): the Foxglove log view's json.dumps
    (sort_keys) raised after the event itself was written, and it was counted as left out (the run degraded for
    it). Its log line is now written unsorted; a view that fails is no lost message."""
    from mcap.reader import make_reader

    path = tmp_path / "mixed.mcap"
    log = writer.RunLog(path, dt=0.01, prefix="twin/default", models=["m"],
                        entities={"ball": {"shape": {"type": "sphere", "radius": 0.02}, "attributes": ["pose"]}})
    log.take("twin/default/event/m/hit", codec.pack({"v": 1, "type": "event", "model": "m", "name": "hit",
                                                    "tick": 1, "t": 0.01, "data": {1: "a", "b": 2}}))
    log.close()
    assert log.dropped == {}
    assert [m["data"] for k, _, m in read_run_log(path) if k.endswith("/hit")] == [{"1": "a", "b": 2}]
    with open(path, "rb") as f:
        lines = [m.data for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/twin/log"]
    assert len(lines) == 1 and b"m.hit" in lines[0]


def test_a_live_log_files_every_message_of_time_0_at_the_robot_s_first_stamp(tmp_path):
    """A live run's time 0 is its robot's first stamp, known once the robot speaks: the initial ownership and the
    run's start, logged at time 0 before then, were filed at the log's opening and the first tick at the robot's
    stamp, two log times for one time 0; and a log cut short kept the opening as its origin (a review's finding).
    Messages on the simulated clock now wait for the origin, and the file says it as soon as it is known."""
    import shutil
    from types import SimpleNamespace

    from conductor.runlog.reader import read_metadata
    from protocol.keys import Keys

    keys = Keys("default")
    log = writer.RunLog(tmp_path / "run.mcap", dt=0.01)
    source = SimpleNamespace(on_t0=None)
    log.take_origin_from(source)
    t0 = log.origin_ns + 5_000_000_000  # (the robot spoke 5 s after the log opened)
    log.take(keys.ownership, codec.encode("ownership", version=0, tick=0, t=0.0, owners={}, change=None))
    time.sleep(0.3)  # (the writer wrote what it had meanwhile)
    source.on_t0(t0 * 1e-9)
    log.take(keys.clock, codec.encode("clock", tick=0, t=0.0, dt=0.01))
    log.take(keys.telemetry("joint_states"), codec.encode("joint_state", stamp=t0 * 1e-9, name=["j1"],
                                                          position=[0.1], velocity=[], effort=[]))
    time.sleep(0.3)
    shutil.copy(tmp_path / "run.mcap", tmp_path / "cut.mcap")  # (as a run killed now leaves it)
    log.close()
    for name in ("cut.mcap", "run.mcap"):
        assert abs(int(read_metadata(tmp_path / name)["twin.log"]["origin_ns"]) - t0) < 1000, name
    times = {k.rsplit("/", 1)[-1]: ns for k, ns, _ in read_run_log(tmp_path / "run.mcap")}
    assert set(times) == {"ownership", "clock", "joint_states"}
    assert all(abs(ns - t0) < 1000 for ns in times.values()), {k: (ns - t0) * 1e-9 for k, ns in times.items()}
