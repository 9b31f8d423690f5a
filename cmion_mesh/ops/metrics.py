"""Metrics and health of a daemon: Prometheus/OpenMetrics text on ``/metrics``, ``/healthz`` beside it.

``Metrics`` keeps a ``prometheus_client.CollectorRegistry`` of its own (never the global one: two
embodiments in one process, as in tests, do not mix) and is fed without touching the hot path:

* What happens (actions, migrations, custody conflicts) is counted from the embodiment's own
  events: ``Simulation.on_event`` subscriptions on the competency manager's and the migration
  manager's events only, so no other event costs anything more (the subscribers of a key are
  cached per key). The handlers run on the loop and only count.
* What is (queue depth, peers alive, companion hosted, minds and pages connected, publications
  dropped) and the kernel's own counters (events published and received, requests answered by
  status and code: ``Simulation.events_raised``, ``events_received``, ``answered()``) are read
  when scraped, by a custom collector: nothing is kept up to date between scrapes.

``MetricsServer`` serves them over HTTP (the standard library's server, on a thread of its own
that sleeps in ``select`` until a request comes), bound to loopback unless an address says
otherwise: ``/metrics`` (OpenMetrics when the scraper asks for it in ``Accept``, else the
Prometheus text format) and ``/healthz``: ``200 ok`` while the update loop has turned within
``stale_after`` seconds (``ops.heartbeat``) and the session is open, ``503`` and the reason
otherwise. Bound to loopback, it answers only requests naming a loopback host (``Host``), as the
web pages do: a site rebound to 127.0.0.1 reads nothing.

Wiring (``cli``, two calls). In ``cmd_up``, with the web bodies inside ``with pages:`` (bound before
the embodiment is announced, so an address in use is refused before anything but the name claim is
on the mesh; ``/healthz`` answers 503 "starting" until the second call)::

    if args.metrics:
        metrics_server = pages.enter_context(MetricsServer(args.metrics))

and in ``_run_daemon``, right after the embodiment has started (sharing ``ops.systemd.Service``'s
heartbeat, None outside systemd: ``Metrics`` then beats its own)::

    with embodiment, systemd.Service(embodiment) as service:
        if metrics_server is not None:
            metrics_server.attach(Metrics(embodiment, heartbeat=service.heartbeat))

(``parse_address(args.metrics)`` early in ``cmd_up`` refuses a malformed address before the session opens.)

``probe()`` is the container's health check (``Containerfile``).
"""

from __future__ import annotations

import http.server
import ipaddress
import logging
import os
import selectors
import socket
import socketserver
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterable, Iterator
from typing import Any, Protocol, Self

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import choose_encoder
from prometheus_client.registry import Collector

from cmion_mesh.errors import ConfigError, MeshError, WebServerError
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import Code, Event
from cmion_mesh.ops.heartbeat import PERIOD, Heartbeat
from cmion_mesh.transport.base import Closeable, Handle, Transport

log = logging.getLogger(__name__)

#: ``/healthz`` is unhealthy once the update loop has not turned for this long (seconds).
STALE_AFTER = 5.0
#: Seconds, for actions (a one-step plan takes milliseconds; a walk across a room, minutes).
ACTION_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0)
#: Seconds, for migrations (10 KiB in tens of ms; large identities over slow links, longer).
MIGRATION_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)
#: Actions and migrations whose start is remembered for their duration, at most (a flood of starts
#: with no end must not grow memory: the oldest is forgotten, and its end is counted without a duration).
MAX_TRACKED = 10_000
ACTION_OUTCOMES = {"ActionSucceeded": "succeeded", "ActionFailed": "failed", "ActionCancelled": "cancelled"}
#: Migration events counted, as (role, outcome): the source ends a migration it started; the
#: target sees a companion arrive or drops an attempt; ``stuck`` counts each report of a commit
#: still unanswered (it is retried).
MIGRATION_OUTCOMES = {
    "MigrationSucceeded": ("source", "succeeded"), "MigrationFailed": ("source", "failed"),
    "MigrationStuck": ("source", "stuck"), "MigrationOccurred": ("target", "arrived"),
    "MigrationDropped": ("target", "dropped"),
}
_CODES = frozenset(code.value for code in Code)
_STATUSES = frozenset({"accepted", "rejected", "conflict"})
#: A scrape or health check that does not send its request within this long is cut.
REQUEST_TIMEOUT = 5.0


class Observed(Protocol):
    """What ``Metrics`` reads of an embodiment (``body.embodiment.Embodiment``)."""

    name: str
    sim: Simulation
    transport: Transport

    @property
    def inhabitant(self) -> str | None: ...


class Metrics(Handle):
    """The metrics of one embodiment, in ``registry``; ``close`` (idempotent) stops counting.

    ``heartbeat``: the update loop's (shared with ``ops.systemd.Service``), else one of its own.
    ``stale_after``: how long the loop may go without turning before ``health()`` says so.
    """

    def __init__(self, embodiment: Observed, *, heartbeat: Heartbeat | None = None, stale_after: float = STALE_AFTER,
                 manager: str = "manager", migration: str = "migration") -> None:
        self.embodiment = embodiment
        self.sim = embodiment.sim
        self.name = embodiment.name
        self._owned_heartbeat: Heartbeat | None = None
        if heartbeat is None:
            heartbeat = self._owned_heartbeat = Heartbeat(self.sim, PERIOD)
        self.heartbeat = heartbeat
        # Never stale between two healthy beats.
        self.stale_after = max(stale_after, 2 * self.heartbeat.period)
        self.registry = CollectorRegistry(auto_describe=True)
        me = self.name
        self.actions = Counter("cmion_mesh_actions", "Actions ended, by outcome", ["embodiment", "outcome"], registry=self.registry)
        self.action_seconds = Histogram("cmion_mesh_action_duration_seconds", "Time from an action's start to its end, by outcome",
                                        ["embodiment", "outcome"], buckets=ACTION_BUCKETS, registry=self.registry)
        self.migrations = Counter("cmion_mesh_migrations", "Migrations ended here, by role (source or target) and outcome",
                                  ["embodiment", "role", "outcome"], registry=self.registry)
        self.migration_seconds = Histogram("cmion_mesh_migration_duration_seconds",
                                           "Time from a migration's start at its source to its end there, by outcome",
                                           ["embodiment", "outcome"], buckets=MIGRATION_BUCKETS, registry=self.registry)
        self.custody_conflicts = Counter("cmion_mesh_custody_conflicts", "Custody conflicts lost: another embodiment holds "
                                         "the companion living here, and keeps it by the rule", ["embodiment"], registry=self.registry)
        # Every series exists from the first scrape on (at 0): a rate over a counter that appears later
        # misses its first counts. Resolved once: the handlers then only count (no label lookup per event).
        self._action_counts = {event: self.actions.labels(me, outcome) for event, outcome in ACTION_OUTCOMES.items()}
        self._action_times = {event: self.action_seconds.labels(me, outcome) for event, outcome in ACTION_OUTCOMES.items()}
        self._migration_counts = {event: self.migrations.labels(me, role, outcome) for event, (role, outcome) in MIGRATION_OUTCOMES.items()}
        self._migration_times = {event: self.migration_seconds.labels(me, MIGRATION_OUTCOMES[event][1])
                                 for event in ("MigrationSucceeded", "MigrationFailed")}
        self._conflicts = self.custody_conflicts.labels(me)
        self.registry.register(_Readings(self))
        self._actions_started: dict[str, float] = {}
        self._migrations_started: dict[str, float] = {}
        self._closed = False
        self._subscriptions: list[Closeable] = []
        try:
            self._subscriptions.append(self.sim.on_event(self._on_action, component=manager))
            self._subscriptions.append(self.sim.on_event(self._on_migration, component=migration))
        except BaseException:
            self.close()
            raise

    # --- counted from events, on the loop -----------------------------------------------------

    def _on_action(self, event: Event) -> None:
        name = event.name
        if name == "ActionStarted":
            data = event.data
            if isinstance(data, dict):
                _remember(self._actions_started, str(data.get("action_id", "")), event.time)
            return
        counter = self._action_counts.get(name)
        if counter is None:
            return  # ActionAttempt
        counter.inc()
        data = event.data
        started = self._actions_started.pop(str(data.get("action_id", "")), None) if isinstance(data, dict) else None
        if started is not None:  # an action refused before it started has no duration
            self._action_times[name].observe(max(0.0, event.time - started))

    def _on_migration(self, event: Event) -> None:
        name = event.name
        data = event.data if isinstance(event.data, dict) else {}
        attempt = str(data.get("attempt") or "")
        if name == "MigrationStarting":
            if attempt:
                _remember(self._migrations_started, attempt, event.time)
            return
        if name == "CustodyConflict":
            # Raised when the keeper changes: on a conflict this embodiment loses (another holder keeps
            # the companion), and again when it ends (no other holder left), which is not one.
            holders = data.get("holders")
            if isinstance(holders, dict) and len(holders) > 1:
                self._conflicts.inc()
            return
        counter = self._migration_counts.get(name)
        if counter is None:
            return
        counter.inc()
        timer = self._migration_times.get(name)
        if timer is not None and attempt:
            started = self._migrations_started.pop(attempt, None)
            if started is not None:  # one refused before it started has none
                timer.observe(max(0.0, event.time - started))

    # --- health --------------------------------------------------------------------------------

    def health(self) -> tuple[bool, str]:
        """Whether the update loop turns and the session is open; the reason when not."""
        if self._closed or self.sim.closed:
            return False, f"embodiment {self.name!r} is stopping: its update loop is closed"
        try:
            self.embodiment.transport.peers()  # raises once the session is closed
        except MeshError as exc:
            return False, f"embodiment {self.name!r}: the zenoh session is not open ({exc})"
        age = self.heartbeat.age()
        if age is None:
            return False, f"embodiment {self.name!r}: the update loop has not turned yet"
        if age > self.stale_after:
            return False, f"embodiment {self.name!r}: the update loop has not turned for {age:.1f} s (limit {self.stale_after:g} s)"
        return True, "ok"

    def exposition(self, accept: str | None) -> tuple[bytes, str]:
        """The registry as text in the format ``accept`` asks for (OpenMetrics or Prometheus), and its content type."""
        encoder, content_type = choose_encoder(accept or "")
        return encoder(self.registry), content_type

    def __enter__(self) -> Self:
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for subscription in self._subscriptions:
            subscription.close()
        if self._owned_heartbeat is not None:
            self._owned_heartbeat.close()


def _remember(started: dict[str, float], key: str, when: float) -> None:
    if len(started) >= MAX_TRACKED:
        started.pop(next(iter(started)))  # the oldest: dicts keep insertion order
    started[key] = when


class _Readings(Collector):
    """What is read when scraped: the kernel's counters and the embodiment's state now."""

    def __init__(self, metrics: Metrics) -> None:
        self._metrics = metrics

    def describe(self) -> Iterable[Metric]:
        return []  # the families vary (minds, pages): nothing to check names against at registration

    def collect(self) -> Iterator[Metric]:
        m = self._metrics
        me, sim, embodiment = m.name, m.sim, m.embodiment
        labels = ["embodiment"]

        def counter(name: str, doc: str, value: float) -> CounterMetricFamily:
            family = CounterMetricFamily(name, doc, labels=labels)
            family.add_metric([me], value)
            return family

        def gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
            family = GaugeMetricFamily(name, doc, labels=labels)
            family.add_metric([me], value)
            return family

        yield counter("cmion_mesh_events_published", "Events this embodiment raised (each published on the mesh)", sim.events_raised)
        yield counter("cmion_mesh_events_received", "Events received from other sessions", sim.events_received)
        answered = CounterMetricFamily("cmion_mesh_requests_answered", "Requests answered over the mesh, by status and code",
                                       labels=["embodiment", "status", "code"])
        # Accepted is there from the first scrape on, at 0, as the counters above are.
        for (status, code), count in sorted({("accepted", ""): 0, **bounded_codes(sim.answered())}.items()):
            answered.add_metric([me, status, code], count)
        yield answered
        yield counter("cmion_mesh_loop_updates", "Updates the loop has run", sim.updates)
        yield gauge("cmion_mesh_request_queue_depth", "Work waiting for the update loop (requests, remote events, calls)", sim.queued())
        age = m.heartbeat.age()
        if age is not None:
            yield gauge("cmion_mesh_loop_heartbeat_age_seconds", "Seconds since the update loop last ran its heartbeat", age)
        yield from _guarded(me, "publications dropped", lambda: [counter(
            "cmion_mesh_publications_dropped", "Publications dropped because the network could not take them in time",
            embodiment.transport.dropped_publications)])
        presence = getattr(embodiment, "presence", None)
        if presence is not None:
            yield from _guarded(me, "peers alive", lambda: [gauge(
                "cmion_mesh_peers_alive", "Other embodiments alive in the mesh, as this one sees them",
                len(presence.alive() - {me}))])
        if getattr(embodiment, "migration", None) is not None:
            yield gauge("cmion_mesh_companion_hosted", "1 while a companion lives here", 1 if embodiment.inhabitant else 0)
        yield from _guarded(me, "connections", lambda: _connections(me, sim))


def bounded_codes(counts: dict[tuple[str, str], int]) -> dict[tuple[str, str], int]:
    """``Simulation.answered()`` with the statuses and codes this version does not know summed as
    "other": a code forwarded from a peer is any string, and no peer may grow the series."""
    out: dict[tuple[str, str], int] = {}
    for (status, code), count in counts.items():
        key = (status if status in _STATUSES else "other", code if code in _CODES else "other")
        out[key] = out.get(key, 0) + count
    return out


def _guarded(embodiment: str, what: str, read: Any) -> list[Metric]:
    """A reading that may fail as the embodiment closes: the scrape goes on without it."""
    try:
        result: list[Metric] = list(read())
        return result
    except Exception as exc:
        log.debug("metrics of %s: cannot read %s: %s", embodiment, what, exc)
        return []


def _connections(me: str, sim: Simulation) -> list[Metric]:
    """Minds linked from outside the process (FAtiMA) and pages open on web bodies, per component."""
    minds = GaugeMetricFamily("cmion_mesh_mind_connected", "1 while the mind outside this process is connected",
                              labels=["embodiment", "mind", "protocol"])
    pages = GaugeMetricFamily("cmion_mesh_web_pages_open", "Pages open on a web body", labels=["embodiment", "component"])
    for component in sim.components:
        link = getattr(component, "connection", None)
        if callable(link):
            info = link()
            if isinstance(info, dict) and "connected" in info:
                minds.add_metric([me, component.name, str(info.get("protocol", ""))], 1 if info["connected"] else 0)
        # A web body keeps its open pages in a set read here by its size alone (an atomic read).
        open_pages = getattr(component, "_pages", None)
        if isinstance(open_pages, set):
            pages.add_metric([me, component.name], len(open_pages))
    return [minds, pages]


# --- the HTTP server ----------------------------------------------------------------------------


def parse_address(text: str) -> tuple[str, int]:
    """``--metrics``'s ``HOST:PORT``, ``:PORT`` or ``PORT`` (loopback when no host), as the web pages' addresses."""
    from cmion_mesh.web.server import parse_bind

    try:
        return parse_bind(text)
    except ConfigError as exc:
        raise ConfigError(f"--metrics: {exc.detail.replace('web address', 'metrics address')}") from None


class _Handler(http.server.BaseHTTPRequestHandler):
    server: _HTTPServer
    server_version = "cmion-mesh"
    timeout = REQUEST_TIMEOUT

    def do_GET(self) -> None:
        owner = self.server.owner
        from cmion_mesh.web.server import host_allowed

        if not host_allowed({"host": self.headers.get("Host", "")}, loopback=owner.loopback):
            self._send(403, b"a server on loopback answers only requests to a loopback name\n")
            return
        path = self.path.partition("?")[0]
        metrics = owner.metrics
        if path == "/healthz":
            healthy, reason = (False, "starting: the embodiment has not joined the mesh yet") if metrics is None else metrics.health()
            self._send(200 if healthy else 503, f"{reason}\n".encode())
        elif path == "/metrics":
            if metrics is None:
                self._send(503, b"starting: the embodiment has not joined the mesh yet\n")
                return
            body, content_type = metrics.exposition(self.headers.get("Accept"))
            self._send(200, body, content_type)
        else:
            self._send(404, b"not found: /metrics or /healthz\n")

    def _send(self, code: int, body: bytes, content_type: str = "text/plain; charset=utf-8") -> None:
        self.send_response(code)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        pass  # no line per scrape: a daemon scraped every 15 s for months would fill its journal with them


class _HTTPServer(http.server.ThreadingHTTPServer):
    daemon_threads = False  # joined at close: every thread this server starts ends with it

    def __init__(self, owner: MetricsServer, address: tuple[str, int]) -> None:
        self.owner = owner
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        super().__init__(address, _Handler)

    def server_bind(self) -> None:
        # HTTPServer's own asks DNS for the host's full name (getfqdn), which can wait on the network.
        socketserver.TCPServer.server_bind(self)
        self.server_name, self.server_port = str(self.server_address[0]), int(self.server_address[1])


class MetricsServer(Handle):
    """Serves ``/metrics`` and ``/healthz`` on ``address`` (``HOST:PORT``, loopback by default) from
    a thread of its own, from construction until ``close()`` (idempotent; closes the attached
    ``Metrics``). Bound at once: an address in use raises ``WebServerError`` naming it, a malformed
    one ``ConfigError``. Until ``attach``, both paths answer 503 "starting"."""

    def __init__(self, address: str, metrics: Metrics | None = None) -> None:
        self.host, port = parse_address(address)
        self.loopback = self.host == "localhost" or ipaddress.ip_address(self.host).is_loopback
        self.metrics = metrics
        try:
            self._server = _HTTPServer(self, (self.host, port))
        except OSError as exc:
            raise WebServerError(f"metrics server cannot listen on {self.host}:{port}: {exc.strerror or exc}") from None
        self.port: int = self._server.server_address[1]
        self._wake_r, self._wake_w = os.pipe()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="metrics-http", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    def attach(self, metrics: Metrics) -> Metrics:
        """Serve ``metrics`` from now on (the server closes it)."""
        self.metrics = metrics
        return metrics

    def _run(self) -> None:
        # Sleeps in select until a request or close: no wake-up while nobody asks (serve_forever polls).
        server = self._server
        with selectors.DefaultSelector() as selector:
            selector.register(server.socket, selectors.EVENT_READ)
            selector.register(self._wake_r, selectors.EVENT_READ)
            while not self._closed:
                for key, _ in selector.select():
                    if key.fileobj is server.socket and not self._closed:
                        self._accept()

    def _accept(self) -> None:
        server = self._server
        try:
            request, client = server.get_request()
        except OSError:
            return
        try:
            server.process_request(request, client)  # a thread per request, joined at close
        except Exception:
            server.handle_error(request, client)
            server.shutdown_request(request)

    def __enter__(self) -> Self:
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        os.write(self._wake_w, b"x")
        if self._thread is not threading.current_thread():
            self._thread.join(REQUEST_TIMEOUT)
        self._server.server_close()  # joins the request threads (each bounded by REQUEST_TIMEOUT)
        os.close(self._wake_r)
        os.close(self._wake_w)
        if self.metrics is not None:
            self.metrics.close()


def serve(address: str, embodiment: Observed | None = None, *, heartbeat: Heartbeat | None = None) -> MetricsServer:
    """A ``MetricsServer`` on ``address``, serving ``embodiment``'s ``Metrics`` at once when given."""
    server = MetricsServer(address)
    if embodiment is not None:
        try:
            server.attach(Metrics(embodiment, heartbeat=heartbeat))
        except BaseException:
            server.close()
            raise
    return server


# --- the container's health check -------------------------------------------------------------


def metrics_option(argv: list[str]) -> str | None:
    """The value of ``--metrics`` in a command line, or None."""
    for i, arg in enumerate(argv):
        if arg == "--metrics" and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith("--metrics="):
            return arg.partition("=")[2]
    return None


def probe(address: str | None = None, *, timeout: float = 3.0) -> int:
    """Exit status of a container health check: 0 when ``/healthz`` answers 200 (or there is nothing
    to check: no metrics address), 1 otherwise, the reason printed.

    The address: ``address``, else ``$CMION_MESH_METRICS``, else ``--metrics`` on the command line
    of the container's first process (the daemon). A wildcard host is asked on loopback."""
    if address is None:
        address = os.environ.get("CMION_MESH_METRICS") or None
    if address is None:
        try:
            with open("/proc/1/cmdline", "rb") as f:
                address = metrics_option([a.decode(errors="replace") for a in f.read().split(b"\0")])
        except OSError:
            address = None
    if not address:
        return 0
    try:
        host, port = parse_address(address)
    except ConfigError as exc:
        print(f"unhealthy: {exc}")
        return 1
    host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    url = f"http://{f'[{host}]' if ':' in host else host}:{port}/healthz"
    started = time.monotonic()
    try:
        with urllib.request.urlopen(url, timeout=timeout) as reply:
            return 0 if reply.status == 200 else 1
    except urllib.error.HTTPError as exc:
        print(f"unhealthy: {url}: {exc.code} {exc.read().decode(errors='replace').strip()}")
    except OSError as exc:
        print(f"unhealthy: {url}: no answer after {time.monotonic() - started:.1f} s ({exc})")
    return 1
