"""Zenoh session configuration shared by every ``twin`` program.

Every program takes the same flags (``--mode``, ``--listen``, ``--connect``, ``--config``,
``--ensemble``, ``--tls-ca``, ``--tls-cert``, ``--tls-key``) and the environment variables of the
same names (``TWIN_MODE``, ``TWIN_LISTEN``, ``TWIN_CONNECT``, ``TWIN_CONFIG``, ``TWIN_ENSEMBLE``,
``TWIN_TLS_CA``, ``TWIN_TLS_CERT``, ``TWIN_TLS_KEY``). Flags win over the environment.
"""
from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import zenoh

__all__ = ["DEFAULT_ENDPOINT", "ENDPOINT_PROTOCOLS", "MAX_MESSAGE_SIZE", "ZenohOptions", "add_zenoh_args",
           "check_endpoint", "check_tls", "options_from_args", "read_access", "read_credentials", "zenoh_problem"]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
MAX_MESSAGE_SIZE = 16 << 20
"""The largest message any twin process accepts from a peer (bytes); a larger one is dropped by Zenoh."""
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe")
"""The router's endpoint when none is given: a client connects to it, a router listens on it."""


@dataclass
class ZenohOptions:
    """How a program opens its Zenoh session: ``mode`` (router, peer or client), endpoints to ``listen`` on
    and ``connect`` to (:data:`DEFAULT_ENDPOINT` when a router or a client has none), a JSON5 ``config_file``
    to start from, the ``ensemble`` (key namespace), mutual-TLS files (PEM paths), ``multicast`` scouting,
    the link lease (ms; None or 0 keeps zenoh's) and ``extra`` settings (config key -> JSON value, applied last).
    """

    mode: str = "client"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    config_file: str | None = None
    ensemble: str = "default"
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    user: str | None = None  # Zenoh user/password authentication (a closed bus: see twin run)
    password: str | None = None
    auth_dictionary: str | None = None  # a router's file of "user:password" lines it admits
    multicast: bool = False
    # 3 s: a link lapses after this long without a word from the other side. 1 s lapsed now and then on a 2-core
    # machine under two CPU burners (a sample of two ensembles side by side: 1 run in 6 degraded, 0 in 6 with
    # 3 s); a killed process's link closes at once either way, only a hung or cut-off one takes this long
    lease_ms: int | None = 3000
    connect_timeout_ms: int | None = None  # give up connecting after this long (None: keep trying forever)
    max_message_size: int = MAX_MESSAGE_SIZE
    extra: dict[str, Any] = field(default_factory=dict)

    def to_config(self) -> zenoh.Config:
        """Build a ``zenoh.Config`` from these options (``zenoh.ZError`` for a setting zenoh refuses, e.g. an
        unknown key in ``extra``)."""
        import zenoh

        if self.config_file:
            cfg = zenoh.Config.from_file(self.config_file)
        else:
            cfg = zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        listen = list(self.listen)
        connect = list(self.connect)
        if self.mode == "router" and not listen:
            listen = [DEFAULT_ENDPOINT]
        if self.mode == "client" and not connect:
            connect = [DEFAULT_ENDPOINT]
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(listen))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(connect))
        cfg.insert_json5("scouting/multicast/enabled", "true" if self.multicast else "false")
        if self.mode == "router" and not self.multicast:
            # a router listens and is connected to; it has nothing to scout for, and the default scouting delay
            # holds zenoh.open for 0.5 s (2 ms without it)
            cfg.insert_json5("scouting/delay", "0")
        if self.lease_ms:
            cfg.insert_json5("transport/link/tx/lease", str(int(self.lease_ms)))
        # a peer may not send this process more than this in one message (Zenoh's default is 1 GiB)
        cfg.insert_json5("transport/link/rx/max_message_size", str(int(self.max_message_size)))
        if self.mode != "router" and self.connect_timeout_ms is not None:
            cfg.insert_json5("connect/timeout_ms", str(int(self.connect_timeout_ms)))
            cfg.insert_json5("connect/exit_on_failure", "true")
        elif self.mode != "router":
            # keep retrying to reach the router forever (router restarts, late start)
            cfg.insert_json5("connect/timeout_ms", "-1")
            cfg.insert_json5("connect/exit_on_failure", "false")
        if self.mode != "router":
            # come back quickly after a cut (zenoh's default backs off to 4 s between tries), also a session that
            # was opened a second at a time (open_patiently)
            cfg.insert_json5("connect/retry", json.dumps({"period_init_ms": 250, "period_max_ms": 1000,
                                                          "period_increase_factor": 2}))
        if self.user and self.password:
            cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(self.user))
            cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(self.password))
        if self.auth_dictionary:
            cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(self.auth_dictionary))
        if self.tls_ca:
            cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(self.tls_ca))
        if self.tls_cert and self.tls_key:
            cfg.insert_json5("transport/link/tls/enable_mtls", "true")
            if listen:
                cfg.insert_json5("transport/link/tls/listen_certificate", json.dumps(self.tls_cert))
                cfg.insert_json5("transport/link/tls/listen_private_key", json.dumps(self.tls_key))
            if connect or self.mode != "router":
                cfg.insert_json5("transport/link/tls/connect_certificate", json.dumps(self.tls_cert))
                cfg.insert_json5("transport/link/tls/connect_private_key", json.dumps(self.tls_key))
        for k, v in self.extra.items():
            cfg.insert_json5(k, json.dumps(v))
        return cfg

    def open(self) -> zenoh.Session:
        """Open a Zenoh session configured by :meth:`to_config` (raises ``zenoh.ZError`` as it does)."""
        import zenoh

        return zenoh.open(self.to_config())

    def open_patiently(self, signalled: Callable[[], bool], give_up_s: float = 0.0,
                       waiting: Callable[[str], None] | None = None) -> zenoh.Session | None:
        """A client's session, tried a second at a time while no router answers (an open that waits for ever
        holds the interpreter, deaf to SIGTERM and Ctrl-C): None once ``signalled()`` or, when ``give_up_s`` > 0,
        after that long. ``waiting`` is told once, after the first try, why nothing answered yet. A router, or
        options with their own connect timeout, open once as :meth:`open` does."""
        import dataclasses
        import time

        import zenoh

        # (a client without endpoints connects to DEFAULT_ENDPOINT: it waits for a router as much as one with them)
        waits = bool(self.connect) or (self.mode == "client" and not self.config_file)
        if self.mode == "router" or not waits or self.connect_timeout_ms is not None:
            return self.open()
        trying = dataclasses.replace(self, connect_timeout_ms=1000)
        deadline = time.monotonic() + give_up_s if give_up_s > 0 else None
        while not signalled():
            began = time.monotonic()
            config = trying.to_config()  # (a setting Zenoh refuses raises here: not a router to wait for)
            try:
                return zenoh.open(config)
            except zenoh.ZError as e:
                if "Unable to connect" not in str(e):
                    raise
                if waiting is not None:
                    waiting(self.unanswered())
                    waiting = None
                time.sleep(max(0.0, began + 1.0 - time.monotonic()))  # (a router that refuses answers at once)
                if deadline is not None and time.monotonic() > deadline:
                    return None
        return None

    def unanswered(self, timeout_s: float | None = None) -> str:
        """Why :meth:`open` as a client found no router, in words: nothing listening at the endpoints, or (a TCP
        port there accepts) a router that did not let this session in: a closed bus (``twin run``'s, ``twin
        serve``'s) admits only its agents and the holders of its access file."""
        import socket

        where = ", ".join(self.connect or [DEFAULT_ENDPOINT])
        within = f" within {timeout_s:g} s" if timeout_s is not None else ""
        for ep in self.connect or [DEFAULT_ENDPOINT]:
            proto, host, port = _split_endpoint(ep)
            if proto not in ("tcp", "tls") or not port.isdigit():
                continue
            try:
                with socket.create_connection((host.strip("[]"), int(port)), timeout=1.0):
                    pass
            except OSError:
                continue
            hint = ("pass the access file it names, --credentials RUN_DIR/access.json" if self.user is None else
                    "the credentials given are not its own")
            short = (" (or the time was too short for a session to open: give a longer --timeout)"
                     if timeout_s is not None and timeout_s < 1.0 else "")
            return (f"the Zenoh router at {ep} did not let this session in{within}: a closed bus (twin run's, "
                    f"twin serve's) admits only its agents and the holders of its access file ({hint}){short}")
        return f"no Zenoh router answered at {where}{within}"


def _split_endpoint(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of an endpoint such as ``tcp/127.0.0.1:7447`` (its ``?``/``#`` settings left
    out; empty strings for what it lacks)."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.split("?", 1)[0].split("#", 1)[0].rpartition(":")
    return proto, host, port


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it is a Zenoh endpoint such as ``tcp/127.0.0.1:7447``; ValueError saying what is wrong."""
    proto, host, port = _split_endpoint(endpoint)
    if "/" not in endpoint or proto not in ENDPOINT_PROTOCOLS:
        raise ValueError(f"endpoint {endpoint!r}: must start with a protocol ({', '.join(ENDPOINT_PROTOCOLS)}), "
                         "e.g. tcp/127.0.0.1:7447")
    if proto in ("tcp", "udp", "tls", "quic", "ws") and not (host and port.isdigit() and int(port) < 65536):
        raise ValueError(f"endpoint {endpoint!r}: must be {proto}/HOST:PORT, e.g. {proto}/127.0.0.1:7447")
    return endpoint


def _env_list(name: str) -> list[str]:
    v = os.environ.get(name, "")
    return [s.strip() for s in v.split(",") if s.strip()]


def add_zenoh_args(p: argparse.ArgumentParser, default_mode: str = "client", listens: str | None = None) -> None:
    """Add the common Zenoh flags to a command's parser (defaults from the ``TWIN_*`` environment variables,
    read now); ``listens``: where the command listens without ``--listen``, for its help."""
    g = p.add_argument_group("zenoh network (flags override TWIN_* environment variables)")
    g.add_argument("--mode", choices=["router", "peer", "client"],
                   default=os.environ.get("TWIN_MODE", default_mode),
                   help=f"zenoh session mode (env TWIN_MODE, default {default_mode})")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; env TWIN_LISTEN, comma separated"
                        + (f"; default {listens})" if listens else ")"))
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to (repeatable; env TWIN_CONNECT; "
                        f"default {DEFAULT_ENDPOINT} for clients)")
    g.add_argument("--config", default=os.environ.get("TWIN_CONFIG"), metavar="FILE",
                   help="a zenoh JSON5 configuration file to start from (env TWIN_CONFIG)")
    g.add_argument("--ensemble", default=os.environ.get("TWIN_ENSEMBLE", "default"),
                   help="ensemble name: the key namespace twin/<ensemble>/ (env TWIN_ENSEMBLE, default 'default')")
    g.add_argument("--tls-ca", default=os.environ.get("TWIN_TLS_CA"), metavar="PEM",
                   help="CA certificate that signs every peer's certificate (env TWIN_TLS_CA)")
    g.add_argument("--tls-cert", default=os.environ.get("TWIN_TLS_CERT"), metavar="PEM",
                   help="this process's certificate, for mutual TLS (env TWIN_TLS_CERT)")
    g.add_argument("--tls-key", default=os.environ.get("TWIN_TLS_KEY"), metavar="PEM",
                   help="this process's private key (env TWIN_TLS_KEY)")
    g.add_argument("--credentials", default=os.environ.get("TWIN_CREDENTIALS"), metavar="FILE",
                   help="a JSON file {user, password} for a router that authenticates (a 'twin run' writes one "
                        "as <run dir>/access.json; env TWIN_CREDENTIALS, or TWIN_USER and TWIN_PASSWORD)")


def options_from_args(a: argparse.Namespace) -> ZenohOptions:
    """The options given by the flags of :func:`add_zenoh_args` (endpoints from ``TWIN_LISTEN`` and
    ``TWIN_CONNECT`` when no flag gives any)."""
    listen = [check_endpoint(e) for e in (a.listen if a.listen is not None else _env_list("TWIN_LISTEN"))]
    connect = [check_endpoint(e) for e in (a.connect if a.connect is not None else _env_list("TWIN_CONNECT"))]
    access = read_access(getattr(a, "credentials", None))
    user, password = (access["user"], access["password"]) if access else read_credentials(None)
    ensemble = a.ensemble
    if access.get("connect") and not connect and a.mode != "router":  # where the twin run or serve that wrote it is
        connect = [check_endpoint(access["connect"])]
        if ensemble == "default":  # (an --ensemble given says which)
            ensemble = access.get("ensemble", ensemble)
    check_tls(a.tls_ca, a.tls_cert, a.tls_key)
    return ZenohOptions(mode=a.mode, listen=listen, connect=connect, config_file=a.config,
                        ensemble=ensemble, tls_ca=a.tls_ca, tls_cert=a.tls_cert, tls_key=a.tls_key,
                        user=user, password=password)


def check_tls(ca: str | None, cert: str | None, key: str | None) -> None:
    """ValueError in one line when the TLS files given cannot make a link: a file missing or not PEM, a certificate
    without its key (or a key without its certificate), a key that is not the certificate's. Zenoh takes each of
    these for a router that is not there yet, and a client waited for it for ever."""
    given = {"--tls-ca": ca, "--tls-cert": cert, "--tls-key": key}
    for flag, path in given.items():
        if path and not os.path.isfile(path):
            raise ValueError(f"{flag} {path}: no such file (env TWIN_{flag[2:].upper().replace('-', '_')})")
    if bool(cert) != bool(key):
        raise ValueError("--tls-cert and --tls-key go together: give this process's certificate and its key")
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization
    except ImportError:  # (the checks below need it; zenoh says the rest when the link is made)
        return
    loaded: dict[str, Any] = {}
    for flag, path in given.items():
        if not path:
            continue
        try:
            with open(path, "rb") as f:
                data = f.read()
            loaded[flag] = (serialization.load_pem_private_key(data, password=None) if flag == "--tls-key"
                            else x509.load_pem_x509_certificate(data))
        except (OSError, ValueError, TypeError) as e:
            raise ValueError(f"{flag} {path}: not a PEM {'private key' if flag == '--tls-key' else 'certificate'} "
                             f"({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    if cert and key:
        def public(k: Any) -> bytes:
            return bytes(k.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo))

        if public(loaded["--tls-cert"].public_key()) != public(loaded["--tls-key"].public_key()):
            raise ValueError(f"--tls-key {key} is not the key of --tls-cert {cert}: give the key made with it")


def read_access(path: str | None) -> dict[str, str]:
    """A credentials file's fields: ``user`` and ``password``, and, in the access file a ``twin run`` or ``twin serve``
    writes, ``connect`` (where its router listens) and ``ensemble`` ({}: no file given). ValueError naming the file
    if it cannot be read."""
    if not path:
        return {}
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        out = {"user": str(doc["user"]), "password": str(doc["password"])}
    except FileNotFoundError:  # (twin run and twin serve remove their access file when they end)
        raise ValueError(f"{path}: no such credentials file (the twin run or twin serve that writes it is not "
                         "running, or ran somewhere else)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a credentials file {{user, password}} ({e})") from None
    out.update({k: str(doc[k]) for k in ("connect", "ensemble") if isinstance(doc.get(k), str) and doc[k]})
    return out


def read_credentials(path: str | None) -> tuple[str | None, str | None]:
    """(user, password) from a credentials file, else from ``TWIN_USER``/``TWIN_PASSWORD`` (None, None: none).
    ValueError naming the file if it cannot be read."""
    if path:
        access = read_access(path)
        return access["user"], access["password"]
    return os.environ.get("TWIN_USER") or None, os.environ.get("TWIN_PASSWORD") or None


def zenoh_problem(e: BaseException) -> str:
    """Zenoh's error text in one line, without its source locations."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(e))
    text = re.sub(r"^Json5Err\(Message \{ msg: \"(.*?)\", location.*$", r"\1", text)
    return " ".join(text.split())
