"""Security for a twin on a shared network: test certificates for mutual TLS, and a Zenoh
access-control configuration derived from a scene.

Identity is the certificate's common name (CN). Every process of an ensemble gets its own certificate
signed by one CA: the router (``router``), the conductor (``conductor``), each model under its scene name
(``physics``, ``in_hand``, ...), the robot or recording player (``robot``) and read-only tools
(``viewer``). The router checks every link with that CA (mutual TLS) and applies the access-control
rules of :func:`acl_config` to each link by its CN:

=============  ===========================================================================================
CN             may send (ingress at the router), under ``twin/<ensemble>/``
=============  ===========================================================================================
conductor      ``ownership``, ``clock``, ``step``, ``event/_conductor/**``; answers ``conductor/**``;
               queries ``model/**``; token ``alive/_conductor``
<model id>     ``state/<id>``, ``done/<id>``, ``out/<id>/**``, ``event/<id>/**``; answers ``model/<id>/**``;
               queries ``conductor/register/<id>``; token ``alive/<id>``
robot          ``telemetry/**``; queries ``conductor/trigger/*`` (the robot's program calls the scene's service
               triggers)
viewer         nothing (subscribes, asks ``conductor/status``)
=============  ===========================================================================================

Everything else is denied (``default_permission: deny``), including every key outside the ensemble,
so a certificate of one ensemble opens nothing in another. Each listed CN may receive anything of its
ensemble (egress is allowed on ``twin/<ensemble>/**``): the twin hides nothing from its own members.
"""
from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, TypeAlias, TypedDict, cast

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.types import CertificateIssuerPrivateKeyTypes, PrivateKeyTypes
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from .keys import RESERVED_IDENTITIES, Keys, check_name

__all__ = ["CONDUCTOR_CN", "ROUTER_CN", "ROBOT_CN", "VIEWER_CN", "ALL_MESSAGES", "CA", "make_ca", "load_ca",
           "make_cert", "make_certs", "san_name", "default_identities", "AclRule", "AclSubject", "AclPolicy",
           "AccessControl", "acl_config", "write_acl"]

CONDUCTOR_CN = "conductor"
ROUTER_CN = "router"
ROBOT_CN = "robot"
VIEWER_CN = "viewer"

#: every message kind Zenoh 1.x access control knows
ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")


CA: TypeAlias = tuple[x509.Certificate, CertificateIssuerPrivateKeyTypes]
"""A certificate authority: its certificate and its private key."""


# ------------------------------------------------------------------ certificates
def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(key: PrivateKeyTypes, path: Path) -> None:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    path.chmod(0o600)


def _write_cert(cert: x509.Certificate, path: Path) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _name(cn: str, org: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, org), x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def make_ca(directory: str | Path, name: str = "twin test CA", days: int = 365) -> CA:
    """Create ``ca.pem`` / ``ca.key`` (a P-256 key, mode 600) valid for ``days`` in ``directory``; returns
    (certificate, key). Overwrites an existing CA."""

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    key = _new_key()
    now = _dt.datetime.now(_dt.UTC)
    subject = _name(name, "twin")
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5)).not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write_cert(cert, d / "ca.pem")
    _write_key(key, d / "ca.key")
    return cert, key


def load_ca(directory: str | Path) -> CA:
    """The CA that :func:`make_ca` wrote in ``directory`` (OSError if absent, ValueError if unreadable)."""
    d = Path(directory)
    cert = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    key = serialization.load_pem_private_key((d / "ca.key").read_bytes(), password=None)
    # make_ca writes an EC key; a key that cannot sign would fail in make_cert's sign(), as it always has
    return cert, cast(CertificateIssuerPrivateKeyTypes, key)


def make_cert(directory: str | Path, cn: str, ca: CA, sans: Iterable[str] = (), days: int = 365) -> tuple[Path, Path]:
    """Issue ``<cn>.pem`` / ``<cn>.key`` signed by ``ca`` = (certificate, key), valid for ``days``; returns
    their paths. ValueError for a ``cn`` that is not a valid name (:func:`~protocol.keys.check_name`).

    The certificate serves both ends of a link (server and client authentication). Its subject
    alternative names are ``cn``, ``localhost``, ``127.0.0.1`` and ``sans`` (IP addresses or DNS
    names): a client checks the router's certificate against the host it connects to.
    """
    check_name("certificate", cn)
    ca_cert, ca_key = ca
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    key = _new_key()
    alt: list[x509.GeneralName] = []
    seen: set[str] = set()
    for s in [cn, "localhost", "127.0.0.1", *sans]:
        if not s or s in seen:
            continue
        seen.add(s)
        try:
            alt.append(san_name(s))
        except ValueError:  # (the identity itself, a valid name, is its own DNS name whatever it looks like)
            if s != cn:
                raise
            alt.append(x509.DNSName(s))
    now = _dt.datetime.now(_dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(_name(cn, "twin")).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5)).not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    cert_path, key_path = d / f"{cn}.pem", d / f"{cn}.key"
    _write_cert(cert, cert_path)
    _write_key(key, key_path)
    return cert_path, key_path


def san_name(text: str) -> x509.GeneralName:
    """A subject alternative name: an IP address, else a DNS name; ValueError for neither (``999.1.1.1``, a
    mistyped address, is no DNS name a client would look up either)."""
    try:
        return x509.IPAddress(ipaddress.ip_address(text))
    except ValueError:
        pass
    labels = text.rstrip(".").split(".")
    if ":" in text or labels[-1].isdigit() or not all(re.fullmatch(r"(\*|[A-Za-z0-9_]([A-Za-z0-9_-]{0,61}"
                                                                   r"[A-Za-z0-9_])?)", x) for x in labels):
        raise ValueError(f"--san {text!r}: neither an IP address nor a DNS name")
    return x509.DNSName(text)


def make_certs(directory: str | Path, names: Iterable[str], sans: Sequence[str] = (),
               reuse_ca: bool = True) -> dict[str, tuple[Path, Path]]:
    """A CA (kept if ``reuse_ca`` and one is there) and one certificate per name in ``directory``. Every name and
    SAN is checked before anything is written (ValueError): a bad one leaves the folder as it was."""
    d = Path(directory)
    names = list(dict.fromkeys(names))
    for n in names:
        check_name("certificate", n)
    for s in sans:
        if s:
            san_name(s)
    if reuse_ca and (d / "ca.pem").exists() and (d / "ca.key").exists():
        ca = load_ca(d)
    else:
        ca = make_ca(d)
    return {n: make_cert(d, n, ca, list(sans)) for n in names}


def default_identities(models: Iterable[str] = ()) -> list[str]:
    """The certificate names a deployment needs: router, conductor, robot, viewer and each of ``models``.
    ValueError for a model named as one of the others (it would get their certificate)."""
    models = list(models)
    _refuse_reserved(models, RESERVED_IDENTITIES)
    return [ROUTER_CN, CONDUCTOR_CN, ROBOT_CN, VIEWER_CN, *models]


def _refuse_reserved(models: Iterable[str], reserved: Iterable[str]) -> None:
    clash = sorted(set(models) & set(reserved))
    if clash:
        raise ValueError(f"model {', '.join(map(repr, clash))}: the name of the deployment's own "
                         f"{'certificate' if len(clash) == 1 else 'certificates'} ({', '.join(sorted(reserved))}); "
                         "a model so named would share its rights: rename the model")


# ---------------------------------------------------------------- access control
class AclRule(TypedDict):
    """An ``access_control.rules`` entry of Zenoh 1.x (the twin's rules only allow)."""

    id: str
    messages: list[str]
    flows: list[str]
    permission: str
    key_exprs: list[str]


class AclSubject(TypedDict):
    """An ``access_control.subjects`` entry: links by certificate common name."""

    id: str
    cert_common_names: list[str]


class AclPolicy(TypedDict):
    """An ``access_control.policies`` entry: which rules apply to which subjects."""

    id: str
    subjects: list[str]
    rules: list[str]


class AccessControl(TypedDict):
    """The ``access_control`` section of a Zenoh 1.x router configuration."""

    enabled: bool
    default_permission: str
    rules: list[AclRule]
    subjects: list[AclSubject]
    policies: list[AclPolicy]


def _rule(rid: str, messages: Iterable[str], flows: Iterable[str], keys: Iterable[str]) -> AclRule:
    return {"id": rid, "messages": list(messages), "flows": list(flows), "permission": "allow",
            "key_exprs": list(keys)}


def acl_config(models: Iterable[str], ensemble: str = "default", *, robot: str = ROBOT_CN,
               viewers: tuple[str, ...] = (VIEWER_CN,), conductor: str = CONDUCTOR_CN) -> AccessControl:
    """The ``access_control`` section for the router of ``ensemble`` whose scene has these ``models``.

    Subjects are matched by certificate common name, so the router must run with mutual TLS. ValueError for
    an ensemble or model name that cannot be a key chunk, or a model named as the conductor's, the robot's, a
    viewer's or the router's certificate (it would get their rights).
    """
    models = list(models)
    _refuse_reserved(models, {ROUTER_CN, robot, conductor, *viewers})
    k = Keys(ensemble)
    everything = k.everything
    rules = [
        # every member may receive anything of its ensemble
        _rule("receive", ALL_MESSAGES, ["egress"], [everything]),
        # every member may subscribe, follow liveliness and ask the conductor's status
        _rule("observe", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"], ["ingress"],
              [everything]),
        _rule("ask-status", ["query"], ["ingress"], [k.conductor("status")]),
        _rule("conductor", ["put", "delete"], ["ingress"],
              [k.ownership, k.clock, k.step_all, f"{k.step_all}/**", k.event("_conductor", "**"),
               k.telemetry("**")]),  # a replay republishes the recording
        _rule("conductor-serve", ["declare_queryable", "reply"], ["ingress"], [k.conductor("**")]),
        _rule("conductor-ask", ["query"], ["ingress"], [k.model_all("*")]),
        _rule("conductor-alive", ["liveliness_token"], ["ingress"], [k.alive("_conductor")]),
        _rule("robot", ["put", "delete"], ["ingress"], [k.telemetry("**")]),
        _rule("robot-trigger", ["query"], ["ingress"], [k.conductor("trigger/*")]),
    ]
    subjects: list[AclSubject] = [{"id": "conductor", "cert_common_names": [conductor]},
                                  {"id": "robot", "cert_common_names": [robot]}]
    policies: list[AclPolicy] = [
        {"id": "conductor", "subjects": ["conductor"],
         "rules": ["receive", "observe", "ask-status", "conductor", "conductor-serve", "conductor-ask",
                   "conductor-alive"]},
        {"id": "robot", "subjects": ["robot"], "rules": ["receive", "observe", "ask-status", "robot", "robot-trigger"]}]
    if viewers:
        subjects.append({"id": "viewer", "cert_common_names": list(viewers)})
        policies.append({"id": "viewer", "subjects": ["viewer"], "rules": ["receive", "observe", "ask-status"]})
    for mid in models:
        check_name("model", mid)
        rid = f"model-{mid}"
        rules.append(_rule(f"{rid}-publish", ["put", "delete"], ["ingress"],
                           [k.state(mid), k.done(mid), k.out(mid, "**"), k.event(mid, "**")]))
        rules.append(_rule(f"{rid}-serve", ["declare_queryable", "reply"], ["ingress"], [k.model_all(mid)]))
        rules.append(_rule(f"{rid}-alive", ["liveliness_token"], ["ingress"], [k.alive(mid)]))
        rules.append(_rule(f"{rid}-register", ["query"], ["ingress"], [k.register_as(mid)]))
        subjects.append({"id": rid, "cert_common_names": [mid]})
        policies.append({"id": rid, "subjects": [rid],
                         "rules": ["receive", "observe", "ask-status", f"{rid}-register", f"{rid}-publish",
                                   f"{rid}-serve", f"{rid}-alive"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def write_acl(models: Iterable[str], ensemble: str, path: str | Path, *,
              full_router: dict[str, Any] | None = None) -> Path:
    """Write ``{"access_control": ...}`` (or a full router config) as JSON (valid JSON5) to ``path``, creating
    its directory; returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    body = full_router if full_router is not None else {"access_control": acl_config(models, ensemble)}
    p.write_text(json.dumps(body, indent=2) + "\n")
    return p
