"""``python -m agents KIND --name NAME [Zenoh flags]``: run one model as an agent process.

``KIND`` is a built-in kind (``physics``, ``grasp_monitor``, ``in_hand``, ``spu``, ``fluid``, ``trivial``)
or ``package.module:Class``. ``python -m agents KIND --help`` documents that kind from its declarations:
its parameters (type, default, doc), the attributes it can own, its outputs, events, evaluators and
services. The agent registers with the conductor of its ensemble and serves until SIGINT/SIGTERM.
``--describe`` prints, as JSON, what the agent would declare when it registers, and exits without joining a bus
(``twin check`` checks a scene against it).
"""
from __future__ import annotations

import argparse
import contextlib
import faulthandler
import json
import os
import signal
import sys

from protocol.config import add_zenoh_args, options_from_args

from .model import Model
from .registry import BUILTIN, resolve_kind
from .runtime import AgentRuntime, check_agent_name, run_agent


def describe_kind(cls: type[Model]) -> str:
    """A kind's interface in words, from its declarations (what ``--help`` prints)."""
    lines = [f"{cls.kind}: {(cls.__doc__ or '').strip().splitlines()[0] if cls.__doc__ else ''}".rstrip(": "), ""]
    lines.append(f"role: {cls.role}; step modes: {', '.join(cls.step_modes)}")
    if cls.params:
        lines.append("\nparameters (the scene's models.<name>.args):")
        for name, p in cls.params.items():
            default = "required" if p.required else f"default {p.default!r}"
            lines.append(f"  {name} ({p.type_name}, {default})")
            if p.doc:
                lines.append(f"      {p.doc}")
    else:
        lines.append("\nparameters: none")
    for title, names in (("can own", cls.attributes), ("outputs", cls.outputs), ("events", cls.events),
                         ("reads", cls.reads), ("evaluators", tuple(cls.evaluators())),
                         ("services", tuple(cls.services()))):
        lines.append(f"{title}: {', '.join(names) if names else '-'}")
    return "\n".join(lines)


def build_parser(cls: type[Model] | None = None, prog: str = "python -m agents",
                 finding_kind: bool = False) -> argparse.ArgumentParser:
    """The command line of an agent; its help ends with the kind's interface when the kind is known.
    ``finding_kind``: the same flags with no help and ``KIND`` optional, to find the kind among them."""
    epilog = describe_kind(cls) if cls is not None else f"built-in kinds: {', '.join(sorted(BUILTIN))}"
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0] if __doc__ else None,
                                epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter,
                                add_help=not finding_kind)
    p.add_argument("kind", nargs="?" if finding_kind else None, help="built-in kind or package.module:Class")
    p.add_argument("--name", help="model name in the scene (default: the kind)")
    p.add_argument("--register-timeout", type=float, default=0.0,
                   help="give up if no conductor answers within this many seconds (default: retry forever)")
    p.add_argument("--describe", action="store_true",
                   help="print what this agent would declare when it registers (JSON: kind, role, parameters, "
                        "attributes, outputs, events, evaluators, services) and exit without joining a bus")
    add_zenoh_args(p)
    return p


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Resolve the kind, parse the flags and run the agent; returns the process exit code (2: bad kind).
    ``prog`` names the program in messages (default ``TWIN_AGENT_PROG``, set by ``twin agent``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = prog or os.environ.get("TWIN_AGENT_PROG") or "python -m agents"
    if hasattr(signal, "SIGUSR1") and sys.stderr is not None:  # kill -USR1 PID: every thread's stack, to the log
        with contextlib.suppress(ValueError, RuntimeError, OSError):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
    # the first word that is not a flag's value (``--name ball trivial``: trivial)
    kind = build_parser(prog=prog, finding_kind=True).parse_known_args(argv)[0].kind
    cls = None
    if kind is not None:
        try:
            cls = resolve_kind(kind)
        except ValueError as e:
            print(f"{prog}: {e}", file=sys.stderr)
            return 2
    args = build_parser(cls, prog).parse_args(argv)
    assert cls is not None  # argparse has required KIND
    try:
        opts = options_from_args(args)
        if not args.describe:  # (a descriptor is asked by kind, fmu:PATH too: no name goes on the bus)
            check_agent_name(args.name or cls.kind)
    except ValueError as e:  # an endpoint, a credentials or TLS file that cannot serve: one line, not a traceback
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    if args.describe:
        desc = AgentRuntime(cls(), args.name or cls.kind, opts).descriptor()
        for k in ("pid", "host"):  # who would register, not what: no process is registering
            desc.pop(k, None)
        print(json.dumps(desc, default=repr))
        return 0
    return run_agent(cls(), args.name or cls.kind, opts, register_timeout=args.register_timeout)


if __name__ == "__main__":
    sys.exit(main())
