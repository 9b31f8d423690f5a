"""The agent-mind line protocol (FAtiMA): action line in -> ``ACTION-FINISHED`` out, a one-step plan.

Processes (all on loopback): a daemon ``cmion-mesh up`` of the bench embodiment (rule ``One`` -> one
``Instant`` step) with ``cmion_mesh.minds.fatima.connector:FAtiMAConnector`` listening on a free port and the
companion living there, so the mind is awake; ``python -m bench.mindproto serve-echo`` (a plain TCP
line echo, for the cost of the socket hops alone); ``python -m bench.core serve-raw`` (a raw zenoh
queryable); the measuring process, which plays the mind itself on one TCP connection (handshake,
then ``One`` lines), as FAtiMA would.

Metrics:

* ``fatima_one``: the line ``One`` sent until ``ACTION-FINISHED <agent> One`` is read back (other
  lines the body sends meanwhile are skipped). CMION 2011 needed about 200 ms for this (its reader
  slept 100 ms per line); the limit below is a tenth of that.
* ``raw_tcp_echo``: a line sent until its echo is read, to a process of its own.
* ``raw_get``: a raw zenoh get round trip, for context.
"""

from __future__ import annotations

import argparse
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path

from bench.actions import _TimedOnce as TimedOnce
from bench.core import RawGet, open_session
from bench.daemons import LIBRARY, RULES, Node, stop_and_report
from bench.harness import StopSignal, interleaved, loopback_config, loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import free_port, unique_mesh
from cmion_mesh.testing.wait import wait_for

EMBODIMENT = "bench-mind"
COMPANION = "bench"
AGENT = "Bench"
CMION_MS = 200.0

LABELS = {
    "raw_get": "raw zenoh get, round trip (context)",
    "raw_tcp_echo": "raw TCP line echo, other process",
    "fatima_one": f"FAtiMA line 'One' -> ACTION-FINISHED (1 step); CMION 2011: ~{CMION_MS:g} ms",
}


def log(text: str) -> None:
    print(f"  [mindproto] {text}", flush=True)


class LineSocket:
    """One TCP connection read line by line, with a deadline on every read."""

    def __init__(self, port: int, timeout: float = 10.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.reader = self.sock.makefile("rb")

    def send(self, line: str) -> None:
        self.sock.sendall(line.encode() + b"\n")

    def read(self) -> str:
        raw = self.reader.readline()
        if not raw:
            raise MeshError("connection closed")
        return raw.decode().rstrip("\r\n")

    def close(self) -> None:
        self.reader.close()
        self.sock.close()


class Echo(TimedOnce):
    metric = "raw_tcp_echo"

    def __init__(self, port: int) -> None:
        self.line = LineSocket(port)

    def once(self) -> None:
        self.line.send("One")
        if self.line.read() != "One":
            raise MeshError("the echo answered something else")


class Mind(Echo):
    """The measuring process as the FAtiMA mind: handshake, then one action at a time."""

    metric = "fatima_one"

    def __init__(self, port: int) -> None:
        self.line = LineSocket(port)
        self.line.send(f"{AGENT} BenchAgent {AGENT} role:BenchAgent")
        while self.line.read() != "OK":
            pass
        self.done = f"ACTION-FINISHED {AGENT} One"

    def once(self) -> None:
        self.line.send("One")
        for _ in range(10_000):
            line = self.line.read()
            if line == self.done:
                return
            if line.startswith("ACTION-FAILED"):
                raise MeshError(f"the body answered {line!r}")
        raise MeshError("no ACTION-FINISHED among 10,000 lines")


def write_config(folder: Path, mind_port: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "ArchitectureConfiguration.xml"
    config.write_text(
        f'<ArchitectureConfiguration Embodiment="{EMBODIMENT}" CompetencyManagerRulesFile="{RULES}"'
        f' CompetencyLibraryConfigurationFile="{LIBRARY}">\n'
        f'  <ArchitectureComponent ClassName="cmion_mesh.minds.fatima.connector:FAtiMAConnector" ConstructorParameters="modular '
        f'port:{mind_port}"/>\n'
        "</ArchitectureConfiguration>\n")
    return config


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    mesh = unique_mesh("bench")
    raw_ep = loopback_endpoint()
    echo_port, mind_port = free_port(), free_port()
    started = time.monotonic()
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-mindproto-")))
        raw_child = start_child("bench.core", "serve-raw", "--listen", raw_ep, "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw_child)
        echo_child = start_child("bench.mindproto", "serve-echo", "--port", str(echo_port), name="serve-echo")
        stack.callback(stop_child, echo_child)
        node = Node(EMBODIMENT, mesh, tmp / EMBODIMENT, companion=COMPANION,
                    architecture=str(write_config(tmp / "config", mind_port)))
        node.start()
        stack.callback(stop_and_report, [node], log)
        raw_child.wait_line("ready", 30.0)
        echo_child.wait_line("ready", 30.0)
        node.wait_up(60.0)
        log(f"daemon, echo and raw peer up after {time.monotonic() - started:.2f} s (mesh {mesh})")
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        echo = Echo(echo_port)
        stack.callback(echo.line.close)
        mind = wait_for(lambda: _connect(mind_port), 20.0, "the FAtiMA connector accepting the mind")
        stack.callback(mind.line.close)
        pooled = interleaved([RawGet(session, mesh), echo, mind], samples=options.samples, warmup=options.warmup,
                             rounds=options.rounds, rewarm=options.rewarm, log=log)
        log(f"measured in {time.monotonic() - started:.1f} s")
    rows = [Row(m, LABELS[m], summarize(pooled[m]), extra={"rounds": options.rounds}) for m in LABELS]
    compare(rows, {"fatima_one": "raw_tcp_echo"}, None)
    rows[2].extra["cmion_2011_ms"] = CMION_MS
    return rows


def _connect(port: int) -> Mind | None:
    try:
        return Mind(port)
    except OSError:
        return None


# --- the echo child ---------------------------------------------------------------------------------


def serve_echo(args: argparse.Namespace) -> int:
    stop = StopSignal(args.parent)
    server = socket.create_server(("127.0.0.1", args.port))

    def serve() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return  # closed: stopping
            threading.Thread(target=echo_lines, args=(conn,), name="echo", daemon=True).start()

    threading.Thread(target=serve, name="accept", daemon=True).start()
    print("ready", flush=True)
    stop.wait()
    server.close()
    return 0


def echo_lines(conn: socket.socket) -> None:
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    with conn, conn.makefile("rb") as lines:
        for line in lines:
            conn.sendall(line)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.mindproto", description="child processes of the mindproto benchmark")
    sub = parser.add_subparsers(dest="command", required=True)
    echo = sub.add_parser("serve-echo", help="a TCP line echo on 127.0.0.1")
    echo.add_argument("--port", type=int, required=True)
    echo.add_argument("--parent", type=int)
    return serve_echo(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
