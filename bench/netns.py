"""Emulated hosts for deployment tests and the scale benchmark: Linux network namespaces joined by a bridge.

::

      host ns "<net>-router"   host ns "<net>-conductor"   ...        (one per service)
         eth0 10.X.Y.1            eth0 10.X.Y.2
           |  veth                   |  veth
      -----+------------ br0 --------+-------------   bridge ns "<net>-br"
                           |  veth (optional)
                      root namespace 10.X.Y.254  (the test process itself, see Net.attach_root)

Every name carries a tag unique to this test run (pid + random), so parallel runs never collide;
each host gets an ``/etc/hosts`` (via ``/etc/netns/<ns>/hosts``) naming every other host, as a
container network's DNS would. :meth:`Net.close` stops every process started through it, removes the
namespaces (their veth pairs go with them) and the hosts files; it runs from fixtures even when the test
fails, and a new :class:`Net` first removes what crashed runs left behind (namespaces whose creating
process is gone). Needs root (CI runs as root) and ``ip`` from iproute2.
"""
from __future__ import annotations

import ipaddress
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from conductor.launch import AgentProcs

PREFIX = "twt"  # every namespace made here starts with it: twt<pid>x<rand>-<host>
ETC_NETNS = Path("/etc/netns")


def available() -> str | None:
    """None if namespaces can be made here, else the reason (for pytest.skip)."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 'ip' not found"
    r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"'ip netns' does not work here: {r.stderr.strip()}"
    return None


def _ip(*args: str, ns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    cmd = ["ip", *(["-n", ns] if ns else []), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    if check and r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {r.stderr.strip() or r.stdout.strip()}")
    return r


def _netns_list() -> list[str]:
    r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=20)
    return [line.split()[0] for line in r.stdout.splitlines() if line.strip()]


def _kill_ns_processes(ns: str) -> None:
    r = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=20)
    for pid in r.stdout.split():
        try:
            os.kill(int(pid), signal.SIGKILL)
        except (ProcessLookupError, ValueError):
            pass


def _delete_ns(ns: str) -> None:
    _kill_ns_processes(ns)
    subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)
    shutil.rmtree(ETC_NETNS / ns, ignore_errors=True)


def remove_stale() -> list[str]:
    """Delete namespaces of earlier runs whose creating process no longer exists."""
    gone = []
    for ns in _netns_list():
        if not ns.startswith(PREFIX):
            continue
        try:
            pid = int(ns[len(PREFIX):].split("x", 1)[0])
        except ValueError:
            continue
        if pid != os.getpid() and not Path(f"/proc/{pid}").exists():
            _delete_ns(ns)
            gone.append(ns)
    return gone


class Host:
    """One emulated machine: a namespace with ``eth0`` on the bridge."""

    def __init__(self, net: Net, name: str, ns: str, ip: str):
        self.net = net
        self.name = name
        self.ns = ns
        self.ip = ip

    def __repr__(self) -> str:
        return f"Host({self.name}, {self.ip})"

    def spawn(self, label: str, cmd: list[str], env: dict | None = None, cwd: str | None = None) -> subprocess.Popen:
        """Start ``cmd`` inside this host (stdout+stderr to ``<logdir>/agent-<label>.log``)."""
        full = ["ip", "netns", "exec", self.ns, *cmd]
        if cwd:
            full = ["ip", "netns", "exec", self.ns, "env", "-C", cwd, *cmd]
        return self.net.procs.spawn(label, full, env=env)

    def run(self, *cmd: str, timeout: float = 20) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", "netns", "exec", self.ns, *cmd], capture_output=True, text=True, timeout=timeout)

    def link(self, up: bool) -> None:
        """Plug or unplug this host's network cable (``ip link set eth0 up|down``)."""
        _ip("link", "set", "eth0", "up" if up else "down", ns=self.ns)


class Net:
    """A bridge namespace and any number of host namespaces (see the module docstring)."""

    def __init__(self, logdir: Path, tag: str | None = None):
        reason = available()
        if reason:
            raise RuntimeError(reason)
        remove_stale()
        self.tag = tag or f"{PREFIX}{os.getpid()}x{random.randrange(16**4):04x}"
        self.logdir = Path(logdir)
        self.procs = AgentProcs(self.logdir)
        self.hosts: dict[str, Host] = {}
        self._namespaces: list[str] = []
        self.subnet = self._pick_subnet()
        self._addrs = iter(list(self.subnet.hosts())[:250])
        self.root_ip: str | None = None
        self._root_if: str | None = None
        self.bridge_ns = f"{self.tag}-br"
        try:
            self._add_ns(self.bridge_ns)
            _ip("link", "add", "br0", "type", "bridge", ns=self.bridge_ns)
            _ip("link", "set", "br0", "up", ns=self.bridge_ns)
        except Exception:
            self.close()
            raise

    @staticmethod
    def _pick_subnet() -> ipaddress.IPv4Network:
        used = subprocess.run(["ip", "-4", "-o", "addr"], capture_output=True, text=True).stdout
        for _ in range(200):
            net = ipaddress.IPv4Network(f"10.{random.randrange(100, 250)}.{random.randrange(256)}.0/24")
            if f" {str(net.network_address)[:-1]}" not in used:
                return net
        raise RuntimeError("no free 10.x.y.0/24 subnet")

    def _add_ns(self, ns: str) -> None:
        _ip("netns", "add", ns)
        self._namespaces.append(ns)
        _ip("link", "set", "lo", "up", ns=ns)

    def add_host(self, name: str) -> Host:
        """A new machine on the LAN, reachable from the others as ``name``."""
        if name in self.hosts:
            raise ValueError(f"host {name!r} exists")
        i = len(self.hosts)
        ns = f"{self.tag}-{name}"
        ip = str(next(self._addrs))
        self._add_ns(ns)
        port = f"p{i}"
        _ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", port, "netns", self.bridge_ns)
        _ip("link", "set", port, "master", "br0", ns=self.bridge_ns)
        _ip("link", "set", port, "up", ns=self.bridge_ns)
        _ip("addr", "add", f"{ip}/{self.subnet.prefixlen}", "dev", "eth0", ns=ns)
        _ip("link", "set", "eth0", "up", ns=ns)
        h = self.hosts[name] = Host(self, name, ns, ip)
        self._write_hosts()
        return h

    def attach_root(self) -> str:
        """Join the test process's own (root) namespace to the LAN; returns its address there."""
        if self.root_ip:
            return self.root_ip
        ifname = f"tw{self.tag[-8:]}"[-15:]
        _ip("link", "add", ifname, "type", "veth", "peer", "name", "proot", "netns", self.bridge_ns)
        self._root_if = ifname
        _ip("link", "set", "proot", "master", "br0", ns=self.bridge_ns)
        _ip("link", "set", "proot", "up", ns=self.bridge_ns)
        ip = str(list(self.subnet.hosts())[253])
        _ip("addr", "add", f"{ip}/{self.subnet.prefixlen}", "dev", ifname)
        _ip("link", "set", ifname, "up")
        self.root_ip = ip
        self._write_hosts()
        return ip

    def _write_hosts(self) -> None:
        lines = ["127.0.0.1 localhost"] + [f"{h.ip} {h.name}" for h in self.hosts.values()]
        if self.root_ip:
            lines.append(f"{self.root_ip} tester")
        text = "\n".join(lines) + "\n"
        for h in self.hosts.values():
            d = ETC_NETNS / h.ns
            d.mkdir(parents=True, exist_ok=True)
            (d / "hosts").write_text(text)

    def wait_reachable(self, src: Host, dst: Host, timeout: float = 10.0) -> None:
        """Wait until ``dst`` answers ``src`` (the bridge learns addresses in a moment)."""
        # a TCP connect to a closed port: "refused" means the host answered (no ping binary needed)
        probe = ("import socket,sys\ns=socket.socket();s.settimeout(1)\n"
                 "try: s.connect((sys.argv[1], 9))\nexcept ConnectionRefusedError: sys.exit(0)\n"
                 "except OSError: sys.exit(1)\nsys.exit(0)")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if src.run(sys.executable, "-c", probe, dst.ip).returncode == 0:
                return
        raise RuntimeError(f"{dst} unreachable from {src}")

    def close(self) -> None:
        try:
            self.procs.stop(timeout=5)
        finally:
            for ns in reversed(self._namespaces):
                _delete_ns(ns)
            self._namespaces = []
            if self._root_if:
                subprocess.run(["ip", "link", "del", self._root_if], capture_output=True)
                self._root_if = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def python_cmd(*args: str) -> list[str]:
    """The twin command line as a host runs it (``twin ...`` in the image)."""
    return [sys.executable, "-m", "conductor.cli", *args]


# ------------------------------------------------------------------ twin helpers
class EventWatch:
    """Follows the conductor's events (``event/_conductor/*``) from a session: wait for one, bounded."""

    def __init__(self, session, ensemble: str):
        import threading

        from protocol.keys import Keys

        self.events: list[tuple[str, dict]] = []
        self._cv = threading.Condition()
        self._sub = session.declare_subscriber(Keys(ensemble).event("_conductor", "*"), self._on)

    def _on(self, sample) -> None:
        from protocol import codec

        try:
            msg = codec.decode(str(sample.key_expr), sample.payload, "event")
        except Exception:
            return
        with self._cv:
            self.events.append((msg.name, dict(msg.data)))
            self._cv.notify_all()

    def wait_for(self, name: str, pred=lambda data: True, timeout: float = 30.0) -> dict:
        deadline = time.monotonic() + timeout
        with self._cv:
            while True:
                for n, d in self.events:
                    if n == name and pred(d):
                        return d
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no {name!r} event within {timeout} s (seen: {[n for n, _ in self.events]})")
                self._cv.wait(left)

    def names(self) -> list[str]:
        with self._cv:
            return [n for n, _ in self.events if n != "trigger"]

    def close(self) -> None:
        self._sub.undeclare()


def wait_tokens(session, key: str, names, timeout: float = 30.0) -> set[str]:
    """Wait until liveliness tokens ``key`` (a ``.../alive/*`` expression) include every name."""
    want = set(names)
    deadline = time.monotonic() + timeout
    seen: set[str] = set()
    while time.monotonic() < deadline:
        seen = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in session.liveliness().get(key, timeout=2.0)
                if r.ok is not None}
        if want <= seen:
            return seen
        time.sleep(0.1)
    raise TimeoutError(f"tokens {sorted(want - seen)} not seen on {key} within {timeout} s (seen {sorted(seen)})")


def wait_exit(proc: subprocess.Popen, timeout: float, log: Path | None = None) -> int:
    """Wait (bounded) for a process to end; on timeout the failure shows the end of its log."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        tail = log.read_text(errors="replace")[-3000:] if log and log.exists() else ""
        raise TimeoutError(f"{proc.args!r} still running after {timeout} s\n{tail}") from None
