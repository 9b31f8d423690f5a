"""Events in a burst reach every subscriber process whole and in order: nothing lost, nothing twice.

Real processes on loopback: a publisher embodiment raises a burst of events back to back on its
update loop (and more from another thread, which ``raise_event`` posts to the loop), while two
subscriber processes follow them each with an update-loop subscription (``Simulation.on_event``,
events handed over in batches) and a ``MeshClient.events`` subscription. Each checks the numbers
it gets. Run as a child: ``python -m tests.test_event_burst pub|sub ...`` (commands on stdin).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Sequence

from cmion_mesh.client import MeshClient
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event
from cmion_mesh.procs import Daemon, free_port
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

PUB = "burst-pub"
LOOP_BURST = 20_000
THREAD_BURST = 2_000
_out = threading.Lock()  # the two subscriptions report from two threads: one whole line each


def say(line: str) -> None:
    with _out:
        print(line, flush=True)


def config(*, listen: str | None = None, connect: str | None = None) -> TransportConfig:
    return TransportConfig(listen=(listen,) if listen else (), connect=(connect,) if connect else (), multicast=False,
                           overrides=() if listen else (("listen/endpoints", "[]"),))


# --- the children -----------------------------------------------------------------------------------


class Source(Component):
    def burst(self, count: int) -> None:  # on the loop: back to back, as fast as the loop raises them
        for i in range(count):
            self.raise_event("n", i)


def publisher(args: argparse.Namespace) -> int:
    with ZenohTransport(config(listen=args.listen)) as transport, Simulation(transport, mesh=args.mesh, embodiment=PUB) as sim:
        source = Source("src")
        sim.add(source)
        print("ready", flush=True)
        for line in sys.stdin:
            command, _, arg = line.strip().partition(" ")
            if command == "ping":
                source.raise_event("ping", int(arg))  # from this thread: posted to the loop
            elif command == "go":
                sim.call(lambda: source.burst(LOOP_BURST))
                for i in range(LOOP_BURST, LOOP_BURST + THREAD_BURST):
                    source.raise_event("n", i)  # from this thread: posted to the loop, after the burst
                source.raise_event("end")
            elif command == "quit":
                break
    return 0


class Checker:
    """The numbers one subscription got: how many, how many out of order or twice."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.received = 0
        self.disordered = 0
        self.last = -1
        self.last_seq = 0
        self.seq_disordered = 0

    def on_event(self, event: Event) -> None:
        if event.name == "ping":
            say(f"ping {self.name} {event.data}")
        elif event.name == "end":
            say(f"end {self.name} " + json.dumps({"received": self.received, "disordered": self.disordered, "last": self.last,
                                                  "seq_disordered": self.seq_disordered}))
        elif event.name == "n":
            self.received += 1
            if event.data != self.last + 1:
                self.disordered += 1
            self.last = event.data
            if event.seq <= self.last_seq:
                self.seq_disordered += 1
            self.last_seq = event.seq


def subscriber(args: argparse.Namespace) -> int:
    loop_side, client_side = Checker(f"{args.name}-loop"), Checker(f"{args.name}-client")
    with ZenohTransport(config(connect=args.connect)) as transport, \
            Simulation(transport, mesh=args.mesh, embodiment=args.name) as sim, MeshClient(transport, args.mesh) as client:
        sim.on_event(loop_side.on_event, embodiment=PUB, component="src")
        with client.events(client_side.on_event, embodiment=PUB, component="src"):
            attached = threading.Event()
            sim.call(attached.set)
            attached.wait(10.0)
            say("ready")
            for line in sys.stdin:
                if line.strip() == "quit":
                    break
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.test_event_burst")
    sub = parser.add_subparsers(dest="role", required=True)
    p = sub.add_parser("pub")
    p.add_argument("--listen", required=True)
    p.add_argument("--mesh", required=True)
    s = sub.add_parser("sub")
    s.add_argument("--connect", required=True)
    s.add_argument("--mesh", required=True)
    s.add_argument("--name", required=True)
    args = parser.parse_args(argv)
    return publisher(args) if args.role == "pub" else subscriber(args)


# --- the test -------------------------------------------------------------------------------------


def test_a_burst_reaches_every_subscriber_whole_and_in_order(mesh: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    child = [sys.executable, "-m", "tests.test_event_burst"]
    names = ["sub-a", "sub-b"]
    processes: list[Daemon] = []
    try:
        pub = Daemon([*child, "pub", "--listen", endpoint, "--mesh", mesh], name="pub", stdin=True)
        processes.append(pub)
        pub.wait_line("ready", 30)
        subs = [Daemon([*child, "sub", "--connect", endpoint, "--mesh", mesh, "--name", n], name=n, stdin=True) for n in names]
        processes += subs
        for s in subs:
            s.wait_line("ready", 30)
        # Both subscriptions of both processes must have reached the publisher: ping until each answers.
        for attempt in range(200):
            pub.send(f"ping {attempt}")
            try:
                for s, n in zip(subs, names, strict=True):
                    for side in ("loop", "client"):
                        s.wait_line(f"ping {n}-{side} {attempt}", 0.1 if attempt < 199 else 5)
                break
            except TimeoutError:
                continue
        pub.send("go")
        total = LOOP_BURST + THREAD_BURST
        for s, n in zip(subs, names, strict=True):
            for side in ("loop", "client"):
                line = s.wait_line(f"end {n}-{side} ", 120)
                got = json.loads(line.split(" ", 2)[2])
                assert got == {"received": total, "disordered": 0, "last": total - 1, "seq_disordered": 0}, (n, side, got)
    finally:
        for p in processes:
            try:
                p.send("quit")
            except (OSError, ValueError):
                pass  # gone already
        for p in processes:
            p.stop()


if __name__ == "__main__":
    sys.exit(main())
