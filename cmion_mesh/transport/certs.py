"""``cmion-mesh certs``: a small certificate authority for one mesh, and one certificate per name.

A certificates folder holds::

    DIR/ca.pem          the authority's certificate (give it to every member)
    DIR/ca.key          the authority's private key, 0600 (keep it with the administrator only)
    DIR/<name>.pem      the certificate of one embodiment or operator (CN = the name)
    DIR/<name>.key      its private key, 0600 (give it to that member only)
    DIR/trust.json      the trust list: the names the mesh admits, each with its role, and the names revoked

Keys are ECDSA P-256 (what rustls, zenoh's TLS stack, accepts everywhere); certificates carry both
server and client authentication usages, since a zenoh peer both listens and connects. The
common name is the identity that zenoh's access control matches (``cert_common_names``), so a
certificate the authority signed is not enough to join: its name must also be in ``trust.json``
(roles: ``embodiment``, limited to its own keys; ``operator``, the whole mesh). Removing a name
from the trust list and restarting the members is how a certificate is revoked: zenoh 1.10 checks
no revocation list. ``certs revoke`` also records the name as revoked (when, why), so that
``certs trust`` and ``certs issue`` do not trust it again unless told (``--unrevoke``), and the
access control never admits it, even if a copy of the list still names it.

Names follow the key-space rules (``keys.check_name``) and may not contain a dot: zenoh's TLS
connector trusts the public Web PKI roots as well as ``ca.pem`` (see docs/security.md), so a
name must be one that no public authority can put in a certificate.

Run as ``cmion-mesh certs ...``.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
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
    """The names a mesh admits, with their role (``embodiment`` or ``operator``), and the names
    revoked (name -> ``{"at": ISO date, "reason": text}``): never admitted, whatever ``names`` says."""

    names: dict[str, str] = field(default_factory=dict)
    revoked: dict[str, dict[str, str]] = field(default_factory=dict)

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
        revoked = raw.get("revoked", {}) if isinstance(raw, dict) else None
        if not isinstance(names, dict) or not isinstance(revoked, dict):
            raise ConfigError('trust list must be {"names": {"<name>": "embodiment" | "operator", ...}, '
                              '"revoked": {"<name>": {"at": ..., "reason": ...}, ...}}', path=str(path))
        trust = cls()
        for name, entry in revoked.items():
            try:
                check_cert_name(name)
            except MeshError as exc:
                raise ConfigError(str(exc), path=str(path)) from None
            trust.revoked[name] = {str(k): str(v) for k, v in entry.items()} if isinstance(entry, dict) else {}
        for name, role in names.items():
            try:
                trust._set(name, role)  # a hand-edited list may name a revoked one too: it is never admitted
            except MeshError as exc:
                raise ConfigError(str(exc), path=str(path)) from None
        return trust

    def _set(self, name: str, role: str) -> None:
        check_cert_name(name)
        if role not in ROLES:
            raise ConfigError(f"role of {name!r} must be one of {', '.join(ROLES)}, not {role!r}")
        self.names[name] = role

    def add(self, name: str, role: str = "embodiment", *, unrevoke: bool = False) -> None:
        """Trust ``name`` with ``role``; a name revoked is refused unless ``unrevoke`` (then it is no
        longer revoked)."""
        if name in self.revoked and not unrevoke:
            entry = self.revoked[name]
            why = f" ({entry['reason']})" if entry.get("reason") else ""
            raise ConfigError(f"{name!r} was revoked on {entry.get('at', '?')}{why}: trust it again only on purpose "
                              "(--unrevoke)")
        self._set(name, role)
        self.revoked.pop(name, None)

    def revoke(self, name: str, reason: str = "") -> None:
        """Remove ``name`` from the names trusted and record it as revoked."""
        check_cert_name(name)
        self.names.pop(name, None)
        self.revoked[name] = {"at": _now().strftime("%Y-%m-%dT%H:%M:%SZ"), "reason": reason}

    def save(self, directory: str | os.PathLike[str]) -> None:
        doc: dict[str, object] = {"names": dict(sorted(self.names.items()))}
        if self.revoked:
            doc["revoked"] = dict(sorted(self.revoked.items()))
        data = json.dumps(doc, indent=2) + "\n"
        write_file(Path(directory) / TRUST_FILE, data.encode(), overwrite=True)

    def role(self, name: str) -> str | None:
        """``name``'s role; None when it is not trusted, or revoked."""
        return None if name in self.revoked else self.names.get(name)

    def admitted(self) -> dict[str, str]:
        """The names the mesh admits (name -> role): those trusted and not revoked."""
        return {name: role for name, role in self.names.items() if name not in self.revoked}


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
          trust: bool = True, days: int = CERT_DAYS, force: bool = False, unrevoke: bool = False) -> tuple[Path, Path]:
    """Issue ``name``'s certificate and key with the folder's authority; add it to the trust list
    unless ``trust`` is false (a name revoked only with ``unrevoke``). Returns the certificate and key paths."""
    check_cert_name(name)
    if role not in ROLES:
        raise ConfigError(f"role must be one of {', '.join(ROLES)}, not {role!r}")
    path = Path(directory)
    ca = load_ca(path)
    trusted = Trust.load(path) if trust else None
    if trusted is not None:
        trusted.add(name, role, unrevoke=unrevoke)  # refused before anything is written, for a name revoked
    key, cert = make_cert(name, ca, sans=default_sans(name, sans), days=days)
    paths = write_pair(path, name, key, cert, overwrite=force)
    if trusted is not None:
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
    revoked: bool = False


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
                            tuple(cert_sans(cert)), trust.role(name), pem.with_suffix(".key").exists(), name in trust.revoked))
    return out


def trust_name(directory: str | os.PathLike[str], name: str, role: str = "embodiment", *, unrevoke: bool = False) -> None:
    """Add ``name`` to the trust list; its certificate, signed by this authority, must already be in the
    folder. A name revoked is refused unless ``unrevoke``."""
    path = Path(directory)
    check_cert_name(name)
    certificate = load_cert(path / f"{name}.pem")
    if not issued_by(certificate, load_cert(path / CA_CERT)) or common_name(certificate) != name:
        raise ConfigError(f"{name}.pem is not a certificate of {name!r} signed by this authority")
    trusted = Trust.load(path)
    trusted.add(name, role, unrevoke=unrevoke)
    trusted.save(path)


def revoke_name(directory: str | os.PathLike[str], name: str, reason: str = "") -> None:
    """Revoke ``name``: out of the trust list, and recorded as revoked, so that neither ``trust`` nor
    ``issue`` trusts it again unless told, and the access control never admits it (the members
    take it when they restart, with the new trust list)."""
    trusted = Trust.load(directory)
    trusted.revoke(name, reason)
    trusted.save(directory)


def untrust_name(directory: str | os.PathLike[str], name: str) -> None:
    """Remove ``name`` from the trust list (revocation takes effect when the members restart)."""
    trusted = Trust.load(directory)
    if trusted.names.pop(name, None) is None:
        raise ConfigError(f"{name!r} is not in the trust list")
    trusted.save(directory)
