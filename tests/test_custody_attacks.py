"""Attacks on a companion's custody, replayed against real daemons in separate processes.

A replayed prepare of a dropped attempt; an eavesdropper capturing prepares; a former host that
kept its custody key trying to take over, clone or wipe the companion (secure mode: mutual TLS,
access control); a stranger poisoning the pin; a flood of first-contact prepares and of actions;
an identity edited at rest. After each: exactly one host, its memory intact.
"""

from __future__ import annotations

import contextlib
import queue
import shutil
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh import keys
from cmion_mesh.cli import main as cli
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import OutcomeUnknown
from cmion_mesh.messages import (
    Act,
    ActionStatus,
    Migrate,
    MigrateAbort,
    MigrateCommit,
    MigratePrepare,
    MindMessage,
    Outcome,
    decode,
    encode,
)
from cmion_mesh.migration import custody, signing
from cmion_mesh.migration.custody import Link
from cmion_mesh.migration.identity import Identity
from cmion_mesh.migration.journal import LOG, Journal
from cmion_mesh.migration.ledger import Entry, Record, read_ledger
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.requests import send_request
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport import certs
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers.custody_helpers import Holder
from .helpers.remote_helpers import diary_embodiment_config
from .test_migration_crash import Node, memory
from .test_security_mtls import Pki, secure_config

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    base = tmp_path_factory.mktemp("pki")
    certs.init(base / "mesh")
    for name in ("robot", "screen", "phone"):
        certs.issue(base / "mesh", name)
    certs.issue(base / "mesh", "admin", role="operator")
    return Pki(base / "mesh", base / "unused", base / "unused")


@pytest.fixture
def trio(tmp_path: Path, mesh: str) -> Iterator[tuple[Node, Node, Node]]:
    ports = {name: free_port() for name in ("a", "b", "c")}
    nodes = []
    for name, port in ports.items():
        others = [f"tcp/127.0.0.1:{p}" for n, p in ports.items() if n != name]
        nodes.append(Node(name, mesh, diary_embodiment_config(tmp_path / name, name), tmp_path / f"state-{name}", port, others,
                          companion="spirit" if name == "a" else None))
    try:
        yield nodes[0], nodes[1], nodes[2]
    finally:
        for node in nodes:
            node.stop()


def homes(client: MeshClient, names: tuple[str, ...]) -> dict[str, Any]:
    found: dict[str, Any] = {}
    for name in names:
        try:
            found[name] = client.describe(name, timeout=1.0).get("inhabitant")
        except OutcomeUnknown:
            found[name] = "?"
    return found


def record_of(state: Path) -> Record | None:
    return read_ledger(state).records.get("spirit")


@contextlib.contextmanager
def pair(trio: tuple[Node, Node, Node], mesh: str) -> Iterator[tuple[ZenohTransport, MeshClient]]:
    """a (spirit's home) and b up, a client joined to both, spirit living on a."""
    a, b, _ = trio
    a.start()
    b.start()
    with ZenohTransport(TransportConfig(connect=(a.endpoint, b.endpoint), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: homes(client, ("a", "b")) == {"a": "spirit", "b": None}, 30, "spirit born on a")
        yield t, client


class Capture:
    """A plain zenoh session that overhears every handshake request sent in the mesh (never replies)."""

    def __init__(self, transport: ZenohTransport, mesh: str) -> None:
        self.seen: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()

        def on_query(query: Any) -> None:
            self.seen.put((query.key, query.payload or b""))
            query.finish()

        self.handle = transport.declare_queryable(f"{keys.mesh_prefix(mesh)}/*/{keys.REQUESTS}/migration/prepare/*", on_query)

    def prepares(self) -> list[tuple[str, MigratePrepare]]:
        out = []
        while not self.seen.empty():
            key, payload = self.seen.get()
            out.append((key, decode(payload, MigratePrepare)))
        return out


def test_a_replayed_prepare_never_loses_the_companion(trio: tuple[Node, Node, Node], mesh: str) -> None:
    """The lost-companion scenario: a dropped attempt's prepare, captured and resent every ~2 ms while
    the companion migrates again, is refused; the migration ends, exactly one host, memory intact."""
    a = trio[0]
    with pair(trio, mesh) as (t, client):
        client.request("a", "mind", "message", MindMessage({"note": "met Ada"}))
        client.migrate("spirit", "b", timeout=30)
        # a dies right after recording 'incoming' for the attempt back; b resumes; a, restarted, drops it
        assert a.daemon is not None
        a.daemon.kill()
        a.start("target:incoming")
        capture = Capture(t, mesh)
        try:
            wait_for(lambda: "a" in {d["name"] for d in client.describe_all(timeout=1.0)}, 30, "a back")
            assert client.request("b", "migration", "migrate", MindMessage({})).status == "rejected"  # a typed request only
            started = client.request("b", "migration", "migrate", Migrate("spirit", "a"))
            assert started.status == "accepted"
            assert a.died() == -9
            captured: list[MigratePrepare] = []

            def overheard() -> bool:  # handed to this process's handlers on a thread of the transport: may lag
                captured.extend(p for k, p in capture.prepares() if k.endswith("/a/rq/migration/prepare/b"))
                return bool(captured)

            with contextlib.suppress(TimeoutError):
                wait_for(overheard, 5, "the prepare to a overheard")
        finally:
            capture.handle.close()
        assert captured, "the prepare to a was overheard"
        stale = captured[0]
        a.start()
        wait_for(lambda: (r := record_of(a.state)) is not None and r.state == "dropped", 30, "a dropped the old attempt")
        wait_for(lambda: homes(client, ("a", "b")) == {"a": None, "b": "spirit"}, 30, "spirit resumed on b")
        # resend the stale prepare every ~2 ms while the companion migrates to a for real
        answers: list[Outcome] = []
        stop = threading.Event()
        key = keys.request_key(mesh, "a", "migration", "prepare", "b")

        def replay() -> None:
            deadline = time.monotonic() + 20
            while not stop.is_set() and time.monotonic() < deadline and len(answers) < 5000:
                try:
                    answers.append(send_request(t, key, stale, timeout=2.0))
                except OutcomeUnknown:
                    pass
                stop.wait(0.002)

        replayer = threading.Thread(target=replay, name="replayer")
        replayer.start()
        try:
            result = client.migrate("spirit", "a", timeout=30)
        finally:
            stop.set()
            replayer.join(30)
        assert result["target"] == "a"
        assert answers and all(o.status == "rejected" for o in answers), [o for o in answers if o.status != "rejected"][:3]
        assert {o.reason.split(":")[0] for o in answers} <= {"stale", "busy", "custody"}, {o.reason for o in answers}
        wait_for(lambda: homes(client, ("a", "b")) == {"a": "spirit", "b": None}, 30, "exactly one host: a")
        assert memory(client, "a") == ["met Ada"]


def test_a_captured_prepare_holds_nothing_that_signs(trio: tuple[Node, Node, Node], mesh: str) -> None:
    """Plain mode: an eavesdropper sees the prepare, but no private key travels in it."""
    a, b, _ = trio
    with pair(trio, mesh) as (t, client):
        source_key = read_ledger(a.state).keys["spirit"]
        capture = Capture(t, mesh)
        try:
            client.migrate("spirit", "b", timeout=30)
            overheard = capture.prepares()
        finally:
            capture.handle.close()
        assert overheard
        target_key = read_ledger(b.state).keys["spirit"]
        for _, prepare in overheard:
            raw = encode(prepare)
            assert source_key not in raw and target_key not in raw, "a private key crossed the wire"
        assert "spirit" not in read_ledger(a.state).keys and source_key not in (a.state / LOG).read_bytes(), \
            "the former host's custody key is deleted"
        # and the overheard prepare, replayed, is refused: the target already holds the companion
        refused = send_request(t, keys.request_key(mesh, "b", "migration", "prepare", "a"), overheard[0][1], timeout=5)
        assert refused.status == "rejected" and "holds 'spirit' itself" in refused.reason


def _secure_daemon(pki: Pki, tmp: Path, mesh: str, name: str, port: int, peers: list[int], *extra: str) -> Daemon:
    argv = ["up", str(diary_embodiment_config(tmp / name, name)), "--name", name, "--mesh", mesh, "--certs", str(pki.dir),
            "--no-multicast", "--listen", f"tcp/127.0.0.1:{port}", "--state-dir", str(tmp / f"state-{name}"), *extra]
    for peer in peers:
        argv += ["--connect", f"tcp/127.0.0.1:{peer}"]
    daemon = Daemon(cli_argv(*argv), name=name)
    daemon.wait_line("up in mesh", 30)
    return daemon


def test_a_former_host_cannot_take_over_clone_or_wipe_in_secure_mode(pki: Pki, tmp_path: Path, mesh: str) -> None:
    """spirit goes robot -> screen -> robot; screen turns hostile, with every custody key it ever had,
    its certificate, and the chain it knew: takeover, clone and wipe-out are all refused."""
    ports = {n: free_port() for n in ("robot", "screen", "phone")}
    daemons = []
    try:
        for name in ports:
            daemons.append(_secure_daemon(pki, tmp_path, mesh, name, ports[name], [p for n, p in ports.items() if n != name],
                                          *(["--companion", "spirit"] if name == "robot" else [])))
        endpoints = [f"tls/127.0.0.1:{p}" for p in ports.values()]
        with ZenohTransport(secure_config(pki, "admin", mesh, *endpoints)) as admin_t:
            admin = MeshClient(admin_t, mesh)
            names = ("robot", "screen", "phone")
            wait_for(lambda: homes(admin, names) == {"robot": "spirit", "screen": None, "phone": None}, 30, "three secure daemons")
            admin.request("robot", "mind", "message", MindMessage({"note": "met Ada"}))
            admin.migrate("spirit", "screen", timeout=30)
            screen_state = tmp_path / "state-screen"
            kept_key = read_ledger(screen_state).keys["spirit"]  # what a hostile screen would keep
            kept_chain = read_ledger(screen_state).records["spirit"].chain
            admin.migrate("spirit", "robot", timeout=30)
            wait_for(lambda: homes(admin, names) == {"robot": "spirit", "screen": None, "phone": None}, 30, "back on robot")
            hostile = Holder("spirit", "screen", kept_chain[-1].epoch, private=kept_key, chain=list(kept_chain))
            altered = Identity("spirit", hostile.epoch, {"mind": {"entries": ["HACKED"]}}).pack()
            # a fork: screen hands custody at its old epoch to a key of its own, up to epoch 20
            fork_key = signing.new_key()
            fork = [*kept_chain, custody.hand_on(kept_key, "spirit", hostile.epoch + 1, "screen", signing.public_of(fork_key),
                                                 "forged", custody.digest(altered))]
            forked = Holder("spirit", "screen", hostile.epoch + 1, private=fork_key, chain=fork)
            with ZenohTransport(secure_config(pki, "screen", mesh, *endpoints)) as screen_t:
                def handshake(target: str, op: str, message: Any) -> Outcome:
                    return send_request(screen_t, keys.request_key(mesh, target, "migration", op, "screen"), message, timeout=5)

                wait_for(lambda: screen_t.alive(f"{keys.mesh_prefix(mesh)}/{keys.ALIVE}/*", timeout=1.0) != [], 20, "joined")
                takeover = handshake("robot", "prepare", forked.prepare("robot", Identity("spirit", forked.epoch, {}).pack(), "t1"))
                assert takeover.status == "rejected" and "holds 'spirit' itself" in takeover.reason, takeover
                for target in ("phone", "robot"):
                    for holder in (hostile, forked):
                        doc = Identity("spirit", holder.epoch, {"mind": {"entries": ["HACKED"]}}).pack()
                        answer = handshake(target, "prepare", holder.prepare(target, doc, f"clone-{target}-{holder.epoch}"))
                        assert answer.status == "rejected", answer
                        assert "custody" in answer.reason, answer.reason
                forged_commit = MigrateCommit("spirit", hostile.epoch, "clone", "screen", "phone",
                                              custody.encode_link(kept_chain[-1]))
                assert handshake("phone", "commit", forged_commit).status == "rejected"
            assert homes(admin, names) == {"robot": "spirit", "screen": None, "phone": None}
            assert memory(admin, "robot") == ["met Ada"]
            phone = record_of(tmp_path / "state-phone")
            assert phone is None or phone.state == "dropped"
    finally:
        for daemon in daemons:
            daemon.kill()


def test_strangers_cannot_poison_the_pin_fill_the_disk_or_stall_actions(trio: tuple[Node, Node, Node], mesh: str) -> None:
    b = trio[1]
    with pair(trio, mesh) as (t, client):

        def to_b(op: str, message: Any, sender: str = "x") -> Outcome:
            return send_request(t, keys.request_key(mesh, "b", "migration", op, sender), message, timeout=5)

        # poisoning: a stranger's "spirit" (its own key) is refused while spirit's holder is alive,
        # and in any case an aborted prepare pins nothing
        impostor = Holder("spirit", "x")
        poisoned = to_b("prepare", impostor.prepare("b", Identity("spirit", 1, {}).pack(), "p1"))
        assert poisoned.status == "rejected" and "custody" in poisoned.reason
        to_b("abort", MigrateAbort("spirit", 1, "p1"))
        # disk fill: first-contact prepares of 300 companions with 64 KiB documents, each aborted
        statuses: dict[str, int] = {}
        blob = {"mind": {"blob": "z" * 65536}}
        for i in range(300):
            holder = Holder(f"x{i}", "x")
            answer = to_b("prepare", holder.prepare("b", Identity(f"x{i}", 1, blob).pack(), f"f{i}"))
            statuses[answer.reason.split(":")[0] if answer.status == "rejected" else "accepted"] = \
                statuses.get(answer.reason.split(":")[0] if answer.status == "rejected" else "accepted", 0) + 1
            if answer.status == "accepted":
                assert to_b("abort", MigrateAbort(f"x{i}", 1, f"f{i}")).status == "accepted"
        assert statuses.get("busy", 0) > 0, statuses  # the sender's budget ran out
        files = list(b.state.iterdir())
        assert len(files) <= 64 + 1, len(files)
        assert sum(f.stat().st_size for f in files) < 256 * 1024, "aborted documents are deleted"
        # the real companion still migrates to b
        client.migrate("spirit", "b", timeout=30)
        # an action flood is bounded: every request answered, busy beyond the limits, and a legitimate
        # action afterwards runs
        act_key = keys.request_key(mesh, "b", "manager", "act")
        outcomes: list[str] = []
        lock = threading.Lock()

        def flood(n: int) -> None:
            for i in range(n):
                try:
                    status = send_request(t, act_key, Act("TestAction", ["test"], action_id=f"flood-{threading.get_ident()}-{i}"),
                                          timeout=10).status
                except OutcomeUnknown:
                    status = "unknown"
                with lock:
                    outcomes.append(status)

        threads = [threading.Thread(target=flood, args=(500,), name=f"flood-{k}") for k in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
        assert len(outcomes) == 2000 and "unknown" not in outcomes
        assert "rejected" in outcomes, "beyond the running-action limit, the flood is refused busy"
        # The flood's last accepted actions are still running when the senders stop: they end.
        wait_for(lambda: client.request("b", "manager", "status", ActionStatus()).value == {"running": []}, 60,
                 "the flood's accepted actions end")
        report = client.act("b", "TestAction", ["test"], timeout=60)
        assert report.status in ("succeeded", "failed"), report


def test_an_identity_edited_at_rest_is_refused_and_reported(trio: tuple[Node, Node, Node], mesh: str) -> None:
    a = trio[0]
    a.start()
    with ZenohTransport(TransportConfig(connect=(a.endpoint,), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: homes(client, ("a",)) == {"a": "spirit"}, 30, "spirit born on a")
        client.request("a", "mind", "message", MindMessage({"note": "met Ada"}))
        assert a.daemon is not None
        a.daemon.stop()
        assert oct((a.state / LOG).stat().st_mode & 0o777) == "0o600" and oct(a.state.stat().st_mode & 0o777) == "0o700"
        # The memory is in a section the manifest names by its hash (SchemaVersion 2): edit those bytes.
        edited = [p for p in (a.state / "sections").iterdir() if b"met Ada" in p.read_bytes()]
        assert len(edited) == 1 and oct(edited[0].stat().st_mode & 0o777) == "0o600"
        document = edited[0]
        document.write_bytes(document.read_bytes().replace(b"met Ada", b"HACKED!"))
        a.start()
        def damaged() -> bool:
            try:
                return "spirit" in client.describe("a", timeout=1.0).get("damaged", {})
            except OutcomeUnknown:
                return False

        wait_for(damaged, 30, "a reports spirit damaged")
        description = client.describe("a", timeout=2.0)
        assert description["inhabitant"] is None
        assert "altered at rest" in description["damaged"]["spirit"] and str(document) in description["damaged"]["spirit"]


# --- claims must be backed, forks are proven and resolved, records agree with their chain ----------------


def _lines(node: Node) -> list[str]:
    return [line for daemon in node.history for line in daemon.lines]


def _logged(node: Node, text: str) -> bool:
    return any(text in line for line in _lines(node))


def _stored(state: Path) -> Record:
    """A daemon's record as its file says (read without opening the folder, which a live daemon owns)."""
    return read_ledger(state).records["spirit"]


def _custody(client: MeshClient, name: str) -> dict[str, Any]:
    try:
        report = client.describe(name, timeout=1.0).get("custody", {}).get("spirit", {})
    except OutcomeUnknown:
        return {"error": "no answer"}
    return report if isinstance(report, dict) else {}


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = cli.main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def _forge(kept: list[Link], key: bytes, up_to: int) -> tuple[list[Link], bytes]:
    """What a former host (b) signs offline with the custody key of the epoch it held: links to itself,
    each to a fresh key of its own, up to epoch ``up_to``."""
    chain = list(kept)
    while chain[-1].epoch < up_to:
        fresh = signing.new_key()
        epoch = chain[-1].epoch + 1
        chain.append(custody.hand_on(key, "spirit", epoch, "b", signing.public_of(fresh), f"forged-{epoch}", custody.digest(b"")))
        key = fresh
    return chain, key


def test_bare_tokens_and_an_inflated_fork_never_win(tmp_path: Path, mesh: str, capsys: pytest.CaptureFixture[str]) -> None:
    """A bare custody token freezes nobody and refuses no migration. A former host (b) that kept its
    state folder forks the chain offline, 500 epochs ahead: refused where the true holder (a) is
    seen, naming b; accepted across a partition (c sees nobody), then, when c and a meet, both
    freeze, durably; `custody show` gives the evidence; `custody resolve` refuses while c cannot be
    reached and refuses to keep the equivocator's branch; then c stands down and a runs it again."""
    ports = {name: free_port() for name in ("a", "b", "c")}

    def node(name: str, peers: list[str], companion: str | None = None) -> Node:
        return Node(name, mesh, diary_embodiment_config(tmp_path / name, name), tmp_path / f"state-{name}", ports[name], peers,
                    companion=companion)

    a = node("a", [f"tcp/127.0.0.1:{ports['b']}"], "spirit")
    b = node("b", [f"tcp/127.0.0.1:{ports['a']}"])
    c = node("c", [a.endpoint])
    loopback = ("tcp/127.0.0.1:0",)
    try:
        a.start()
        b.start()
        with ZenohTransport(TransportConfig(connect=(a.endpoint, b.endpoint), listen=loopback, multicast=False)) as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: homes(client, ("a", "b")) == {"a": "spirit", "b": None}, 30, "spirit born on a")
            # A bare token, at an epoch far above the holder's: a hint nobody can back.
            bare = t.declare_token(keys.custody_key(mesh, "mallory", "spirit", 1002))
            wait_for(lambda: _logged(a, "ignored the custody claim of 'mallory' on 'spirit' at epoch 1002"), 20,
                     "a logs the claim it ignored, naming the claimant")
            assert homes(client, ("a", "b")) == {"a": "spirit", "b": None}
            assert client.request("a", "mind", "message", MindMessage({"note": "met Ada"})).status == "accepted", "a's mind is awake"
            client.migrate("spirit", "b", timeout=30)  # the token refuses no migration
            kept = _stored(b.state)  # b's state folder as b keeps it: its chain and custody key of epoch 2
            kept_key = read_ledger(b.state).keys["spirit"]
            client.migrate("spirit", "a", timeout=30)
            bare.close()
            assert kept.state == "active" and kept.epoch == 2
            assert b.daemon is not None
            b.daemon.kill()
        forged, forged_key = _forge(kept.chain, kept_key, 503)
        assert len(forged) - len(kept.chain) == 501
        former = Holder("spirit", "b", 503, private=forged_key, chain=forged)
        hacked = Identity("spirit", 503, {"mind": {"entries": ["HACKED"], "arrivals": []}}).pack()

        def offer_to_c(attempt: str) -> tuple[Outcome, MigratePrepare, ZenohTransport]:
            tc = ZenohTransport(TransportConfig(mode="client", connect=(c.endpoint,), multicast=False))
            joined = keys.alive_key(mesh, "c")
            wait_for(lambda: tc.alive(joined, timeout=1.0), 20, "joined c")
            prepare = former.prepare("c", hacked, attempt)
            return send_request(tc, keys.request_key(mesh, "c", "migration", "prepare", "b"), prepare, timeout=10), prepare, tc

        # 1. c sees the true holder: the fork is refused, and c names the equivocator.
        c.start()
        with ZenohTransport(TransportConfig(mode="client", connect=(c.endpoint,), multicast=False)) as watch:
            wait_for(lambda: watch.alive(keys.custody_key(mesh, "a", "spirit", 3), timeout=1.0), 20, "c sees a's token")
        refused, _, tc = offer_to_c("forged-1")
        tc.close()
        assert refused.status == "rejected", refused
        assert "forks from the chain offered by 'b'" in refused.reason and "'b' signed two links for epoch 3" in refused.reason
        wait_for(lambda: _logged(c, "CUSTODY FORK of spirit: 'b' signed two links for epoch 3"), 5, "the log line")
        assert "spirit" not in read_ledger(c.state).records
        # 2. c cut off (a port nobody knows, no peers): the fork is accepted, and committed.
        assert c.daemon is not None
        c.daemon.stop()
        c.port, c.peers = free_port(), []
        c.start()
        accepted, prepare, tc = offer_to_c("forged-2")
        with tc:
            assert accepted.status == "accepted", accepted
            commit = former.commit(prepare, accepted)
            assert send_request(tc, keys.request_key(mesh, "c", "migration", "commit", "b"), commit, timeout=10).status == "accepted"
            wait_for(lambda: _stored(c.state).state == "active", 10, "c runs the forged branch")
        assert _stored(c.state).epoch == 504
        # 3. They meet: both freeze, each with the evidence on its disk.
        c.daemon.stop()
        c.peers = [a.endpoint]
        c.start()
        both = (a.endpoint, c.endpoint)
        mesh_args = ("--mesh", mesh, "--no-multicast", "--connect", a.endpoint, "--connect", c.endpoint)
        with ZenohTransport(TransportConfig(mode="client", connect=both, multicast=False)) as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: _custody(client, "a").get("frozen") and _custody(client, "c").get("frozen"), 30, "both frozen")
            assert homes(client, ("a", "c")) == {"a": None, "c": None}
            report = _custody(client, "a")
            assert report["equivocators"] == ["b"] and report["branches"]["c"]["equivocators"] == ["b"]
            assert report["branches"]["a"] == {"epoch": 3, "equivocators": []} and report["branches"]["c"]["epoch"] == 504
            assert (tmp_path / "state-a" / "spirit.fork.json").exists() and (c.state / "spirit.fork.json").exists()
            wait_for(lambda: _logged(a, "CUSTODY FORK of spirit: 'b' signed two links for epoch 3"), 5, "the log line")
            assert client.request("a", "mind", "message", MindMessage({"note": "x"})).status == "rejected", "a's mind is asleep"
            frozen = client.request("a", "migration", "migrate", Migrate("spirit", "c"))
            assert frozen.status == "rejected" and "frozen by a fork" in frozen.reason
            code, out, _ = _cli(capsys, "custody", "show", "spirit", *mesh_args)
            assert code == 0
            assert "fork at epoch 3: 'b' signed two links for epoch 3 of 'spirit'" in out
            assert "certs revoke" in out and "cmion-mesh custody resolve spirit --keep EMBODIMENT (e.g. a)" in out
            # 4. c cannot be reached: keeping a would make two.
            c.daemon.kill()
            code, _, err = _cli(capsys, "custody", "resolve", "spirit", "--keep", "a", "--mesh", mesh, "--no-multicast",
                                "--connect", a.endpoint)
            assert code == 1 and "keeping 'a' would make two: 'c' (epoch 504)" in err, err
            assert _custody(client, "a").get("frozen"), "a restart of nothing: a is still frozen"
        # 5. c back (frozen from its disk); the equivocator's branch is not kept; a's is.
        c.start()
        with ZenohTransport(TransportConfig(mode="client", connect=both, multicast=False)) as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: _custody(client, "c").get("frozen"), 30, "c frozen again after its restart")
            code, _, err = _cli(capsys, "custody", "resolve", "spirit", "--keep", "c", *mesh_args)
            assert code == 1 and "'b' (who equivocated)" in err and "--force" in err, err
            code, out, err = _cli(capsys, "custody", "resolve", "spirit", "--keep", "a", *mesh_args)
            assert code == 0, err
            assert "c stood down" in out
            wait_for(lambda: homes(client, ("a", "c")) == {"a": "spirit", "c": None}, 20, "exactly one runs it: a")
            assert memory(client, "a") == ["met Ada"]
            retired = _stored(c.state)
            assert retired.state == "dropped" and retired.chain[-1].holder == "a" and retired.epoch == 3
            assert not (tmp_path / "state-a" / "spirit.fork.json").exists() and not (c.state / "spirit.fork.json").exists()
    finally:
        for each in (a, b, c):
            each.stop()


def test_a_bare_custody_token_of_a_trusted_member_is_ignored_in_secure_mode(pki: Pki, tmp_path: Path, mesh: str) -> None:
    ports = {n: free_port() for n in ("robot", "screen")}
    daemons = []
    try:
        for name in ports:
            daemons.append(_secure_daemon(pki, tmp_path, mesh, name, ports[name], [p for n, p in ports.items() if n != name],
                                          *(["--companion", "spirit"] if name == "robot" else [])))
        endpoints = [f"tls/127.0.0.1:{p}" for p in ports.values()]
        names = ("robot", "screen")
        with ZenohTransport(secure_config(pki, "admin", mesh, *endpoints)) as admin_t, \
                ZenohTransport(secure_config(pki, "phone", mesh, *endpoints)) as phone_t:
            admin = MeshClient(admin_t, mesh)
            wait_for(lambda: homes(admin, names) == {"robot": "spirit", "screen": None}, 30, "two secure daemons")
            # phone, a trusted member, under its own certificate (what the access control allows it)
            token = phone_t.declare_token(keys.custody_key(mesh, "phone", "spirit", 1002))
            try:
                wait_for(lambda: any("ignored the custody claim of 'phone' on 'spirit' at epoch 1002" in line
                                     for line in daemons[0].lines), 20, "robot logs the claim it ignored")
                assert homes(admin, names) == {"robot": "spirit", "screen": None}
                assert admin.request("robot", "mind", "message", MindMessage({"note": "met Ada"})).status == "accepted"
                assert admin.migrate("spirit", "screen", timeout=30)["target"] == "screen"
            finally:
                token.close()
            wait_for(lambda: homes(admin, names) == {"robot": None, "screen": "spirit"}, 20, "spirit on screen")
            assert memory(admin, "screen") == ["met Ada"]
    finally:
        for daemon in daemons:
            daemon.kill()


def test_a_record_its_chain_does_not_back_never_runs(trio: tuple[Node, Node, Node], mesh: str, tmp_path: Path) -> None:
    """A former host rolled back to a backup with its epoch raised is damaged (and the true holder keeps
    running); rolled back as it was, it stands down for good (its key signed the link the holder has);
    the holder's own record with its epoch raised is damaged, never run."""
    a, b, _ = trio
    with pair(trio, mesh) as (_, client):
        client.request("a", "mind", "message", MindMessage({"note": "met Ada"}))
        backup = tmp_path / "backup-a"
        shutil.copytree(a.state, backup, ignore=shutil.ignore_patterns("daemon.lock"))
        client.migrate("spirit", "b", timeout=30)

        def restore(epoch_raise: int) -> None:
            assert a.daemon is not None
            a.daemon.stop()
            shutil.rmtree(a.state)
            shutil.copytree(backup, a.state)
            _raise_epoch(a.state, epoch_raise)
            a.start()

        restore(4)
        wait_for(lambda: "spirit" in client.describe("a", timeout=1.0).get("damaged", {}), 30, "a reports spirit damaged")
        damaged = client.describe("a", timeout=2.0)["damaged"]["spirit"]
        assert "record says epoch 5, its chain of custody ends at epoch 1" in damaged and str(a.state / LOG) in damaged
        assert homes(client, ("a", "b")) == {"a": None, "b": "spirit"}
        assert client.request("b", "mind", "message", MindMessage({"note": "on b"})).status == "accepted", "b keeps running"
        restore(0)
        wait_for(lambda: _stored(a.state).state == "released", 30, "a stands down for good")
        wait_for(lambda: _logged(a, "custody of spirit moved on without this copy: 'b' holds it at epoch 2"), 5, "the log line")
        assert homes(client, ("a", "b")) == {"a": None, "b": "spirit"}
        assert memory(client, "b") == ["met Ada", "on b"]
        assert b.daemon is not None
        b.daemon.stop()
        _raise_epoch(b.state, 1)
        b.start()
        wait_for(lambda: "spirit" in client.describe("b", timeout=1.0).get("damaged", {}), 30, "b reports spirit damaged")
        assert "record says epoch 3, its chain of custody ends at epoch 2" in client.describe("b", timeout=2.0)["damaged"]["spirit"]
        assert homes(client, ("a", "b")) == {"a": None, "b": None}


def _raise_epoch(state: Path, by: int) -> None:
    """Edit the record at rest: an entry appended with its epoch raised (checksummed, as a forger would)."""
    record = read_ledger(state).records["spirit"]
    journal = Journal(state)
    journal.append(msgspec.msgpack.encode(Entry("spirit", msgspec.structs.replace(record, epoch=record.epoch + by))))
    journal.close()
