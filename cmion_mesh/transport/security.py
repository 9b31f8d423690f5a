"""Authenticated mesh: zenoh over mutual TLS only, with access control by certificate name.

Plain mode (no ``--certs``) stays the zero-configuration default for a trusted LAN: links are
unauthenticated and unencrypted. With ``--certs DIR`` (a folder made by ``cmion-mesh certs``) a
process joins as one identity (its certificate's common name) and its zenoh session:

* links only over TLS 1.3 with mutual authentication against ``DIR/ca.pem``
  (``transport/link/protocols = ["tls"]``: no TCP, UDP, QUIC... link is opened or accepted;
  ``tcp/`` endpoints given on the command line are turned into ``tls/`` ones);
* applies zenoh access control to every link, by the peer certificate's common name, with
  ``default_permission: deny``: a peer whose name is not in ``DIR/trust.json`` gets nothing and
  can do nothing, even with a certificate of the right authority.

What a trusted **embodiment** ``X`` may do (checked by every member on its links to ``X``)::

    publish, delete, answer, declare queryables    cmion/<mesh>/X/**, cmion/<mesh>/X/@outcome/**
    query and subscribe                             cmion/<mesh>/X/**
    liveliness tokens                               cmion/<mesh>/@alive/X, cmion/<mesh>/@competency/X/**,
                                                    cmion/<mesh>/@custody/X/**, cmion/<mesh>/@claim/X/*
    subscribe to others' public keys                cmion/<mesh>/*/{bb,wm,ev}/**
    query others' public keys                       cmion/<mesh>/*/{bb,wm}/**, cmion/<mesh>/*/rq/embodiment/describe
    migration handshake, as sender X only           cmion/<mesh>/*/rq/migration/*/X
    migration invitations, as inviter X only        cmion/<mesh>/*/rq/invitation/invite/X
    liveliness queries and subscriptions            cmion/<mesh>/@alive/**, cmion/<mesh>/@competency/**,
                                                    cmion/<mesh>/@custody/**, cmion/<mesh>/@claim/**

and what a member sends to ``X`` (egress) is limited to what ``X`` may read. An **operator**
(administrator's tools) may do anything under ``cmion/<mesh>/``, and only an operator may
subscribe to the answers embodiments give (``cmion/<mesh>/*/@outcome/**``: ``cmion-mesh record``).

Migration handshake keys are per sender: ``cmion/<mesh>/<target>/rq/migration/<op>/<sender>``
(``migration_key``; ``chain``, asking a custody claimant to back its token, too). The access
control lets ``S`` query only keys whose last chunk is ``S``, so a target knows the sender of a
handshake message from the key it arrived on. A name revoked (``certs revoke``) is never admitted.

A certificate that cannot be used (another name, another authority, expired, its key missing or
not its own, a name not trusted) is a configuration error at start (exit code 2, naming the file);
one or an authority that expires within ``EXPIRY_WARNING_DAYS`` is a warning in the log at every
start (``certificate of <name> expires in <n> days``; fields ``identity``, ``cert``, ``expires``,
``days_left``). What fails on a link later (a peer's certificate refused) is zenoh's to log.

Only ``transport.zenoh`` imports zenoh: this module produces settings (json5 key, value) that
reach the session through ``TransportConfig.overrides``.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, InvalidName
from cmion_mesh.transport.base import TransportConfig

if TYPE_CHECKING:
    # Imported where used: certificates mean cryptography, whose import costs every daemon start
    # time, and only secure mode needs them.
    from cmion_mesh.transport import certs

log = logging.getLogger(__name__)

#: A certificate (or the authority) that expires within this many days is a warning at each start.
EXPIRY_WARNING_DAYS = 30

#: Every message kind zenoh 1.10's access control knows (``AclMessage``).
MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
            "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")
#: The handshake operations whose keys carry their sender (``migrate`` is a command to a source,
#: not a handshake message: it stays ``.../rq/migration/migrate``, reachable by the source's own
#: identity and operators only).
HANDSHAKE_OPS = ("prepare", "commit", "abort", "status", "chain")
#: Listen endpoint when none is given: all interfaces, a port the system picks (zenoh's own
#: default for a peer, over TLS instead of TCP).
DEFAULT_LISTEN = "tls/[::]:0"
PLAIN_WARNING = ("plain mode: zenoh links are neither authenticated nor encrypted; anyone who can reach this "
                 "network can read and write the mesh (start with --certs DIR for mutual TLS and access control)")


# --- migration keys per sender ---------------------------------------------------------------------


def migration_key(mesh: str, target: str, op: str, sender: str) -> str:
    """Key of handshake message ``op`` from ``sender`` to ``target``: ``cmion/<mesh>/<target>/rq/migration/<op>/<sender>``."""
    if op not in HANDSHAKE_OPS:
        raise ConfigError(f"{op!r} is not a handshake operation ({', '.join(HANDSHAKE_OPS)})")
    return keys.request_key(mesh, target, "migration", op, sender)


def migration_selector(mesh: str, target: str) -> str:
    """What ``target`` declares its handshake queryable on: every operation, every sender."""
    return f"{keys.embodiment_prefix(mesh, target)}/{keys.REQUESTS}/migration/*/*"


def migration_sender(key: str) -> tuple[str, str]:
    """``(op, sender)`` of a handshake key; ``InvalidName`` if ``key`` is not one."""
    chunks = key.split("/")
    if len(chunks) != 7 or chunks[0] != keys.ROOT or chunks[3] != keys.REQUESTS or chunks[4] != "migration" \
            or chunks[5] not in HANDSHAKE_OPS:
        raise InvalidName(f"key {key!r} is not a handshake key {keys.ROOT}/<mesh>/<target>/rq/migration/<op>/<sender>")
    return chunks[5], keys.check_name(chunks[6], "sender")


# --- access control ---------------------------------------------------------------------------------


def _rule(rule_id: str, flows: Sequence[str], messages: Sequence[str], key_exprs: Sequence[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": list(flows), "messages": list(messages), "key_exprs": list(key_exprs)}


def access_control(mesh: str, trust: certs.Trust, *, mode: str = "peer") -> dict[str, Any]:
    """zenoh's ``access_control`` section for ``mesh`` and the names in ``trust`` (default deny).

    Flows are seen from the member enforcing them: ``ingress`` is what the peer ``X`` sends
    (its own actions), ``egress`` what this member sends to ``X``.

    In ``client`` mode the session talks only to the member it connected to, which forwards the
    whole mesh to it: every trusted name is then allowed everything under ``cmion/<mesh>/`` (the
    member filtered it by sender on its own links), and untrusted names still nothing.
    """
    from cmion_mesh.transport import certs

    m = keys.mesh_prefix(mesh)
    alive, competency = f"{m}/{keys.ALIVE}", f"{m}/{keys.COMPETENCY}"
    custody, claim = f"{m}/{keys.CUSTODY}", f"{m}/{keys.CLAIM}"
    everything = [f"{m}/**", f"{alive}/**", f"{competency}/**", f"{custody}/**", f"{claim}/**", keys.outcome_pattern(mesh)]
    if mode == "client":
        names = sorted(trust.admitted())
        for name in names:
            certs.check_cert_name(name)
        return {"enabled": True, "default_permission": "deny",
                "rules": [_rule("from-my-router", ["ingress", "egress"], MESSAGES, everything)],
                "subjects": [{"id": f"member:{n}", "cert_common_names": [n], "link_protocols": ["tls"]} for n in names],
                "policies": [{"id": "my-router", "rules": ["from-my-router"], "subjects": [f"member:{n}" for n in names]}] if names else []}
    subscribe_public = [f"{m}/*/{keys.BLACKBOARD}/**", f"{m}/*/{keys.WORLD_MODEL}/**", f"{m}/*/{keys.EVENTS}/**"]
    query_public = [f"{m}/*/{keys.BLACKBOARD}/**", f"{m}/*/{keys.WORLD_MODEL}/**", f"{m}/*/{keys.REQUESTS}/embodiment/describe"]
    liveliness_public = [f"{alive}/**", f"{competency}/**", f"{custody}/**", f"{claim}/**"]
    rules = [
        # What any trusted embodiment may do and be sent.
        _rule("public-subscribe", ["ingress"], ["declare_subscriber"], subscribe_public),
        _rule("public-query", ["ingress"], ["query"], query_public),
        _rule("public-liveliness", ["ingress", "egress"], ["liveliness_query", "declare_liveliness_subscriber"], liveliness_public),
        _rule("send-public-data", ["egress"], ["put", "delete"], subscribe_public),
        _rule("send-public-replies", ["egress"], ["reply"], query_public),
        _rule("send-public-queries", ["egress"], ["query"], query_public),
        _rule("send-tokens", ["egress"], ["liveliness_token"], [f"{alive}/*", f"{competency}/**", f"{custody}/**", f"{claim}/**"]),
        _rule("send-declarations", ["egress"], ["declare_subscriber", "declare_queryable"], [f"{m}/**", keys.outcome_pattern(mesh)]),
    ]
    shared = [r["id"] for r in rules]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    operators: list[str] = []
    for name, role in sorted(trust.admitted().items()):  # a name revoked is never admitted
        certs.check_cert_name(name)
        subject = f"{role}:{name}"
        subjects.append({"id": subject, "cert_common_names": [name], "link_protocols": ["tls"]})
        if role == "operator":
            operators.append(subject)
            continue
        own = f"{m}/{name}/**"
        answers = keys.outcome_pattern(mesh, name)  # ``**`` never matches the verbatim ``@outcome``
        handshakes = f"{m}/*/{keys.REQUESTS}/migration/*/{name}"
        invitations = f"{m}/*/{keys.REQUESTS}/invitation/invite/{name}"
        mine = [
            _rule(f"{name}:own", ["ingress"],
                  ["put", "delete", "declare_queryable", "reply", "declare_subscriber", "query"], [own]),
            _rule(f"{name}:answers", ["ingress"], ["put"], [answers]),
            _rule(f"{name}:tokens", ["ingress"], ["liveliness_token"],
                  [f"{alive}/{name}", f"{competency}/{name}/**", f"{custody}/{name}/**", f"{claim}/{name}/*"]),
            _rule(f"{name}:handshakes", ["ingress"], ["query"], [handshakes]),
            _rule(f"{name}:send-own", ["egress"], ["put", "delete", "query", "reply"], [own]),
            _rule(f"{name}:send-answers", ["egress"], ["put"], [answers]),
            _rule(f"{name}:send-handshake-replies", ["egress"], ["reply"], [handshakes]),
            _rule(f"{name}:invitations", ["ingress"], ["query"], [invitations]),
            _rule(f"{name}:send-invitation-replies", ["egress"], ["reply"], [invitations]),
        ]
        rules.extend(mine)
        policies.append({"id": f"embodiment:{name}", "rules": shared + [r["id"] for r in mine], "subjects": [subject]})
    if operators:
        rules.append(_rule("operator", ["ingress", "egress"], MESSAGES, everything))
        policies.append({"id": "operators", "rules": ["operator"], "subjects": operators})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


# --- credentials and TLS ----------------------------------------------------------------------------


class Credentials(msgspec.Struct, frozen=True):
    """One identity's files in a certificates folder, checked."""

    directory: Path
    name: str
    role: str
    ca: Path
    cert: Path
    key: Path
    authority: str  # the authority's common name, for messages


def load_credentials(directory: str | os.PathLike[str], name: str, trust: certs.Trust | None = None) -> Credentials:
    """Check that ``directory`` holds a usable identity ``name``: the authority, a certificate of
    ``name`` it signed and that has not expired, its key (0600, matching), and ``name`` in the trust list."""
    from cmion_mesh.transport import certs

    folder = Path(directory)
    certs.check_cert_name(name)
    ca_path, cert_path, key_path = folder / certs.CA_CERT, folder / f"{name}.pem", folder / f"{name}.key"
    ca = certs.load_cert(ca_path)
    cert = certs.load_cert(cert_path)
    key = certs.load_key(key_path)
    if certs.common_name(cert) != name:
        raise ConfigError(f"certificate is for {certs.common_name(cert)!r}, not {name!r}", path=str(cert_path))
    if not certs.issued_by(cert, ca):
        raise ConfigError(f"certificate was not issued by the authority in {ca_path}", path=str(cert_path))
    if cert.not_valid_after_utc <= certs._now():
        raise ConfigError(f"certificate expired on {cert.not_valid_after_utc:%Y-%m-%d}", path=str(cert_path))
    if not certs.same_key(cert, key):
        raise ConfigError(f"{key_path.name} does not belong to {cert_path.name}", path=str(key_path))
    for what, held, path in (("certificate of " + name, cert, cert_path), ("the authority's certificate", ca, ca_path)):
        left = held.not_valid_after_utc - certs._now()
        if left.days < EXPIRY_WARNING_DAYS:
            date = f"{held.not_valid_after_utc:%Y-%m-%d}"
            when = f"expired on {date}" if left.total_seconds() <= 0 else f"expires in {left.days} days ({date})"
            from cmion_mesh import logs  # only with certificates near their end: one-shots without --certs never load it

            logs.event(log, f"{what} {when}: issue a new one, or the mesh refuses this process", level=logging.WARNING,
                       identity=name, cert=str(path), expires=date, days_left=max(0, left.days))
    trust = trust if trust is not None else certs.Trust.load(folder)
    role = trust.role(name)
    if role is None:
        raise ConfigError(f"{name!r} is not in the trust list, so the mesh would refuse it "
                          f"(cmion-mesh certs trust {folder} {name})", path=str(folder / certs.TRUST_FILE))
    return Credentials(folder, name, role, ca_path.resolve(), cert_path.resolve(), key_path.resolve(), certs.common_name(ca))


def tls_settings(cred: Credentials, *, verify_names: bool = False) -> dict[str, Any]:
    """zenoh's ``transport/link/tls`` section: one certificate for both listening and connecting.

    ``verify_names`` checks a listener's certificate against the address dialled (its SANs);
    off by default because peers found by multicast are dialled at whatever address they have,
    and identity is the certificate's name, which access control checks on every link.
    """
    return {
        "root_ca_certificate": str(cred.ca),
        "listen_private_key": str(cred.key),
        "listen_certificate": str(cred.cert),
        "enable_mtls": True,
        "connect_private_key": str(cred.key),
        "connect_certificate": str(cred.cert),
        "verify_name_on_connect": verify_names,
        "close_link_on_expiration": True,
    }


def to_tls(endpoint: str) -> str:
    """``tcp/host:port`` -> ``tls/host:port``; ``tls/`` endpoints unchanged; any other protocol refused."""
    proto, sep, rest = endpoint.partition("/")
    if not sep or not rest:
        raise ConfigError(f"endpoint {endpoint!r} is not of the form <protocol>/<address>")
    if proto in ("tcp", "tls"):
        return f"tls/{rest}"
    raise ConfigError(f"endpoint {endpoint!r}: with --certs only TLS links are used (give tcp/ or tls/ endpoints)")


def settings(cred: Credentials, mesh: str, trust: certs.Trust, *, listen: Iterable[str] = (), connect: Iterable[str] = (),
             verify_names: bool = False, default_listen: bool = True, mode: str = "peer") -> list[tuple[str, Any]]:
    """The zenoh settings (json5 key path, value) of a secure session, in the order to insert them."""
    out: list[tuple[str, Any]] = [
        ("transport/link/protocols", ["tls"]),
        ("transport/link/tls", tls_settings(cred, verify_names=verify_names)),
        ("access_control", access_control(mesh, trust, mode=mode)),
    ]
    listen_tls = [to_tls(e) for e in listen]
    if listen_tls or default_listen:
        out.append(("listen/endpoints", listen_tls or [DEFAULT_LISTEN]))
    connect_tls = [to_tls(e) for e in connect]
    if connect_tls:
        out.append(("connect/endpoints", connect_tls))
    return out


def secure(config: TransportConfig, directory: str | os.PathLike[str], name: str, mesh: str, *,
           verify_names: bool = False) -> TransportConfig:
    """``config`` turned secure: its endpoints over TLS, mTLS with ``name``'s certificate, access control.

    With no ``listen`` endpoint and no zenoh file, a peer listens on ``tls/[::]:0`` (zenoh's
    default would be ``tcp/[::]:0``). A zenoh file's own endpoints must be ``tls/``: zenoh refuses
    to open a session with any other protocol, since only TLS is allowed (and a file without
    listen endpoints gets zenoh's ``tcp/[::]:0``, so it must list them).
    """
    from cmion_mesh.transport import certs

    cred = load_credentials(directory, name)
    trust = certs.Trust.load(directory)
    pairs = settings(cred, mesh, trust, listen=config.listen, connect=config.connect, verify_names=verify_names,
                     default_listen=config.config_file is None and config.mode != "client", mode=config.mode)
    overrides = tuple((key, json.dumps(value)) for key, value in pairs)
    return msgspec.structs.replace(config, listen=tuple(to_tls(e) for e in config.listen),
                                   connect=tuple(to_tls(e) for e in config.connect), overrides=config.overrides + overrides)


def config_document(directory: str | os.PathLike[str], name: str, mesh: str, *, listen: Iterable[str] = (),
                    connect: Iterable[str] = (), multicast: bool = True, verify_names: bool = False,
                    mode: str = "peer") -> dict[str, Any]:
    """A whole zenoh configuration (as a dict) for identity ``name``: what ``--config FILE`` takes,
    and what a client in another language can load."""
    from cmion_mesh.transport import certs

    cred = load_credentials(directory, name)
    trust = certs.Trust.load(directory)
    doc: dict[str, Any] = {"mode": mode}
    for path, value in settings(cred, mesh, trust, listen=listen, connect=connect, verify_names=verify_names,
                                default_listen=mode != "client", mode=mode):
        node = doc
        *parents, leaf = path.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    if not multicast:
        doc.setdefault("scouting", {})["multicast"] = {"enabled": False}
    return doc


def config_json5(directory: str | os.PathLike[str], name: str, mesh: str, **options: Any) -> str:
    """``config_document`` as text (JSON, which is valid JSON5), with a header comment."""
    doc = config_document(directory, name, mesh, **options)
    header = (f"// zenoh configuration of {name!r} in mesh {mesh!r}: mutual TLS only, access control by certificate name.\n"
              f"// Generated by `cmion-mesh certs config`; regenerate it when the trust list changes.\n")
    return header + json.dumps(doc, indent=2) + "\n"


# --- what a process runs as ------------------------------------------------------------------------


def choose_identity(directory: str | os.PathLike[str], chosen: str | None = None) -> str:
    """Who this process speaks as: ``chosen`` (``--identity``, else the embodiment's name), else the
    one private key in the certificates folder (a member's folder holds its own key only)."""
    from cmion_mesh.transport import certs

    if chosen:
        return chosen
    owned = sorted(p.stem for p in Path(directory).glob("*.key") if p.name != certs.CA_KEY)
    if len(owned) == 1:
        return owned[0]
    raise ConfigError(f"--certs needs --identity NAME: which certificate of {directory} this process speaks as "
                      f"({', '.join(owned) or 'it holds no private key'})")


def apply(config: TransportConfig, *, certs_dir: str | os.PathLike[str] | None, mesh: str, identity: str | None = None,
          name: str | None = None, verify_names: bool = False) -> TransportConfig:
    """``config`` unchanged without a certificates folder; else made secure as ``identity`` (or
    ``name``, the embodiment) in ``mesh``."""
    if not certs_dir:
        return config
    return secure(config, certs_dir, choose_identity(certs_dir, identity or name), mesh, verify_names=verify_names)


def describe(*, certs_dir: str | os.PathLike[str] | None, identity: str | None = None, name: str | None = None) -> str:
    """One line for a daemon to print at start: which mode it runs in."""
    if not certs_dir:
        return PLAIN_WARNING
    from cmion_mesh.transport import certs

    who = choose_identity(certs_dir, identity or name)
    cred = load_credentials(certs_dir, who)
    trust = certs.Trust.load(certs_dir)
    return (f"secure mode: mutual TLS only, as {who!r} ({cred.role}) under authority {cred.authority!r}; "
            f"access control admits {len(trust.admitted())} name(s): {', '.join(sorted(trust.admitted()))}")
