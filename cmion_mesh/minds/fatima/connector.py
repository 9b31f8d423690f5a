"""CMION's agent-mind line protocol: the original LIREC mind (FAtiMA, Java) as a companion's mind.

``FAtiMAConnector`` is a ``Mind`` that listens on TCP (CMION's port 46874 by default, on loopback
unless told otherwise) for one FAtiMA connection and translates between FAtiMA's lines and the
embodiment: FAtiMA's actions go to the competency manager's rules, the world model's changes go to
FAtiMA, and around a migration FAtiMA's whole state (an opaque hex string) travels in the
companion's identity document. Name it in an ArchitectureConfiguration as CMION did::

    <ArchitectureComponent ClassName="cmion_mesh.minds.fatima.connector:FAtiMAConnector"
                           ConstructorParameters="modular persistent migrating"/>

**Options** (words of the constructor parameters, separated by spaces or commas, any order):
CMION's ``modular`` (FAtiMA-Modular: ``PROPERTY-CHANGED * e(p) v``; without it the old
``PROPERTY-CHANGED e(p) v``), ``persistent`` (``PROPERTY-CHANGED-PERSISTENT``/``-NONPERSISTENT``
with ``modular``, and ``P:``/``NP:`` pairs in ``LOOK-AT``), ``migrating`` (the mind's state
migrates) and ``sleeping`` (accepted; the migration manager decides when the mind sleeps). Our
extensions: ``port:N`` (default 46874, or ``CMION_MESH_FATIMA_PORT`` when set; ``port:0`` takes a free port, written to the blackboard as
``<name>/port``), ``host:ADDR`` (default 127.0.0.1; ``host:0.0.0.0`` for every interface),
``name:N`` (the component's name, default ``fatima``), ``stop-wait:S`` (seconds between ``CMD Stop``
and ``CMD GET-STATE``, default 0.5; CMION waited 2), ``state-timeout:S`` (how long FAtiMA may
take to answer ``GET-STATE``/``SET-STATE``, default 4; with ``migrating``, the two must add up to
less than the migration's ``SECTION_DEADLINE``) and ``handshake-timeout:S`` (how long a new
connection may take to send its handshake, default 5). An unknown word is a configuration error.

**Connections.** One mind at a time: while one is connected, another connection is refused
(closed at once, with a warning naming both peers, once per host and ``REFUSED_LOG_INTERVAL``);
when the connected mind's socket closes, the next connection is accepted. The first line must be
a handshake (``parse_handshake``), of at most ``MAX_HANDSHAKE_LINE`` bytes, within
``handshake-timeout`` (``HANDSHAKE_TIMEOUT``) seconds, or the connection is closed. Until then a
connection is pending and holds nothing: the mind is the first to complete a handshake (the others
pending are then closed), so a connection that sends a few bytes and stops keeps no mind out. At
most ``MAX_PENDING`` wait at a time: one more closes the oldest. Lines are UTF-8 ending in ``\\n`` (``\\r\\n`` accepted), at
most ``MAX_LINE`` bytes (a longer one closes the connection with an error naming the peer; one
that is not UTF-8 is dropped and logged). Sockets are read and written by threads of their own:
the update loop never waits for the mind. Both directions are bounded (``Link``): at most
``MAX_IN_FLIGHT`` lines wait for the loop (then TCP holds the mind back), at most ``MAX_QUEUED``
bytes wait to be written (then the mind is disconnected: it is not reading).

**No storm on failure.** FAtiMA retries a failed action about every 250 ms, forever. An action
that failed is held (``FailureGate``): a retry of the identical action (same name and parameters)
within its hold window does not run the rules again; it is answered ``ACTION-FAILED`` after
``HELD_ANSWER_DELAY`` seconds (so the mind retries about once a second, not four times), and
counted (``held_retries`` in ``connection()``). The window starts at ``HOLD_FIRST`` seconds and
doubles with every failed rerun up to ``HOLD_MOST``; a success forgets it.

**Raw messages** (``{"line": ...}`` to ``.../rq/<name>/message``) go to the mind as they are; as the
daemon stops the mind is sent ``CMD Save`` (FAtiMA compares with ``Save``; CMION's ``SAVE`` was ignored).

**Remote actions** (``RemoteAction`` events, e.g. ``MigrationInvitation <embodiment>``) reach the
mind as CMION's connector sent them before its last revision: ``ACTION-FINISHED <subject> <action>
[params]``, FAtiMA's perception of another agent's action (subject ``World`` when the event names
none). CMION's last revision sent ``CMD GET-PROPERTIES`` instead, so the mind never heard of them.

**Migration** (option ``migrating``): see ``docs/fatima.md``. The source stops the mind, asks for
its state and puts the hex into the mind's section unchanged; if the mind does not answer within
``state-timeout`` the migration is abandoned (the mind is woken: ``CMD Start``); with no mind
connected, one connecting within ``stop-wait`` + ``state-timeout`` is asked, else the migration is
refused (``MindStateUnavailable``): the companion never leaves with an empty mind. The target sends
``CMD SET-STATE``, waits for ``STATE-SET``, then ``CMD Start``, ``ACTION-FINISHED`` for the action
that migrated it (as CMION's ``successMsg``) and ``ACTION-FAILED`` for the others that were running
(cancelled at the source), a ``LOOK-AT`` per entity and ``CMD GET-PROPERTIES``. With no mind
connected when the companion arrives, the state is kept (and carried on, should the companion leave
first) and set in the next mind that connects. Late answers (a ``STATE`` or ``STATE-SET`` whose
request was given up) are logged and ignored.
"""

from __future__ import annotations

import functools
import logging
import os
import queue
import selectors
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import msgspec

from cmion_mesh import keys, xmlsafe
from cmion_mesh.body.manager import CompetencyManager
from cmion_mesh.errors import MeshError, ProtocolError, XmlError
from cmion_mesh.ion import Simulation, Timer
from cmion_mesh.messages import ActionReport, AddContainer, Event, SetProperty
from cmion_mesh.migration.manager import SECTION_DEADLINE, MigrationCompetency, MigrationManager
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.storage import Store

log = logging.getLogger(__name__)

DEFAULT_PORT = 46874
#: The port a connector listens on when its parameters name none (instead of ``DEFAULT_PORT``).
PORT_VARIABLE = "CMION_MESH_FATIMA_PORT"
DEFAULT_HOST = "127.0.0.1"
#: Longest line accepted from the mind (a STATE line of CMION's minds is 34-46 k characters).
MAX_LINE = 16 * 1024 * 1024
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
#: Seconds a new connection has to send its handshake (its first line), by default (option
#: ``handshake-timeout:S``): beyond, it is closed. Until its handshake a connection is only pending:
#: it never holds the mind's place, so one that sends a few bytes and stops keeps nobody out.
HANDSHAKE_TIMEOUT = 5.0
#: Connections accepted and not yet handshaken at a time: one more closes the oldest of them (a
#: mind sends its handshake as it connects, so it is the newest, and gets its turn).
MAX_PENDING = 8
#: Longest first line: a handshake is a few words, and a pending connection must not fill the
#: memory with ``MAX_LINE`` bytes before saying who it is.
MAX_HANDSHAKE_LINE = 64 * 1024
#: Seconds before a held retry of a failed action is answered ``ACTION-FAILED``.
HELD_ANSWER_DELAY = 1.0
#: First and longest hold window of a failed action (seconds): retries within it do not run the rules.
HOLD_FIRST = 2.0
HOLD_MOST = 30.0
#: Sent as the body stops: FAtiMA compares the command with "Save" (CMION sent "SAVE", which it ignored).
SAVE_COMMAND = "CMD Save"
#: Failed actions remembered by the gate (the oldest is forgotten beyond).
MAX_HELD = 1024
#: Subjects in the semantic memory that CMION did not copy into the world model.
_NOT_ENTITIES = frozenset({"ProbBias", "IOS", "IOF", "ActionContext", ""})
_READ_CHUNK = 256 * 1024

ActionKey = tuple[str, tuple[str, ...]]


# --- options ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Options:
    modular: bool = False
    persistent: bool = False
    migrating: bool = False
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    name: str = "fatima"
    stop_wait: float = 0.5
    state_timeout: float = 4.0
    handshake_timeout: float = HANDSHAKE_TIMEOUT


_FLAGS = ("modular", "persistent", "migrating", "sleeping")


def parse_options(parameters: Sequence[str]) -> Options:
    """CMION's option words plus our ``key:value`` extensions; ``MeshError`` naming a bad word."""
    flags: set[str] = set()
    values: dict[str, Any] = {}
    for word in " ".join(parameters).replace(",", " ").split():
        key, sep, raw = word.partition(":")
        key = key.lower()
        if not sep:
            if key not in _FLAGS:
                raise MeshError(f"unknown option {word!r} of the FAtiMA connector (known: {', '.join(_FLAGS)}, port:N, host:ADDR, "
                                "name:N, stop-wait:S, state-timeout:S, handshake-timeout:S)")
            flags.add(key)
            continue
        try:
            if key == "port":
                port = int(raw)
                if not 0 <= port <= 65535:
                    raise ValueError("not a TCP port")
                values["port"] = port
            elif key == "host":
                if not raw:
                    raise ValueError("empty")
                values["host"] = raw
            elif key == "name":
                values["name"] = keys.check_name(raw, "component")
            elif key in ("stop-wait", "state-timeout"):
                seconds = float(raw)
                if not 0.0 <= seconds <= 600.0:
                    raise ValueError("not a number of seconds from 0 to 600")
                values[key.replace("-", "_")] = seconds
            elif key == "handshake-timeout":
                seconds = float(raw)
                if not 0.0 < seconds <= 600.0:  # 0 would close every connection before its handshake
                    raise ValueError("not a number of seconds above 0, up to 600")
                values["handshake_timeout"] = seconds
            else:
                raise ValueError("unknown option")
        except ValueError as exc:
            raise MeshError(f"option {word!r} of the FAtiMA connector: {exc}") from None
    if "port" not in values and os.environ.get(PORT_VARIABLE, "").strip():
        # CMION's files leave the port to the code (46874): two embodiments on one machine need another.
        raw = os.environ[PORT_VARIABLE].strip()
        if not raw.isdigit() or int(raw) > 65535:
            raise MeshError(f"{PORT_VARIABLE}={raw!r} is not a TCP port")
        values["port"] = int(raw)
    options = Options(modular="modular" in flags, persistent="persistent" in flags, migrating="migrating" in flags, **values)
    if options.migrating and options.stop_wait + options.state_timeout >= SECTION_DEADLINE:
        # Past the migration manager's deadline the migration is abandoned with a vaguer reason
        # ("components ... did not give their sections") while the connector still waits.
        raise MeshError(f"options stop-wait:{options.stop_wait:g} and state-timeout:{options.state_timeout:g} of the FAtiMA "
                        f"connector add up to {options.stop_wait + options.state_timeout:g} s: with 'migrating' they must stay "
                        f"under the {SECTION_DEADLINE:g} s a migration gives each component for its section")
    return options


# --- the protocol's lines (pure functions) ---------------------------------------------------------


def format_value(value: Any) -> str:
    """A world-model value as CMION wrote it: ``True``/``False`` for booleans, JSON for structures;
    never a line break (a value must not end the line)."""
    if isinstance(value, bool):
        text = "True" if value else "False"
    elif value is None:
        text = "null"
    elif isinstance(value, str):
        text = value
    elif isinstance(value, (int, float)):
        text = repr(value)
    else:
        text = msgspec.json.encode(value).decode()
    return text.replace("\r", " ").replace("\n", " ") if ("\n" in text or "\r" in text) else text


def _token(text: str) -> str:
    """One space-free token (``LOOK-AT`` pairs are split on spaces by the mind)."""
    return "_".join(text.split()) if any(c.isspace() for c in text) else text


def action_text(name: str, parameters: Iterable[str]) -> str:
    return " ".join((name, *parameters))


def property_changed_line(entity: str, name: str, value: Any, persistent: bool, options: Options) -> str:
    if not options.modular:
        return f"PROPERTY-CHANGED {entity}({name}) {format_value(value)}"
    command = "PROPERTY-CHANGED"
    if options.persistent:
        command += "-PERSISTENT" if persistent else "-NONPERSISTENT"
    return f"{command} * {entity}({name}) {format_value(value)}"


def look_at_line(entity: str, properties: Mapping[str, Any], persistent_pairs: bool) -> str:
    """``LOOK-AT e p:v ...`` from a ``Store.tree`` node's ``properties`` ({name: {value, persistent}})."""
    parts = [f"LOOK-AT {entity}"]
    for name, prop in properties.items():
        value = prop.get("value") if isinstance(prop, Mapping) else prop
        mark = ("P:" if isinstance(prop, Mapping) and prop.get("persistent") else "NP:") if persistent_pairs else ""
        parts.append(f"{mark}{_token(name)}:{_token(format_value(value))}")
    return " ".join(parts)


@dataclass(frozen=True)
class Handshake:
    agent: str
    role: str
    display_name: str
    properties: dict[str, str]


#: First words of the mind's other lines: a first line starting with one is not a handshake.
_NOT_AGENT_NAMES = frozenset({"look-at", "CANCEL-ACTION", "STATE", "STATE-SET", "PROPERTY-CHANGED"})


def parse_handshake(line: str) -> Handshake:
    """``<agentName> <role> <displayName> k:v ...``; ``ProtocolError`` saying what is wrong otherwise."""

    def bad(why: str) -> ProtocolError:
        return ProtocolError(f"the first line must be the handshake '<agentName> <role> <displayName> k:v ...': {why}; "
                             f"got {line[:120]!r}")

    tokens = line.split()
    if len(tokens) < 3:
        raise bad(f"{len(tokens)} word(s), not at least 3")
    agent, role, display = tokens[:3]
    if agent in _NOT_AGENT_NAMES or agent.startswith("<"):
        raise bad(f"{agent!r} starts another message of the protocol")
    if not keys.is_name(agent):
        raise bad(f"agent name {agent!r} is not a valid name (no / * $ # ? nor a leading @)")
    for what, word in (("agent name", agent), ("role", role), ("display name", display)):
        if ":" in word:
            raise bad(f"the {what} {word!r} is a k:v pair (a name is missing)")
    properties: dict[str, str] = {}
    for pair in tokens[3:]:
        name, sep, value = pair.partition(":")
        if not sep or not keys.is_name(name):
            raise bad(f"{pair!r} is not a property 'name:value' with a valid name")
        properties[name] = value
    return Handshake(agent, role, display, properties)


def parse_emotional_state(line: str, where: str) -> dict[str, Any]:
    """``{"mood": float or text, "emotions": [attributes of each Emotion element]}``; ``XmlError``."""
    root = xmlsafe.loads(line.encode("utf-8"), None, name=where, max_bytes=MAX_LINE).getroot()
    mood_text = root.findtext("Mood")
    mood: Any = None
    if mood_text is not None:
        try:
            mood = float(mood_text)
        except ValueError:
            mood = mood_text.strip()
    emotions = [dict(el.attrib) for el in root.iter("Emotion")]
    return {"mood": mood, "emotions": emotions}


def parse_semantic_memory(line: str, agent: str, where: str) -> list[tuple[str, str, str, bool]]:
    """``(entity, property, value, persistent)`` of each ``<Property name="E(p)" .../>``, ``SELF``
    read as ``agent``, FAtiMA's own bookkeeping (``ProbBias``, ``IOS``, ``IOF``, ``ActionContext``)
    left out, as CMION did; ``XmlError`` if the line is not XML."""
    root = xmlsafe.loads(line.encode("utf-8"), None, name=where, max_bytes=MAX_LINE).getroot()
    found = []
    for el in root.iter("Property"):
        full = el.get("name", "")
        owner, sep, rest = full.partition("(")
        if not sep or not rest.endswith(")") or owner in _NOT_ENTITIES:
            continue
        found.append((agent if owner == "SELF" else owner, rest[:-1], el.get("value", ""),
                      el.get("persistent", "false").strip().lower() == "true"))
    return found


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


# --- the connector -----------------------------------------------------------------------------------


@dataclass
class _Running:
    key: ActionKey
    link: Link


@dataclass
class _Outgoing:
    """The source's side of a migration while the mind's state is asked for."""

    token: Any
    link: Link | None  # None: no mind was connected as the migration started; the next one is asked
    timer: Timer | None = None
    asked: bool = False  # CMD GET-STATE went out: a STATE before it answered an older request


@dataclass
class _Arrival:
    """The target's side: a state to set in the mind, then its new world to tell it."""

    state: dict[str, Any]
    link: Link | None = None  # the mind it was sent to, awaiting STATE-SET
    sent: int = 0  # which of that link's SET-STATEs it was (its STATE-SET is the answer of that number)
    timer: Timer | None = None
    awake: bool = False
    world: dict[str, Any] | None = None


class FAtiMAConnector(Mind):
    """CMION's ``FAtiMAConnector``: the FAtiMA mind over the agent-mind line protocol (see the module)."""

    def __init__(self, *parameters: str) -> None:
        self.options = parse_options(parameters)
        super().__init__(self.options.name)
        self.gate = FailureGate()
        self.listener: Listener | None = None
        self.link: Link | None = None  # the connected mind (loop)
        self._links_lock = threading.Lock()
        self._accepted: Link | None = None  # the handshaken mind the listener knows of (under the lock)
        # Connections not yet handshaken, oldest first (under the lock): at most MAX_PENDING; one
        # removed from here (timed out, pushed out, refused) can no longer become the mind.
        self._pending: dict[Link, None] = {}
        self._running: dict[str, _Running] = {}
        self._outgoing: _Outgoing | None = None
        self._given: tuple[Link, str] | None = None  # the mind that gave its state to a migration, and the state
        self._arrival: _Arrival | None = None
        self._held_timers: dict[ActionKey, Timer] = {}
        self._counts = {"actions": 0, "failures": 0, "connections": 0}
        self._closing = False
        self._properties_due = False
        # Facts the mind's semantic memory wrote into the world model: their change events are not
        # told back to the mind, which knows them ({(entity, property): (value as told, persistent)}).
        self._told: OrderedDict[tuple[str, str], tuple[str, bool]] = OrderedDict()
        # (host, what) -> (last logged, not logged since): for the warnings of ``_warn_limited``.
        self._refused: dict[tuple[str, str], tuple[float, int]] = {}
        self._refused_lock = threading.Lock()

    # --- life cycle (loop) --------------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        if not isinstance(sim.components_by_name().get(keys.WORLD_MODEL), Store):
            log.warning("FAtiMA connector %r runs without the embodiment's world model (outside its daemon?): look-at "
                        "answers name no properties and the mind does not migrate", self.name)
        sim.on_event(self._migration_event, component="migration")
        self._blackboard(AddContainer("", self.name, "mind"))
        try:
            self.listener = Listener(self.options.host, self.options.port, self._accept)
        except MeshError as exc:
            log.error("FAtiMA connector %r: %s: no FAtiMA mind can connect", self.name, exc)
            self.raise_event("MindServerFailed", {"mind": self.name, "reason": str(exc)})
        else:
            self._blackboard(SetProperty(self.name, "port", self.listener.port))
            self._blackboard(SetProperty(self.name, "connected", False))
        super().attach(sim)

    def detach(self) -> None:
        self._closing = True
        if self.listener is not None:
            self.listener.close()
        with self._links_lock:
            link, self._accepted = self._accepted, None
            pending, self._pending = list(self._pending), {}
        for waiting in pending:
            waiting.close()
        if link is not None:
            if link.handshaken and link.open:
                link.send(SAVE_COMMAND)  # the body stops: the mind keeps what it learnt in its files
            link.close(drain=2.0)
        self.link = None

    def connection(self) -> dict[str, Any]:
        """For the embodiment's description: where it listens, which mind is connected, the counts."""
        link = self.link
        with self._links_lock:
            pending = len(self._pending)
        return {"protocol": "fatima", "listening": self.listener.address if self.listener is not None else None,
                "connected": link is not None and link.handshaken, "peer": link.peer if link is not None else None,
                "agent": link.agent if link is not None else None, "held_retries": self.gate.held_retries,
                "lines_in_flight": link.in_flight if link is not None else 0,
                "bytes_queued": link.queued if link is not None else 0, "pending": pending, **self._counts}

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

    def _take_line(self, link: Link, line: str) -> None:
        try:
            self._on_line(link, line)
        finally:
            link.line_done()

    def _closed_in(self, link: Link, why: str) -> None:
        if not self.sim.post(functools.partial(self._disconnected, link, why)):
            link.close()

    def _connected(self, link: Link) -> None:
        """A pending connection (loop): its handshake is due within ``handshake_timeout``."""
        if not link.closed:
            link.handshake_timer = self.sim.call_later(self.options.handshake_timeout,
                                                       functools.partial(self._handshake_overdue, link))

    def _handshake_overdue(self, link: Link) -> None:
        if not link.handshaken:
            self._drop_pending(link, f"no handshake within {self.options.handshake_timeout:g} s")

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
        if self._closing:
            return
        log.warning("FAtiMA mind %s at %s disconnected (%s); its %d running action(s) are cancelled",
                    link.agent, link.peer, why, len(self._running))
        self.raise_event("MindDisconnected", {"mind": self.name, "agent": link.agent, "peer": link.peer, "reason": why})
        self._blackboard(SetProperty(self.name, "connected", False))
        for action_id in list(self._running):
            self.cancel(action_id)
        self._running.clear()
        for timer in self._held_timers.values():
            timer.cancel()
        self._held_timers.clear()
        self.gate.clear()
        self._told.clear()
        if self._outgoing is not None and self._outgoing.link is link:
            self._state_overdue(self._outgoing, f"disconnected ({why}) while its state was asked for")
        if self._arrival is not None and self._arrival.link is link:
            self._unwait_arrival()
            self._arrival.link = None  # kept: set in the next mind that connects

    # --- lines from the mind (loop) -----------------------------------------------------------------

    def _on_line(self, link: Link, line: str) -> None:
        if link is not self.link:
            if not link.handshaken and self._is_pending(link):
                self._handshake(link, line)
            return  # else lines read before the connection was closed: nobody wants them now
        head, _, rest = line.strip().partition(" ")
        where = f"FAtiMA mind {link.agent} at {link.peer}"
        if head == "look-at":
            self._look_at(link, rest.split()[0] if rest.split() else "")
        elif head == "STATE":
            self._state_received(link, rest.strip())
        elif head == "STATE-SET":
            self._state_set_answer(link)
        elif head == "CANCEL-ACTION":
            self._cancel_action(rest.split())
        elif head.startswith("<"):
            self._xml(link, line.strip(), where)
        elif head.startswith("PROPERTY-CHANGED") or head == "":
            pass  # the mind does not change the world by itself (CMION ignored these too)
        else:
            self._action(link, head, tuple(rest.split()))

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
        self._counts["connections"] += 1
        link.agent = hello.agent
        link.handshaken = True
        link.send("OK")
        # The mind's own properties make it an agent of the world model, as in CMION. A property
        # there already keeps its persistence (its semantic memory said which): otherwise it would
        # flip with every connection, and each flip is told to the mind again.
        self._world(AddContainer("", hello.agent, "agent"))
        known = self._world_tree().get("children", {}).get(hello.agent, {}).get("properties", {})
        for name, value in hello.properties.items():
            current = known.get(name)
            self._world(SetProperty(hello.agent, name, value, bool(isinstance(current, dict) and current.get("persistent"))))
        self.sim.request(keys.BLACKBOARD, "set_property", SetProperty("", "agentName", hello.agent))
        facts: dict[str, Any] = {"connected": True, "peer": link.peer, "agent": hello.agent, "role": hello.role,
                                 "display_name": hello.display_name}
        for fact, value in facts.items():
            self._blackboard(SetProperty(self.name, fact, value))
        self.raise_event("MindConnected", {"mind": self.name, "agent": hello.agent, "peer": link.peer, "role": hello.role})
        if self._arrival is not None and self.options.migrating:
            self._set_state(link)
        elif not self.awake:
            link.send("CMD Stop")
            outgoing = self._outgoing
            if outgoing is not None and outgoing.link is None:  # a migration waits for a mind to ask
                outgoing.link = link
                self.sim.call_later(self.options.stop_wait, functools.partial(self._ask_state, outgoing))
        else:
            link.send("CMD GET-PROPERTIES")
            for entity in self._entities(self._world_tree()):
                link.send(f"ENTITY-ADDED {entity}")

    def _look_at(self, link: Link, entity: str) -> None:
        if not entity:
            log.warning("FAtiMA mind %s at %s: 'look-at' without an entity ignored", link.agent, link.peer)
            return
        self._send_look_at(link, entity, self._world_tree())

    def _send_look_at(self, link: Link, entity: str, tree: Mapping[str, Any]) -> None:
        node = tree.get("children", {}).get(entity)
        link.send(look_at_line(entity, node.get("properties", {}) if isinstance(node, dict) else {}, self.options.persistent))
        link.send(f"ACTION-FINISHED {link.agent} look-at {entity}")

    def _xml(self, link: Link, line: str, where: str) -> None:
        try:
            if line.startswith("<EmotionalState"):
                state = parse_emotional_state(line, where)
                self._blackboard(SetProperty(self.name, "EmotionalState", line))
                self._blackboard(SetProperty(self.name, "mood", state["mood"]))
                self._blackboard(SetProperty(self.name, "emotions", state["emotions"]))
                self.sim.request(keys.BLACKBOARD, "set_property", SetProperty("", "FatimaMood", format_value(state["mood"])))
            elif line.startswith("<SemanticMemory"):
                self._semantic_memory(link, parse_semantic_memory(line, link.agent, where))
            elif line.startswith("<MemoryResult"):
                xmlsafe.loads(line.encode("utf-8"), None, name=where, max_bytes=MAX_LINE)
                self._blackboard(SetProperty(self.name, "MemoryResult", line))
            # <Relations ...> and other reports: not used by a single-agent body (CMION ignored them)
        except XmlError as exc:
            log.warning("%s sent a malformed line, ignored: %s", where, exc)

    def _semantic_memory(self, link: Link, facts: list[tuple[str, str, str, bool]]) -> None:
        """Keep the mind's knowledge on the blackboard, and copy it into the world model as CMION did
        (only what differs, so an unchanged fact is not told back to the mind)."""
        self._blackboard(SetProperty(self.name, "SemanticMemory",
                                     [{"name": f"{e}({p})", "value": v, "persistent": pers} for e, p, v, pers in facts]))
        tree = self._world_tree()
        children = tree.get("children", {})
        added: set[str] = set()
        for entity, name, value, persistent in facts:
            if not (keys.is_name(entity) and keys.is_name(name)):
                continue
            node = children.get(entity)
            if node is None and entity not in added:
                kind = "object" if any(e == entity and p == "isObject" and v.lower() == "true" for e, p, v, _ in facts) else "agent"
                self._world(AddContainer("", entity, kind))
                added.add(entity)
            current = node.get("properties", {}).get(name) if isinstance(node, dict) else None
            if isinstance(current, dict) and format_value(current.get("value")) == value and bool(current.get("persistent")) == persistent:
                continue
            self._told[(entity, name)] = (value, persistent)
            self._told.move_to_end((entity, name))
            while len(self._told) > MAX_HELD:
                self._told.popitem(last=False)
            self._world(SetProperty(entity, name, value, persistent))

    # --- actions --------------------------------------------------------------------------------------

    def _action(self, link: Link, name: str, parameters: tuple[str, ...]) -> None:
        key: ActionKey = (name, parameters)
        held = self.gate.held(key)
        if held is not None:
            if not held.answering:
                held.answering = True
                self._held_timers[key] = self.sim.call_later(HELD_ANSWER_DELAY, functools.partial(self._answer_held, link, key))
            return
        self._counts["actions"] += 1
        try:
            action_id = self.act(name, parameters, link.agent)
        except MeshError as exc:
            self._failed(link, key, str(exc))
            return
        self._running[action_id] = _Running(key, link)

    def _answer_held(self, link: Link, key: ActionKey) -> None:
        self._held_timers.pop(key, None)
        failure = self.gate.get(key)
        if failure is not None:
            failure.answering = False
        if link is self.link and link.open:
            link.send(f"ACTION-FAILED {link.agent} {action_text(*key)}")

    def _failed(self, link: Link, key: ActionKey, reason: str) -> None:
        previous = self.gate.get(key)
        retried = previous.retries if previous is not None else 0
        failure = self.gate.failed(key, reason)
        self._counts["failures"] += 1
        log.info("FAtiMA action %r of %s failed (%s); retries held for %.0f s%s", action_text(*key), link.agent, reason,
                 failure.hold, f" ({retried} retries answered since the last run)" if retried else "")
        if link is self.link and link.open:
            link.send(f"ACTION-FAILED {link.agent} {action_text(*key)}")

    def _cancel_action(self, tokens: list[str]) -> None:
        if not tokens:
            return
        key: ActionKey = (tokens[0], tuple(tokens[1:]))
        exact = [i for i, r in self._running.items() if r.key == key]
        named = [i for i, r in self._running.items() if r.key[0] == key[0]]
        chosen = exact or named[-1:]
        for action_id in chosen:
            self.cancel(action_id)

    def on_action_succeeded(self, report: ActionReport) -> None:
        running = self._running.pop(report.action_id, None)
        if running is None:
            return
        self.gate.succeeded(running.key)
        link = running.link
        if link is self.link and link.open:
            link.send(f"ACTION-FINISHED {link.agent} {action_text(*running.key)}")

    def on_action_failed(self, report: ActionReport) -> None:
        running = self._running.pop(report.action_id, None)
        if running is not None:
            self._failed(running.link, running.key, report.reason or "failed")

    def on_action_cancelled(self, report: ActionReport) -> None:
        # FAtiMA takes no feedback on a cancellation (CMION sent none).
        self._running.pop(report.action_id, None)

    def on_remote_action(self, action: MindAction) -> None:
        link = self._ready()
        if link is not None:
            link.send(f"ACTION-FINISHED {action.subject or 'World'} {action_text(action.name, action.parameters)}")

    # --- perceptions (loop) -------------------------------------------------------------------------

    def _ready(self) -> Link | None:
        link = self.link
        return link if link is not None and link.handshaken and link.open else None

    def on_entity_added(self, name: str, kind: str) -> None:
        link = self._ready()
        if link is not None:
            link.send(f"ENTITY-ADDED {name}")

    def on_entity_removed(self, name: str, kind: str) -> None:
        link = self._ready()
        if link is not None:
            link.send(f"ENTITY-REMOVED {name}")

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        if self._told and self._told.pop((entity, name), None) == (format_value(value), persistent):
            return  # the mind's own semantic memory wrote it: it knows
        link = self._ready()
        if link is not None and entity and "/" not in entity:  # entities are the world model's top level
            link.send(property_changed_line(entity, name, value, persistent, self.options))

    def on_property_removed(self, entity: str, name: str, persistent: bool) -> None:
        link = self._ready()
        if link is not None and entity and "/" not in entity:
            link.send(f"PROPERTY-REMOVED {entity} {name}")

    # --- sleep, wake, migration (loop) --------------------------------------------------------------

    def on_sleep(self) -> None:
        link = self._ready()
        if link is not None:
            link.send("CMD Stop")

    def on_wake(self) -> None:
        arrival = self._arrival
        if arrival is not None and arrival.link is not None:
            arrival.awake = True  # CMD Start once the state is set
            return
        link = self._ready()
        if link is not None:
            link.send("CMD Start")
            self._properties_due = True  # unless on_arrived, which follows a wake on arrival, asks first
            self.sim.call(functools.partial(self._ask_properties, link))

    def _ask_properties(self, link: Link) -> None:
        if self._properties_due and link is self._ready():
            link.send("CMD GET-PROPERTIES")
        self._properties_due = False

    def on_message(self, data: dict[str, Any]) -> None:
        """A raw message ``{"line": "..."}`` is sent to the mind as it is (CMION's raw messages)."""
        line = data.get("line")
        link = self._ready()
        if not isinstance(line, str) or "\n" in line or "\r" in line:
            raise MeshError(f"mind {self.name!r} takes a raw message {{'line': 'one line of text'}}, not {str(data)[:80]}")
        if link is None:
            raise MeshError(f"no FAtiMA mind is connected to {self.name!r}")
        link.send(line)

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        arrival = self._arrival
        if arrival is not None and arrival.link is not None:
            arrival.world = world_model
            return
        link = self._ready()
        if link is not None:
            self._tell_world(link, world_model)

    def _tell_world(self, link: Link, tree: Mapping[str, Any]) -> None:
        for entity in self._entities(tree):
            self._send_look_at(link, entity, tree)
        link.send("CMD GET-PROPERTIES")
        self._properties_due = False

    def _migration_event(self, event: Event) -> None:
        if event.name == "MigrationStarting":
            self._migration_starting()
        elif event.name in ("MigrationFailed", "MigrationSucceeded") and self._outgoing is not None:
            outgoing, self._outgoing = self._outgoing, None
            if outgoing.timer is not None:
                outgoing.timer.cancel()
        if event.name == "MigrationSucceeded":  # the companion left: a state kept for it left with it
            self._unwait_arrival()
            self._arrival = None
            self._companion_left()

    def _companion_left(self) -> None:
        """The mind's actions went with the companion (told to its mind where it arrived): those still
        running here are cancelled, nothing more about them is told to the mind left behind."""
        migrating = set(self._actions_running(MigrationCompetency.type))
        for action_id in list(self._running):
            if action_id not in migrating:  # the Migrate action ends by itself, with the migration
                self.cancel(action_id)
        self._running.clear()

    def _migration_starting(self) -> None:
        manager = self._migration()
        if not self.options.migrating or manager is None:
            return
        link = self._ready()
        if link is None and self._arrival is not None:
            return  # the state kept for the next mind is carried by state()
        try:
            token = manager.wait(self.name)
        except MeshError:
            return  # the migration ended already
        outgoing = _Outgoing(token, link)
        self._outgoing = outgoing
        wait = self.options.stop_wait + self.options.state_timeout
        if link is None:
            # Leaving without it would carry an empty mind: a mind connecting meanwhile is asked instead.
            log.warning("FAtiMA connector %r: the companion starts leaving with no FAtiMA mind connected; a mind that "
                        "connects within %g s is asked for its state, else the migration is refused", self.name, wait)
        else:
            # CMD Stop went out as the mind was put to sleep; give FAtiMA's cycle a moment to end.
            self.sim.call_later(self.options.stop_wait, functools.partial(self._ask_state, outgoing))
        outgoing.timer = self.sim.call_later(wait, functools.partial(self._state_overdue, outgoing))

    def _ask_state(self, outgoing: _Outgoing) -> None:
        link = outgoing.link
        if self._outgoing is outgoing and link is not None and link.open:
            outgoing.asked = True
            link.send("CMD GET-STATE")

    def _state_overdue(self, outgoing: _Outgoing, why: str = "") -> None:
        if self._outgoing is not outgoing:
            return
        self._outgoing = None
        if outgoing.timer is not None:
            outgoing.timer.cancel()
        link = outgoing.link
        wait = self.options.stop_wait + self.options.state_timeout
        if link is None:
            listening = self.listener.address if self.listener is not None else "no address (it could not listen)"
            reason = (f"no FAtiMA mind is connected to connector {self.name!r} (listening on {listening}) to give the "
                      f"companion's mind state; none connected within {wait:g} s")
        else:
            reason = (f"the FAtiMA mind {link.agent} at {link.peer} (connector {self.name!r}) "
                      f"{why or f'did not answer GET-STATE within {self.options.state_timeout:g} s'}")
        log.error("%s: the migration is refused", reason)
        self.raise_event("MindStateUnavailable", {"mind": self.name, "agent": link.agent if link is not None else "",
                                                  "peer": link.peer if link is not None else "", "reason": reason})
        manager = self._migration()
        if manager is not None:
            manager.refuse(outgoing.token, reason)

    def _state_received(self, link: Link, hex_state: str) -> None:
        outgoing = self._outgoing
        if outgoing is None or outgoing.link is not link or not outgoing.asked:
            # A late answer to a GET-STATE whose migration was abandoned: an older state than the mind's.
            log.warning("FAtiMA mind %s at %s sent a STATE nobody asked for (late, or before CMD GET-STATE): ignored",
                        link.agent, link.peer)
            return
        if not hex_state or any(c.isspace() for c in hex_state):
            self._state_overdue(outgoing, "answered GET-STATE with no state (or more than one token)")
            return
        self._outgoing = None
        if outgoing.timer is not None:
            outgoing.timer.cancel()
        self._given = (link, hex_state)
        # The Migrate action succeeds where the companion arrives (CMION's successMsg); the others
        # end here with the companion, so the mind is told they failed and retries those it still wants.
        migrating = set(self._actions_running(MigrationCompetency.type))
        finished: list[str] = []
        failed: list[str] = []
        for action_id, running in self._running.items():
            if running.link is link:
                (finished if action_id in migrating else failed).append(action_text(*running.key))
        manager = self._migration()
        if manager is not None:
            manager.resolve(outgoing.token, {
                "state": hex_state, "agent": link.agent, "from": self.sim.embodiment,
                "finished": [f"ACTION-FINISHED {link.agent} {text}" for text in finished],
                "failed": [f"ACTION-FAILED {link.agent} {text}" for text in failed]})

    def _actions_running(self, competency_type: str) -> list[str]:
        manager = self.sim.components_by_name().get("manager")
        return manager.actions_running(competency_type) if isinstance(manager, CompetencyManager) else []

    def state(self) -> dict[str, Any]:
        """A state that arrived and is not yet set in a mind (carried on if the companion leaves first)."""
        return dict(self._arrival.state) if self._arrival is not None else {}

    def restore(self, state: dict[str, Any]) -> None:
        if not self.options.migrating or not isinstance(state.get("state"), str):
            return
        if state.get("from") == self.sim.embodiment:
            # Resumed here after a migration failed past its packing: the document holds the state
            # this embodiment's mind gave, and its actions did not end.
            given = self._given
            if given is not None and given[0] is self._ready() and given[1] == state["state"]:
                return  # the mind that gave it is still here, holding it
            state = {**state, "finished": [], "failed": []}
        self._unwait_arrival()
        self._arrival = _Arrival(dict(state))
        link = self._ready()
        if link is not None:
            self._set_state(link)
        else:
            log.warning("FAtiMA connector %r: the companion's mind state arrived with no FAtiMA mind connected; it is set "
                        "in the next one that connects", self.name)

    def _set_state(self, link: Link) -> None:
        arrival = self._arrival
        assert arrival is not None
        arrival.link = link
        link.set_states_sent += 1
        arrival.sent = link.set_states_sent
        arrival.awake = arrival.awake or self.awake
        link.send(f"CMD SET-STATE {arrival.state['state']}")
        arrival.timer = self.sim.call_later(self.options.state_timeout, functools.partial(self._set_overdue, arrival))

    def _set_overdue(self, arrival: _Arrival) -> None:
        if self._arrival is arrival and arrival.link is not None:
            log.error("FAtiMA mind %s at %s did not answer SET-STATE within %g s: started anyway", arrival.link.agent,
                      arrival.link.peer, self.options.state_timeout)
            self._state_set(arrival.link, confirmed=False)

    def _state_set_answer(self, link: Link) -> None:
        """A ``STATE-SET`` line: the mind answers SET-STATEs in order, so it is the answer to the
        next one of this link; one whose arrival timed out, or was replaced, is ignored."""
        link.set_states_answered += 1
        answer = link.set_states_answered
        arrival = self._arrival
        if arrival is not None and arrival.link is link and arrival.sent == answer:
            self._state_set(link)
            return
        awaited = f"#{arrival.sent} is awaited" if arrival is not None and arrival.link is link else "none is awaited"
        log.warning("FAtiMA mind %s at %s answered SET-STATE #%d late (%s): ignored, the state kept as it is",
                    link.agent, link.peer, answer, awaited)

    def _state_set(self, link: Link, *, confirmed: bool = True) -> None:
        arrival = self._arrival
        if arrival is None or arrival.link is not link:
            return
        self._unwait_arrival()
        if confirmed:
            self._arrival = None
        else:
            arrival.link = None  # kept: set again in the next mind that connects
        if not (arrival.awake or self.awake):
            link.send("CMD Stop")
            return
        link.send("CMD Start")
        for name in ("finished", "failed"):
            lines = arrival.state.get(name)
            for line in lines if isinstance(lines, list) else []:
                if isinstance(line, str) and line.startswith("ACTION-") and "\n" not in line:
                    link.send(line)
        self._tell_world(link, arrival.world if arrival.world is not None else self._world_tree())

    def _unwait_arrival(self) -> None:
        arrival = self._arrival
        if arrival is not None and arrival.timer is not None:
            arrival.timer.cancel()
            arrival.timer = None

    def _migration(self) -> MigrationManager | None:
        manager = self.sim.components_by_name().get("migration")
        return manager if isinstance(manager, MigrationManager) else None

    # --- stores ---------------------------------------------------------------------------------------

    def _blackboard(self, write: SetProperty | AddContainer) -> None:
        self.sim.request(keys.BLACKBOARD, "set_property" if isinstance(write, SetProperty) else "add_container", write)

    def _world(self, write: SetProperty | AddContainer) -> None:
        self.sim.request(keys.WORLD_MODEL, "set_property" if isinstance(write, SetProperty) else "add_container", write)

    def _world_tree(self) -> dict[str, Any]:
        store = self.sim.components_by_name().get(keys.WORLD_MODEL)
        return store.tree() if isinstance(store, Store) else {}

    @staticmethod
    def _entities(tree: Mapping[str, Any]) -> list[str]:
        """Agents first, then objects, as CMION told them."""
        children = tree.get("children", {})
        return sorted(children, key=lambda n: (children[n].get("kind") != "agent", n))
