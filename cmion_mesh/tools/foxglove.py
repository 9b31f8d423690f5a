"""``cmion-mesh foxglove``: the mesh live in Foxglove, over the Foxglove WebSocket protocol.

A ``FoxgloveServer`` serves what the mesh says as it says it, with Foxglove's own SDK
(``foxglove-sdk``, the extra ``cmion-mesh[foxglove]``): Foxglove connects to
``ws://HOST:PORT`` (Open connection, Foxglove WebSocket) and shows events, storage, liveliness,
requests answered and the story as log lines, on the very channels and schemas a recording has
(``tools/recording_format.py`` defines both: ``route``, ``route_token``, ``SCHEMAS``). A channel
is advertised the first time something is said on it, and the last messages of each channel are
kept (``KEEP``, at most ``KEEP_BYTES`` but always the last one): the first client to subscribe to
a channel gets them at once, in order, then what is said after. So the messages that come in a
burst with a new channel (a migration's steps) are not lost to the client it was just advertised
to, and a panel opened late shows the latest state. A client subscribing to a channel another one
already has gets what is said after only (the kept ones again would reach the other too).

Read-only: the server offers no publishing, services or parameters, so nothing that connects
can act on the mesh. Loopback by default; any program (a web page too) that reaches the address
reads the mesh.

Threads: the transport's workers stamp what they receive and hand it to a bounded inbox
(``recording.Inbox``: what does not fit is dropped and counted), and so do the SDK's callbacks
(a client subscribing); one worker routes it and logs it on the server's channels. The SDK runs
its own (native) threads; ``close`` stops everything.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError
from cmion_mesh.tools.recording import MAX_CHANNELS, MAX_QUEUED_BYTES, MAX_QUEUED_SAMPLES, Inbox
from cmion_mesh.tools.recording_format import SCHEMAS, Routed, follow, mesh_filters, overflow_topic, route, route_token
from cmion_mesh.transport.base import Closeable, Transport

if TYPE_CHECKING:
    import foxglove

#: Foxglove's own default port for its WebSocket connection.
DEFAULT_PORT = 8765
#: Messages kept per channel for its first subscriber, and the most bytes they take (the last
#: message is kept whatever its size).
KEEP = 32
KEEP_BYTES = 256 * 1024
#: Most often a drop (or a failure to log) is reported.
REPORT_INTERVAL = 1.0
INSTALL_HINT = "pip install 'cmion-mesh[foxglove]'"


def sdk() -> Any:
    """The ``foxglove`` module (Foxglove's SDK), or a ``ConfigError`` saying how to install it."""
    try:
        import foxglove
    except ImportError as exc:
        raise ConfigError(f"the Foxglove connection needs Foxglove's SDK ({exc}): {INSTALL_HINT}") from None
    return foxglove


class FoxgloveServer:
    """Serves ``mesh`` (through ``transport``) on ``ws://host:port`` from construction until
    ``close()`` (idempotent; a context manager). ``port`` 0: a free one (``port`` says which).
    ``filters``: key expressions as ``record``'s (default: the whole mesh and its requests'
    answers); liveliness is always served."""

    def __init__(
        self, transport: Transport, mesh: str, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
        filters: Sequence[str] = (), max_queued: int = MAX_QUEUED_SAMPLES, report: Callable[[str], None] | None = None,
    ) -> None:
        self.mesh = keys.check_name(mesh, "mesh")
        self.host = host
        self.filters = mesh_filters(mesh, filters)
        fox = sdk()
        self._fox = fox
        self._report = report or (lambda text: print(text, file=sys.stderr, flush=True))
        self._context = fox.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._by_id: dict[int, foxglove.Channel] = {}
        # channel id -> its last messages: (number of the message, JSON bytes, log time), and their bytes
        self._kept: dict[int, deque[tuple[int, bytes, int]]] = {}
        self._kept_bytes: dict[int, int] = {}
        self._subscribed: dict[int, set[int]] = {}  # channel id -> the clients subscribed to it
        self._schemas: dict[str, foxglove.Schema] = {}
        self._inbox = Inbox(max_queued, MAX_QUEUED_BYTES)
        self._lock = threading.Lock()
        self._closed = False
        self.messages = 0
        self.failed = 0
        try:
            self._server = fox.start_server(name=f"cmion-mesh {self.mesh}", host=host, port=port, context=self._context,
                                            server_listener=_Listener(self))
        except RuntimeError as exc:  # the SDK's error: the address is in use, or no address at all
            raise ConfigError(f"cannot serve Foxglove on {host}:{port}: {exc}") from None
        self.port: int = self._server.port
        self._worker = threading.Thread(target=self._run, name="foxglove-worker", daemon=True)
        self._worker.start()
        self._subscriptions: list[Closeable] = []
        try:
            self._subscriptions = follow(transport, mesh, self.filters, self._inbox.put_samples, self._inbox.put_token)
        except BaseException:
            self.close()
            raise

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    @property
    def dropped(self) -> int:
        """Samples dropped because the worker fell behind."""
        return self._inbox.dropped

    def topics(self) -> list[str]:
        """The channels advertised so far."""
        with self._lock:
            return sorted(self._channels)

    def subscribers(self, topic: str) -> int:
        """How many clients subscribe to the channel ``topic`` now."""
        with self._lock:
            channel = self._channels.get(topic)
            return len(self._subscribed.get(channel.id(), ())) if channel is not None else 0

    def __enter__(self) -> FoxgloveServer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # --- on the SDK's threads: hand over, nothing more ------------------------------------------------

    def subscribed(self, client: int, channel: int, yes: bool) -> None:
        """A client subscribed to a channel (``yes``) or no longer is: the first one gets the kept
        messages logged before now (those logged after reach it anyway)."""
        with self._lock:
            clients = self._subscribed.setdefault(channel, set())
            first = yes and not clients
            (clients.add if yes else clients.discard)(client)
        if first:
            self._inbox.put((self.messages, channel), 1, 0)

    # --- the worker -------------------------------------------------------------------------------

    def _run(self) -> None:
        reported_drops = reported_failures = 0
        last_report = 0.0
        while True:
            items = self._inbox.take(REPORT_INTERVAL)
            for stamp, item in items:
                if isinstance(item, int):
                    self._resend(item, logged_before=stamp)
                    continue
                if isinstance(item, tuple):
                    key, alive = item
                    routed = route_token(key, alive, stamp)
                else:
                    routed = [r for sample in item for r in route(sample, stamp)]
                for message in routed:
                    self._log(message, stamp)
            now = time.monotonic()
            dropped, failed = self._inbox.dropped, self.failed
            if (dropped, failed) != (reported_drops, reported_failures) and (now - last_report >= REPORT_INTERVAL or self._inbox.closed):
                self._report(f"foxglove: {dropped} samples dropped (the server fell behind), {failed} messages not served")
                reported_drops, reported_failures, last_report = dropped, failed, now
            if self._inbox.closed and not items:
                return

    def _log(self, routed: Routed, stamp: int) -> None:
        try:
            channel = self._channel(routed)
            self.messages += 1
            self._keep(channel.id(), routed.data, stamp)
            channel.log(routed.data, log_time=stamp)
        except Exception:  # the SDK refused it: counted, reported
            self.failed += 1

    def _keep(self, channel_id: int, data: bytes, stamp: int) -> None:
        kept = self._kept.setdefault(channel_id, deque())
        kept.append((self.messages, data, stamp))
        size = self._kept_bytes.get(channel_id, 0) + len(data)
        while len(kept) > 1 and (len(kept) > KEEP or size > KEEP_BYTES):
            size -= len(kept.popleft()[1])
        self._kept_bytes[channel_id] = size

    def _resend(self, channel_id: int, *, logged_before: int) -> None:
        """The kept messages of a channel that were logged before its first client subscribed
        (message numbers up to ``logged_before``), to the channel (that is, to that client)."""
        channel = self._by_id.get(channel_id)
        for number, data, stamp in list(self._kept.get(channel_id, ())):
            if channel is None or number > logged_before:
                break
            try:
                channel.log(data, log_time=stamp)
            except Exception:
                self.failed += 1

    def _channel(self, routed: Routed) -> foxglove.Channel:
        topic = routed.topic
        channel = self._channels.get(topic)
        if channel is None and len(self._channels) >= MAX_CHANNELS:
            topic = overflow_topic(routed, self.mesh)
            channel = self._channels.get(topic)
        if channel is None:
            schema = self._schemas.get(routed.schema)
            if schema is None:
                schema = self._schemas[routed.schema] = self._fox.Schema(name=routed.schema, encoding="jsonschema",
                                                                        data=SCHEMAS[routed.schema])
            channel = self._fox.Channel(topic, schema=schema, message_encoding="json", context=self._context)
            with self._lock:
                self._channels[topic] = channel
                self._by_id[channel.id()] = channel
        return channel

    def close(self) -> None:
        """Stop serving: the subscriptions first, then the worker (what is waiting is served), the
        channels (unadvertised) and the server."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for subscription in self._subscriptions:
            subscription.close()
        self._inbox.close()
        self._worker.join()
        with self._lock:
            channels = list(self._channels.values())
        for channel in channels:
            channel.close()
        self._server.stop()


class _Listener:
    """The SDK's ``ServerListener``: subscriptions told to the server (and nothing else allowed)."""

    def __init__(self, server: FoxgloveServer) -> None:
        self._server = server

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self._server.subscribed(client.id, channel.id, True)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self._server.subscribed(client.id, channel.id, False)
