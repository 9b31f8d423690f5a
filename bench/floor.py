"""The handshake's floor: what moving custody costs on this machine with nothing but Python, zenoh
and the disk, for the ``migration`` benchmark to set beside the real migration in the same run.

``python -m bench.floor --name N --tag T --folder DIR --listen EP [--connect EP] --parent PID`` is
one bare peer. Two of them do, per migration, the messages and durable points that any handshake
keeping one companion in exactly one place cannot do without (``cmion_mesh/migration/handshake.py``):

* the source, asked ``<tag>/<source>/migrate`` (payload ``"<target>"``), answers at once and, on a
  worker thread, sends the whole document in one ``<tag>/<target>/prepare`` get while another
  thread writes and ``fdatasync``s its own copy beside it (the copy it would resume from);
* the target hashes the document (SHA-256), writes and ``fdatasync``s it, appends ``incoming`` to
  its log and ``fdatasync``s, then answers;
* the source appends ``prepared`` and ``handed`` (the commit point) with one ``fdatasync`` and sends
  ``<tag>/<target>/commit``;
* the target appends ``active``, ``fdatasync``s, publishes ``<tag>/event/<target>`` = ``occurred``
  (``CongestionControl.BLOCK``, as events are) and answers; the source then appends ``released``
  and publishes ``released``.

Everything that makes the real handshake safe and usable is left out: no signatures, custody chain,
manifest or XSD, no sections sent ahead in chunks or kept for a delta, no claims, no crash
recovery, no component model or update loop. So this is a floor, not a rival: the ratio of a
migration to it is what all of that costs.

``<tag>/<name>/make`` (payload: a size in bytes) draws a fresh document of random bytes, untimed,
as the benchmark's mind does before every measured migration. Queries are drained from a
``FifoChannel`` by one thread (zenoh's receive path never waits on Python), the handshake of a
source runs on another.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from bench.core import CHANNEL_CAPACITY, _drain, close_raw, open_session
from bench.daemons import client_config
from bench.harness import StopSignal, loopback_config, loopback_endpoint, start_child, stop_child
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import Daemon
from cmion_mesh.testing.wait import wait_for

REQUEST_TIMEOUT = 30.0


def answered(session: zenoh.Session, key: str, payload: bytes, timeout: float = REQUEST_TIMEOUT) -> bool:
    """Whether exactly one peer answered the get ``key`` (none, an error or a timeout: no)."""
    return sum(reply.ok is not None for reply in session.get(key, payload=payload, timeout=timeout)) == 1


class FloorPeer:
    """One bare peer (child process): its log, its document and the handshake of either side."""

    def __init__(self, session: zenoh.Session, name: str, tag: str, folder: Path) -> None:
        self.session = session
        self.name = name
        self.tag = tag
        self.folder = folder
        self.document = b""
        self.log = os.open(folder / f"{name}.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        self.events = session.declare_publisher(f"{tag}/event/{name}", congestion_control=zenoh.CongestionControl.BLOCK)
        self.jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()

    def append(self, entry: bytes) -> None:
        os.write(self.log, entry)
        os.fdatasync(self.log)

    def keep(self, copy: str, data: bytes) -> None:
        fd = os.open(self.folder / f"{self.name}-{copy}", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, data)
            os.fdatasync(fd)
        finally:
            os.close(fd)

    def ask(self, peer: str, op: str, payload: bytes) -> None:
        if not answered(self.session, f"{self.tag}/{peer}/{op}", payload):
            raise MeshError(f"floor {op} to {peer}: no answer")

    def migrate(self, target: str) -> None:
        """Worker thread: the source's side of one handshake."""
        document = self.document
        digest = hashlib.sha256(document).hexdigest().encode()
        beside = threading.Thread(target=self.keep, args=("outgoing", document), name="keep")
        beside.start()
        try:
            self.ask(target, "prepare", document)
        finally:
            beside.join()
        self.append(b"prepared " + digest + b"\nhanded\n")
        self.ask(target, "commit", b"")
        self.append(b"released\n")
        self.events.put(b"released")

    def answer(self, query: zenoh.Query) -> None:
        """Drain thread: one request."""
        with query:
            op = str(query.key_expr).rsplit("/", 1)[-1]
            body = query.payload.to_bytes() if query.payload is not None else b""
            if op == "make":
                self.document = os.urandom(int(body))
            elif op == "reach":  # joining (untimed): the other peer answers this one
                try:
                    self.ask(body.decode(), "hello", b"")
                except (MeshError, zenoh.ZError) as exc:
                    query.reply_err(str(exc).encode())
                    return
            elif op == "migrate":
                self.jobs.put(functools.partial(self.migrate, body.decode()))
            elif op == "prepare":
                hashlib.sha256(body).hexdigest()
                self.keep("incoming", body)
                self.append(b"incoming\n")
            elif op == "commit":
                self.append(b"active\n")
                self.events.put(b"occurred")
            query.reply(query.key_expr, b"ok")

    def work(self) -> None:
        """Worker thread: handshakes, one at a time, until ``None``."""
        while (job := self.jobs.get()) is not None:
            try:
                job()
            except Exception as exc:  # reported, and the measuring process times out naming the floor
                print(f"floor {self.name}: {exc}", flush=True)


def serve(args: argparse.Namespace) -> int:
    stop = StopSignal(args.parent)
    config = loopback_config(listen=args.listen, connect=args.connect) if args.connect else loopback_config(listen=args.listen)
    session = open_session(config)
    peer = FloorPeer(session, args.name, args.tag, Path(args.folder))
    queryable = session.declare_queryable(f"{args.tag}/{args.name}/*", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
    worker = threading.Thread(target=peer.work, name="handshake", daemon=True)
    worker.start()
    drain = _drain("answer", queryable.handler.recv, peer.answer)
    try:
        print(f"ready floor peer {args.name} on {args.listen}", flush=True)
        stop.wait()
    finally:
        peer.jobs.put(None)
        worker.join(5.0)
        close_raw(session, [queryable, peer.events], [drain])
        os.close(peer.log)
    return 0


class Floor:
    """The measuring side: two bare peers, a session connected to both, one handshake at a time."""

    def __init__(self, tag: str, folder: Path) -> None:
        self.tag = tag
        self.home, self.other = "a", "b"
        self.events: queue.SimpleQueue[tuple[float, bytes]] = queue.SimpleQueue()
        self.children: list[Daemon] = []
        listens = (loopback_endpoint(), loopback_endpoint())
        for name, listen, connect in (("a", listens[0], ""), ("b", listens[1], listens[0])):
            extra = ("--connect", connect) if connect else ()
            self.children.append(start_child("bench.floor", "--name", name, "--tag", tag, "--folder", str(folder),
                                             "--listen", listen, *extra, name=f"floor-{name}"))
        try:
            for child in self.children:
                child.wait_line("ready", 30.0)
        except BaseException:
            for child in self.children:
                stop_child(child)
            raise
        self.session = open_session(client_config(*listens))
        self.subscriber = self.session.declare_subscriber(f"{tag}/event/*", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        self.drain = _drain("floor-events", self.subscriber.handler.recv,
                            lambda sample: self.events.put((time.perf_counter(), sample.payload.to_bytes())))
        try:
            self.join()
        except BaseException:
            self.close()
            raise

    def ask(self, peer: str, op: str, payload: bytes, timeout: float = REQUEST_TIMEOUT) -> bool:
        return answered(self.session, f"{self.tag}/{peer}/{op}", payload, timeout)

    def join(self) -> None:
        """Until this session reaches both peers and each reaches the other (a fresh session knows nobody)."""
        wait_for(lambda: self.ask("a", "reach", b"b", 2.0) and self.ask("b", "reach", b"a", 2.0), 30.0,
                 "the bare handshake's peers reaching each other")

    def make(self, size: int) -> None:
        """A fresh document of ``size`` random bytes at the peer holding it (untimed)."""
        if not self.ask(self.home, "make", str(size).encode()):
            raise MeshError(f"floor peer {self.home}: no answer to make")

    def once(self) -> float:
        """One bare handshake home -> other: seconds from ``migrate`` sent to ``occurred`` received."""
        while not self.events.empty():
            self.events.get_nowait()
        t0 = time.perf_counter()
        if not self.ask(self.home, "migrate", self.other.encode()):
            raise MeshError(f"floor peer {self.home}: no answer to migrate")
        seen: dict[bytes, float] = {}
        deadline = time.monotonic() + REQUEST_TIMEOUT
        while len(seen) < 2:
            try:
                at, what = self.events.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise MeshError(f"floor migration {self.home} -> {self.other}: no end within {REQUEST_TIMEOUT:g} s, "
                                f"saw {sorted(seen)}") from None
            seen[what] = at
        self.home, self.other = self.other, self.home
        return seen[b"occurred"] - t0

    def close(self) -> None:
        try:
            self.subscriber.undeclare()  # type: ignore[no-untyped-call]
        except Exception:
            pass
        self.drain.join(5.0)
        self.session.close()  # type: ignore[no-untyped-call]
        for child in self.children:
            stop_child(child)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.floor", description=__doc__.split("\n\n")[0])
    parser.add_argument("--name", required=True)
    parser.add_argument("--tag", required=True)
    parser.add_argument("--folder", required=True)
    parser.add_argument("--listen", required=True)
    parser.add_argument("--connect", default="")
    parser.add_argument("--parent", type=int, default=None)
    return serve(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
