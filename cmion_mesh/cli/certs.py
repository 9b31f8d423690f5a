"""``certs``: a certificate authority and certificates for an authenticated mesh (docs/security.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cmion_mesh import keys
from cmion_mesh.cli.common import json_option, subverb, table
from cmion_mesh.errors import ExitCode
from cmion_mesh.transport import certs, security
from cmion_mesh.transport.certs import CA_DAYS, CERT_DAYS, DEFAULT_SANS, ROLES


def certs_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="certs_command", required=True, metavar="COMMAND")
    folder = "the certificates folder"
    p = subverb(sub, "init", "create the certificate authority and an empty trust list in DIR",
                "cmion-mesh certs init pki/ --label 'Lab mesh'")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("--label", help="what the authority's name says (default: the folder's name)")
    p.add_argument("--days", type=int, default=CA_DAYS, help="validity (default: %(default)s days)")
    p.add_argument("--force", action="store_true", help="replace an existing authority (every certificate must then be reissued)")

    p = subverb(sub, "issue", "issue the certificate of an embodiment (or operator) NAME and trust it",
                "cmion-mesh certs issue pki/ robot --san robot.lab.example --san 10.0.0.5")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="embodiment name (the certificate's common name)")
    p.add_argument("--san", action="append", default=[], metavar="HOST_OR_IP",
                   help="a DNS name or IP address the embodiment is reached at; repeatable "
                        f"(always added: the name itself, {', '.join(DEFAULT_SANS)})")
    p.add_argument("--role", choices=ROLES, default="embodiment",
                   help="embodiment: its own keys only; operator: the whole mesh (tools of an administrator)")
    p.add_argument("--no-trust", action="store_true", help="do not add NAME to the trust list")
    p.add_argument("--unrevoke", action="store_true", help="trust NAME although it was revoked")
    p.add_argument("--days", type=int, default=CERT_DAYS, help="validity (default: %(default)s days)")
    p.add_argument("--force", action="store_true", help="replace an existing certificate of NAME")

    p = subverb(sub, "list", "list the certificates in DIR, whether the authority signed them and who is trusted",
                "cmion-mesh certs list pki/")
    p.add_argument("dir", metavar="DIR", help=folder)
    json_option(p)

    p = subverb(sub, "trust", "add NAME to the trust list (its certificate must already exist)",
                "cmion-mesh certs trust pki/ operator --role operator")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="the certificate's name")
    p.add_argument("--role", choices=ROLES, default="embodiment", help="what NAME may do (default: %(default)s)")
    p.add_argument("--unrevoke", action="store_true", help="trust NAME although it was revoked (certs revoke)")

    p = subverb(sub, "revoke", "revoke NAME: out of the trust list, recorded as revoked so that trust and issue do "
                               "not add it back; the access control never admits it (restart the members)",
                "cmion-mesh certs revoke pki/ screen --reason 'stolen'")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="the certificate's name")
    p.add_argument("--reason", default="", help="why (kept in the trust list), e.g. 'equivocated custody of spirit'")

    p = subverb(sub, "untrust", "remove NAME from the trust list (revocation: restart the members afterwards)",
                "cmion-mesh certs untrust pki/ phone")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="the certificate's name")

    p = subverb(sub, "config", "print the zenoh JSON5 configuration of NAME (mTLS + access control), e.g. "
                               "for a client written in another language",
                "cmion-mesh certs config pki/ robot --listen tcp/0.0.0.0:7447 -o robot.json5")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="whose configuration")
    p.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: %(default)s)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="endpoint to listen on; repeatable")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="endpoint to connect to; repeatable")
    p.add_argument("--no-multicast", action="store_true", help="turn multicast scouting off in the file")
    p.add_argument("--verify-names", action="store_true", help="check the peer's address against its certificate's SANs")
    p.add_argument("-o", "--output", metavar="FILE", help="write to FILE instead of standard output")


def cmd_certs(args: argparse.Namespace) -> int:
    directory = Path(args.dir)
    command = args.certs_command
    if command == "init":
        ca = certs.init(directory, label=args.label, days=args.days, force=args.force)
        print(f"authority created: {ca} (keep {directory / certs.CA_KEY} with the administrator only)")
        print(f"next: cmion-mesh certs issue {directory} <embodiment>")
    elif command == "issue":
        cert, key = certs.issue(directory, args.name, sans=args.san, role=args.role, trust=not args.no_trust,
                                days=args.days, force=args.force, unrevoke=args.unrevoke)
        trusted = "not in the trust list" if args.no_trust else f"trusted as {args.role}"
        print(f"issued {cert} and {key} for {args.name!r} ({trusted})")
        print(f"give the member {directory / certs.CA_CERT}, {directory / certs.TRUST_FILE}, {cert.name} and {key.name}; "
              f"start it with --certs DIR")
    elif command == "list":
        infos = certs.inventory(directory)
        if args.json:
            print(json.dumps([info.__dict__ for info in infos]))
            return ExitCode.OK
        rows = [("NAME", "ROLE", "SIGNED BY CA", "EXPIRES", "KEY", "SANS")]
        for i in infos:
            rows.append((i.name, "(REVOKED)" if i.revoked else i.role or "(not trusted)", "yes" if i.issued_by_ca else "NO",
                         i.not_after + (" (EXPIRED)" if i.expired else ""), "yes" if i.key_present else "-", ",".join(i.sans)))
        table(rows)
        missing = sorted(set(certs.Trust.load(directory).names) - {i.name for i in infos})
        if missing:
            print(f"trusted but without a certificate here: {', '.join(missing)}")
    elif command == "trust":
        certs.trust_name(directory, args.name, args.role, unrevoke=args.unrevoke)
        print(f"{args.name!r} trusted as {args.role}")
    elif command == "revoke":
        certs.revoke_name(directory, args.name, args.reason)
        print(f"{args.name!r} revoked: out of the trust list, and `certs trust` will not add it back unless told "
              f"(--unrevoke); give the members the new {certs.TRUST_FILE} and restart them for it to take effect")
    elif command == "untrust":
        certs.untrust_name(directory, args.name)
        print(f"{args.name!r} removed from the trust list: restart the mesh's members for it to take effect")
    else:
        text = security.config_json5(directory, args.name, args.mesh, listen=args.listen, connect=args.connect,
                                     multicast=not args.no_multicast, verify_names=args.verify_names)
        if args.output:
            certs.write_file(Path(args.output), text.encode(), private=False, overwrite=True)
        else:
            print(text)
    return ExitCode.OK
