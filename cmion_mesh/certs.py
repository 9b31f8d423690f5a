"""``cmion-mesh certs``: a small certificate authority for one mesh, and one certificate per name.

A certificates folder holds::

    DIR/ca.pem          the authority's certificate (give it to every member)
    DIR/ca.key          the authority's private key, 0600 (keep it with the administrator only)
    DIR/<name>.pem      the certificate of one embodiment or operator (CN = the name)
    DIR/<name>.key      its private key, 0600 (give it to that member only)
    DIR/trust.json      the trust list: the names the mesh admits, each with its role

Keys are ECDSA P-256 (what rustls, zenoh's TLS stack, accepts everywhere); certificates carry both
server and client authentication usages, since a zenoh peer both listens and connects. The
common name is the identity that zenoh's access control matches (``cert_common_names``), so a
certificate the authority signed is not enough to join: its name must also be in ``trust.json``
(roles: ``embodiment``, limited to its own keys; ``operator``, the whole mesh). Removing a name
from the trust list (``certs untrust``) and restarting the members is how a certificate is
revoked: zenoh 1.10 checks no revocation list.

Names follow the key-space rules (``keys.check_name``) and may not contain a dot: zenoh's TLS
connector trusts the public Web PKI roots as well as ``ca.pem`` (see docs/security.md), so a
name must be one that no public authority can put in a certificate.

Run as ``cmion-mesh certs ...`` or ``python -m cmion_mesh.certs ...``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import json
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, MeshError

EXIT_OK, EXIT_FAILED = 0, 1
CA_CERT, CA_KEY, TRUST_FILE = "ca.pem", "ca.key", "trust.json"
ROLES = ("embodiment", "operator")
#: Subject alternative names every certificate gets, so that loopback connections verify by name.
DEFAULT_SANS = ("localhost", "127.0.0.1", "::1")
CA_DAYS, CERT_DAYS = 3650, 730
_RESERVED = {"ca", "trust"}

PrivateKey = ec.EllipticCurvePrivateKey


# --- names ---------------------------------------------------------------------------------------


def check_cert_name(name: str) -> str:
    """A name a certificate may carry: a key-space name, without dots, not a reserved file name."""
    keys.check_name(name, "certificate name")
    if "." in name:
        raise ConfigError(f"certificate name {name!r} contains '.': zenoh's TLS connector also trusts public "
                          "authorities, which can certify domain names, so mesh names must not look like one")
    if name.lower() in _RESERVED or name.startswith("-"):
        raise ConfigError(f"certificate name {name!r} is reserved")
    return name


def _san(value: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(value))
    except ValueError:
        pass
    try:
        value.encode("ascii")
    except UnicodeEncodeError:
        raise ConfigError(f"subject alternative name {value!r} is neither an IP address nor an ASCII DNS name") from None
    if not value or any(c.isspace() for c in value) or "/" in value:
        raise ConfigError(f"subject alternative name {value!r} is not a DNS name")
    return x509.DNSName(value)


def _hostname_like(name: str) -> bool:
    return name.isascii() and all(c.isalnum() or c in "-_" for c in name) and not name.startswith("-")


def default_sans(name: str, extra: Iterable[str] = ()) -> list[str]:
    """The SANs of ``name``'s certificate: its name (when it can be a host name), loopback, then ``extra``."""
    out = [name] if _hostname_like(name) else []
    for value in (*DEFAULT_SANS, *extra):
        if value not in out:
            out.append(value)
    return out


# --- keys and certificates (no files) ------------------------------------------------------------


def new_key() -> PrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def make_ca(common_name: str, *, key: PrivateKey | None = None, days: int = CA_DAYS) -> tuple[PrivateKey, x509.Certificate]:
    """A self-signed authority that may sign end certificates only (path length 0)."""
    key = key or new_key()
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name),
                         x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cmion-mesh")])
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(hours=1))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def make_cert(name: str, issuer: tuple[PrivateKey, x509.Certificate] | None, *, sans: Sequence[str] = (),
              key: PrivateKey | None = None, days: int = CERT_DAYS) -> tuple[PrivateKey, x509.Certificate]:
    """An end certificate for ``name`` (CN), signed by ``issuer``; ``issuer=None`` makes it self-signed
    (what a rogue would present: the tests use it)."""
    key = key or new_key()
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name),
                         x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cmion-mesh")])
    signer_key, issuer_name = (key, subject) if issuer is None else (issuer[0], issuer[1].subject)
    now = _now()
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(hours=1))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=False, crl_sign=False,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
    )
    if sans:
        builder = builder.add_extension(x509.SubjectAlternativeName([_san(s) for s in sans]), critical=False)
    if issuer is not None:
        builder = builder.add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer[0].public_key()), critical=False)
    return key, builder.sign(signer_key, hashes.SHA256())


def common_name(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = names[0].value if names else ""
    return value if isinstance(value, str) else value.decode()


def cert_sans(cert: x509.Certificate) -> list[str]:
    try:
        ext = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    return [str(v) for v in ext.get_values_for_type(x509.DNSName)] + [str(v) for v in ext.get_values_for_type(x509.IPAddress)]


def same_key(cert: x509.Certificate, key: PrivateKey) -> bool:
    """Whether ``key`` is the private half of ``cert``'s public key."""
    spki = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    return cert.public_key().public_bytes(*spki) == key.public_key().public_bytes(*spki)


def issued_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    """Whether ``ca`` signed ``cert`` (signature and issuer name)."""
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


# --- files ---------------------------------------------------------------------------------------


def key_pem(key: PrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())


def cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def write_file(path: Path, data: bytes, *, private: bool = False, overwrite: bool = False) -> None:
    """Write atomically (temporary file, fsync, rename); a private file is 0600 from its creation on."""
    if path.exists() and not overwrite:
        raise ConfigError("exists already (use --force to replace it)", path=str(path))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_pair(directory: Path, stem: str, key: PrivateKey, cert: x509.Certificate, *, overwrite: bool = False) -> tuple[Path, Path]:
    """``DIR/<stem>.pem`` and ``DIR/<stem>.key`` (0600)."""
    cert_path, key_path = directory / f"{stem}.pem", directory / f"{stem}.key"
    if not overwrite:
        for p in (cert_path, key_path):
            if p.exists():
                raise ConfigError("exists already (use --force to replace it)", path=str(p))
    write_file(key_path, key_pem(key), private=True, overwrite=overwrite)
    write_file(cert_path, cert_pem(cert), overwrite=overwrite)
    return cert_path, key_path


def load_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except FileNotFoundError:
        raise ConfigError("certificate not found", path=str(path)) from None
    except ValueError as exc:
        raise ConfigError(f"not a PEM certificate: {exc}", path=str(path)) from None


def load_key(path: Path) -> PrivateKey:
    check_private_file(path)
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except ValueError as exc:
        raise ConfigError(f"not an unencrypted PEM private key: {exc}", path=str(path)) from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ConfigError("not an EC private key", path=str(path))
    return key


def check_private_file(path: Path) -> None:
    """A private key must exist and be readable by its owner only."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise ConfigError("private key not found", path=str(path)) from None
    if mode & 0o077:
        raise ConfigError(f"private key is readable by others (mode {mode & 0o777:o}); chmod 600 it", path=str(path))


# --- trust list ----------------------------------------------------------------------------------


@dataclass
class Trust:
    """The names a mesh admits, with their role (``embodiment`` or ``operator``)."""

    names: dict[str, str] = field(default_factory=dict)

    @classmethod
    def load(cls, directory: str | os.PathLike[str]) -> Trust:
        path = Path(directory) / TRUST_FILE
        try:
            raw = json.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError("no trust list (run `cmion-mesh certs init` on this folder)", path=str(path)) from None
        except (ValueError, UnicodeDecodeError) as exc:
            raise ConfigError(f"unreadable trust list: {exc}", path=str(path)) from None
        names = raw.get("names") if isinstance(raw, dict) else None
        if not isinstance(names, dict):
            raise ConfigError('trust list must be {"names": {"<name>": "embodiment" | "operator", ...}}', path=str(path))
        trust = cls()
        for name, role in names.items():
            try:
                trust.add(name, role)
            except MeshError as exc:
                raise ConfigError(str(exc), path=str(path)) from None
        return trust

    def add(self, name: str, role: str = "embodiment") -> None:
        check_cert_name(name)
        if role not in ROLES:
            raise ConfigError(f"role of {name!r} must be one of {', '.join(ROLES)}, not {role!r}")
        self.names[name] = role

    def save(self, directory: str | os.PathLike[str]) -> None:
        data = json.dumps({"names": dict(sorted(self.names.items()))}, indent=2) + "\n"
        write_file(Path(directory) / TRUST_FILE, data.encode(), overwrite=True)

    def role(self, name: str) -> str | None:
        return self.names.get(name)


# --- the operations behind the commands ----------------------------------------------------------


def init(directory: str | os.PathLike[str], *, label: str | None = None, days: int = CA_DAYS, force: bool = False) -> Path:
    """Create the authority (``ca.pem``, ``ca.key``) and an empty trust list in ``directory``."""
    path = Path(directory)
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    key, cert = make_ca(f"cmion-mesh CA {label or path.resolve().name}", days=days)
    write_pair(path, "ca", key, cert, overwrite=force)
    if force or not (path / TRUST_FILE).exists():
        Trust().save(path)
    return path / CA_CERT


def load_ca(directory: str | os.PathLike[str]) -> tuple[PrivateKey, x509.Certificate]:
    path = Path(directory)
    cert = load_cert(path / CA_CERT)
    key = load_key(path / CA_KEY)
    if not same_key(cert, key):
        raise ConfigError("ca.key does not belong to ca.pem", path=str(path / CA_KEY))
    return key, cert


def issue(directory: str | os.PathLike[str], name: str, *, sans: Sequence[str] = (), role: str = "embodiment",
          trust: bool = True, days: int = CERT_DAYS, force: bool = False) -> tuple[Path, Path]:
    """Issue ``name``'s certificate and key with the folder's authority; add it to the trust list
    unless ``trust`` is false. Returns the certificate and key paths."""
    check_cert_name(name)
    if role not in ROLES:
        raise ConfigError(f"role must be one of {', '.join(ROLES)}, not {role!r}")
    path = Path(directory)
    ca = load_ca(path)
    key, cert = make_cert(name, ca, sans=default_sans(name, sans), days=days)
    paths = write_pair(path, name, key, cert, overwrite=force)
    if trust:
        trusted = Trust.load(path)
        trusted.add(name, role)
        trusted.save(path)
    return paths


@dataclass(frozen=True)
class CertInfo:
    name: str
    file: str
    issued_by_ca: bool
    not_after: str
    expired: bool
    sans: tuple[str, ...]
    role: str | None
    key_present: bool


def inventory(directory: str | os.PathLike[str]) -> list[CertInfo]:
    """Every certificate in the folder (except the authority's), checked against ``ca.pem`` and the trust list."""
    path = Path(directory)
    ca = load_cert(path / CA_CERT)
    try:
        trust = Trust.load(path)
    except ConfigError:
        trust = Trust()
    out = []
    for pem in sorted(path.glob("*.pem")):
        if pem.name == CA_CERT:
            continue
        try:
            cert = load_cert(pem)
        except ConfigError:
            continue
        name = common_name(cert)
        after = cert.not_valid_after_utc
        out.append(CertInfo(name, pem.name, issued_by(cert, ca), after.strftime("%Y-%m-%d"), after < _now(),
                            tuple(cert_sans(cert)), trust.role(name), pem.with_suffix(".key").exists()))
    return out


# --- command line ----------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``certs`` subcommands, on ``parser`` (the ``certs`` sub-parser, or a parser of its own)."""
    sub = parser.add_subparsers(dest="certs_command", required=True)
    p = sub.add_parser("init", help="create the certificate authority and an empty trust list in DIR")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("--label", help="what the authority's name says (default: the folder's name)")
    p.add_argument("--days", type=int, default=CA_DAYS, help="validity (default: %(default)s days)")
    p.add_argument("--force", action="store_true", help="replace an existing authority (every certificate must then be reissued)")

    p = sub.add_parser("issue", help="issue the certificate of an embodiment (or operator) NAME and trust it")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("name", metavar="NAME", help="embodiment name (the certificate's common name)")
    p.add_argument("--san", action="append", default=[], metavar="HOST_OR_IP",
                   help="a DNS name or IP address the embodiment is reached at; repeatable "
                        f"(always added: the name itself, {', '.join(DEFAULT_SANS)})")
    p.add_argument("--role", choices=ROLES, default="embodiment",
                   help="embodiment: its own keys only; operator: the whole mesh (tools of an administrator)")
    p.add_argument("--no-trust", action="store_true", help="do not add NAME to the trust list")
    p.add_argument("--days", type=int, default=CERT_DAYS, help="validity (default: %(default)s days)")
    p.add_argument("--force", action="store_true", help="replace an existing certificate of NAME")

    p = sub.add_parser("list", help="list the certificates in DIR, whether the authority signed them and who is trusted")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser("trust", help="add NAME to the trust list (its certificate must already exist)")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("name", metavar="NAME")
    p.add_argument("--role", choices=ROLES, default="embodiment")

    p = sub.add_parser("untrust", help="remove NAME from the trust list (revocation: restart the members afterwards)")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("name", metavar="NAME")

    p = sub.add_parser("config", help="print the zenoh JSON5 configuration of NAME (mTLS + access control), e.g. "
                                      "for a client written in another language")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("name", metavar="NAME")
    p.add_argument("--mesh", default=keys.DEFAULT_MESH)
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--no-multicast", action="store_true")
    p.add_argument("--verify-names", action="store_true", help="check the peer's address against its certificate's SANs")
    p.add_argument("-o", "--output", metavar="FILE", help="write to FILE instead of standard output")


def run(args: argparse.Namespace) -> int:
    """Run a parsed ``certs`` command; errors are one line on stderr and exit code 1."""
    try:
        return _run(args)
    except MeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED


def _run(args: argparse.Namespace) -> int:
    command = args.certs_command
    directory = Path(args.dir)
    if command == "init":
        ca = init(directory, label=args.label, days=args.days, force=args.force)
        print(f"authority created: {ca} (keep {directory / CA_KEY} with the administrator only)")
        print(f"next: cmion-mesh certs issue {directory} <embodiment>")
        return EXIT_OK
    if command == "issue":
        cert, key = issue(directory, args.name, sans=args.san, role=args.role, trust=not args.no_trust,
                          days=args.days, force=args.force)
        trusted = "not in the trust list" if args.no_trust else f"trusted as {args.role}"
        print(f"issued {cert} and {key} for {args.name!r} ({trusted})")
        print(f"give the member {directory / CA_CERT}, {directory / TRUST_FILE}, {cert.name} and {key.name}; "
              f"start it with --certs DIR")
        return EXIT_OK
    if command == "list":
        infos = inventory(directory)
        if args.json:
            print(json.dumps([info.__dict__ for info in infos]))
            return EXIT_OK
        rows = [("NAME", "ROLE", "SIGNED BY CA", "EXPIRES", "KEY", "SANS")]
        for i in infos:
            rows.append((i.name, i.role or "(not trusted)", "yes" if i.issued_by_ca else "NO",
                         i.not_after + (" (EXPIRED)" if i.expired else ""), "yes" if i.key_present else "-", ",".join(i.sans)))
        widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
        for r in rows:
            print("  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip())
        trust = Trust.load(directory)
        missing = sorted(set(trust.names) - {i.name for i in infos})
        if missing:
            print(f"trusted but without a certificate here: {', '.join(missing)}")
        return EXIT_OK
    if command == "trust":
        check_cert_name(args.name)
        certificate = load_cert(directory / f"{args.name}.pem")
        if not issued_by(certificate, load_cert(directory / CA_CERT)) or common_name(certificate) != args.name:
            raise ConfigError(f"{args.name}.pem is not a certificate of {args.name!r} signed by this authority")
        trust = Trust.load(directory)
        trust.add(args.name, args.role)
        trust.save(directory)
        print(f"{args.name!r} trusted as {args.role}")
        return EXIT_OK
    if command == "untrust":
        trust = Trust.load(directory)
        if trust.names.pop(args.name, None) is None:
            raise ConfigError(f"{args.name!r} is not in the trust list")
        trust.save(directory)
        print(f"{args.name!r} removed from the trust list: restart the mesh's members for it to take effect")
        return EXIT_OK
    if command == "config":
        from cmion_mesh import security

        text = security.config_json5(directory, args.name, args.mesh, listen=args.listen, connect=args.connect,
                                     multicast=not args.no_multicast, verify_names=args.verify_names)
        if args.output:
            write_file(Path(args.output), text.encode(), private=False, overwrite=True)
        else:
            print(text)
        return EXIT_OK
    raise ConfigError(f"unknown certs command {command!r}")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="cmion-mesh certs", description="Certificates for an authenticated mesh.")
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
