"""A stand-in for the FAtiMA agent mind, written from the line protocol (docs/fatima.md), not from FAtiMA.

It is the other side of ``cmion_mesh.minds.fatima.connector`` and knows nothing of cmion-mesh (standard library
only). It connects, sends its handshake, records every line it receives, answers the body's
commands as FAtiMA does (``CMD GET-STATE`` with a given opaque hex state, ``CMD SET-STATE`` with
``STATE-SET``, ``CMD GET-PROPERTIES`` with its semantic memory, ``CMD Stop``/``Start``), and
retries a failed action every 250 ms while it runs, forever, like FAtiMA.

As a process (``python -m cmion_mesh.testing.fatima_peer --port N ...``) it prints ``< line`` for
every line received, ``> line`` for every line sent and ``# ...`` for what happens to the
connection, and takes commands on standard input, one a line:

``act ACTION [PARAMS]``   send an action, retried on ACTION-FAILED until it finishes or is dropped
``drop ACTION [PARAMS]``  stop retrying it
``send LINE``             send a raw line
``emotion MOOD``          send an ``<EmotionalState>`` line
``mute-state`` / ``answer-state``   stop / start answering ``CMD GET-STATE``
``disconnect`` / ``connect``        close the connection / connect again (a new handshake)
``flood LINE`` / ``stop-flood``     send LINE over and over, as fast as the body takes it / stop
``flood-reading LINE``    the same, never more than ``FLOOD_WINDOW`` lines ahead of the answers read
                          (``ACTION-FINISHED``/``-FAILED``): a flooding mind that reads its answers
``stop-reading`` / ``read``         stop / start reading what the body sends (a mind that hangs)
``quiet`` / ``verbose``   stop / start keeping and printing received lines (they are still answered)
``quit``                  leave (so does the end of standard input)

``Peer`` is the same thing as a class, for benchmarks that play the mind in their own process.
"""

from __future__ import annotations

import heapq
import itertools
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

RETRY_INTERVAL = 0.25
#: Lines a ``flood-reading`` keeps sent ahead of the answers it has read.
FLOOD_WINDOW = 10_000


class Peer:
    """A FAtiMA-like mind on one TCP connection (see the module's docstring)."""

    def __init__(self, host: str, port: int, *, agent: str = "Spirit", role: str = "TestAgent", display: str = "Spirit",
                 properties: Sequence[str] = ("role:TestAgent", "isTestMind:True"), state: str = "",
                 answer_state: bool = True, retry_interval: float = RETRY_INTERVAL,
                 echo: Callable[[str], None] | None = None) -> None:
        self.host, self.port = host, port
        self.agent, self.role, self.display = agent, role, display
        self.properties = list(properties)
        self.state = state
        self.answer_state = answer_state
        self.retry_interval = retry_interval
        self.echo = echo
        self.received: list[str] = []
        self.sent: list[str] = []
        self.quiet = False  # received lines are answered, not kept nor echoed (a flood's answers)
        self._reading = threading.Event()
        self._reading.set()
        self._send_lock = threading.Lock()  # one line at a time on the socket (floods run on a thread)
        self._flood: tuple[threading.Thread, threading.Event] | None = None
        self.answers = 0  # ACTION-FINISHED / ACTION-FAILED lines received (under _lock)
        self.set_state: str | None = None  # the last state the body set
        self.running = True
        self._lock = threading.Condition()
        self._sock: socket.socket | None = None
        self._reader: threading.Thread | None = None
        self._retrying: set[str] = set()
        self._held_back: set[str] = set()  # retries due while the body had the mind stopped
        self._due: list[tuple[float, int, str]] = []
        self._seq = itertools.count()
        self._closed = False
        self._timer = threading.Thread(target=self._retry_loop, name="peer-retries", daemon=True)
        self._timer.start()

    # --- connection ---------------------------------------------------------------------------------

    def connect(self, timeout: float = 10.0) -> None:
        """Connect (trying again until ``timeout`` while nobody listens) and send the handshake."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                sock = socket.create_connection((self.host, self.port), timeout=2.0)
                break
            except OSError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.05)
        sock.settimeout(None)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._sock = sock
        self._reader = threading.Thread(target=self._read, args=(sock,), name="peer-read", daemon=True)
        self._reader.start()
        self._note(f"# connected to {self.host}:{self.port}")
        self.send(" ".join([self.agent, self.role, self.display, *self.properties]))

    def disconnect(self) -> None:
        self.stop_flood()
        self._reading.set()
        with self._lock:
            sock, self._sock = self._sock, None
            self._retrying.clear()
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(5.0)

    def close(self) -> None:
        self.disconnect()
        with self._lock:
            self._closed = True
            self._lock.notify_all()
        self._timer.join(5.0)

    def __enter__(self) -> Peer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # --- sending ------------------------------------------------------------------------------------

    def send(self, line: str) -> None:
        with self._lock:
            sock = self._sock
            self.sent.append(line)
        if sock is None:
            self._note(f"# not connected: {line[:80]} not sent")
            return
        try:
            with self._send_lock:
                sock.sendall(line.encode("utf-8") + b"\n")
        except OSError as exc:
            self._note(f"# send failed: {exc}")
            return
        self._note(f"> {line}")

    def act(self, action: str) -> None:
        """Send an action and retry it on every ACTION-FAILED until it finishes (or ``drop``)."""
        with self._lock:
            self._retrying.add(action)
        self.send(action)

    def drop(self, action: str) -> None:
        with self._lock:
            self._retrying.discard(action)

    def flood(self, line: str, *, window: int = 0) -> None:
        """Send ``line`` over and over on a thread of its own, until ``stop_flood`` or a failed send;
        with ``window``, never more than that many lines ahead of the answers received."""
        self.stop_flood()
        stop = threading.Event()
        thread = threading.Thread(target=self._flood_loop, args=(line, stop, window), name="peer-flood", daemon=True)
        self._flood = (thread, stop)
        thread.start()

    def stop_flood(self) -> None:
        flood, self._flood = self._flood, None
        if flood is not None:
            flood[1].set()
            with self._lock:
                self._lock.notify_all()  # a flood waiting for answers
            flood[0].join(10.0)

    def _flood_loop(self, line: str, stop: threading.Event, window: int) -> None:
        batch = (line.encode("utf-8") + b"\n") * 256
        sent = 0
        why = "stopped"
        with self._lock:
            answered = self.answers
        self._note(f"# flooding: {line[:80]}")
        while not stop.is_set():
            with self._lock:
                while window and sent - (self.answers - answered) > window and not stop.is_set():
                    self._lock.wait(1.0)
                sock = self._sock
            if sock is None:
                why = "not connected"
                break
            try:
                with self._send_lock:
                    sock.sendall(batch)
            except OSError as exc:
                why = f"send failed: {exc}"
                break
            sent += 256
        self._note(f"# flood ended after {sent} lines ({why})")

    def stop_reading(self) -> None:
        self._reading.clear()

    def read(self) -> None:
        self._reading.set()

    def emotion(self, mood: str) -> None:
        self.send(f"<EmotionalState><Mood>{mood}</Mood><Emotion type=\"JOY\" direction=\"User\" intensity=\"2.5\"/>"
                  "</EmotionalState>")

    # --- receiving ----------------------------------------------------------------------------------

    def _read(self, sock: socket.socket) -> None:
        with sock.makefile("r", encoding="utf-8", newline="\n") as lines:
            try:
                for raw in lines:
                    self._reading.wait()  # stopped: the body's lines pile up in the socket
                    self._received(raw.rstrip("\n").rstrip("\r"))
            except (OSError, ValueError):
                pass
        self._note("# disconnected")

    def _received(self, line: str) -> None:
        if not self.quiet:
            with self._lock:
                self.received.append(line)
                self._lock.notify_all()
            self._note(f"< {line}")
        head, _, rest = line.partition(" ")
        if line == "CMD GET-STATE":
            if self.answer_state:
                self.send(f"STATE {self.state}")
        elif line.startswith("CMD SET-STATE "):
            self.set_state = line[len("CMD SET-STATE "):]
            self.send("STATE-SET")
        elif line == "CMD Stop":
            self.running = False
        elif line == "CMD Start":
            self.running = True
            with self._lock:  # retries that fell due while stopped
                for action in self._held_back & self._retrying:
                    self._schedule(action, 0.0)
                self._held_back.clear()
        elif line == "CMD GET-PROPERTIES":
            items = "".join(f"<Property persistent=\"true\" name={quoteattr(f'SELF({k})')} value={quoteattr(v)}/>"
                            for k, _, v in (p.partition(":") for p in self.properties))
            self.send(f"<SemanticMemory><STM>{items}</STM><LTM></LTM></SemanticMemory>")
        elif head in ("ACTION-FAILED", "ACTION-FINISHED"):
            subject, _, action = rest.partition(" ")
            if subject != self.agent:
                return
            with self._lock:
                self.answers += 1
                self._lock.notify_all()
                if head == "ACTION-FINISHED":
                    self._retrying.discard(action)
                elif action in self._retrying:
                    self._schedule(action, self.retry_interval)

    def _schedule(self, action: str, delay: float) -> None:
        heapq.heappush(self._due, (time.monotonic() + delay, next(self._seq), action))
        self._lock.notify_all()

    def _retry_loop(self) -> None:
        with self._lock:
            while not self._closed:
                if not self._due:
                    self._lock.wait()
                    continue
                due, _, action = self._due[0]
                left = due - time.monotonic()
                if left > 0:
                    self._lock.wait(left)
                    continue
                heapq.heappop(self._due)
                if action in self._retrying and not self.running:
                    self._held_back.add(action)
                elif action in self._retrying and self._sock is not None:
                    self._lock.release()
                    try:
                        self.send(action)
                    finally:
                        self._lock.acquire()

    def wait_for(self, match: Callable[[str], bool], timeout: float = 10.0, *, start: int = 0) -> str:
        """The first received line from index ``start`` on that ``match``es; ``TimeoutError`` otherwise."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                for line in self.received[start:]:
                    if match(line):
                        return line
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no such line within {timeout:g} s; received: {[r[:100] for r in self.received[-10:]]}")
                self._lock.wait(left)

    def _note(self, text: str) -> None:
        if self.echo is not None:
            self.echo(text)


# --- as a process ----------------------------------------------------------------------------------------


def _print(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


USAGE = """usage: python -m cmion_mesh.testing.fatima_peer [--host H] [--port N] [--agent NAME] [--role ROLE]
       [--display NAME] [--prop K:V]... [--state-file FILE] [--mute-state] [--retry-interval S] [--connect-timeout S]

--host, --port       where the body listens (default 127.0.0.1, 46874)
--agent, --role, --display   the handshake's names (default Spirit, TestAgent, Spirit)
--prop K:V           a property of the handshake; repeatable (default role:TestAgent isTestMind:True)
--state-file FILE    a file holding the hex state to answer CMD GET-STATE with
--mute-state         never answer CMD GET-STATE
--retry-interval S   seconds between retries of a failed action (default 0.25)
--connect-timeout S  how long to try connecting (default 10)"""


@dataclass
class PeerArgs:
    host: str = "127.0.0.1"
    port: int = 46874
    agent: str = "Spirit"
    role: str = "TestAgent"
    display: str = "Spirit"
    prop: list[str] | None = None
    state_file: str = ""
    mute_state: bool = False
    retry_interval: float = RETRY_INTERVAL
    connect_timeout: float = 10.0


def parse_args(argv: Sequence[str]) -> PeerArgs:
    """The few options of the stand-in (a standalone program: no command-line library of the package)."""
    args = PeerArgs()
    words = list(argv)
    while words:
        option = words.pop(0)
        name = option.removeprefix("--").replace("-", "_")
        if option in ("-h", "--help"):
            raise SystemExit(USAGE)
        if name == "mute_state":
            args.mute_state = True
            continue
        if not option.startswith("--") or name not in PeerArgs.__dataclass_fields__ or not words:
            raise SystemExit(f"bad option {option!r}\n{USAGE}")
        value = words.pop(0)
        try:
            if name == "prop":
                args.prop = [*(args.prop or []), value]
            elif name == "port":
                args.port = int(value)
            elif name in ("retry_interval", "connect_timeout"):
                setattr(args, name, float(value))
            else:
                setattr(args, name, value)
        except ValueError:
            raise SystemExit(f"{option}: not a number: {value!r}") from None
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    state = ""
    if args.state_file:
        with open(args.state_file, encoding="ascii") as f:
            state = f.read().strip()
    properties = args.prop if args.prop is not None else ["role:TestAgent", "isTestMind:True"]
    with Peer(args.host, args.port, agent=args.agent, role=args.role, display=args.display, properties=properties, state=state,
              answer_state=not args.mute_state, retry_interval=args.retry_interval, echo=_print) as peer:
        try:
            peer.connect(args.connect_timeout)
        except OSError as exc:
            _print(f"# cannot connect to {args.host}:{args.port}: {exc}")
            return 1
        for raw in sys.stdin:
            command, _, rest = raw.strip().partition(" ")
            if command == "quit":
                break
            if command == "act":
                peer.act(rest)
            elif command == "drop":
                peer.drop(rest)
            elif command == "send":
                peer.send(rest)
            elif command == "emotion":
                peer.emotion(rest)
            elif command in ("mute-state", "answer-state"):
                peer.answer_state = command == "answer-state"
                _print(f"# {command}")
            elif command in ("flood", "flood-reading"):
                peer.flood(rest, window=FLOOD_WINDOW if command == "flood-reading" else 0)
            elif command == "stop-flood":
                peer.stop_flood()
            elif command == "stop-reading":
                peer.stop_reading()
                _print("# stopped reading")
            elif command == "read":
                peer.read()
                _print("# reading")
            elif command in ("quiet", "verbose"):
                peer.quiet = command == "quiet"
                _print(f"# {command}")
            elif command == "disconnect":
                peer.disconnect()
            elif command == "connect":
                peer.connect(args.connect_timeout)
            elif command:
                _print(f"# unknown command {command!r}")
    return 0


class PeerProcess:
    """The stand-in in a process of its own, driven through its standard input; every output line kept."""

    def __init__(self, port: int, *args: str, host: str = "127.0.0.1") -> None:
        argv = [sys.executable, "-m", "cmion_mesh.testing.fatima_peer", "--host", host, "--port", str(port), *args]
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, encoding="utf-8", bufsize=1)
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, name="peer-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            with self._cond:
                self.lines.append(raw.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self.lines.append("# exited")
            self._cond.notify_all()

    def command(self, text: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()

    def mark(self) -> int:
        """The number of lines so far: ``wait``/``received`` from here on see only later lines."""
        with self._cond:
            return len(self.lines)

    def received(self, start: int = 0) -> list[str]:
        with self._cond:
            return [line[2:] for line in self.lines[start:] if line.startswith("< ")]

    def sent(self, start: int = 0) -> list[str]:
        with self._cond:
            return [line[2:] for line in self.lines[start:] if line.startswith("> ")]

    def wait(self, match: Callable[[str], bool], timeout: float = 10.0, *, start: int = 0) -> str:
        """The first output line from ``start`` on that ``match``es (``< ``/``> ``/``# `` included)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for line in self.lines[start:]:
                    if match(line):
                        return line
                left = deadline - time.monotonic()
                if left <= 0 or (self.lines and self.lines[-1] == "# exited"):
                    tail = "\n".join(line[:160] for line in self.lines[-25:])
                    raise TimeoutError(f"stand-in FAtiMA: no such line within {timeout:g} s; output:\n{tail}")
                self._cond.wait(left)

    def got(self, line: str, timeout: float = 10.0, *, start: int = 0) -> str:
        """Wait for exactly ``line`` received from the body."""
        return self.wait(lambda out: out == f"< {line}", timeout, start=start)[2:]

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.command("quit")
                self.proc.wait(5.0)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5.0)
        if self.proc.stdin is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        self._reader.join(5.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def __enter__(self) -> PeerProcess:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


if __name__ == "__main__":
    sys.exit(main())
