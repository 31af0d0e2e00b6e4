"""Ctrl-C on a command that stops its runs (conductor.launch.ctrl_c_stops): the first asks them to stop, the same
signal delivered again at once is that stop, a later one interrupts at once. Real signals to this process."""
import os
import signal
import threading
import time

import pytest

from conductor.launch import ECHO_S, ctrl_c_stops


def test_a_second_signal_is_an_echo_at_first_then_an_interrupt():
    asked: list[str] = []
    done = threading.Event()

    def stop(reason: str) -> None:
        asked.append(reason)
        done.set()

    before = signal.getsignal(signal.SIGINT)
    echoed = False
    with pytest.raises(KeyboardInterrupt):
        with ctrl_c_stops(stop):
            os.kill(os.getpid(), signal.SIGINT)  # (its handler runs before the next line)
            os.kill(os.getpid(), signal.SIGINT)  # the same Ctrl-C again (a wrapper passed it on): nothing more
            assert done.wait(5.0)
            time.sleep(0.1)
            assert asked == ["Ctrl-C"]
            echoed = True
            time.sleep(ECHO_S)
            os.kill(os.getpid(), signal.SIGINT)  # a user who means it: at once
            time.sleep(1.0)  # (the handler raises in this thread before this ends)
    assert echoed, "the echo interrupted"
    assert signal.getsignal(signal.SIGINT) is before  # put back when the block ends
