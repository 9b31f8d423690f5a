"""Growth curve (a): sustained event throughput against the number of subscriber processes.

One publisher process and ``max(groups)`` subscriber processes, all on loopback. The publisher
holds a raw zenoh session and a cmion ``Simulation`` (embodiment ``fan-pub``, component ``src``);
each subscriber holds a raw zenoh session and a cmion ``Simulation`` of its own. Subscriber ``i``
takes part in the runs with ``k > i`` subscribers: for raw zenoh it subscribes to
``bench/<tag>/raw/burst<k>`` (a ``FifoChannel`` drained by a thread, as in ``bench.core``), for
cmion it handles ``fan-pub/src/burst<k>`` on its update loop (``sim.on_event``).

A run: the measuring process asks the publisher (a query to its control queryable) for a burst
of ``count`` events on group ``k``, published back to back as fast as the publisher can
(``CongestionControl.BLOCK``: a slow subscriber slows the publisher down rather than losing
anything), then an end marker. Each event carries its sequence number (64 bytes of data, as in
``bench.core``); every subscriber checks that it got each number exactly once and in order and
prints a line at the end marker. Throughput = ``count`` / (last event received by the slowest
subscriber - first publish), on ``CLOCK_MONOTONIC``, shared by all processes. A run that loses or
reorders an event is reported as a failure.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import threading
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

import zenoh

from bench.core import CHANNEL_CAPACITY, _drain, close_raw, open_session, payload_text, seq_of
from bench.harness import StopSignal, loopback_config, loopback_endpoint, start_child, stop_child
from bench.stats import Summary, summarize
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event
from cmion_mesh.procs import Daemon
from cmion_mesh.transport.zenoh import ZenohTransport

PUB = "fan-pub"
SOURCE = "src"
DONE = re.compile(r"done kind=(\S+) group=(\d+) id=(\S+) received=(\d+) missing=(\d+) reordered=(\d+) first=(\d+) last=(\d+)")


def raw_key(tag: str, group: int) -> str:
    return f"bench/{tag}/raw/burst{group}"


def control_key(tag: str) -> str:
    return f"bench/{tag}/ctl/burst"


# --- publisher -----------------------------------------------------------------------------------


class Source(Component):
    def __init__(self) -> None:
        super().__init__(SOURCE)

    def burst(self, group: int, count: int, burst_id: str, done: threading.Event, times: list[int]) -> None:  # on the loop
        name = f"burst{group}"
        times.append(time.perf_counter_ns())
        for seq in range(1, count + 1):
            self.raise_event(name, payload_text(seq))
        self.raise_event(name, {"end": burst_id})
        times.append(time.perf_counter_ns())
        done.set()


def serve_pub(args: argparse.Namespace) -> int:
    stop = StopSignal(args.parent)
    session = open_session(loopback_config(listen=args.raw_listen))
    transport = ZenohTransport(loopback_config(listen=args.mesh_listen))
    sim = Simulation(transport, mesh=args.mesh, embodiment=PUB).start()
    source = Source()
    sim.add(source)
    publishers: dict[int, zenoh.Publisher] = {}
    entities: list[Any] = []
    workers: list[threading.Thread] = []

    def raw_burst(group: int, count: int, burst_id: str) -> list[int]:
        pub = publishers.get(group)
        if pub is None:
            pub = publishers[group] = session.declare_publisher(raw_key(args.tag, group),
                                                                congestion_control=zenoh.CongestionControl.BLOCK)
            entities.append(pub)
        t0 = time.perf_counter_ns()
        for seq in range(1, count + 1):
            pub.put(payload_text(seq).encode())
        pub.put(f"end:{burst_id}".encode())
        return [t0, time.perf_counter_ns()]

    def answer(query: zenoh.Query) -> None:
        with query:
            request = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
            group, count, burst_id = int(request["group"]), int(request["count"]), str(request["id"])
            if request["kind"] == "raw":
                times = raw_burst(group, count, burst_id)
            else:
                done = threading.Event()
                times = []
                sim.call(lambda: source.burst(group, count, burst_id, done, times))
                done.wait(120.0)
            query.reply(control_key(args.tag), json.dumps({"t_start": times[0], "t_end": times[-1]}).encode())

    try:
        control = session.declare_queryable(control_key(args.tag), zenoh.handlers.FifoChannel(16))
        entities.append(control)
        workers.append(_drain("control", control.handler.recv, answer))
        print(f"ready publisher raw {args.raw_listen} mesh {args.mesh_listen}", flush=True)
        stop.wait()
    finally:
        sim.close()
        transport.close()
        close_raw(session, entities, workers)
    return 0


# --- subscribers ---------------------------------------------------------------------------------


@dataclass
class Tracker:
    """Sequence checking for one (kind, group) at one subscriber."""

    kind: str
    group: int
    expected: int = 1
    received: int = 0
    missing: int = 0
    reordered: int = 0
    first: int = 0
    last: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_seq(self, seq: int) -> None:
        now = time.perf_counter_ns()
        if not self.received:
            self.first = now
        self.received += 1
        self.last = now
        if seq == self.expected:
            self.expected += 1
        elif seq > self.expected:
            self.missing += seq - self.expected
            self.expected = seq + 1
        else:
            self.reordered += 1

    def on_end(self, burst_id: str) -> None:
        print(f"done kind={self.kind} group={self.group} id={burst_id} received={self.received} missing={self.missing} "
              f"reordered={self.reordered} first={self.first} last={self.last}", flush=True)
        self.expected, self.received, self.missing, self.reordered, self.first, self.last = 1, 0, 0, 0, 0, 0


def serve_sub(args: argparse.Namespace) -> int:
    stop = StopSignal(args.parent)
    groups = [int(g) for g in args.groups.split(",") if int(g) > args.index]
    session = open_session(loopback_config(connect=args.raw_connect))
    transport = ZenohTransport(loopback_config(connect=args.mesh_connect))
    sim = Simulation(transport, mesh=args.mesh, embodiment=f"fan-sub{args.index}").start()
    entities: list[Any] = []
    workers: list[threading.Thread] = []
    try:
        for group in groups:
            raw = Tracker("raw", group)
            mesh = Tracker("mesh", group)

            def on_raw(sample: zenoh.Sample, tracker: Tracker = raw) -> None:
                data = sample.payload.to_bytes()
                if data.startswith(b"end:"):
                    tracker.on_end(data[4:].decode())
                else:
                    tracker.on_seq(seq_of(data))

            def on_mesh(event: Event, tracker: Tracker = mesh) -> None:
                if isinstance(event.data, dict):
                    tracker.on_end(str(event.data.get("end")))
                elif isinstance(event.data, str):
                    tracker.on_seq(seq_of(event.data))

            subscriber = session.declare_subscriber(raw_key(args.tag, group), zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
            entities.append(subscriber)
            workers.append(_drain(f"raw{group}", subscriber.handler.recv, on_raw))
            sim.on_event(on_mesh, embodiment=PUB, component=SOURCE, event=f"burst{group}")
        ready = threading.Event()
        sim.call(ready.set)
        ready.wait(10.0)
        print(f"ready subscriber {args.index} groups {groups}", flush=True)
        stop.wait()
    finally:
        sim.close()
        transport.close()
        close_raw(session, entities, workers)
    return 0


# --- the measurement (measuring process) ----------------------------------------------------------


@dataclass
class Result:
    kind: str
    group: int
    rates: list[float] = field(default_factory=list)  # events/s per run
    lost: int = 0
    reordered: int = 0

    def summary(self) -> Summary:
        return summarize(self.rates, 1.0)


def log(text: str) -> None:
    print(f"  [fanout] {text}", flush=True)


def measure(mesh_name: str, groups: Sequence[int], count: int, rounds: int) -> list[Result]:
    tag = mesh_name
    raw_ep, mesh_ep = loopback_endpoint(), loopback_endpoint()
    results = {(kind, g): Result(kind, g) for g in groups for kind in ("raw", "mesh")}
    ids = iter(range(1, 1_000_000))
    with ExitStack() as stack:
        pub = start_child("bench.fanout", "pub", "--raw-listen", raw_ep, "--mesh-listen", mesh_ep, "--mesh", mesh_name,
                          "--tag", tag, name="fan-pub")
        stack.callback(stop_child, pub)
        pub.wait_line("ready", 30.0)
        subs: list[Daemon] = []
        for i in range(max(groups)):
            sub = start_child("bench.fanout", "sub", "--index", str(i), "--raw-connect", raw_ep, "--mesh-connect", mesh_ep,
                              "--mesh", mesh_name, "--tag", tag, "--groups", ",".join(map(str, groups)), name=f"fan-sub{i}")
            stack.callback(stop_child, sub)
            subs.append(sub)
        for sub in subs:
            sub.wait_line("ready", 60.0)
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)

        def burst(kind: str, group: int, n: int, timeout: float = 120.0) -> tuple[str, int]:
            burst_id = f"b{next(ids)}"
            request = json.dumps({"kind": kind, "group": group, "count": n, "id": burst_id}).encode()
            replies = [r.ok.payload.to_bytes() for r in session.get(control_key(tag), payload=request, timeout=timeout)
                       if r.ok is not None]
            if not replies:
                raise TimeoutError(f"publisher did not answer the burst {burst_id}")
            return burst_id, int(json.loads(replies[0])["t_start"])

        def done_lines(burst_id: str, group: int, timeout: float) -> list[re.Match[str]]:
            out = []
            for sub in subs[:group]:
                line = sub.wait_line(f"id={burst_id} ", timeout)
                match = DONE.search(line)
                assert match is not None, line
                out.append(match)
            return out

        for group in groups:
            for kind in ("raw", "mesh"):
                for _attempt in range(10):  # until every subscription has reached the publisher
                    burst_id, _ = burst(kind, group, 100)
                    try:
                        got = done_lines(burst_id, group, 5.0)
                    except TimeoutError:
                        continue
                    if all(int(m.group(4)) == 100 for m in got):
                        break
                else:
                    raise TimeoutError(f"{kind} group {group}: subscribers never all received a warm-up burst")
        log(f"{max(groups)} subscriber processes ready; {rounds} round(s) of {count} events per run")
        for r in range(rounds):
            for group in groups:
                for kind in ("raw", "mesh"):
                    burst_id, t_start = burst(kind, group, count)
                    got = done_lines(burst_id, group, 120.0)
                    last = max(int(m.group(8)) for m in got)
                    result = results[(kind, group)]
                    result.rates.append(count / ((last - t_start) / 1e9))
                    result.lost += sum(int(m.group(5)) + max(0, count - int(m.group(4))) for m in got)
                    result.reordered += sum(int(m.group(6)) for m in got)
            log(f"round {r + 1}/{rounds} done")
    return list(results.values())


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.fanout", description="child processes of the fan-out curve")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pub")
    p.add_argument("--raw-listen", required=True)
    p.add_argument("--mesh-listen", required=True)
    p.add_argument("--mesh", required=True)
    p.add_argument("--tag", required=True)
    p.add_argument("--parent", type=int)
    s = sub.add_parser("sub")
    s.add_argument("--index", type=int, required=True)
    s.add_argument("--raw-connect", required=True)
    s.add_argument("--mesh-connect", required=True)
    s.add_argument("--mesh", required=True)
    s.add_argument("--tag", required=True)
    s.add_argument("--groups", required=True)
    s.add_argument("--parent", type=int)
    args = parser.parse_args(argv)
    return serve_pub(args) if args.command == "pub" else serve_sub(args)


if __name__ == "__main__":
    sys.exit(main())
