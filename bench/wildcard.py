"""Growth curve (b): a wildcard get of a whole blackboard against the number of properties.

One child process (``python -m bench.wildcard serve``) holds an embodiment ``bb-store`` (its
blackboard answers reads on its zenoh queryable, as in every daemon) with a ``loader`` component,
and a raw zenoh session with a queryable that answers ``bench/<tag>/raw/many/<n>/**`` with ``n``
replies carrying the same bytes a blackboard property would (an encoded ``Property``).

The loader fills the blackboard to the size asked (request ``loader/fill``, a ``fill`` message ``{"total": n}``):
properties ``p000000``... at the root, applied on the update loop as the store applies a write
(``Store._apply`` under its lock) but without publishing a change event for each, which nobody
listens to and which would dominate the fill time at 100k properties. The measuring process then
times ``MeshClient.read(".../bb/**")`` (every property decoded into a dict, as ``cmion-mesh bb get``
does) against a raw zenoh get of the same number of replies (payloads collected as bytes), in
alternation, and checks that every property came back.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Sequence
from contextlib import ExitStack
from typing import Any

import zenoh

from bench.core import CHANNEL_CAPACITY, _drain, close_raw, open_session
from bench.harness import StopSignal, loopback_config, loopback_endpoint, start_child, stop_child
from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Component
from cmion_mesh.messages import Message, Property, SetProperty, encode
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.storage import Blackboard
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.zenoh import ZenohTransport

STORE = "bb-store"


def raw_prefix(tag: str) -> str:
    return f"bench/{tag}/raw/many"


class Fill(Message, frozen=True, tag="fill"):
    """``loader/fill``: fill the blackboard up to ``total`` properties."""

    total: int


class Loader(Component):
    """``fill {"total": n}``: add properties ``p<i>`` to the blackboard until it holds ``n``."""

    requests = {"fill": Fill}

    def __init__(self, blackboard: Blackboard) -> None:
        super().__init__("loader")
        self.blackboard = blackboard
        self.count = 0

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            total = request.payload.total
            with self.blackboard._lock:
                while self.count < total:
                    self.blackboard._apply(SetProperty("", f"p{self.count:06d}", self.count), set())
                    self.count += 1
            request.accept({"total": self.count})


def serve(args: argparse.Namespace) -> int:
    from cmion_mesh.body.embodiment import Embodiment

    stop = StopSignal(args.parent)
    session = open_session(loopback_config(listen=args.raw_listen))
    entities: list[Any] = []
    workers: list[threading.Thread] = []
    prefix = raw_prefix(args.tag)

    def answer(query: zenoh.Query) -> None:
        with query:
            n = int(str(query.key_expr)[len(prefix) + 1:].split("/", 1)[0])
            for i in range(n):
                query.reply(f"{prefix}/{n}/p{i:06d}", encode(Property(i)))

    try:
        queryable = session.declare_queryable(f"{prefix}/**", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        entities.append(queryable)
        workers.append(_drain("many", queryable.handler.recv, answer))
        with Embodiment(STORE, mesh=args.mesh, transport_config=loopback_config(listen=args.mesh_listen)) as body:
            body.add(Loader(body.blackboard))
            ready = threading.Event()
            body.sim.call(ready.set)
            ready.wait(10.0)
            print(f"ready store {STORE} in {args.mesh}", flush=True)
            stop.wait()
    finally:
        close_raw(session, entities, workers)
    return 0


def log(text: str) -> None:
    print(f"  [wildcard] {text}", flush=True)


def measure(mesh: str, sizes: Sequence[int], repeats: dict[int, int]) -> dict[tuple[str, int], list[float]]:
    raw_ep, mesh_ep = loopback_endpoint(), loopback_endpoint()
    out: dict[tuple[str, int], list[float]] = {}
    with ExitStack() as stack:
        child = start_child("bench.wildcard", "serve", "--raw-listen", raw_ep, "--mesh-listen", mesh_ep, "--mesh", mesh,
                            "--tag", mesh, name="bb-store")
        stack.callback(stop_child, child)
        child.wait_line("ready", 30.0)
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        transport = ZenohTransport(loopback_config(connect=mesh_ep))
        stack.callback(transport.close)
        client = MeshClient(transport, mesh)
        client.wait_for_embodiment(STORE, timeout=20.0)
        selector = f"{keys.storage_key(mesh, STORE, keys.BLACKBOARD, ())}/**"

        def raw_get(n: int) -> int:
            got = 0
            for reply in session.get(f"{raw_prefix(mesh)}/{n}/**", timeout=300.0, consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is not None:
                    reply.ok.payload.to_bytes()
                    got += 1
            return got

        def mesh_get() -> int:
            return sum(1 for entry in client.read(selector, timeout=300.0).values() if isinstance(entry, Property))

        wait_for(lambda: raw_get(1) == 1, 20.0, "the raw queryable answering")
        for size in sizes:
            t0 = time.monotonic()
            outcome = client.request(STORE, "loader", "fill", Fill(size), timeout=300.0)
            if outcome.status != "accepted":
                raise MeshError(f"fill to {size}: {outcome.reason}")
            fill = time.monotonic() - t0
            raw_get(size)  # warm-up
            mesh_get()
            for _ in range(repeats[size]):
                t = time.perf_counter()
                got = raw_get(size)
                out.setdefault(("raw", size), []).append(time.perf_counter() - t)
                if got != size:
                    raise MeshError(f"raw get: {got} replies, not {size}")
                t = time.perf_counter()
                got = mesh_get()
                out.setdefault(("mesh", size), []).append(time.perf_counter() - t)
                if got != size:
                    raise MeshError(f"wildcard get of the blackboard: {got} properties, not {size}")
            log(f"{size} properties (filled in {fill:.2f} s): {repeats[size]} gets each")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.wildcard", description="child process of the wildcard-get curve")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("serve")
    p.add_argument("--raw-listen", required=True)
    p.add_argument("--mesh-listen", required=True)
    p.add_argument("--mesh", required=True)
    p.add_argument("--tag", required=True)
    p.add_argument("--parent", type=int)
    return serve(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
