"""The transport's error contract, on the zenoh adapter and on the in-memory double alike.

Every call raises ``ClosedError`` once the transport is closed and ``TransportError`` naming the
key when the session refuses it; ``zenoh.ZError`` never escapes the adapter. Handlers of one
selector share one zenoh declaration, against tokens of a peer in another process (run as a child:
``python -m tests.test_transport tokens ENDPOINT``, commands on stdin).
"""

from __future__ import annotations

import contextlib
import gc
import sys
import threading
import weakref
from collections.abc import Callable, Iterator

import pytest

from cmion_mesh.errors import ClosedError, TransportError
from cmion_mesh.procs import Daemon, free_port
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import MAX_BATCH, Declared, IncomingQuery, Sample, Transport, TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(30)

#: Each operation of the interface, called with a valid key (``k``) or selector.
CALLS: dict[str, Callable[[Transport, str], object]] = {
    "publish": lambda t, k: t.publish(k, b"x"),
    "publish (drop)": lambda t, k: t.publish(k, b"x", block=False),
    "delete": lambda t, k: t.delete(k),
    "subscribe": lambda t, k: t.subscribe(k, lambda sample: None),
    "subscribe_batches": lambda t, k: t.subscribe_batches(k, lambda batch: None),
    "declare_queryable": lambda t, k: t.declare_queryable(k, lambda query: query.finish()),
    "get": lambda t, k: t.get(k, timeout=0.2),
    "get_first": lambda t, k: t.get_first(k, timeout=0.2),
    "get_values": lambda t, k: t.get_values(k, timeout=0.2),
    "declare_token": lambda t, k: t.declare_token(k),
    "alive": lambda t, k: t.alive(k, timeout=0.2),
    "watch_liveliness": lambda t, k: t.watch_liveliness(k, lambda key, alive: None),
    "peers": lambda t, k: t.peers(),
}
#: The operations zenoh checks the key expression of (it lets a publication or delete on a
#: wildcard through).
CHECKED = ["subscribe", "subscribe_batches", "declare_queryable", "get", "get_first", "get_values", "declare_token", "alive",
           "watch_liveliness", "publish (drop)"]


@pytest.fixture
def zenoh_transport() -> Iterator[ZenohTransport]:
    with ZenohTransport(TransportConfig(multicast=False, overrides=(("listen/endpoints", "[]"),))) as t:
        yield t


@pytest.mark.parametrize("operation", CHECKED)
def test_zenoh_refusals_are_transport_errors_naming_the_key(operation: str, zenoh_transport: ZenohTransport) -> None:
    with pytest.raises(TransportError, match=r"cmion/a//b"):
        handle = CALLS[operation](zenoh_transport, "cmion/a//b")
        getattr(handle, "close", lambda: None)()


@pytest.mark.parametrize("operation", sorted(CALLS))
def test_every_call_after_close_is_a_closed_error(operation: str, network: MemoryNetwork) -> None:
    zenoh_transport = ZenohTransport(TransportConfig(multicast=False, overrides=(("listen/endpoints", "[]"),)))
    memory = MemoryTransport(network, "gone")
    for transport in (zenoh_transport, memory):
        transport.close()
        transport.close()  # idempotent
        with pytest.raises(ClosedError):
            CALLS[operation](transport, "cmion/a/b")


def test_peers_belong_to_the_interface(zenoh_transport: ZenohTransport, network: MemoryNetwork) -> None:
    assert zenoh_transport.peers() == []  # no endpoint, no scouting: alone
    with MemoryTransport(network, "a") as a, MemoryTransport(network, "b") as b:
        assert a.peers() == [b.id] and b.peers() == [a.id]


@pytest.fixture(params=["zenoh", "memory"])
def any_transport(request: pytest.FixtureRequest, network: MemoryNetwork) -> Iterator[Transport]:
    if request.param == "zenoh":
        with ZenohTransport(TransportConfig(multicast=False, overrides=(("listen/endpoints", "[]"),))) as z:
            yield z
    else:
        with MemoryTransport(network, "batches") as m:
            yield m


def test_batches_hand_over_what_arrived_in_order_and_whole(any_transport: Transport) -> None:
    got: list[list[bytes]] = []
    first = threading.Event()
    release = threading.Event()

    def on_batch(batch: list[Sample]) -> None:
        got.append([s.payload for s in batch])
        first.set()
        release.wait(10.0)  # a slow handler: what arrives meanwhile waits in the channel

    with any_transport.subscribe_batches("cmion/t/batch", on_batch):
        any_transport.publish("cmion/t/batch", b"0")
        wait_for(first.is_set, 10.0, "the first batch")
        for i in range(1, 1000):
            any_transport.publish("cmion/t/batch", str(i).encode())
        release.set()
        wait_for(lambda: sum(len(b) for b in got) == 1000, 10.0, "every sample")
    assert [p for b in got for p in b] == [str(i).encode() for i in range(1000)]
    assert max(len(b) for b in got) > 1, "what waited came in batches"
    assert all(len(b) <= MAX_BATCH for b in got)


def test_a_failing_handler_loses_no_other_sample(any_transport: Transport) -> None:
    got: list[bytes] = []

    def on_sample(sample: Sample) -> None:
        if sample.payload == b"3":
            raise RuntimeError("this one fails")
        got.append(sample.payload)

    with any_transport.subscribe("cmion/t/fail", on_sample):
        for i in range(10):
            any_transport.publish("cmion/t/fail", str(i).encode())
        wait_for(lambda: len(got) == 9, 10.0, "the nine others")
    assert got == [str(i).encode() for i in range(10) if i != 3]


@pytest.mark.parametrize("selector", ["cmion/t/whole", "cmion/t/*"])
def test_a_sample_has_every_field(any_transport: Transport, selector: str) -> None:
    """Samples are made without the named tuple's constructor on the hot path: each must still
    carry every field (a missing default broke unpacking ``key, payload, deleted, attachment``)."""
    got: list[Sample] = []
    with any_transport.subscribe(selector, got.append):
        any_transport.publish("cmion/t/whole", b"x")
        wait_for(lambda: bool(got), 10.0, "the sample")
    key, payload, deleted, attachment = got[0]
    assert (key, payload, deleted, attachment) == ("cmion/t/whole", b"x", False, None)
    assert len(got[0]) == len(Sample._fields)


def test_get_values_gives_the_ok_replies_by_key(any_transport: Transport) -> None:
    def answer(query: IncomingQuery) -> None:
        query.reply("cmion/t/values/a", b"first")
        query.reply("cmion/t/values/b", b"b")
        query.reply("cmion/t/values/a", b"later")  # of two for one key, the later one
        query.reply_err(b"refused")
        query.finish()

    with any_transport.declare_queryable("cmion/t/values/**", answer):
        values = any_transport.get_values("cmion/t/values/**", timeout=5.0)
    assert values == {"cmion/t/values/a": b"later", "cmion/t/values/b": b"b"}


def test_get_first_returns_the_first_reply_without_waiting_for_the_query_to_end(
        zenoh_transport: ZenohTransport) -> None:
    # A request has one replier: its answer is all the caller needs, and zenoh's final message (the
    # query's end) follows the reply late enough to cost a migration about a millisecond per step.
    release = threading.Event()
    finished = threading.Event()

    def answer(query: IncomingQuery) -> None:
        query.reply("cmion/t/first", b"first")
        release.wait(10.0)  # bounded: the test sets it once get_first has returned
        query.reply("cmion/t/first", b"second")
        query.finish()
        finished.set()

    with zenoh_transport.declare_queryable("cmion/t/first", answer):
        try:
            reply = zenoh_transport.get_first("cmion/t/first", b"q", timeout=10.0)
            assert reply is not None and reply.ok and reply.payload == b"first"
            assert not finished.is_set(), "get_first waited for the query's end"
        finally:
            release.set()
        assert finished.wait(10.0)
        assert zenoh_transport.get_first("cmion/t/nobody", timeout=0.5) is None


# --- handlers sharing a declaration, against a peer in another process ------------------------------


def tokens(endpoint: str) -> int:
    """The child: a peer listening on ``endpoint`` that declares (``up KEY``) and undeclares
    (``down KEY``) liveliness tokens and publishes (``pub KEY``: the payload ``KEY``) as told on
    stdin, each acknowledged on stdout (``pub`` once a subscriber of the key is known)."""
    held: dict[str, object] = {}
    with ZenohTransport(TransportConfig(listen=(endpoint,), multicast=False)) as transport:
        print("ready", flush=True)
        for line in sys.stdin:
            command, _, key = line.strip().partition(" ")
            if command == "up":
                held[key] = transport.declare_token(key)
            elif command == "down":
                held.pop(key).close()  # type: ignore[attr-defined]
            elif command == "pub":
                if not transport.wait_subscribers(key, 20):
                    print(f"nobody subscribes to {key}", flush=True)
                    continue
                transport.publish(key, key.encode())
            else:
                break
            print(f"{command} {key}", flush=True)
    return 0


@contextlib.contextmanager
def peer_and_transport(name: str) -> Iterator[tuple[Daemon, ZenohTransport]]:
    """This module's ``tokens`` peer in a process of its own (ready), and a transport connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Daemon([sys.executable, "-m", "tests.test_transport", "tokens", endpoint], name=name, stdin=True) as peer, \
            ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False,
                                           overrides=(("listen/endpoints", "[]"),))) as transport:
        peer.wait_line("ready", 30)
        yield peer, transport


def test_liveliness_watches_of_one_selector_share_a_declaration(mesh: str) -> None:
    """A second watch of the same selector joins the first one's liveliness subscriber: it is given
    the peer's token (as the history its own declaration would have brought), then every change;
    closing the first leaves the second watching; the last one closed undeclares."""
    alive = f"cmion/{mesh}/@alive"
    with peer_and_transport("tokens") as (peer, transport):
        peer.send(f"up {alive}/a")
        first: list[tuple[str, bool]] = []
        second: list[tuple[str, bool]] = []
        declared = transport.declarations
        watch = transport.watch_liveliness(f"{alive}/*", lambda key, up: first.append((key, up)))
        wait_for(lambda: first == [(f"{alive}/a", True)], 20, "the first watch sees the peer's token")
        later = transport.watch_liveliness(f"{alive}/*", lambda key, up: second.append((key, up)))
        assert transport.declarations == declared + 1, "one zenoh declaration for the two watches"
        wait_for(lambda: second == [(f"{alive}/a", True)], 10, "the later watch is given the token alive")
        watch.close()
        peer.send(f"up {alive}/b")
        peer.send(f"down {alive}/a")
        wait_for(lambda: second[1:] == [(f"{alive}/b", True), (f"{alive}/a", False)], 20,
                 "the later watch goes on after the first closed")
        assert first == [(f"{alive}/a", True)], "a closed watch hears nothing more"
        later.close()
        assert transport.declarations == declared, "the last one closed undeclares"
        again: list[tuple[str, bool]] = []
        with transport.watch_liveliness(f"{alive}/*", lambda key, up: again.append((key, up))):
            wait_for(lambda: again == [(f"{alive}/b", True)], 20, "declared afresh, with zenoh's history")
        peer.send("quit")


def test_subscribers_of_one_selector_share_a_declaration(mesh: str) -> None:
    key = f"cmion/{mesh}/shared/ev"
    with peer_and_transport("publisher") as (peer, transport):
        one: list[str] = []
        two: list[str] = []
        declared = transport.declarations
        first = transport.subscribe(f"{key}/*", lambda sample: one.append(sample.key), remote_only=True)
        second = transport.subscribe_batches(f"{key}/*", lambda batch: two.extend(s.key for s in batch), remote_only=True)
        assert transport.declarations == declared + 1, "one zenoh declaration for the two handlers"
        peer.send(f"pub {key}/1")
        wait_for(lambda: one == [f"{key}/1"] and two == [f"{key}/1"], 20, "both handlers")
        first.close()
        peer.send(f"pub {key}/2")
        wait_for(lambda: two == [f"{key}/1", f"{key}/2"], 20, "the other handler goes on")
        assert one == [f"{key}/1"], "a closed handler hears nothing more"
        assert transport.declarations == declared + 1
        second.close()
        assert transport.declarations == declared
        peer.send("quit")

if __name__ == "__main__":
    if sys.argv[1:2] == ["tokens"]:
        sys.exit(tokens(sys.argv[2]))


def test_what_a_transport_closed_it_holds_no_more(any_transport: Transport) -> None:
    """A daemon declares a custody token at every step of every migration: a transport that kept
    each one it ever declared would grow for as long as the daemon runs. After thousands declared
    and closed, it holds about what is open, and closing the transport still closes what is."""
    kept = [any_transport.declare_token(f"cmion/decl/kept/{i}") for i in range(3)]
    closed = []
    for epoch in range(3000):
        token = any_transport.declare_token(f"cmion/decl/custody/{epoch}")
        token.close()
        closed.append(weakref.ref(token))
        del token
    gc.collect()
    held = sum(ref() is not None for ref in closed)
    assert held <= 2 * Declared.MIN_PRUNE, f"the transport still holds {held} of the tokens it closed"
    if isinstance(any_transport, ZenohTransport):
        assert any_transport.declarations == 3
    any_transport.close()
    assert all(token.closed for token in kept)  # type: ignore[attr-defined]


def test_declared_drops_closed_handles_as_it_grows() -> None:
    class Item:
        def __init__(self) -> None:
            self.closed = False

        def close(self) -> None:
            self.closed = True

    declared: Declared[Item] = Declared()
    open_ones = [declared.add(Item()) for _ in range(100)]
    for _ in range(10_000):
        declared.add(Item()).close()
        assert len(declared) <= 2 * max(Declared.MIN_PRUNE, 100) + 1
    assert declared.open() == 100
    taken = declared.take()
    assert [item for item in taken if not item.closed] == open_ones
    assert len(declared) == 0
