"""The FAtiMA mind's connection: the listener, who may be the mind, and the socket's threads.

**Connections.** One mind at a time: while one is connected, another connection is refused
(closed at once, with a warning naming both peers, once per host and ``REFUSED_LOG_INTERVAL``);
when the connected mind's socket closes, the next connection is accepted. The first line must be
a handshake (``parse_handshake``), of at most ``MAX_HANDSHAKE_LINE`` bytes, within
``handshake-timeout`` (``HANDSHAKE_TIMEOUT``) seconds, or the connection is closed. Until then a
connection is pending and holds nothing: the mind is the first to complete a handshake (the others
pending are then closed), so a connection that sends a few bytes and stops keeps no mind out. At
most ``MAX_PENDING`` wait at a time: one more closes the oldest (``Switchboard``). Lines are UTF-8
ending in ``\\n`` (``\\r\\n`` accepted), at most ``MAX_LINE`` bytes (a longer one closes the
connection with an error naming the peer; one that is not UTF-8 is dropped and logged). Sockets
are read and written by threads of their own: the update loop never waits for the mind. Both
directions are bounded (``Link``): at most ``MAX_IN_FLIGHT`` lines wait for the loop (then TCP holds
the mind back), at most ``MAX_QUEUED`` bytes wait to be written (then the mind is disconnected: it
is not reading).

**No storm on failure.** FAtiMA retries a failed action about every 250 ms, forever. An action
that failed is held (``FailureGate``): a retry of the identical action (same name and parameters)
within its hold window does not run the rules again; the connector answers it ``ACTION-FAILED``
after a delay (so the mind retries about once a second, not four times), and it is counted
(``held_retries``). The window starts at ``HOLD_FIRST`` seconds and doubles with every failed rerun
up to ``HOLD_MOST``; a success forgets it.
"""

from __future__ import annotations

import functools
import logging
import queue
import selectors
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Simulation
from cmion_mesh.minds.fatima.protocol import MAX_LINE, ActionKey, Handshake, parse_handshake
from cmion_mesh.timers import Timer

log = logging.getLogger(__name__)

#: A write the mind does not take within this many seconds closes the connection.
SEND_TIMEOUT = 30.0
#: Lines read from the mind and not yet handled by the update loop: beyond, the reader stops reading,
#: so a flooding mind is held back by TCP instead of filling the loop's queue (and the memory).
MAX_IN_FLIGHT = 64
#: Bytes waiting to be written to the mind (beyond the line being written): beyond, the mind is not
#: reading and is disconnected, instead of the queue growing without end.
MAX_QUEUED = 8 * 1024 * 1024
#: Refused connections from one host are logged once in this many seconds (the others are counted).
REFUSED_LOG_INTERVAL = 10.0
#: Connections accepted and not yet handshaken at a time: one more closes the oldest of them (a
#: mind sends its handshake as it connects, so it is the newest, and gets its turn).
MAX_PENDING = 8
#: Longest first line: a handshake is a few words, and a pending connection must not fill the
#: memory with ``MAX_LINE`` bytes before saying who it is.
MAX_HANDSHAKE_LINE = 64 * 1024
#: First and longest hold window of a failed action (seconds): retries within it do not run the rules.
HOLD_FIRST = 2.0
HOLD_MOST = 30.0
#: Failed actions remembered by the gate (the oldest is forgotten beyond).
MAX_HELD = 1024
_READ_CHUNK = 256 * 1024


# --- the back-off of failed actions ------------------------------------------------------------------


@dataclass
class HeldFailure:
    reason: str
    failed_at: float
    hold: float
    retries: int = 0  # retries answered from the hold since the last run
    answering: bool = False  # a held answer is scheduled


class FailureGate:
    """Which failed actions are held, and for how long (see the module's docstring)."""

    def __init__(self, first: float = HOLD_FIRST, most: float = HOLD_MOST, clock: Callable[[], float] = time.monotonic) -> None:
        self.first = first
        self.most = most
        self.clock = clock
        self._held: OrderedDict[ActionKey, HeldFailure] = OrderedDict()
        self.held_retries = 0  # in total

    def held(self, key: ActionKey) -> HeldFailure | None:
        """The failure to answer from, if ``key`` failed within its hold window (counts the retry)."""
        failure = self._held.get(key)
        if failure is None or self.clock() - failure.failed_at >= failure.hold:
            return None
        failure.retries += 1
        self.held_retries += 1
        return failure

    def failed(self, key: ActionKey, reason: str) -> HeldFailure:
        previous = self._held.pop(key, None)
        hold = self.first if previous is None else min(self.most, previous.hold * 2)
        failure = HeldFailure(reason, self.clock(), hold)
        self._held[key] = failure
        while len(self._held) > MAX_HELD:
            self._held.popitem(last=False)
        return failure

    def get(self, key: ActionKey) -> HeldFailure | None:
        return self._held.get(key)

    def succeeded(self, key: ActionKey) -> None:
        self._held.pop(key, None)

    def clear(self) -> None:
        self._held.clear()


# --- sockets -----------------------------------------------------------------------------------------


def _peer_name(address: Any) -> str:
    if isinstance(address, tuple) and len(address) >= 2:
        return f"{address[0]}:{address[1]}"
    return str(address)


class Link:
    """One mind connection: a reader thread handing lines on, a writer thread sending queued lines.

    Both directions are bounded: at most ``MAX_IN_FLIGHT`` lines read and not yet handled (the loop
    calls ``line_done`` for each; meanwhile the reader stops reading and TCP holds the mind back),
    and at most ``MAX_QUEUED`` bytes waiting to be written (beyond, the mind is not reading and the
    link reports itself closed)."""

    def __init__(self, sock: socket.socket, peer: str, on_line: Callable[[Link, str], None],
                 on_closed: Callable[[Link, str], None]) -> None:
        self.sock = sock
        self.peer = peer
        self.agent = ""
        self.handshaken = False
        self.connected_at = time.time()
        self.handshake_timer: Timer | None = None  # the deadline of its handshake (loop)
        self._on_line = on_line
        self._on_closed = on_closed
        self._out: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._closed = threading.Event()
        self._dead = threading.Event()  # the reader or writer found the connection gone
        self._reported = threading.Lock()
        self._told = False
        self._flow = threading.Condition()
        self.in_flight = 0  # lines handed to the loop, not yet handled (under _flow)
        self.queued = 0  # bytes waiting for the writer (under _flow)
        self.peak_in_flight = 0
        self.peak_queued = 0
        # Requests of the body the mind answers in order, counted to match each answer to its request.
        self.set_states_sent = 0
        self.set_states_answered = 0
        sock.settimeout(SEND_TIMEOUT)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        # A mind whose host froze or vanished is noticed in about 25 s (not the system's 2 hours),
        # so that the next connection is not refused for long.
        for option, value in (("TCP_KEEPIDLE", 10), ("TCP_KEEPINTVL", 5), ("TCP_KEEPCNT", 3)):
            if hasattr(socket, option):
                sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)
        self._reader = threading.Thread(target=self._read, name=f"fatima-read-{peer}", daemon=True)
        self._writer = threading.Thread(target=self._write, name=f"fatima-write-{peer}", daemon=True)

    def start(self) -> None:
        self._reader.start()
        self._writer.start()

    @property
    def open(self) -> bool:
        return not (self._closed.is_set() or self._dead.is_set())

    @property
    def closed(self) -> bool:
        """``close`` was called (it may still be under way)."""
        return self._closed.is_set()

    def send(self, line: str) -> None:
        if not self.open:
            return
        data = line.encode("utf-8") + b"\n"
        with self._flow:
            backlog = self.queued
            if backlog <= MAX_QUEUED:
                self.queued += len(data)
                self.peak_queued = max(self.peak_queued, self.queued)
        if backlog > MAX_QUEUED:
            why = f"mind is not reading: more than {MAX_QUEUED} bytes wait to be sent to it"
            log.error("FAtiMA mind %s at %s: %s; connection closed", self.agent or "(before its handshake)", self.peer, why)
            self._report(why)
            return
        self._out.put(data)

    def line_done(self) -> None:
        """The loop has handled one line handed on: the reader may hand on another."""
        with self._flow:
            self.in_flight -= 1
            self._flow.notify_all()

    def _hand_on(self, line: str) -> bool:
        """Wait for room in the loop, then hand ``line`` on; False once the link is closing."""
        with self._flow:
            while self.in_flight >= MAX_IN_FLIGHT and self.open:
                self._flow.wait()
            if not self.open:
                return False
            self.in_flight += 1
            self.peak_in_flight = max(self.peak_in_flight, self.in_flight)
        self._on_line(self, line)
        return True

    def _report(self, why: str) -> None:
        self._dead.set()
        with self._flow:
            self._flow.notify_all()
        with self._reported:
            if self._told:
                return
            self._told = True
        self._on_closed(self, why)

    def _read(self) -> None:
        buffer = bytearray()
        searched = 0
        limit = MAX_HANDSHAKE_LINE  # until the first line is handed on: then MAX_LINE
        why = "closed by the mind"
        try:
            while not self._closed.is_set():
                try:
                    chunk = self.sock.recv(_READ_CHUNK)
                except TimeoutError:
                    continue  # the timeout is there for sends; a quiet mind is no fault
                if not chunk:
                    break
                buffer += chunk
                while True:
                    end = buffer.find(b"\n", searched)
                    if end < 0 or end > limit:
                        searched = len(buffer)
                        break
                    raw = bytes(buffer[:end])
                    del buffer[: end + 1]
                    searched = 0
                    if raw.endswith(b"\r"):
                        raw = raw[:-1]
                    try:
                        line = raw.decode("utf-8")
                    except UnicodeDecodeError as exc:
                        # The protocol is UTF-8: a line that is not is dropped whole, never guessed at.
                        log.warning("FAtiMA mind %s at %s sent a line that is not UTF-8 (%s), dropped: %r",
                                    self.agent or "(before its handshake)", self.peer, exc.reason, raw[:80])
                        continue
                    if not self._hand_on(line):
                        break
                    limit = MAX_LINE
                if not self.open:
                    break  # closing: what is left was the mind's, for a loop that no longer wants it
                if len(buffer) > limit and buffer.find(b"\n", 0, limit + 1) < 0:
                    why = f"sent a line longer than {limit} bytes"
                    log.error("FAtiMA mind at %s %s: connection closed", self.peer, why)
                    buffer.clear()
                    break
        except OSError as exc:
            why = f"connection lost: {exc}"
        if buffer and not self._closed.is_set() and not self._dead.is_set():
            log.warning("FAtiMA mind %s at %s: the connection ended inside a line; its %d byte(s) discarded: %r",
                        self.agent or "(before its handshake)", self.peer, len(buffer), bytes(buffer[:120]))
        self._report(why)

    def _write(self) -> None:
        while True:
            data = self._out.get()
            if data is None:
                return
            with self._flow:  # the line being written no longer counts: the backlog behind it does
                self.queued -= len(data)
            try:
                self.sock.sendall(data)
            except OSError as exc:
                self._report(f"cannot write to it: {exc}")
                return

    def close(self, *, drain: float = 0.0) -> None:
        """Close; with ``drain``, first give the writer that many seconds to send what is queued."""
        if self._closed.is_set():
            return
        self._closed.set()
        with self._flow:
            self._flow.notify_all()  # a reader waiting for room in the loop
        self._out.put(None)
        if drain and self._writer.ident is not None and self._writer is not threading.current_thread():
            self._writer.join(drain)
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass  # already disconnected
        for thread in (self._reader, self._writer):
            if thread.ident is not None and thread is not threading.current_thread():
                thread.join(SEND_TIMEOUT)
        self.sock.close()


class Listener:
    """The TCP server: a thread accepting connections and handing each socket on."""

    def __init__(self, host: str, port: int, on_accept: Callable[[socket.socket, str], None]) -> None:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.sock.bind((host, port))
            self.sock.listen(MAX_PENDING)
        except OSError as exc:
            self.sock.close()
            raise MeshError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self.address = _peer_name(self.sock.getsockname())
        self.port: int = self.sock.getsockname()[1]
        self._on_accept = on_accept
        self._wake_r, self._wake_w = socket.socketpair()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"fatima-listen-{self.port}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self.sock, selectors.EVENT_READ)
            selector.register(self._wake_r, selectors.EVENT_READ)
            while not self._stop.is_set():
                for key, _ in selector.select():
                    if key.fileobj is self._wake_r or self._stop.is_set():
                        return
                    try:
                        conn, address = self.sock.accept()
                    except OSError as exc:
                        log.warning("FAtiMA listener on %s: accept failed: %s", self.address, exc)
                        continue
                    self._on_accept(conn, _peer_name(address))

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._wake_w.send(b"x")
        self._thread.join(10.0)
        for s in (self.sock, self._wake_r, self._wake_w):
            s.close()



# --- who may be the mind ---------------------------------------------------------------------------


class Switchboard:
    """The listener and the connections to it: which one is the mind (the first to complete its
    handshake while none is connected), which are pending (bounded, timed out), which are refused.

    Connections come in on the listener's thread and lines on the readers' threads; all are handed
    to the update loop, where the connector hears of the mind (``on_mind``), of its lines
    (``on_line``) and of its end (``on_lost``), never of a connection that is not the mind."""

    def __init__(self, name: str, handshake_timeout: float, *, on_mind: Callable[[Link, Handshake], None],
                 on_line: Callable[[Link, str], None], on_lost: Callable[[Link, str], None]) -> None:
        self.name = name
        self.handshake_timeout = handshake_timeout
        self._on_mind = on_mind
        self._on_line = on_line
        self._on_lost = on_lost
        self._sim: Simulation | None = None
        self.listener: Listener | None = None
        self.link: Link | None = None  # the connected mind (loop)
        self._links_lock = threading.Lock()
        self._accepted: Link | None = None  # the handshaken mind the listener knows of (under the lock)
        # Connections not yet handshaken, oldest first (under the lock): at most MAX_PENDING; one
        # removed from here (timed out, pushed out, refused) can no longer become the mind.
        self._pending: dict[Link, None] = {}
        self._closing = False
        self.connections = 0  # minds that completed a handshake
        # (host, what) -> (last logged, not logged since): for the warnings of ``_warn_limited``.
        self._refused: dict[tuple[str, str], tuple[float, int]] = {}
        self._refused_lock = threading.Lock()

    @property
    def sim(self) -> Simulation:
        if self._sim is None:
            raise MeshError(f"the switchboard of {self.name!r} is not listening")
        return self._sim

    def listen(self, sim: Simulation, host: str, port: int) -> Listener:
        """Start listening (on the loop, as the connector is attached); ``MeshError`` if it cannot."""
        self._sim = sim
        self.listener = Listener(host, port, self._accept)
        return self.listener

    def pending(self) -> int:
        with self._links_lock:
            return len(self._pending)

    def close(self, farewell: str = "") -> None:
        """Stop listening and close every connection; the mind is first sent ``farewell`` (if any)
        and given 2 s to take what is queued for it. Idempotent."""
        self._closing = True
        if self.listener is not None:
            self.listener.close()
        with self._links_lock:
            link, self._accepted = self._accepted, None
            pending, self._pending = list(self._pending), {}
        for waiting in pending:
            waiting.close()
        if link is not None:
            if farewell and link.handshaken and link.open:
                link.send(farewell)
            link.close(drain=2.0)
        self.link = None

    def __enter__(self) -> Switchboard:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    # --- connections (accept thread -> loop) --------------------------------------------------------

    def _accept(self, conn: socket.socket, peer: str) -> None:
        """A new connection: refused while a mind is connected, else pending until its handshake
        (``_handshake``), its deadline (``_handshake_overdue``) or a newer one pushing it out."""
        refused_by: str | None = None
        pushed_out: Link | None = None
        with self._links_lock:
            current = self._accepted
            if current is not None and current.open:
                refused_by = current.peer
            else:
                pushed_out = next(iter(self._pending)) if len(self._pending) >= MAX_PENDING else None
                if pushed_out is not None:
                    del self._pending[pushed_out]
                link = Link(conn, peer, self._line_in, self._closed_in)
                self._pending[link] = None
        if refused_by is not None:
            self._warn_limited(peer, "refused", f"refused a connection from {peer}: the mind at {refused_by} is connected "
                                                "(one mind at a time)")
            conn.close()
            return
        if pushed_out is not None:
            why = f"{MAX_PENDING} newer connections wait for theirs"
            if not self.sim.post(functools.partial(self._drop_pending, pushed_out, why)):
                pushed_out.close()
        if self.sim.post(functools.partial(self._connected, link)):
            link.start()  # after the loop has it: its lines come after it, its deadline before them
        else:
            link.close()

    def _warn_limited(self, peer: str, what: str, message: str) -> None:
        """A warning per host, kind (``what``) and ``REFUSED_LOG_INTERVAL`` (a mind retrying in a
        loop, or a host opening connection after connection, must not flood the log), saying how
        many went unlogged since the last."""
        host = peer.rsplit(":", 1)[0]
        now = time.monotonic()
        with self._refused_lock:
            last, unlogged = self._refused.get((host, what), (-REFUSED_LOG_INTERVAL, 0))
            if now - last < REFUSED_LOG_INTERVAL:
                self._refused[(host, what)] = (last, unlogged + 1)
                return
            while len(self._refused) >= MAX_HELD:
                del self._refused[next(iter(self._refused))]
            self._refused[(host, what)] = (now, 0)
        more = f" ({unlogged} more from {host} {what} unlogged since the last warning)" if unlogged else ""
        log.warning("FAtiMA connector %r: %s%s", self.name, message, more)

    def _line_in(self, link: Link, line: str) -> None:
        if not self.sim.post(functools.partial(self._take_line, link, line)):
            link.line_done()

    def _closed_in(self, link: Link, why: str) -> None:
        if not self.sim.post(functools.partial(self._disconnected, link, why)):
            link.close()

    # --- the loop ------------------------------------------------------------------------------------

    def _take_line(self, link: Link, line: str) -> None:
        try:
            if link is self.link:
                self._on_line(link, line)
            elif not link.handshaken and self._is_pending(link):
                self._handshake(link, line)
            # else lines read before the connection was closed: nobody wants them now
        finally:
            link.line_done()

    def _connected(self, link: Link) -> None:
        """A pending connection (loop): its handshake is due within ``handshake_timeout``."""
        if not link.closed:
            link.handshake_timer = self.sim.call_later(self.handshake_timeout,
                                                       functools.partial(self._handshake_overdue, link))

    def _handshake_overdue(self, link: Link) -> None:
        if not link.handshaken:
            self._drop_pending(link, f"no handshake within {self.handshake_timeout:g} s")

    def _is_pending(self, link: Link) -> bool:
        with self._links_lock:
            return link in self._pending

    def _drop_pending(self, link: Link, why: str) -> None:
        """Close a connection that has not handshaken (loop); said once, whatever closes it first."""
        with self._links_lock:
            self._pending.pop(link, None)
        if link.handshake_timer is not None:
            link.handshake_timer.cancel()
            link.handshake_timer = None
        if link.closed:
            return
        link.close()
        self._warn_limited(link.peer, "closed before a handshake",
                           f"closed the connection from {link.peer} before its handshake: {why}")

    def _disconnected(self, link: Link, why: str) -> None:
        if not link.handshaken:
            self._drop_pending(link, why)
            return
        with self._links_lock:
            if self._accepted is link:
                self._accepted = None
        link.close()
        if link is not self.link:
            return
        self.link = None
        if not self._closing:
            self._on_lost(link, why)

    def _handshake(self, link: Link, line: str) -> None:
        try:
            hello = parse_handshake(line)
        except MeshError as exc:
            self._drop_pending(link, f"bad handshake: {exc}")
            return
        with self._links_lock:
            current = self._accepted
            others: list[Link] = []
            taken_by: str | None = None
            if current is not None and current.open:
                taken_by = current.peer  # a mind connected since this one was accepted
                self._pending.pop(link, None)
            else:
                self._accepted = link
                others = [other for other in self._pending if other is not link]
                self._pending.clear()
        if taken_by is not None:
            self._drop_pending(link, f"the mind at {taken_by} is connected (one mind at a time)")
            return
        for other in others:  # the place is taken: they would be refused at their handshake
            self._drop_pending(other, f"the mind at {link.peer} connected first (one mind at a time)")
        if link.handshake_timer is not None:
            link.handshake_timer.cancel()
            link.handshake_timer = None
        old = self.link
        if old is not None:  # its end was seen by the listener before its report came here
            self._disconnected(old, "connection lost")
        self.link = link
        self.connections += 1
        link.agent = hello.agent
        link.handshaken = True
        link.send("OK")
        self._on_mind(link, hello)
