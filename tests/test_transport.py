"""The transport's error contract, on the zenoh adapter and on the in-memory double alike.

Every call raises ``ClosedError`` once the transport is closed and ``TransportError`` naming the
key when the session refuses it; ``zenoh.ZError`` never escapes the adapter.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from cmion_mesh.errors import ClosedError, TransportError
from cmion_mesh.memory_transport import MemoryNetwork, MemoryTransport
from cmion_mesh.transport import Transport, TransportConfig
from cmion_mesh.zenoh_transport import ZenohTransport

pytestmark = pytest.mark.timeout(30)

#: Each operation of the interface, called with a valid key (``k``) or selector.
CALLS: dict[str, Callable[[Transport, str], object]] = {
    "publish": lambda t, k: t.publish(k, b"x"),
    "publish (drop)": lambda t, k: t.publish(k, b"x", block=False),
    "delete": lambda t, k: t.delete(k),
    "subscribe": lambda t, k: t.subscribe(k, lambda sample: None),
    "declare_queryable": lambda t, k: t.declare_queryable(k, lambda query: query.finish()),
    "get": lambda t, k: t.get(k, timeout=0.2),
    "declare_token": lambda t, k: t.declare_token(k),
    "alive": lambda t, k: t.alive(k, timeout=0.2),
    "watch_liveliness": lambda t, k: t.watch_liveliness(k, lambda key, alive: None),
    "peers": lambda t, k: t.peers(),
}
#: The operations zenoh checks the key expression of (it lets a publication or delete on a
#: wildcard through).
CHECKED = ["subscribe", "declare_queryable", "get", "declare_token", "alive", "watch_liveliness", "publish (drop)"]


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
