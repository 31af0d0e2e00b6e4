"""``twin certs`` and ``twin acl``: what a twin needs on a shared network (see docs/deployment.md)."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from protocol.security import acl_config, default_identities, make_certs, write_acl

from ..scene import load_scene
from .run import DefaultsHelp


def cmd_certs(args) -> int:
    scene = None
    if args.scene:
        scene = load_scene(args.scene)
    names = default_identities(scene.models if scene is not None else ())
    names += [n for part in args.names or [] for n in part.split(",") if n]
    sans = [s for part in args.san or [] for s in part.split(",") if s]
    d = Path(args.dir)
    before = {p.name for p in d.glob("*.pem")} if d.is_dir() else set()
    new_ca = args.new_ca or not ((d / "ca.pem").exists() and (d / "ca.key").exists())
    try:
        certs = make_certs(args.dir, names, sans, reuse_ca=not args.new_ca)
    except ValueError as e:
        print(f"twin certs: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # (a folder it cannot write: it was a traceback)
        print(f"twin certs: cannot write the certificates into {args.dir}: {e.strerror or e}", file=sys.stderr)
        return 2
    made = "a new one" + (", replacing the one there" if "ca.pem" in before else "") if new_ca else "the one there"
    print(f"CA: {d / 'ca.pem'}, {made} (its key {d / 'ca.key'} signs further certificates: keep it off the network)")
    for n, (cert, key) in certs.items():
        print(f"  {n:16s} {cert}  {key}" + ("   (replaced)" if cert.name in before else ""))
    stale = sorted(before - {"ca.pem"} - {c.name for c, _ in certs.values()}) if new_ca else []
    if stale:  # signed by the CA just replaced: they no longer verify against ca.pem
        print(f"warning: {', '.join(stale)} in {d} {'was' if len(stale) == 1 else 'were'} signed by the CA this "
              "replaced and no longer verify against it: make them again (--names) or remove them", file=sys.stderr)
    print(f"use: --tls-ca {d / 'ca.pem'} --tls-cert {d / 'NAME.pem'} --tls-key {d / 'NAME.key'} with tls/HOST:PORT "
          "endpoints")
    return 0


def cmd_acl(args) -> int:
    scene = load_scene(args.scene)
    body = {"access_control": acl_config(scene.models, args.ensemble)}
    if args.out == "-":
        print(json.dumps(body, indent=2))
        return 0
    try:
        path = write_acl(scene.models, args.ensemble, args.out, full_router=body)
    except OSError as e:  # (a folder given for the file, a place it cannot write: it was a traceback)
        print(f"twin acl: cannot write {args.out}: {e.strerror or e}", file=sys.stderr)
        return 2
    print(f"wrote {path}: access control for ensemble {args.ensemble!r} ({len(scene.models)} models: "
          f"{', '.join(scene.models)}); run the router with mutual TLS and --config {path}")
    return 0


def register(sub) -> None:
    c = sub.add_parser("certs", help="make a test CA and a certificate per service (mutual TLS)",
                       description="Write a certificate authority (ca.pem, ca.key) and one certificate + key per "
                                   "identity into DIR: router, conductor, robot, viewer, every model of --scene and "
                                   "--names. The certificate's common name is the identity that the access-control "
                                   "rules of 'twin acl' check. An existing CA in DIR is reused.",
                       formatter_class=DefaultsHelp)
    c.add_argument("dir", help="output folder")
    c.add_argument("--scene", help="also make one certificate per model of this scene")
    c.add_argument("--names", action="append", metavar="A,B", help="more identities (repeatable, comma separated)")
    c.add_argument("--san", action="append", metavar="HOST",
                   help="extra subject alternative names for every certificate: the IP addresses or DNS names "
                        "clients use to reach the router (repeatable, comma separated)")
    c.add_argument("--new-ca", action="store_true", help="make a new CA even if DIR has one")
    c.set_defaults(func=cmd_certs)

    a = sub.add_parser("acl", help="write the Zenoh access-control configuration of a scene",
                       description="Write a Zenoh configuration file holding the access-control rules for SCENE's "
                                   "ensemble: only the conductor may publish ownership, clock and step and answer "
                                   "conductor/**; only model <id> may publish state/<id>, done/<id>, out/<id>/**, "
                                   "event/<id>/**, answer model/<id>/** and hold its alive/<id> token; only the robot "
                                   "(and a replaying conductor) publishes telemetry; everything else is denied. "
                                   "Identities are certificate common names, so the router must use mutual TLS: "
                                   "twin router --config FILE --listen tls/0.0.0.0:7447 --tls-ca ca.pem "
                                   "--tls-cert router.pem --tls-key router.key",
                       formatter_class=DefaultsHelp)
    a.add_argument("scene", help="scene YAML file")
    a.add_argument("--out", required=True, metavar="FILE", help="output file (JSON5-compatible JSON; '-' prints it)")
    a.add_argument("--ensemble", default=os.environ.get("TWIN_ENSEMBLE", "default"),
                   help="ensemble name (env TWIN_ENSEMBLE)")
    a.set_defaults(func=cmd_acl)
