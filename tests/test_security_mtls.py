"""Authenticated mesh: mutual TLS only, access control by certificate name (docs/security.md).

Daemons run in their own processes on loopback, given their zenoh settings as a JSON5 file
(``cmion-mesh up --config``, as ``cmion-mesh certs config`` writes it); clients run in this
process. Every refusal is checked after a control that shows the same path working, so that
"nothing came back" means refused, not "not connected yet".
"""

from __future__ import annotations

import json
import os
import queue
import stat
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import keys
from cmion_mesh.cli import main as cli
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, OutcomeUnknown, StorageError
from cmion_mesh.messages import SetProperty
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.testing.wait import migrate_once_seen, wait_for
from cmion_mesh.transport import certs, security
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import CMION_2011

pytestmark = pytest.mark.timeout(180)

#: How long a refused peer is given to get anything at all (each try is a full query timeout).
REFUSED_TRIES, REFUSED_TIMEOUT = 3, 1.0


# --- fixtures ------------------------------------------------------------------------------------


@dataclass
class Pki:
    dir: Path  # the mesh's authority: robot, phone, screen (embodiments), admin (operator), intruder (not trusted)
    other: Path  # another authority, which also issued a certificate named "robot"
    rogue: Path  # a self-signed certificate named "robot", with the real ca.pem beside it


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    base = tmp_path_factory.mktemp("pki")
    mesh_dir, other, rogue = base / "mesh", base / "other", base / "rogue"
    certs.init(mesh_dir)
    for name in ("robot", "phone", "screen"):
        certs.issue(mesh_dir, name)
    certs.issue(mesh_dir, "admin", role="operator")
    certs.issue(mesh_dir, "intruder", trust=False)
    certs.init(other)
    certs.issue(other, "robot")
    rogue.mkdir(mode=0o700)
    key, cert = certs.make_cert("robot", None, sans=certs.default_sans("robot"))
    certs.write_pair(rogue, "robot", key, cert)
    return Pki(mesh_dir, other, rogue)


def secure_config(pki: Pki, name: str, mesh: str, *connect: str, mode: str = "peer", listen: str = "tcp/127.0.0.1:0") -> TransportConfig:
    """A trusted identity's client settings, through the same code path as ``--certs``."""
    return security.secure(TransportConfig(mode=mode, connect=connect, listen=() if mode == "client" else (listen,),
                                           multicast=False), pki.dir, name, mesh)


def attacker_config(ca: Path, cert: Path, key: Path, *, connect: str) -> TransportConfig:
    """A peer that presents ``cert`` (its own business: no access control of its own) over TLS."""
    cred = security.Credentials(cert.parent, certs.common_name(certs.load_cert(cert)), "embodiment", ca, cert, key, "?")
    tls = security.tls_settings(cred)
    return TransportConfig(connect=(connect,), listen=("tls/127.0.0.1:0",), multicast=False,
                           overrides=(("transport/link/tls", json.dumps(tls)),))


def start_secure_daemon(pki: Pki, tmp: Path, mesh: str, name: str, *extra: str, connect: str | None = None) -> tuple[Daemon, str]:
    """``cmion-mesh up`` as ``name``, its zenoh settings in a file as ``cmion-mesh certs config`` writes it."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    config = tmp / f"{name}.json5"
    argv = ["config", str(pki.dir), name, "--mesh", mesh, "--listen", endpoint, "--no-multicast", "-o", str(config)]
    if connect:
        argv += ["--connect", connect]
    assert cli.main(["certs", *argv]) == 0
    daemon = Daemon(cli_argv("up", "--name", name, "--mesh", mesh, "--config", str(config), "--no-multicast", *extra), name=name)
    try:
        daemon.wait_line("up in mesh", 30)
    except BaseException:
        daemon.kill()
        raise
    return daemon, endpoint


def listening_ports(pid: int) -> set[int]:
    """TCP ports process ``pid`` listens on (Linux /proc)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def nothing_for(what: str, attempt: Any, tries: int = REFUSED_TRIES) -> None:
    """``attempt()`` returns something falsy every time, over several tries (each bounded by its own timeout)."""
    for _ in range(tries):
        got = attempt()
        assert not got, f"{what}: got {got!r}"


def collect(transport: ZenohTransport, selector: str) -> tuple[Any, queue.SimpleQueue[str]]:
    got: queue.SimpleQueue[str] = queue.SimpleQueue()
    return transport.subscribe(selector, lambda sample: got.put(sample.key)), got


@pytest.fixture
def robot(pki: Pki, tmp_path: Path, mesh: str) -> Iterator[tuple[Daemon, str]]:
    daemon, endpoint = start_secure_daemon(pki, tmp_path, mesh, "robot", "--world-model", str(CMION_2011 / "worldModelInit.xml"))
    with daemon:
        yield daemon, endpoint
    assert daemon.proc.returncode == 0, "\n".join(daemon.lines)


# --- the mesh over mutual TLS ------------------------------------------------------------------------


def test_mtls_mesh_between_daemons(pki: Pki, tmp_path: Path, mesh: str, robot: tuple[Daemon, str]) -> None:
    robot_daemon, robot_endpoint = robot
    phone_daemon, phone_endpoint = start_secure_daemon(pki, tmp_path, mesh, "phone", connect=robot_endpoint)
    with phone_daemon:
        # The administrator's tool is a zenoh *client* of the phone only: what it reads of the robot
        # crosses the phone-robot link, which both daemons opened over mTLS and filter by name.
        with ZenohTransport(secure_config(pki, "admin", mesh, phone_endpoint, mode="client")) as t:
            admin = MeshClient(t, mesh)
            seen = wait_for(lambda: admin.read_store("robot", "wm", timeout=2), 20, "robot's world model through the phone")
            assert seen[f"cmion/{mesh}/robot/wm/UserA/speaksEnglish"].value == "True"
            wait_for(lambda: {d["name"] for d in admin.describe_all(timeout=2)} == {"robot", "phone"}, 20,
                     "both daemons alive and described")
            # Rights are per link: forwarded by the phone, even an operator's write carries the
            # phone's rights to the robot, and the phone may not write the robot's keys.
            with pytest.raises(OutcomeUnknown):
                admin.write("robot", "bb", SetProperty("", "battery", 0.1), timeout=REFUSED_TIMEOUT)
            admin.set_property("phone", "bb", "", "volume", 1)  # its own keys: allowed on the one link it crosses

        # Connected to the robot itself, the operator writes its blackboard and reads it back.
        with ZenohTransport(secure_config(pki, "admin", mesh, robot_endpoint)) as t:
            admin = MeshClient(t, mesh)
            wait_for(lambda: admin.read_store("robot", "bb", timeout=2), 20, "admin reaches the robot")
            # An operator (a recorder) hears how the robot answers requests; the robot tells it.
            told: list[str] = []
            with t.subscribe(keys.outcome_pattern(mesh), lambda sample: told.append(sample.key)):
                def answer_told() -> bool:
                    admin.set_property("robot", "bb", "", "battery", 0.5)
                    return bool(wait_for_quietly(lambda: told, 1.0))
                wait_for(answer_told, 20, "the robot's answer told to the operator")
            assert told[0] == f"cmion/{mesh}/robot/@outcome/bb/set_property"
            assert admin.get_property("robot", "bb", "", "battery").value == 0.5

        # An embodiment's own tool (a peer with the phone's certificate) reads others' public keys
        # and writes its own embodiment's, but cannot write the robot's: nobody answers it.
        with ZenohTransport(secure_config(pki, "phone", mesh, robot_endpoint, phone_endpoint)) as t:
            phone = MeshClient(t, mesh)
            wait_for(lambda: phone.read_store("robot", "bb", timeout=2), 20, "phone's tool reads the robot")
            wait_for(lambda: phone.read_store("phone", "bb", timeout=2), 20, "phone's tool reads the phone")
            assert phone.get_property("robot", "bb", "", "battery").value == 0.5
            with pytest.raises(OutcomeUnknown):
                phone.write("robot", "bb", SetProperty("", "battery", 0.0), timeout=REFUSED_TIMEOUT)
            assert phone.get_property("robot", "bb", "", "battery").value == 0.5
            phone.set_property("phone", "bb", "", "volume", 3)
            assert phone.get_property("phone", "bb", "", "volume").value == 3
        assert robot_daemon.proc.poll() is None
    assert phone_daemon.proc.returncode == 0, "\n".join(phone_daemon.lines)


def test_refused_peers_get_nothing(pki: Pki, tmp_path: Path, mesh: str, robot: tuple[Daemon, str]) -> None:
    """A rogue certificate, a wrong authority, a wrong name and plain TCP: no read, no write, no events."""
    robot_daemon, endpoint = robot
    port = int(endpoint.rsplit(":", 1)[1])
    assert listening_ports(robot_daemon.proc.pid) == {port}, "the daemon listens on its TLS port only"
    bb = f"cmion/{mesh}/robot/bb"

    with ZenohTransport(secure_config(pki, "phone", mesh, endpoint)) as member_t, \
            ZenohTransport(secure_config(pki, "admin", mesh, endpoint)) as admin_t:
        member, admin = MeshClient(member_t, mesh), MeshClient(admin_t, mesh)
        wait_for(lambda: member.read_store("robot", "wm", timeout=2), 20, "control: a trusted member reads the robot")
        member_sub, member_events = collect(member_t, f"{bb}/**")

        refused = {
            "rogue (self-signed, CN robot)": attacker_config(pki.dir / "ca.pem", pki.rogue / "robot.pem", pki.rogue / "robot.key",
                                                             connect=endpoint),
            "wrong authority (CN robot)": attacker_config(pki.other / "ca.pem", pki.other / "robot.pem", pki.other / "robot.key",
                                                          connect=endpoint),
            "wrong name (right authority, not trusted)": attacker_config(pki.dir / "ca.pem", pki.dir / "intruder.pem",
                                                                         pki.dir / "intruder.key", connect=endpoint),
            "plain TCP": TransportConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=("tcp/127.0.0.1:0",), multicast=False),
        }
        for what, config in refused.items():
            with ZenohTransport(config) as t:
                client = MeshClient(t, mesh)
                if what.startswith("wrong name"):
                    # Its certificate is valid, so its link is up (the control); the access control gives it nothing.
                    wait_for(t.peers, 10, "the untrusted name's TLS link")
                sub, events = collect(t, f"cmion/{mesh}/robot/ev/**")
                bb_sub, bb_events = collect(t, f"{bb}/**")
                nothing_for(f"{what}: read", lambda c=client: c.read_store("robot", "wm", timeout=REFUSED_TIMEOUT))
                nothing_for(f"{what}: describe", lambda tt=t: tt.get(f"cmion/{mesh}/robot/rq/embodiment/describe", timeout=REFUSED_TIMEOUT))
                nothing_for(f"{what}: liveliness", lambda tt=t: tt.alive(f"cmion/{mesh}/@alive/*", timeout=REFUSED_TIMEOUT))
                with pytest.raises(OutcomeUnknown):
                    client.write("robot", "bb", SetProperty("", "owned", what), timeout=REFUSED_TIMEOUT)
                # A trusted writer changes the blackboard: a trusted member hears it, the refused peer does not.
                def heard(tag: str = what) -> bool:
                    admin.set_property("robot", "bb", "", "tick", tag)
                    return _drain_until(member_events, f"{bb}/tick")

                wait_for(heard, 10, "control: a trusted member hears the change")
                with pytest.raises(queue.Empty):
                    bb_events.get(timeout=0.5)
                assert events.empty(), f"{what} heard an event"
                sub.close()
                bb_sub.close()
                if not what.startswith("wrong name"):
                    assert t.peers() == [], f"{what}: a link was opened"
        assert admin.get_property("robot", "bb", "", "tick").value == "plain TCP"
        with pytest.raises(StorageError, match="no property"):
            admin.get_property("robot", "bb", "", "owned", timeout=REFUSED_TIMEOUT)
        member_sub.close()


def _drain_until(q: queue.SimpleQueue[str], key: str) -> bool:
    while True:
        try:
            if q.get(timeout=0.2) == key:
                return True
        except queue.Empty:
            return False


# --- per-sender migration keys ---------------------------------------------------------------------------

PEER = r"""
import json, signal, sys, zenoh
from cmion_mesh.transport import security
directory, name, mesh, listen, answer = sys.argv[1:6]
doc = security.config_document(directory, name, mesh, listen=[listen], multicast=False)
session = zenoh.open(zenoh.Config.from_json5(json.dumps(doc)))
queryables = [session.declare_queryable(sel, lambda q: q.reply(q.key_expr, answer.encode())) for sel in sys.argv[6:]]
print("serving", flush=True)
signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGINT})
signal.sigwait({signal.SIGTERM, signal.SIGINT})
for q in queryables:
    q.undeclare()
session.close()
"""


def test_each_embodiment_speaks_only_for_itself(pki: Pki, mesh: str) -> None:
    """The target answers handshake queries on ``.../rq/migration/<op>/<sender>``; each peer can only
    send as itself, and no peer can answer or publish for another's keys."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    target = security.migration_selector(mesh, "robot")
    stolen = f"cmion/{mesh}/phone/bb/**"  # the robot's identity trying to answer for the phone
    daemon = Daemon([sys.executable, "-c", PEER, str(pki.dir), "robot", mesh, endpoint, "robot", target, stolen,
                     f"cmion/{mesh}/robot/rq/migration/*"], name="robot-peer")
    with daemon:
        daemon.wait_line("serving", 30)
        phone_endpoint = f"tls/127.0.0.1:{free_port()}"
        with ZenohTransport(secure_config(pki, "phone", mesh, endpoint, listen=phone_endpoint)) as phone_t, \
                ZenohTransport(secure_config(pki, "screen", mesh, endpoint)) as screen_t, \
                ZenohTransport(secure_config(pki, "admin", mesh, endpoint, phone_endpoint)) as admin_t:
            as_phone = security.migration_key(mesh, "robot", "prepare", "phone")
            replies = wait_for(lambda: phone_t.get(as_phone, b"doc", timeout=2), 20, "control: phone's own prepare is answered")
            assert [(r.key, r.payload) for r in replies] == [(as_phone, b"robot")]
            wait_for(lambda: screen_t.get(security.migration_key(mesh, "robot", "commit", "screen"), timeout=2), 20, "control: screen")
            for op in security.HANDSHAKE_OPS:
                assert len(screen_t.get(security.migration_key(mesh, "robot", op, "screen"), timeout=2)) == 1
            # An operator may send the source-only command (and is connected: the control for what follows).
            migrate = f"cmion/{mesh}/robot/rq/migration/migrate"
            assert [r.payload for r in wait_for(lambda: admin_t.get(migrate, timeout=2), 20, "control: admin")] == [b"robot"]
            # Sending as another embodiment, on the old sender-less key, or the source-only command: nothing.
            refused = (security.migration_key(mesh, "robot", "prepare", "screen"), security.migration_key(mesh, "robot", "commit", "admin"),
                       f"cmion/{mesh}/robot/rq/migration/prepare", f"cmion/{mesh}/robot/rq/migration/migrate",
                       f"cmion/{mesh}/robot/rq/migration/*/*", f"cmion/{mesh}/robot/rq/migration/prepare/*")
            for key in refused:
                assert phone_t.get(key, b"doc", timeout=REFUSED_TIMEOUT) == [], key
            # The robot's identity declared a queryable on the phone's keys: no member routes to it.
            assert screen_t.get(f"cmion/{mesh}/phone/bb/**", timeout=REFUSED_TIMEOUT) == []
            assert admin_t.get(f"cmion/{mesh}/phone/bb/**", timeout=REFUSED_TIMEOUT) == []

            # The phone publishes a forged robot event, then its own: the operator hears only its own.
            sub, heard = collect(admin_t, f"cmion/{mesh}/*/ev/**")
            forged, own = f"cmion/{mesh}/robot/ev/manager/ActionSucceeded", f"cmion/{mesh}/phone/ev/manager/ActionSucceeded"

            keys_heard: list[str] = []

            def own_heard() -> bool:
                phone_t.publish(forged, b"forged")
                phone_t.publish(own, b"own")
                while True:
                    try:
                        keys_heard.append(heard.get(timeout=0.2))
                    except queue.Empty:
                        return False
                    if keys_heard[-1] == own:
                        return True

            wait_for(own_heard, 20, "control: the operator hears the phone's own event")
            phone_t.publish(forged, b"forged")
            phone_t.publish(own, b"own")
            keys_heard.append(heard.get(timeout=5))  # same link, in order: a forged one would come first
            assert forged not in keys_heard and keys_heard[-1] == own, keys_heard
            sub.close()
    assert security.migration_sender(as_phone) == ("prepare", "phone")


# --- the ACL generator -----------------------------------------------------------------------------------


def wait_for_quietly(condition: Any, timeout: float) -> Any:
    """``wait_for``, returning a falsy value instead of raising when ``timeout`` passes."""
    try:
        return wait_for(condition, timeout, "quietly")
    except TimeoutError:
        return None


def allowed(acl: dict[str, Any], name: str, flow: str, message: str, key: str) -> bool:
    """What the generated access control decides for a concrete ``key`` (zenoh: an allow rule of the
    subject whose key expression includes the key; default deny; ``*``/``**`` never match ``@`` chunks)."""
    subjects = {s["id"] for s in acl["subjects"] if name in s["cert_common_names"]}
    rules = {r["id"]: r for r in acl["rules"]}
    for policy in acl["policies"]:
        if subjects & set(policy["subjects"]):
            for rule in (rules[i] for i in policy["rules"]):
                if flow in rule["flows"] and message in rule["messages"] and rule["permission"] == "allow" \
                        and any(_includes(pattern, key) for pattern in rule["key_exprs"]):
                    return True
    return acl["default_permission"] == "allow"


def _includes(pattern: str, key: str) -> bool:
    pat, chunks = pattern.split("/"), key.split("/")
    verbatim = [i for i, c in enumerate(chunks) if c.startswith("@")]
    # a verbatim chunk of the key must be matched by the same chunk of the pattern, never by a wildcard
    if any(c not in pat for c in (chunks[i] for i in verbatim)):
        return False
    return keys.matches(pattern, key)


def test_acl_generator(pki: Pki) -> None:
    trust = certs.Trust.load(pki.dir)
    acl = security.access_control("m", trust)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert sorted(s["id"] for s in acl["subjects"]) == ["embodiment:phone", "embodiment:robot", "embodiment:screen", "operator:admin"]
    assert all(s["link_protocols"] == ["tls"] for s in acl["subjects"])
    assert "intruder" not in json.dumps(acl)
    assert {r["id"] for r in acl["rules"]} >= {"phone:own", "phone:handshakes", "phone:tokens", "operator"}
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["phone:handshakes"] == {"id": "phone:handshakes", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
                                         "key_exprs": ["cmion/m/*/rq/migration/*/phone"]}
    assert set(acl["rules"][0]) == {"id", "permission", "flows", "messages", "key_exprs"}
    assert all(m in security.MESSAGES for r in acl["rules"] for m in r["messages"])

    def may(name: str, message: str, key: str, flow: str = "ingress") -> bool:
        return allowed(acl, name, flow, message, key)

    # its own keys
    assert may("phone", "put", "cmion/m/phone/bb/volume") and may("phone", "declare_queryable", "cmion/m/phone/rq/bb/*")
    assert may("phone", "liveliness_token", "cmion/m/@alive/phone")
    assert may("phone", "liveliness_token", "cmion/m/@competency/phone/Speak/tts")
    assert not may("phone", "put", "cmion/m/robot/bb/volume") and not may("phone", "declare_queryable", "cmion/m/robot/bb/**")
    assert not may("phone", "liveliness_token", "cmion/m/@alive/robot")
    assert not may("phone", "reply", "cmion/m/robot/wm/x")
    # others' public keys: read only
    assert may("phone", "query", "cmion/m/robot/wm/UserA/name")
    assert may("phone", "declare_subscriber", "cmion/m/robot/ev/manager/ActionSucceeded")
    assert may("phone", "query", "cmion/m/robot/rq/embodiment/describe") and may("phone", "liveliness_query", "cmion/m/@alive/robot")
    assert not may("phone", "query", "cmion/m/robot/rq/bb/set_property") and not may("phone", "query", "cmion/m/robot/rq/manager/act")
    # migration: per sender, handshake operations only
    assert may("phone", "query", "cmion/m/robot/rq/migration/prepare/phone")
    assert not may("phone", "query", "cmion/m/robot/rq/migration/prepare/screen")
    assert not may("phone", "query", "cmion/m/robot/rq/migration/migrate")
    assert may("robot", "reply", "cmion/m/robot/rq/migration/prepare/phone")
    assert may("phone", "reply", "cmion/m/robot/rq/migration/prepare/phone", flow="egress")  # the answer goes back to phone
    assert not may("screen", "reply", "cmion/m/robot/rq/migration/prepare/phone", flow="egress")
    # invitations: per inviter, like the handshake
    assert may("phone", "query", "cmion/m/robot/rq/invitation/invite/phone")
    assert not may("phone", "query", "cmion/m/robot/rq/invitation/invite/screen")
    assert not may("phone", "query", "cmion/m/robot/rq/invitation/send")
    assert may("phone", "reply", "cmion/m/robot/rq/invitation/invite/phone", flow="egress")
    # what members are sent: public data, their own keys
    assert may("screen", "put", "cmion/m/robot/ev/bb/PropertyChanged", flow="egress")
    assert not may("screen", "query", "cmion/m/robot/rq/bb/set_property", flow="egress")
    assert may("robot", "query", "cmion/m/robot/rq/bb/set_property", flow="egress")
    # how requests were answered: each embodiment tells its own; only operators (recorders) listen
    assert may("phone", "put", "cmion/m/phone/@outcome/bb/set_property")
    assert not may("phone", "put", "cmion/m/robot/@outcome/bb/set_property")
    assert not may("phone", "declare_subscriber", "cmion/m/robot/@outcome/bb/set_property")
    assert may("admin", "declare_subscriber", "cmion/m/robot/@outcome/bb/set_property")
    assert may("admin", "put", "cmion/m/robot/@outcome/bb/set_property", flow="egress")
    # operators: anything in the mesh; untrusted names and other meshes: nothing
    assert may("admin", "query", "cmion/m/robot/rq/manager/act") and may("admin", "liveliness_token", "cmion/m/@alive/x")
    assert not may("admin", "query", "cmion/other/robot/bb/x")
    assert not any(may("intruder", m, "cmion/m/robot/bb/x", flow) for m in security.MESSAGES for flow in ("ingress", "egress"))


def test_generated_config_is_accepted_by_zenoh(pki: Pki) -> None:
    import zenoh

    text = security.config_json5(pki.dir, "robot", "m", listen=["tcp/127.0.0.1:7447"], connect=["tls/10.0.0.2:7447"], multicast=False)
    config = zenoh.Config.from_json5(text)
    assert json.loads(config.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(config.get_json("listen/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(config.get_json("connect/endpoints")) == ["tls/10.0.0.2:7447"]
    tls = json.loads(config.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["root_ca_certificate"] == str((pki.dir / "ca.pem").resolve())
    assert tls["listen_certificate"] == tls["connect_certificate"] == str((pki.dir / "robot.pem").resolve())
    assert json.loads(config.get_json("access_control/default_permission")) == "deny"
    # an empty trust list is a valid, closed mesh
    zenoh.Config().insert_json5("access_control", json.dumps(security.access_control("m", certs.Trust())))


# --- command line and settings -----------------------------------------------------------------------------


def test_certs_commands(tmp_path: Path) -> None:
    d = tmp_path / "pki"

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(cli_argv("certs", *args), capture_output=True, text=True, timeout=60)

    missing = run("issue", str(tmp_path / "none"), "robot")
    assert missing.returncode == 2 and "certificate not found" in missing.stderr and "ca.pem" in missing.stderr  # configuration
    assert run("init", str(d)).returncode == 0
    assert run("init", str(d)).returncode == 2  # never overwrites an authority silently
    out = run("issue", str(d), "robot", "--san", "robot.lan", "--san", "192.168.1.20")
    assert out.returncode == 0, out.stderr
    assert run("issue", str(d), "tablet", "--no-trust").returncode == 0
    refused = run("issue", str(d), "robot.lan")
    assert refused.returncode == 2 and "contains '.'" in refused.stderr
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    for private in ("ca.key", "robot.key", "tablet.key"):
        assert stat.S_IMODE((d / private).stat().st_mode) == 0o600
    listing = json.loads(run("list", str(d), "--json").stdout)
    by_name = {i["name"]: i for i in listing}
    assert by_name["robot"]["role"] == "embodiment" and by_name["robot"]["issued_by_ca"]
    assert set(by_name["robot"]["sans"]) == {"robot", "localhost", "robot.lan", "127.0.0.1", "::1", "192.168.1.20"}
    assert by_name["tablet"]["role"] is None
    assert "(not trusted)" in run("list", str(d)).stdout
    cert = certs.load_cert(d / "robot.pem")
    assert certs.common_name(cert) == "robot" and certs.issued_by(cert, certs.load_cert(d / "ca.pem"))
    assert run("trust", str(d), "tablet").returncode == 0 and certs.Trust.load(d).role("tablet") == "embodiment"
    assert run("untrust", str(d), "tablet").returncode == 0 and certs.Trust.load(d).role("tablet") is None
    with pytest.raises(ConfigError, match="not in the trust list"):
        security.load_credentials(d, "tablet")
    os.chmod(d / "robot.key", 0o644)
    with pytest.raises(ConfigError, match="readable by others"):
        security.load_credentials(d, "robot")


def test_apply_turns_a_plain_config_secure(pki: Pki) -> None:
    plain = TransportConfig(listen=("tcp/0.0.0.0:7447",), connect=("tcp/10.0.0.2:7447",))
    assert security.apply(plain, certs_dir=None, mesh="m") is plain
    assert security.describe(certs_dir=None).startswith("plain mode")
    with pytest.raises(ConfigError, match="--identity"):
        security.apply(plain, certs_dir=pki.dir, mesh="m")
    config = security.apply(plain, certs_dir=pki.dir, mesh="m", name="robot")
    assert config.listen == ("tls/0.0.0.0:7447",) and config.connect == ("tls/10.0.0.2:7447",)
    overrides = dict(config.overrides)
    assert json.loads(overrides["transport/link/protocols"]) == ["tls"]
    assert json.loads(overrides["listen/endpoints"]) == ["tls/0.0.0.0:7447"]
    assert json.loads(overrides["access_control"])["policies"]
    described = security.describe(certs_dir=pki.dir, name="robot")
    assert "secure mode" in described and "'robot' (embodiment)" in described
    # no endpoint given: a TLS listener, never zenoh's default tcp/[::]:0
    bare = security.apply(TransportConfig(), certs_dir=pki.dir, mesh="m", identity="admin")
    assert json.loads(dict(bare.overrides)["listen/endpoints"]) == [security.DEFAULT_LISTEN]
    with pytest.raises(ConfigError, match="only TLS"):
        security.apply(TransportConfig(listen=("udp/0.0.0.0:7447",)), certs_dir=pki.dir, mesh="m", name="robot")
    with pytest.raises(ConfigError, match="not in the trust list"):
        security.apply(plain, certs_dir=pki.dir, mesh="m", identity="intruder")


def test_cli_flag_when_wired(pki: Pki, mesh: str) -> None:
    """``cmion-mesh up --certs DIR`` (once cli/main.py has the flag): the daemon says it is secure, listens over TLS only."""
    from cmion_mesh.cli import main as cli

    _, unknown = cli.build_parser("up").parse_known_args(["up", "--certs", str(pki.dir)])
    if unknown:
        pytest.skip("cli/main.py does not have --certs yet")
    port = free_port()
    with Daemon(cli_argv("up", "--name", "robot", "--mesh", mesh, "--certs", str(pki.dir), "--listen", f"tcp/127.0.0.1:{port}",
                         "--no-multicast"), name="robot") as daemon:
        daemon.wait_line("up in mesh", 30)
        assert any("secure mode" in line for line in daemon.lines), daemon.lines
        assert listening_ports(daemon.proc.pid) == {port}
        with ZenohTransport(secure_config(pki, "phone", mesh, f"tls/127.0.0.1:{port}")) as t:
            assert wait_for(lambda: MeshClient(t, mesh).describe_all(timeout=2), 20, "robot described")[0]["name"] == "robot"
    assert daemon.proc.returncode == 0
    with Daemon(cli_argv("up", "--name", "robot", "--mesh", mesh, "--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast"),
                name="plain") as plain:
        plain.wait_line("up in mesh", 30)
        assert any("plain mode" in line for line in plain.lines), plain.lines


# --- a LAN: multicast scouting finds TLS locators only -------------------------------------------------------

LAN_PROBE = r"""
import json, sys, time
from cmion_mesh.transport import security
from cmion_mesh.client import MeshClient
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport
spec = json.loads(sys.argv[1])
config = TransportConfig(multicast=True, multicast_interface="eth0", listen=("tcp/0.0.0.0:0",))
if spec.get("certs"):
    config = security.secure(config, spec["certs"], spec["identity"], spec["mesh"])
seen = []
with ZenohTransport(config) as t:
    client = MeshClient(t, spec["mesh"])
    deadline = time.monotonic() + spec["timeout"]
    while time.monotonic() < deadline and seen != spec["expect"]:
        seen = sorted(d["name"] for d in client.describe_all(timeout=1.0))
    peers = len(t.peers())
print(json.dumps({"seen": seen, "peers": peers}))
"""


def test_secure_daemons_find_each_other_by_multicast(pki: Pki, mesh: str, tmp_path: Path) -> None:
    """No address given anywhere: scouting finds the daemons' TLS locators (LAN addresses, which no
    certificate names), they link over mTLS; a plain peer on the same LAN finds nothing to join."""
    from cmion_mesh.testing import netns
    from cmion_mesh.testing.netns import Lan

    from .test_router import assert_gone

    reason = netns.unavailable_reason()
    if reason is not None:
        pytest.skip(f"network namespaces unavailable: {reason}")
    with Lan(3) as lan:
        names = lan.namespaces()
        h1, h2, h3 = lan.hosts
        assert lan.multicast_reaches(h1, [h2, h3]) == {"h2", "h3"}, "the LAN does not carry multicast"
        daemons = []
        for host, name in ((h1, "robot"), (h2, "phone")):
            doc = security.config_document(pki.dir, name, mesh)
            doc["scouting"] = {"multicast": {"enabled": True, "interface": "eth0"}}
            config = tmp_path / f"{name}.json5"
            config.write_text(json.dumps(doc))
            daemons.append(host.popen(cli_argv("up", "--name", name, "--mesh", mesh, "--config", str(config)), name=name))
        for daemon in daemons:
            daemon.wait_line("up in mesh", 30)

        def probe(spec: dict[str, Any]) -> dict[str, Any]:
            result = h3.run([sys.executable, "-c", LAN_PROBE, json.dumps({"mesh": mesh, **spec})], timeout=60, check=False)
            assert result.returncode == 0, result.stderr
            out: dict[str, Any] = json.loads(result.stdout.strip().splitlines()[-1])
            return out

        found = probe({"certs": str(pki.dir), "identity": "admin", "expect": ["phone", "robot"], "timeout": 20})
        assert found["seen"] == ["phone", "robot"], found

        def linked() -> bool:  # robot (h1) and phone (h2) hold a session over the LAN, on their TLS ports
            peers = [line.split()[3] for line in h1.run(["ss", "-tnH", "state", "established"]).stdout.splitlines()]
            return any(p.rsplit(":", 1)[0].strip("[]").removeprefix("::ffff:") == h2.address for p in peers)

        wait_for(linked, 10, "a session between robot (h1) and phone (h2)")
        plain = probe({"expect": ["phone", "robot"], "timeout": 5})
        assert plain == {"seen": [], "peers": 0}, plain
        for daemon in daemons:
            assert daemon.stop() == 0, "\n".join(daemon.lines)
    assert_gone(names)


def test_migration_over_mutual_tls(pki: Pki, tmp_path: Path, mesh: str) -> None:
    """A companion migrates between daemons in secure mode: the handshake travels on per-sender keys
    that the access control ties to each embodiment's certificate; an operator starts it."""
    robot_port, screen_port = free_port(), free_port()
    common = ["--mesh", mesh, "--certs", str(pki.dir), "--no-multicast"]
    robot = Daemon(cli_argv("up", "--name", "robot", *common, "--listen", f"tcp/127.0.0.1:{robot_port}",
                            "--state-dir", str(tmp_path / "robot"), "--companion", "spirit"), name="robot")
    screen = Daemon(cli_argv("up", "--name", "screen", *common, "--listen", f"tcp/127.0.0.1:{screen_port}",
                             "--connect", f"tcp/127.0.0.1:{robot_port}", "--state-dir", str(tmp_path / "screen")), name="screen")
    with robot, screen:
        robot.wait_line("up in mesh", 30)
        screen.wait_line("up in mesh", 30)
        admin = secure_config(pki, "admin", mesh, f"tls/127.0.0.1:{robot_port}", f"tls/127.0.0.1:{screen_port}")
        with ZenohTransport(admin) as t:
            client = MeshClient(t, mesh)

            def homes() -> dict[str, Any]:
                return {d["name"]: d.get("inhabitant") for d in client.describe_all(timeout=1.0)}

            wait_for(lambda: homes() == {"robot": "spirit", "screen": None}, 30, "both secure daemons, spirit on the robot")
            result = migrate_once_seen(client, "spirit", "screen")  # the admin's links say nothing of the robot's
            assert result["target"] == "screen" and result["epoch"] == 2
            wait_for(lambda: homes() == {"robot": None, "screen": "spirit"}, 20, "spirit moved over mutual TLS")
