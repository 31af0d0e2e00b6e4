"""The ``twin`` command line: one parser, every command registered explicitly. ``twin COMMAND --help``
explains each command."""
from __future__ import annotations

import argparse
import contextlib
import faulthandler
import logging
import os
import signal
import sys
from typing import Any

import zenoh

from bench.cli import register_bench, register_evaluate
from protocol.config import zenoh_problem
from protocol.errors import SceneError, TwinError
from recordings.cli import register_record, register_robot

from . import check, deploy, run, serve, view

DESCRIPTION = """\
twin: a multi-agent heterogeneous digital twin for robots on Eclipse Zenoh.

Each model of the robot and its world runs as its own agent process; the conductor steps them,
moves the responsibility for each object's attributes between them as the robot acts, and logs
everything. Start with:  twin run scenes/ball_drop.yaml --recording recordings/ball_drop_00.mcap
"""


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING - 10 * verbose
    logging.basicConfig(level=max(logging.DEBUG, level), format="%(asctime)s %(name)s %(levelname)s: %(message)s",
                        datefmt="%H:%M:%S")



def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="twin", description=DESCRIPTION,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    run.register(sub)  # router, agent, conductor, run
    serve.register(sub)  # serve, status, submit, trigger, stop
    view.register(sub)
    check.register(sub)
    register_record(sub)
    register_robot(sub)
    register_evaluate(sub)
    register_bench(sub)
    deploy.register(sub)  # certs, acl
    return p


def dump_stacks_on_sigusr1() -> None:
    """``kill -USR1 PID`` writes the stack of every thread of a twin process to its stderr (an agent's: to its
    log), to see where one that seems stuck is, without stopping it."""
    if hasattr(signal, "SIGUSR1") and sys.stderr is not None:
        with contextlib.suppress(ValueError, RuntimeError, OSError):  # (not the main thread; no file descriptor)
            faulthandler.register(signal.SIGUSR1, all_threads=True)


class _Unbroken:
    """``sys.stdout`` that outlives its reader: once the reader has gone (``twin run ... | head``), what is printed
    goes nowhere instead of raising BrokenPipeError in whichever thread printed, so the run still goes to its end
    and writes its summary and run log."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def _gone(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)

    def write(self, text: str) -> int:
        try:
            return int(self._stream.write(text))
        except BrokenPipeError:
            self._gone()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._gone()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    dump_stacks_on_sigusr1()
    if argv[:1] == ["agent"]:  # everything after 'agent' is the agent's own command line (its --help too)
        return run.cmd_agent(argparse.Namespace(agent_args=argv[1:]))
    p = build_parser()
    args = p.parse_args(argv)
    _setup_logging(args.verbose)
    if not getattr(args, "func", None):
        p.print_help()
        print("\ntwin: give a command (above); twin COMMAND --help says what it does", file=sys.stderr)
        return 2
    stdout = sys.stdout
    if stdout is not None and not isinstance(stdout, _Unbroken):
        sys.stdout = _Unbroken(stdout)  # type: ignore[assignment]
    try:
        return _run(args)
    finally:
        sys.stdout = stdout


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except SceneError as e:
        print(f"scene error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:  # a bad endpoint or option value, an unreadable or unfitting input file (InputError)
        print(f"twin: {e}", file=sys.stderr)
        return 2
    except zenoh.ZError as e:  # e.g. a port already in use
        print(f"twin: zenoh: {zenoh_problem(e)}", file=sys.stderr)
        return 1
    except TwinError as e:
        print(f"twin: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # (where no stop is handled: e.g. twin evaluate reading its recordings)
        print("twin: stopped by Ctrl-C", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
