"""Core latency: cmion_mesh events, property gets and set requests vs raw zenoh, across processes.

Three processes, all on loopback (see ``bench.harness``):

* ``serve-raw`` (child): a plain zenoh peer. A subscriber on ``<raw>/ping`` whose worker thread
  drains a ``FifoChannel`` and re-publishes each payload on ``<raw>/pong`` (declared publisher,
  ``CongestionControl.BLOCK``); a queryable on ``<raw>/get`` whose worker drains a ``FifoChannel``
  and replies a fixed 64-byte payload (``with query:`` finalizes it).
* ``serve-mesh`` (child): an ``Embodiment`` ``bench-b`` (blackboard with a 64-byte property
  ``probe``) plus a component ``echo`` that handles ``bench-a``'s ``pinger/ping`` events
  (``sim.on_event``) by raising ``echo/pong`` with the same data.
* the measuring process (``run``): a raw zenoh session connected to ``serve-raw`` and a
  ``ZenohTransport`` connected to ``serve-mesh`` carrying a ``Simulation`` ``bench-a`` with the
  component ``pinger`` and a ``MeshClient``.

Metrics (all round trips timed in the measuring process with ``time.perf_counter``):

* ``raw_pubsub``: put on ping -> pong received; RTT/2.
* ``mesh_event``: ``pinger`` raises ``ping`` on the update loop -> ``pong`` handled on the loop,
  which raises the next ping at once; RTT/2.
* ``raw_get``: ``session.get`` -> the reply received and the query finalized.
* ``mesh_property_get``: ``MeshClient.get_property`` (a zenoh get on the property key, answered by
  the blackboard on its queryable worker, decoded to a ``Property``).
* ``mesh_set_property``: ``MeshClient.write(SetProperty)`` -> its ``Outcome`` (accepted), i.e. a
  query to the blackboard's request queryable, mediated on ``bench-b``'s update loop.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any

import zenoh

from bench.harness import (
    StopSignal,
    interleaved,
    loopback_config,
    loopback_endpoint,
    retry_until,
    start_child,
    stop_child,
)
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event, SetProperty, encode
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport, build_config

PAYLOAD_BYTES = 64
SEQ_DIGITS = 16
CHANNEL_CAPACITY = 4096

A_NAME = "bench-a"
B_NAME = "bench-b"
PINGER = "pinger"
ECHO = "echo"
PROPERTY = "probe"
WRITTEN = "written"

LABELS = {
    "raw_pubsub": "raw zenoh pub/sub, one-way (RTT/2)",
    "mesh_event": "cmion event delivery, one-way (RTT/2)",
    "raw_get": "raw zenoh get, round trip",
    "mesh_property_get": "cmion property get, round trip",
    "mesh_set_property": "cmion set_property -> Outcome, round trip",
}
#: cmion metric -> the raw metric it is compared with.
PAIRS = {"mesh_event": "raw_pubsub", "mesh_property_get": "raw_get", "mesh_set_property": "raw_get"}
GROUPS = {
    "events": ("raw_pubsub", "mesh_event"),
    "get": ("raw_get", "mesh_property_get"),
    "set": ("raw_get", "mesh_set_property"),
}
ORDER = ("raw_pubsub", "mesh_event", "raw_get", "mesh_property_get", "mesh_set_property")


def raw_keys(tag: str) -> tuple[str, str, str]:
    base = f"bench/{tag}/raw"
    return f"{base}/ping", f"{base}/pong", f"{base}/get"


def payload_text(seq: int) -> str:
    """A 64-character payload that starts with its sequence number (to discard stale echoes)."""
    return f"{seq:0{SEQ_DIGITS}d}".ljust(PAYLOAD_BYTES, ".")


def seq_of(text: str | bytes) -> int:
    head = text[:SEQ_DIGITS]
    try:
        return int(head)
    except ValueError:
        return -1


def open_session(cfg: TransportConfig) -> zenoh.Session:
    """A raw zenoh session configured exactly as ``ZenohTransport`` would be for ``cfg``."""
    return zenoh.open(build_config(cfg))


def _drain(name: str, recv: Callable[[], Any], handle: Callable[[Any], None]) -> threading.Thread:
    """The usual zenoh-python worker: one thread draining a FifoChannel until it closes."""

    def run() -> None:
        while True:
            try:
                item = recv()
            except zenoh.ZError:
                return
            handle(item)

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    return thread


# --- children ------------------------------------------------------------------------------------


def serve_raw(args: argparse.Namespace) -> int:
    stop = StopSignal(args.parent)
    ping, pong, get = raw_keys(args.tag)
    reply = payload_text(0).encode()
    session = open_session(loopback_config(listen=args.listen))
    workers: list[threading.Thread] = []
    entities: list[Any] = []
    try:
        publisher = session.declare_publisher(pong, congestion_control=zenoh.CongestionControl.BLOCK)
        subscriber = session.declare_subscriber(ping, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        queryable = session.declare_queryable(get, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))

        def echo(sample: zenoh.Sample) -> None:
            publisher.put(sample.payload.to_bytes())

        def answer(query: zenoh.Query) -> None:
            with query:
                query.reply(get, reply)

        entities += [publisher, subscriber, queryable]
        workers.append(_drain("echo", subscriber.handler.recv, echo))
        workers.append(_drain("answer", queryable.handler.recv, answer))
        print(f"ready raw zenoh peer on {args.listen} (zid {session.zid()})", flush=True)
        stop.wait()
    finally:
        close_raw(session, entities, workers)
    return 0


def close_raw(session: zenoh.Session, entities: Sequence[Any], workers: Sequence[threading.Thread]) -> None:
    """Undeclare, let the workers see their channels close and end, then close the session.

    A daemon thread still inside a zenoh call when the interpreter exits aborts the process
    ("FATAL: exception not rethrown"), so workers are joined before exit.
    """
    for entity in entities:
        try:
            entity.undeclare()
        except Exception:
            pass
    for worker in workers:
        worker.join(5.0)
    session.close()  # type: ignore[no-untyped-call]


class Echo(Component):
    """Handles ``<peer>/pinger/ping`` and raises ``echo/pong`` with the same data."""

    def __init__(self, peer: str) -> None:
        super().__init__(ECHO)
        self.peer = peer

    def attach(self, sim: Simulation) -> None:
        sim.on_event(self.on_ping, embodiment=self.peer, component=PINGER, event="ping")

    def on_ping(self, event: Event) -> None:
        self.raise_event("pong", event.data)


def serve_mesh(args: argparse.Namespace) -> int:
    from cmion_mesh.body.embodiment import Embodiment

    stop = StopSignal(args.parent)
    with Embodiment(B_NAME, mesh=args.mesh, transport_config=loopback_config(listen=args.listen)) as body:
        body.blackboard.apply_now(SetProperty("", PROPERTY, payload_text(0)))
        body.add(Echo(args.peer))
        attached = threading.Event()
        body.sim.call(attached.set)  # runs after every queued attach: the queryables are declared
        if not attached.wait(10.0):
            raise TimeoutError("the embodiment's update loop did not start")
        print(f"ready embodiment {B_NAME} in mesh {args.mesh} on {args.listen} (zenoh id {body.transport.id})", flush=True)
        stop.wait()
    return 0


# --- probes (measuring process) ------------------------------------------------------------------


class RawPubSub:
    metric = "raw_pubsub"

    def __init__(self, session: zenoh.Session, tag: str) -> None:
        ping, pong, _ = raw_keys(tag)
        self.publisher = session.declare_publisher(ping, congestion_control=zenoh.CongestionControl.BLOCK)
        self.subscriber = session.declare_subscriber(pong, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        self.seq = 0

    def _put(self) -> None:
        self.seq += 1
        self.publisher.put(payload_text(self.seq).encode())

    def contact(self) -> None:
        answered = threading.Event()

        def receive() -> None:
            try:
                self.subscriber.handler.recv()
            except zenoh.ZError:
                return  # closed after a failed contact
            answered.set()

        threading.Thread(target=receive, name="raw-contact", daemon=True).start()
        retry_until(self._put, answered, timeout=20.0, what="raw pub/sub echo")

    def measure(self, count: int) -> list[float]:
        recv = self.subscriber.handler.recv
        out: list[float] = []
        for _ in range(count):
            self.seq += 1
            payload = payload_text(self.seq).encode()
            expect = self.seq
            t0 = time.perf_counter()
            self.publisher.put(payload)
            while seq_of(recv().payload.to_bytes()) != expect:
                pass  # a stale echo of a first-contact retry
            out.append((time.perf_counter() - t0) / 2)
        return out


class RawGet:
    metric = "raw_get"

    def __init__(self, session: zenoh.Session, tag: str) -> None:
        self.session = session
        self.key = raw_keys(tag)[2]

    def once(self) -> bool:
        got = 0
        for reply in self.session.get(self.key, timeout=5.0):
            ok = reply.ok
            if ok is not None and len(ok.payload.to_bytes()) == PAYLOAD_BYTES:
                got += 1
        return got == 1

    def contact(self) -> None:
        wait_for(self.once, 20.0, "raw queryable answering")

    def measure(self, count: int) -> list[float]:
        out: list[float] = []
        for _ in range(count):
            t0 = time.perf_counter()
            ok = self.once()
            out.append(time.perf_counter() - t0)
            if not ok:
                raise MeshError(f"{self.key}: no reply")
        return out


class Pinger(Component):
    """Raises ``ping`` and times the matching ``pong``; the next ping is raised from the pong handler."""

    def __init__(self) -> None:
        super().__init__(PINGER)
        self.seq = 0
        self.expect = -1
        self.remaining = 0
        self.t_sent = 0.0
        self.samples: list[float] = []
        self.done = threading.Event()
        self.answered = threading.Event()

    def ping(self) -> None:  # on the loop
        self.seq += 1
        self.raise_event("ping", payload_text(self.seq))

    def begin(self, count: int) -> None:  # on the loop
        self.samples = []
        self.remaining = count
        self._send()

    def _send(self) -> None:
        self.seq += 1
        self.expect = self.seq
        data = payload_text(self.seq)
        self.t_sent = time.perf_counter()
        self.raise_event("ping", data)

    def on_pong(self, event: Event) -> None:  # on the loop
        now = time.perf_counter()
        self.answered.set()
        if self.remaining <= 0 or not isinstance(event.data, str) or seq_of(event.data) != self.expect:
            return
        self.samples.append((now - self.t_sent) / 2)
        self.remaining -= 1
        if self.remaining:
            self._send()
        else:
            self.done.set()


class MeshEvents:
    metric = "mesh_event"

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self.pinger = Pinger()
        sim.add(self.pinger)
        sim.on_event(self.pinger.on_pong, embodiment=B_NAME, component=ECHO, event="pong")

    def contact(self) -> None:
        retry_until(lambda: self.sim.call(self.pinger.ping), self.pinger.answered, timeout=20.0, what="cmion event echo")

    def measure(self, count: int) -> list[float]:
        self.pinger.done.clear()
        self.sim.call(lambda: self.pinger.begin(count))
        # the caller's deadline bounds this; done is set by the loop after the last pong
        self.pinger.done.wait()
        return list(self.pinger.samples)


class MeshPropertyGet:
    metric = "mesh_property_get"

    def __init__(self, client: MeshClient) -> None:
        self.client = client

    def once(self) -> bool:
        prop = self.client.get_property(B_NAME, keys.BLACKBOARD, "", PROPERTY, timeout=5.0)
        return bool(prop.value == payload_text(0))

    def contact(self) -> None:
        def answered() -> bool:
            try:
                return self.once()
            except MeshError:
                return False

        wait_for(answered, 20.0, "cmion blackboard answering")

    def measure(self, count: int) -> list[float]:
        out: list[float] = []
        for _ in range(count):
            t0 = time.perf_counter()
            ok = self.once()
            out.append(time.perf_counter() - t0)
            if not ok:
                raise MeshError("property get returned an unexpected value")
        return out


class MeshSetProperty:
    metric = "mesh_set_property"

    def __init__(self, client: MeshClient) -> None:
        self.client = client
        self.seq = 0

    def once(self) -> str:
        self.seq += 1
        outcome = self.client.write(B_NAME, keys.BLACKBOARD, SetProperty("", WRITTEN, payload_text(self.seq)), timeout=5.0)
        return outcome.status

    def contact(self) -> None:
        wait_for(lambda: self.once() == "accepted", 20.0, "cmion set_property accepted")

    def measure(self, count: int) -> list[float]:
        out: list[float] = []
        for _ in range(count):
            t0 = time.perf_counter()
            status = self.once()
            out.append(time.perf_counter() - t0)
            if status != "accepted":
                raise MeshError(f"set_property: {status}")
        return out


# --- the benchmark -------------------------------------------------------------------------------


def metrics_for(groups: frozenset[str]) -> list[str]:
    wanted = {m for g in groups for m in GROUPS[g]}
    return [m for m in ORDER if m in wanted]


def log(text: str) -> None:
    print(f"  [core] {text}", flush=True)


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    from cmion_mesh.procs import unique_mesh

    metrics = metrics_for(groups)
    mesh = unique_mesh("bench")
    raw_ep, mesh_ep = loopback_endpoint(), loopback_endpoint()
    started = time.monotonic()
    with ExitStack() as stack:
        raw_child = start_child("bench.core", "serve-raw", "--listen", raw_ep, "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw_child)
        mesh_child = start_child("bench.core", "serve-mesh", "--listen", mesh_ep, "--mesh", mesh, "--peer", A_NAME,
                                 name="serve-mesh")
        stack.callback(stop_child, mesh_child)
        raw_child.wait_line("ready", 30.0)
        mesh_child.wait_line("ready", 30.0)
        log(f"children ready after {time.monotonic() - started:.2f} s (raw {raw_ep}, mesh {mesh_ep}, mesh name {mesh})")

        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        transport = ZenohTransport(loopback_config(connect=mesh_ep))
        stack.callback(transport.close)
        sim = Simulation(transport, mesh=mesh, embodiment=A_NAME).start()
        stack.callback(sim.close)
        client = MeshClient(transport, mesh)

        makers: dict[str, Callable[[], Any]] = {
            "raw_pubsub": lambda: RawPubSub(session, mesh),
            "mesh_event": lambda: MeshEvents(sim),
            "raw_get": lambda: RawGet(session, mesh),
            "mesh_property_get": lambda: MeshPropertyGet(client),
            "mesh_set_property": lambda: MeshSetProperty(client),
        }
        probes = [makers[m]() for m in metrics]
        pooled = interleaved(probes, samples=options.samples, warmup=options.warmup, rounds=options.rounds,
                             rewarm=options.rewarm, log=log)
        log(f"measured in {time.monotonic() - started:.1f} s")

    event_wire = len(encode(Event(A_NAME, PINGER, "ping", payload_text(1), 1, time.time())))
    wire = {"raw_pubsub": PAYLOAD_BYTES, "mesh_event": event_wire, "raw_get": PAYLOAD_BYTES}
    rows = [
        Row(m, LABELS[m], summarize(pooled[m]), extra={"rounds": options.rounds, "payload_bytes": PAYLOAD_BYTES,
                                                       **({"wire_bytes": wire[m]} if m in wire else {})})
        for m in metrics
    ]
    compare(rows, PAIRS, None)  # targets: bench.targets
    return rows


# --- command line of the children ---------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.core", description="child processes of the core benchmark")
    sub = parser.add_subparsers(dest="command", required=True)
    raw = sub.add_parser("serve-raw", help="a raw zenoh echo subscriber and queryable")
    raw.add_argument("--listen", required=True)
    raw.add_argument("--tag", required=True, help="key prefix bench/<tag>/raw")
    raw.add_argument("--parent", type=int)
    mesh = sub.add_parser("serve-mesh", help="a cmion embodiment with an echo component")
    mesh.add_argument("--listen", required=True)
    mesh.add_argument("--mesh", required=True)
    mesh.add_argument("--peer", required=True, help="the embodiment whose pings to echo")
    mesh.add_argument("--parent", type=int)
    args = parser.parse_args(argv)
    if args.command == "serve-raw":
        return serve_raw(args)
    return serve_mesh(args)


if __name__ == "__main__":
    sys.exit(main())
