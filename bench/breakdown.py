"""Where the time goes: per-hop timestamps of an event echo and a set request, vs raw zenoh.

A diagnostic, not a score: ``python -m bench --only breakdown`` (not run by default). It runs the
same ping-pongs as ``bench.core`` with one child (raw echo + embodiment ``bench-b``) and wraps,
in both processes, the cmion methods each message passes through so that every thread hop is
timestamped. ``time.perf_counter_ns`` is ``CLOCK_MONOTONIC`` on Linux, one clock for all
processes, so cross-process differences are meaningful. The child's records are fetched at the
end with a plain zenoh get. The wrappers cost a few microseconds per hop (extra clock reads):
compare segments with each other, not the totals with ``bench.core``.

The path of a cmion event, per direction::

    raise_event (loop) -> encode + publish -> wire -> zenoh rx -> FifoChannel -> subscriber worker
    -> decode + inbox.put -> loop thread wakes (queue.get) -> _update -> handler

and of a raw one: ``put -> wire -> zenoh rx -> FifoChannel -> worker (or the caller's recv)``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import zenoh

from bench.core import (
    A_NAME,
    B_NAME,
    CHANNEL_CAPACITY,
    ECHO,
    PROPERTY,
    Echo,
    MeshEvents,
    MeshSetProperty,
    Pinger,
    RawGet,
    RawPubSub,
    close_raw,
    open_session,
    payload_text,
    raw_keys,
    seq_of,
)
from bench.harness import (
    StopSignal,
    loopback_config,
    loopback_endpoint,
    start_child,
    stop_child,
    with_deadline,
)
from bench.registry import Options, Row
from bench.stats import summarize
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import Event, SetProperty
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.storage import Store
from cmion_mesh.transport import zenoh as zenoh_transport
from cmion_mesh.transport.base import Sample
from cmion_mesh.transport.zenoh import ZenohTransport

ns = time.perf_counter_ns


@dataclass
class Book:
    """Timestamps of the message in flight (traffic is strictly one at a time) and the records."""

    channel_out: int = 0  # the transport's worker got the sample/query from its FifoChannel
    worker_in: int = 0  # cmion's handler (Simulation._on_remote_events/_on_query) entered
    worker_out: int = 0
    update_in: int = 0
    handle_in: int = 0
    events: list[dict[str, int]] = field(default_factory=list)
    requests: list[dict[str, int]] = field(default_factory=list)
    raw_echo: list[list[int]] = field(default_factory=list)
    raw_get: list[list[int]] = field(default_factory=list)


BOOK = Book()


def instrument() -> None:
    """Wrap the cmion methods on a message's path (class-level: only this process's objects)."""
    on_events = Simulation._on_remote_events
    on_query = Simulation._on_query
    update = Simulation._update
    handle = Store.handle_requests
    send = IncomingRequest._send
    query_init = zenoh_transport._Query.__init__
    make_sample, sample_of = zenoh_transport._sample, zenoh_transport._sample_of

    def traced_sample(sample: Any) -> Sample:
        BOOK.channel_out = ns()
        return make_sample(sample)

    def traced_sample_of(key: str) -> Any:  # subscriptions on one concrete key convert with this
        convert = sample_of(key)

        def traced(sample: Any) -> Sample:
            BOOK.channel_out = ns()
            return convert(sample)

        return traced

    def traced_query_init(self: Any, query: Any) -> None:
        BOOK.channel_out = ns()
        query_init(self, query)

    def traced_events(self: Simulation, sub: Any, batch: Any) -> None:
        BOOK.worker_in = ns()
        on_events(self, sub, batch)
        BOOK.worker_out = ns()

    def traced_query(self: Simulation, component: Any, query: Any) -> None:
        BOOK.worker_in = ns()
        on_query(self, component, query)
        BOOK.worker_out = ns()

    def traced_update(self: Simulation, items: list[Any]) -> None:
        BOOK.update_in = ns()
        update(self, items)

    def traced_handle(self: Store, batch: list[IncomingRequest]) -> None:
        BOOK.handle_in = ns()
        handle(self, batch)
        if BOOK.requests:
            BOOK.requests[-1]["handle_out"] = ns()  # after the post-reply work: publish + PropertyChanged

    def traced_send(self: IncomingRequest, outcome: Any) -> None:
        t_in = ns()
        send(self, outcome)
        value = getattr(self.payload, "value", "")
        BOOK.requests.append({"seq": seq_of(value) if isinstance(value, str) else -1, "channel_out": BOOK.channel_out,
                              "worker_in": BOOK.worker_in, "worker_out": BOOK.worker_out, "update_in": BOOK.update_in,
                              "handle_in": BOOK.handle_in, "send_in": t_in, "send_out": ns()})

    Simulation._on_remote_events = traced_events  # type: ignore[method-assign]
    Simulation._on_query = traced_query  # type: ignore[method-assign]
    Simulation._update = traced_update  # type: ignore[method-assign]
    Store.handle_requests = traced_handle  # type: ignore[method-assign]
    IncomingRequest._send = traced_send  # type: ignore[method-assign]
    zenoh_transport._sample = traced_sample
    zenoh_transport._sample_of = traced_sample_of
    zenoh_transport._Query.__init__ = traced_query_init  # type: ignore[method-assign]


class TracedEcho(Echo):
    def on_ping(self, event: Event) -> None:
        t_handler = ns()
        rec = {"seq": seq_of(event.data), "channel_out": BOOK.channel_out, "worker_in": BOOK.worker_in,
               "worker_out": BOOK.worker_out, "update_in": BOOK.update_in, "handler": t_handler, "raise": ns()}
        self.raise_event("pong", event.data)
        rec["raised"] = ns()
        BOOK.events.append(rec)


# --- the child ------------------------------------------------------------------------------------


def serve(args: argparse.Namespace) -> int:
    stop = StopSignal(args.parent)
    instrument()
    ping, pong, get = raw_keys(args.tag)
    reply = payload_text(0).encode()
    session = open_session(loopback_config(listen=args.listen))
    entities: list[Any] = []
    workers: list[threading.Thread] = []
    try:
        publisher = session.declare_publisher(pong, congestion_control=zenoh.CongestionControl.BLOCK)
        subscriber = session.declare_subscriber(ping, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        queryable = session.declare_queryable(get, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        book_q = session.declare_queryable(f"bench/{args.tag}/book")
        entities += [publisher, subscriber, queryable, book_q]

        def echo() -> None:
            while True:
                try:
                    sample = subscriber.handler.recv()
                except zenoh.ZError:
                    return
                t_in = ns()
                data = sample.payload.to_bytes()
                publisher.put(data)
                BOOK.raw_echo.append([seq_of(data), t_in, ns()])

        def answer() -> None:
            while True:
                try:
                    query = queryable.handler.recv()
                except zenoh.ZError:
                    return
                t_in = ns()
                with query:
                    query.reply(get, reply)
                BOOK.raw_get.append([t_in, ns()])

        def book() -> None:
            while True:
                try:
                    query = book_q.handler.recv()
                except zenoh.ZError:
                    return
                with query:
                    query.reply(query.key_expr, json.dumps(BOOK.__dict__))

        for fn in (echo, answer, book):
            workers.append(threading.Thread(target=fn, daemon=True))
            workers[-1].start()
        with Embodiment(B_NAME, mesh=args.mesh, transport_config=loopback_config(listen=args.mesh_listen)) as body:
            body.blackboard.apply_now(SetProperty("", PROPERTY, payload_text(0)))
            body.add(TracedEcho(args.peer))
            attached = threading.Event()
            body.sim.call(attached.set)
            if not attached.wait(10.0):
                raise TimeoutError("the embodiment's update loop did not start")
            print("ready", flush=True)
            stop.wait()
    finally:
        close_raw(session, entities, workers)
    return 0


# --- the measuring side ---------------------------------------------------------------------------


class TracedPinger(Pinger):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[dict[str, int]] = []
        self._t0 = 0
        self._t_raised = 0

    def _send(self) -> None:
        self.seq += 1
        self.expect = self.seq
        data = payload_text(self.seq)
        self.t_sent = time.perf_counter()
        self._t0 = ns()
        self.raise_event("ping", data)
        self._t_raised = ns()

    def on_pong(self, event: Event) -> None:
        t_handler = ns()
        if self.remaining > 0 and isinstance(event.data, str) and seq_of(event.data) == self.expect:
            self.records.append({"seq": self.expect, "raise": self._t0, "raised": self._t_raised,
                                 "channel_out": BOOK.channel_out, "worker_in": BOOK.worker_in, "worker_out": BOOK.worker_out,
                                 "update_in": BOOK.update_in, "handler": t_handler})
        super().on_pong(event)


class TracedMeshEvents(MeshEvents):
    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self.traced = TracedPinger()
        self.pinger = self.traced
        sim.add(self.pinger)
        sim.on_event(self.pinger.on_pong, embodiment=B_NAME, component=ECHO, event="pong")


class TracedRawPubSub(RawPubSub):
    records: list[list[int]]

    def measure(self, count: int) -> list[float]:
        if not hasattr(self, "records"):
            self.records = []
        recv = self.subscriber.handler.recv
        out: list[float] = []
        for _ in range(count):
            self.seq += 1
            payload = payload_text(self.seq).encode()
            t0 = ns()
            self.publisher.put(payload)
            t_put = ns()
            while seq_of(recv().payload.to_bytes()) != self.seq:
                pass
            t_recv = ns()
            self.records.append([self.seq, t0, t_put, t_recv])
            out.append((t_recv - t0) / 2e9)
        return out


class TracedSet(MeshSetProperty):
    records: list[list[int]]

    def __init__(self, client: MeshClient, transport: ZenohTransport) -> None:
        super().__init__(client)
        self.records = []
        self.t_get_in = 0
        self.t_get_done = 0
        get = transport.get

        def traced_get(selector: str, payload: bytes | None = None, *, timeout: float = 10.0) -> Any:
            self.t_get_in = ns()
            replies = get(selector, payload, timeout=timeout)
            self.t_get_done = ns()
            return replies

        transport.get = traced_get  # type: ignore[method-assign]

    def measure(self, count: int) -> list[float]:
        out: list[float] = []
        for _ in range(count):
            t0 = ns()
            status = self.once()
            t_end = ns()
            if status != "accepted":
                raise RuntimeError(status)
            self.records.append([self.seq, t0, self.t_get_in, self.t_get_done, t_end])
            out.append((t_end - t0) / 1e9)
        return out


class TracedRawGet(RawGet):
    records: list[list[int]]

    def measure(self, count: int) -> list[float]:
        if not hasattr(self, "records"):
            self.records = []
        out: list[float] = []
        for _ in range(count):
            t0 = ns()
            self.once()
            t_end = ns()
            self.records.append([t0, t_end])
            out.append((t_end - t0) / 1e9)
        return out


def _segments(pairs: dict[str, list[float]]) -> list[Row]:
    return [Row(name, name, summarize([v / 1e9 for v in values])) for name, values in pairs.items() if values]


def analyse(a_events: list[dict[str, int]], b_events: list[dict[str, int]], a_raw: list[list[int]], b_raw: list[list[int]],
            a_set: list[list[int]], b_set: list[dict[str, int]], a_get: list[list[int]], b_get: list[list[int]]) -> list[Row]:
    seg: dict[str, list[float]] = {}

    def add(name: str, value: int) -> None:
        seg.setdefault(name, []).append(float(value))

    b_by_seq = {r[0]: r for r in b_raw}
    for seq, t0, t_put, t_recv in a_raw:
        b = b_by_seq.get(seq)
        if b is None:
            continue
        _, b_in, b_out = b
        add("raw ev: A put() call", t_put - t0)
        add("raw ev: A put -> B worker has sample", b_in - t0)
        add("raw ev: B put() call", b_out - b_in)
        add("raw ev: B worker has sample -> A recv returns", t_recv - b_in)
        add("raw ev: one-way (RTT/2)", (t_recv - t0) // 2)
    b_ev = {r["seq"]: r for r in b_events}
    for a in a_events:
        be = b_ev.get(a["seq"])
        if be is None:
            continue
        add("ev: A raise_event() call (encode+publish)", a["raised"] - a["raise"])
        add("ev: A raise -> B transport worker has sample", be["channel_out"] - a["raise"])
        add("ev: B transport worker: wrap Sample", be["worker_in"] - be["channel_out"])
        add("ev: B worker decode + inbox.put", be["worker_out"] - be["worker_in"])
        add("ev: B inbox.put -> loop _update starts (wakeup)", be["update_in"] - be["worker_out"])
        add("ev: B _update -> handler", be["handler"] - be["update_in"])
        add("ev: B raise_event() call (encode+publish)", be["raised"] - be["raise"])
        add("ev: B raise -> A transport worker has sample", a["channel_out"] - be["raise"])
        add("ev: A transport worker: wrap Sample", a["worker_in"] - a["channel_out"])
        add("ev: A worker decode + inbox.put", a["worker_out"] - a["worker_in"])
        add("ev: A inbox.put -> loop _update starts (wakeup)", a["update_in"] - a["worker_out"])
        add("ev: A _update -> handler", a["handler"] - a["update_in"])
        add("ev: one-way (RTT/2)", (a["handler"] - a["raise"]) // 2)
    for (t0, t_end), (b_in, b_out) in zip(a_get, b_get[-len(a_get):], strict=False):
        add("raw get: A get -> B worker has query", b_in - t0)
        add("raw get: B reply + finalize", b_out - b_in)
        add("raw get: B finalized -> A has reply", t_end - b_out)
        add("raw get: round trip", t_end - t0)
    b_rq = {r["seq"]: r for r in b_set if "handle_out" in r}
    for seq, t0, t_get_in, t_get, t_end in a_set:
        br = b_rq.get(seq)
        if br is None:
            continue
        add("set: A client.write -> transport.get (key, encode)", t_get_in - t0)
        add("set: A transport.get -> B transport worker has query", br["channel_out"] - t_get_in)
        add("set: B transport worker: wrap query", br["worker_in"] - br["channel_out"])
        add("set: B worker decode + inbox.put", br["worker_out"] - br["worker_in"])
        add("set: B inbox.put -> loop _update starts (wakeup)", br["update_in"] - br["worker_out"])
        add("set: B _update -> handle_requests", br["handle_in"] - br["update_in"])
        add("set: B handle_requests -> accept() (apply)", br["send_in"] - br["handle_in"])
        add("set: B accept(): encode Outcome + reply + finalize", br["send_out"] - br["send_in"])
        add("set: B finalized -> A transport.get returns", t_get - br["send_out"])
        add("set: A decode Outcome", t_end - t_get)
        add("set: B after reply: publish + PropertyChanged event", br["handle_out"] - br["send_out"])
        add("set: round trip", t_end - t0)
    return _segments(seg)


def log(text: str) -> None:
    print(f"  [breakdown] {text}", flush=True)


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    from cmion_mesh.procs import unique_mesh

    instrument()
    mesh = unique_mesh("bench")
    raw_ep, mesh_ep = loopback_endpoint(), loopback_endpoint()
    with ExitStack() as stack:
        child = start_child("bench.breakdown", "serve", "--listen", raw_ep, "--mesh-listen", mesh_ep, "--mesh", mesh,
                            "--peer", A_NAME, "--tag", mesh, name="breakdown")
        stack.callback(stop_child, child)
        child.wait_line("ready", 30.0)
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        transport = ZenohTransport(loopback_config(connect=mesh_ep))
        stack.callback(transport.close)
        sim = Simulation(transport, mesh=mesh, embodiment=A_NAME).start()
        stack.callback(sim.close)
        client = MeshClient(transport, mesh)
        raw, get = TracedRawPubSub(session, mesh), TracedRawGet(session, mesh)
        events, sets = TracedMeshEvents(sim), TracedSet(client, transport)
        probes: Sequence[Any] = (raw, events, get, sets)
        for p in probes:
            with_deadline(p.contact, 30.0, f"{p.metric} contact")
            with_deadline(partial(p.measure, options.warmup), 60.0, f"{p.metric} warm-up")
        raw.records.clear()
        events.traced.records.clear()
        get.records.clear()
        sets.records.clear()
        for _ in range(options.rounds):
            for p in probes:
                with_deadline(partial(p.measure, max(1, options.samples // options.rounds)), 60.0, p.metric)
        log("fetching the child's timestamps")
        book: dict[str, Any] = {}
        for reply in session.get(f"bench/{mesh}/book", timeout=10.0):
            if reply.ok is not None:
                book = json.loads(reply.ok.payload.to_bytes())
        if not book:
            raise RuntimeError("the child did not return its timestamps")
    return analyse(events.traced.records, book["events"], raw.records, book["raw_echo"], sets.records, book["requests"],
                   get.records, book["raw_get"])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.breakdown")
    sub = parser.add_subparsers(dest="command", required=True)
    srv = sub.add_parser("serve")
    srv.add_argument("--listen", required=True)
    srv.add_argument("--mesh-listen", required=True)
    srv.add_argument("--mesh", required=True)
    srv.add_argument("--peer", required=True)
    srv.add_argument("--tag", required=True)
    srv.add_argument("--parent", type=int)
    args = parser.parse_args(argv)
    return serve(args)


if __name__ == "__main__":
    sys.exit(main())
