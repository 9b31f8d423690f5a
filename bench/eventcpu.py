"""What an event costs in CPU, per thread, vs raw zenoh: a diagnostic that load does not skew.

``python -m bench --only eventcpu`` (not run by default). Latency and throughput on a shared
machine move with whatever else runs (a woken thread waits for a core); the CPU time a thread
spends on each event does not, or far less. Two sessions in this process, linked over loopback:
a ``Simulation`` raising ``count`` events back to back on its loop (``fan-out``'s publisher) and
another one handling them on its loop (``sim.on_event``), against a raw declared publisher
(``CongestionControl.BLOCK``) and a raw ``FifoChannel`` subscriber drained by a thread, on the
same link. Each thread's CPU clock (``pthread_getcpuclockid``) is read before and after a burst;
the rows are CPU microseconds per event, one sample per burst (``--rounds`` bursts, raw and cmion
alternating). Every event is checked to arrive once and in order.

Only compare rows of one run: the absolute figures depend on the processor.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from functools import partial

import zenoh

from bench.core import CHANNEL_CAPACITY, payload_text, seq_of
from bench.harness import loopback_config, loopback_endpoint
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.zenoh import ZenohTransport

PUB, SUB, SOURCE, NAME = "cpu-pub", "cpu-sub", "src", "e"


def log(text: str) -> None:
    print(f"  [eventcpu] {text}", flush=True)


def cpu_clock(thread: threading.Thread) -> Callable[[], float]:
    """Seconds of CPU ``thread`` has used so far (readable from any thread)."""
    if thread.ident is None:
        raise RuntimeError(f"thread {thread.name} has not started")
    clock = time.pthread_getcpuclockid(thread.ident)
    return lambda: time.clock_gettime(clock)


def thread_named(name: str) -> threading.Thread:
    found = [t for t in threading.enumerate() if t.name == name]
    if len(found) != 1:
        raise RuntimeError(f"expected one thread named {name!r}, found {len(found)}")
    return found[0]


class Source(Component):
    def burst(self, count: int, done: threading.Event) -> None:  # on the loop
        for seq in range(1, count + 1):
            self.raise_event(NAME, payload_text(seq))
        done.set()


class Counter:
    """Checks that sequence numbers arrive once each, in order; ``done`` at ``expected``."""

    def __init__(self) -> None:
        self.next = 1
        self.expected = 0
        self.wrong = 0
        self.done = threading.Event()

    def reset(self, count: int) -> None:
        self.next, self.expected, self.wrong = 1, count, 0
        self.done.clear()

    def on_seq(self, seq: int) -> None:
        if seq != self.next:
            self.wrong += 1
        self.next = seq + 1
        if seq == self.expected:
            self.done.set()


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    from cmion_mesh.procs import unique_mesh

    count = 5_000 if options.quick else 20_000
    rounds = max(3, options.rounds)
    mesh = unique_mesh("bench")
    endpoint = loopback_endpoint()
    raw_key = f"bench/{mesh}/raw/cpu"
    samples: dict[str, list[float]] = {k: [] for k in ("raw_pub", "raw_sub", "pub", "worker", "loop")}
    failures: list[str] = []
    with ExitStack() as stack:
        t_pub = stack.enter_context(ZenohTransport(loopback_config(listen=endpoint)))
        t_sub = stack.enter_context(ZenohTransport(loopback_config(connect=endpoint)))
        pub_sim = stack.enter_context(Simulation(t_pub, mesh=mesh, embodiment=PUB))
        sub_sim = stack.enter_context(Simulation(t_sub, mesh=mesh, embodiment=SUB))
        source = Source(SOURCE)
        pub_sim.add(source)
        mesh_counter, raw_counter = Counter(), Counter()

        def on_event(event: Event) -> None:
            if isinstance(event.data, str):
                mesh_counter.on_seq(seq_of(event.data))

        sub_sim.on_event(on_event, embodiment=PUB, component=SOURCE, event=NAME)
        # the raw side on the same two sessions and link (the adapter's own session: a diagnostic)
        raw_sub = t_sub._session.declare_subscriber(raw_key, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        stack.callback(raw_sub.undeclare)
        raw_pub = t_pub._session.declare_publisher(raw_key, congestion_control=zenoh.CongestionControl.BLOCK)
        stack.callback(raw_pub.undeclare)

        def drain() -> None:
            while True:
                try:
                    sample = raw_sub.handler.recv()
                except zenoh.ZError:
                    return  # undeclared
                raw_counter.on_seq(seq_of(sample.payload.to_bytes()))

        raw_thread = threading.Thread(target=drain, name="eventcpu-raw", daemon=True)
        raw_thread.start()
        stack.callback(raw_thread.join, 5.0)

        def linked() -> bool:  # both subscriptions reached from the other session
            mesh_counter.reset(1)
            raw_counter.reset(1)
            pub_sim.call(lambda: source.raise_event(NAME, payload_text(1)))
            raw_pub.put(payload_text(1).encode())
            return mesh_counter.done.wait(0.2) and raw_counter.done.wait(0.2)

        wait_for(linked, 20.0, "the two sessions linked")
        # The subscriber session's dispatch thread (one per session: ``transport/inbox.py``) decodes
        # and hands over; zenoh's own callback thread only queues the sample (not measured here).
        dispatch = t_sub._dispatch.thread
        if dispatch is None:
            raise RuntimeError("the subscriber session's dispatch thread has not started")
        clocks = {"pub": cpu_clock(thread_named(f"ion-{PUB}")), "worker": cpu_clock(dispatch),
                  "loop": cpu_clock(thread_named(f"ion-{SUB}")), "raw_sub": cpu_clock(raw_thread)}
        for i in range(rounds + 1):  # the first round warms up
            raw_counter.reset(count)
            before_sub, before_pub = clocks["raw_sub"](), time.thread_time()
            for seq in range(1, count + 1):
                raw_pub.put(payload_text(seq).encode())
            raw_pub_cpu = time.thread_time() - before_pub
            if not raw_counter.done.wait(60.0):
                raise RuntimeError(f"raw burst: {raw_counter.next - 1} of {count} events arrived")
            raw_sub_cpu = clocks["raw_sub"]() - before_sub
            mesh_counter.reset(count)
            sent = threading.Event()
            before = {k: clocks[k]() for k in ("pub", "worker", "loop")}
            pub_sim.call(partial(source.burst, count, sent))
            if not (sent.wait(60.0) and mesh_counter.done.wait(60.0)):
                raise RuntimeError(f"cmion burst: {mesh_counter.next - 1} of {count} events arrived")
            spent = {k: clocks[k]() - before[k] for k in before}
            for counter, kind in ((raw_counter, "raw"), (mesh_counter, "cmion")):
                if counter.wrong:
                    failures.append(f"{kind} round {i}: {counter.wrong} events lost or out of order")
            if i == 0:
                continue
            samples["raw_pub"].append(raw_pub_cpu / count)
            samples["raw_sub"].append(raw_sub_cpu / count)
            for k, v in spent.items():
                samples[k].append(v / count)
            log(f"round {i}/{rounds}: {count} events each")
    us = 1e6

    def row(metric: str, label: str, key: str) -> Row:
        return Row(metric, label, summarize(samples[key], us), unit="us", failures=list(failures))

    both = [w + lp for w, lp in zip(samples["worker"], samples["loop"], strict=True)]
    samples["sub"] = both
    rows = [
        row("cpu_raw_pub", "raw zenoh publisher: put, CPU per event", "raw_pub"),
        row("cpu_pub", "cmion publisher loop: raise_event (+ local dispatch), CPU per event", "pub"),
        row("cpu_raw_sub", "raw zenoh subscriber thread, CPU per event", "raw_sub"),
        row("cpu_sub_worker", "cmion subscriber: the session's dispatch thread (decode, hand-over), CPU per event", "worker"),
        row("cpu_sub_loop", "cmion subscriber: update loop (dispatch, handler), CPU per event", "loop"),
        row("cpu_sub", "cmion subscriber: both threads, CPU per event", "sub"),
    ]
    compare(rows, {"cpu_pub": "cpu_raw_pub", "cpu_sub": "cpu_raw_sub"}, None)
    return rows
