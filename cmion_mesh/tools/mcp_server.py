"""An MCP server for one companion (``cmion-mesh mcp COMPANION``): any MCP client drives the body
the companion lives in now, on the official ``mcp`` SDK (its low-level ``Server``).

What is offered is decided by ``companion_view`` from the host's ``describe``: the body's
abilities as tools, with ``migrate`` and ``peers``; its world model and blackboard as resources.
This module is the I/O around it:

* **following the companion**: the custody liveliness tokens say who holds it (the holder at the
  highest epoch: a target claims the next epoch as it receives it, and withdraws if the handshake
  is abandoned), and so do the arrival events (``MigrationOccurred``..., all a member's
  certificate may follow in secure mode); when the host changes, the new one is described and
  the clients are told (tools and resources list changed, both resources updated). Presence
  changes re-list the ``migrate`` targets.
* **notifications** in both eras the SDK serves: to the sessions of the handshake era directly
  (``notifications/tools/list_changed``, ``resources/updated`` to those that subscribed), and to
  ``subscriptions/listen`` streams of the 2026 era through the SDK's in-memory bus.
* **tool calls**: ``tools/mcp_calls.py`` (actions with progress and cancellation, ``migrate``,
  ``peers``); this module checks the call first (a tool the body has, arguments, read-only).

Threads: the MCP server runs on one asyncio loop; mesh requests, which wait, run in worker
threads (``anyio.to_thread``); zenoh callbacks only hand their sample to the loop
(``call_soon_threadsafe``), never blocking. Only the loop touches the state below.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import socket
from collections.abc import Callable, Iterator
from functools import partial
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import mcp_types as types
from anyio.abc import TaskStatus
from mcp.server.lowlevel.server import NotificationOptions, Server
from mcp.server.session import ServerSession
from mcp.server.subscriptions import InMemorySubscriptionBus, ListenHandler, ResourcesListChanged, ResourceUpdated, ToolsListChanged

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import InvalidArguments, MeshError
from cmion_mesh.messages import Event
from cmion_mesh.tools.companion_view import ResourceSpec, ToolSpec, companion_resources, companion_tools, store_document
from cmion_mesh.tools.mcp_calls import DESCRIBE_TIMEOUT, ToolCalls, text_result
from cmion_mesh.transport.base import Closeable
from cmion_mesh.web.server import _Server as UvicornServer  # uvicorn's, waiting for shutdown without polling

log = logging.getLogger(__name__)
T = TypeVar("T")

READ_TIMEOUT = 5.0
#: The events by which an embodiment says the companion lives there now.
ARRIVALS = frozenset({"MigrationOccurred", "CompanionResumed", "CompanionBorn"})
#: How long custody tokens are let settle before the host they name is taken as the companion's.
SETTLE = 0.1


def _connection_of(session: ServerSession) -> object:
    # A ServerSession is built per request; the connection it belongs to is what lasts (and what a
    # notification outside any request is sent on). The SDK keeps it private: fall back to the
    # session itself, which still works, only with less deduplication.
    return getattr(session, "_connection", session)


class CompanionServer:
    """The MCP server of ``companion`` in the mesh of ``client``. ``serve_stdio`` or ``serve_http``
    (each returns when the client leaves, or on Ctrl-C); ``close`` (idempotent) stops following."""

    def __init__(self, client: MeshClient, companion: str, *, allow_actions: bool = False, join_timeout: float = 5.0,
                 secure: bool = False) -> None:
        self.client = client
        self.join_timeout = join_timeout
        self.companion = keys.check_name(companion, "companion")
        self.allow_actions = allow_actions
        self.host: str | None = None
        self.description: dict[str, Any] = {}
        self.alive: set[str] = set()
        self.tools: dict[str, ToolSpec] = {}
        self.resources: dict[str, ResourceSpec] = {}
        self._settling = False
        self._holders: dict[str, int] = {}  # embodiment -> epoch of its custody token of the companion
        self._describing = 0  # generation of the last describe asked: a late answer of an older one is dropped
        self._sessions: dict[object, ServerSession] = {}  # handshake-era connections, by connection
        self._subscribed: dict[str, set[object]] = {}  # uri -> connections that subscribed to it
        self._pending_updates: set[str] = set()
        self.calls = ToolCalls(client, self.companion, secure=secure)
        self._handles: list[Closeable] = []
        self._host_handles: list[Closeable] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        self.bus = InMemorySubscriptionBus()
        self.listen = ListenHandler(self.bus)
        self.server: Server[Any] = Server(
            "cmion-mesh", version=_version(),
            instructions=f"You drive {self.companion}, a companion that lives in one body (embodiment) at a time and can "
                         "migrate between bodies with its memory. The tools are the actions of the body it lives in now; "
                         "they change when it migrates. Resources: that body's world model and blackboard.",
            on_list_tools=self._list_tools, on_call_tool=self._call_tool, on_list_resources=self._list_resources,
            on_read_resource=self._read_resource, on_subscribe_resource=self._subscribe, on_unsubscribe_resource=self._unsubscribe,
            on_subscriptions_listen=self.listen,
        )
        self.server.middleware = []  # the SDK's tracing middleware: a span per message, for nobody here
        self.server.add_notification_handler("notifications/initialized", types.NotificationParams, self._initialized)

    # --- starting and stopping ------------------------------------------------------------------

    async def start(self) -> None:
        """Find the companion, describe its body, and follow it (on the running loop)."""
        self._loop = asyncio.get_running_loop()
        host = await self._thread(partial(self.client.find_companion, self.companion, timeout=self.join_timeout))
        description = await self._thread(partial(self.client.describe, host, timeout=DESCRIBE_TIMEOUT))
        presence = self.client.presence
        self.alive = presence.alive()
        self.host = host
        self._set_description(host, description)
        await self._follow_host(host)
        transport = self.client.transport
        self._handles.append(presence.listen(lambda name, alive: self._later(self._on_presence, name, alive)))
        self._handles.append(transport.watch_liveliness(keys.custody_pattern(self.client.mesh),
                                                        lambda key, alive: self._later(self._on_custody, key, alive)))
        # The arrivals too: in secure mode a member may follow events but not custody tokens.
        self._handles.append(self.client.events(self._on_migration_event, component="migration"))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.listen.close()
        handles, self._handles = self._handles + self._host_handles, []
        self._host_handles = []
        for handle in handles:
            try:
                handle.close()
            except MeshError:
                pass

    def __enter__(self) -> CompanionServer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    async def serve_stdio(self, on_ready: Callable[[], None] = lambda: None) -> None:
        """Serve the client on this process's stdin and stdout until it leaves (EOF)."""
        from mcp.server.stdio import stdio_server

        await self.start()
        on_ready()
        # No signal handling of our own here: the SDK reads stdin in a worker thread that a cancel
        # cannot interrupt. A client ends the server by closing its stdin (then exit 0); SIGINT is
        # exit 130, SIGTERM the default, as for any stdio server.
        async with stdio_server() as (read, write):
            await self.server.run(read, write, self._options())

    async def serve_http(self, sock: socket.socket, on_ready: Callable[[str], None]) -> None:
        """Serve streamable HTTP on the bound ``sock`` (at ``/mcp``) until SIGINT/SIGTERM."""
        import uvicorn

        await self.start()
        host, port = sock.getsockname()[:2]
        shown = f"[{host}]" if ":" in host else host
        server = _HttpServer(uvicorn.Config(self.server.streamable_http_app(host=host), log_level="warning", lifespan="on"),
                             lambda _loop: on_ready(f"http://{shown}:{port}/mcp"))
        async with anyio.create_task_group() as group:
            await group.start(_on_signal, server.stop)
            await server.serve(sockets=[sock])
            group.cancel_scope.cancel()

    def _options(self) -> Any:
        return self.server.create_initialization_options(NotificationOptions(resources_changed=True, tools_changed=True))

    # --- the loop's helpers -------------------------------------------------------------------

    def _later(self, fn: Callable[..., object], *args: Any) -> None:
        """From any thread (a zenoh callback): run ``fn`` on the loop; never blocks."""
        loop = self._loop
        if loop is not None and not self._closed:
            try:
                loop.call_soon_threadsafe(fn, *args)
            except RuntimeError:
                pass  # the loop has closed: nobody left to tell

    async def _thread(self, fn: Callable[..., T], *args: Any) -> T:
        return await anyio.to_thread.run_sync(partial(fn, *args))

    def _spawn(self, coroutine: Any) -> None:
        if self._loop is not None:
            task = self._loop.create_task(coroutine)
            task.add_done_callback(_log_failure)

    # --- following the companion (loop) ----------------------------------------------------------

    def _on_custody(self, key: str, alive: bool) -> None:
        try:
            holder, companion, epoch = key.split("/")[-3:]
            number = int(epoch)
        except ValueError:
            return  # not a custody token of this grammar
        if companion != self.companion:
            return
        if alive:
            self._holders[holder] = max(number, self._holders.get(holder, 0))
        elif self._holders.get(holder) == number:
            del self._holders[holder]
        if not self._settling and self._loop is not None:
            # A host re-declares its token as it turns from receiving to running (withdrawn, then
            # declared again): the tokens are read once they have settled, not at each flicker.
            self._settling = True
            self._loop.call_later(SETTLE, self._settle)

    def _settle(self) -> None:
        self._settling = False
        best = max(self._holders.items(), key=lambda item: (item[1], item[0]))[0] if self._holders else None
        if best != self.host and not self._closed:
            self._move(best)

    def _on_migration_event(self, event: Event) -> None:
        # A zenoh worker: an arrival of this companion, or a change of its policy, is handed to the loop.
        if isinstance(event.data, dict) and event.data.get("companion") == self.companion:
            if event.name in ARRIVALS:
                self._later(self._arrived, event.embodiment)
            elif event.name == "PolicyChanged":
                self._later(self._policy_changed, event.embodiment, event.data.get("accepts"))

    def _arrived(self, host: str) -> None:
        if host != self.host and not self._closed:
            self._move(host)

    def _policy_changed(self, host: str, accepts: Any) -> None:
        if host == self.host:
            self.description = {**self.description, "policy": accepts if isinstance(accepts, list) else None}
            self._retool()

    def _on_presence(self, name: str, alive: bool) -> None:
        if alive:
            self.alive.add(name)
        else:
            self.alive.discard(name)
        if self.host is not None:
            self._retool()

    def _move(self, host: str | None) -> None:
        """The companion now lives on ``host`` (None: nowhere to be seen)."""
        log.debug("companion %s now on %s", self.companion, host or "(nowhere)")
        self.host = host
        self._describing += 1
        generation = self._describing
        old, self._host_handles = self._host_handles, []
        self._spawn(self._thread(_close_all, old))
        if host is None:
            self._set_description(None, {})
            self._spawn(self._announce_move())
            return

        async def describe() -> None:
            try:
                description = await self._thread(partial(self.client.describe, host, timeout=DESCRIBE_TIMEOUT))
            except MeshError as exc:
                log.warning("companion %s moved to %s, which did not describe itself: %s", self.companion, host, exc)
                description = {"name": host}
            if generation != self._describing:
                return  # moved on again meanwhile
            self._set_description(host, description)
            await self._follow_host(host)
            await self._announce_move()

        self._spawn(describe())

    def _set_description(self, host: str | None, description: dict[str, Any]) -> None:
        self.description = description
        self.resources = {r.uri: r for r in companion_resources(self.companion, host)}
        self._retool(announce=False)

    def _retool(self, *, announce: bool = True) -> None:
        if self.host is None:
            tools = [t for t in companion_tools(self.companion, {"name": ""}, alive=(), policy=None) if t.kind == "peers"]
        else:
            accepts = self.description.get("policy")  # describe's: a list of names, or None for any
            tools = companion_tools(self.companion, self.description, alive=self.alive,
                                    policy=[str(a) for a in accepts] if isinstance(accepts, list) else None)
        before = [(t.name, t.description, t.input_schema) for t in self.tools.values()]
        self.tools = {t.name: t for t in tools}
        if announce and before != [(t.name, t.description, t.input_schema) for t in tools]:
            self._spawn(self._notify_tools())

    async def _announce_move(self) -> None:
        await self._notify_tools()
        await self._notify_all(lambda s: s.send_resource_list_changed(), ResourcesListChanged())
        for uri in list(self._subscribed) + [r.uri for r in self.resources.values()]:
            self._updated(uri)

    async def _follow_host(self, host: str) -> None:
        handles = await self._thread(self._watch_host, host)
        if self.host != host or self._closed:  # moved on while these were declared
            self._spawn(self._thread(_close_all, handles))
        else:
            self._host_handles.extend(handles)

    def _watch_host(self, host: str) -> list[Closeable]:
        """(A worker thread.) Follow ``host``'s stores and the events of its action runs."""
        handles: list[Closeable] = []
        for spec in companion_resources(self.companion, host):
            prefix = keys.storage_key(self.client.mesh, host, spec.store, ())
            handles.append(self.client.watch(f"{prefix}/**", partial(self._on_store_change, spec.uri)))
        handles.append(self.client.events(self._on_run_event, embodiment=host, event="Progress"))
        handles.append(self.client.events(self._on_run_event, embodiment=host, component="execution"))
        return handles

    def _on_store_change(self, uri: str, _key: str, _entry: object) -> None:
        self._later(self._updated, uri)  # a zenoh worker: the loop decides whom to tell

    def _on_run_event(self, event: Event) -> None:
        # A zenoh worker: only runs (``<action id>#<attempt>...``) are of interest; the loop picks ours.
        if isinstance(event.data, dict) and "#" in str(event.data.get("run_id", "")):
            self._later(self._run_event, str(event.data["run_id"]).split("#", 1)[0], event)

    def _run_event(self, action_id: str, event: Event) -> None:
        self.calls.run_event(action_id, event)

    # --- notifications (loop) --------------------------------------------------------------------

    async def _notify_all(self, send: Callable[[ServerSession], Any], event: Any, only: set[object] | None = None) -> None:
        for connection, session in list(self._sessions.items()):
            if only is not None and connection not in only:
                continue
            try:
                await send(session)
            except Exception:  # the connection has gone (a closed stream): forget it
                self._sessions.pop(connection, None)
                for subscribers in self._subscribed.values():
                    subscribers.discard(connection)
        await self.bus.publish(event)

    async def _notify_tools(self) -> None:
        await self._notify_all(lambda s: s.send_tool_list_changed(), ToolsListChanged())

    def _updated(self, uri: str) -> None:
        """A resource changed: one notification per burst (a plan writes several properties in one update)."""
        if uri in self._pending_updates:
            return
        self._pending_updates.add(uri)

        async def send() -> None:
            await asyncio.sleep(0)  # the rest of the burst, already queued on the loop, joins this one
            self._pending_updates.discard(uri)
            await self._notify_all(lambda s: s.send_resource_updated(uri), ResourceUpdated(uri=uri),
                                   only=self._subscribed.get(uri, set()))

        self._spawn(send())

    async def _initialized(self, ctx: Any, _params: types.NotificationParams) -> None:
        self._sessions.setdefault(_connection_of(ctx.session), ctx.session)

    # --- requests (loop) -------------------------------------------------------------------------

    async def _list_tools(self, _ctx: Any, _params: types.PaginatedRequestParams | None) -> types.ListToolsResult:
        tools = []
        for spec in self.tools.values():
            note = "" if spec.read_only or self.allow_actions else " (this server is read-only: calls are refused)"
            tools.append(types.Tool(name=spec.name, description=spec.description + note, input_schema=spec.input_schema,
                                    annotations=types.ToolAnnotations(read_only_hint=spec.read_only,
                                                                      open_world_hint=not spec.read_only)))
        return types.ListToolsResult(tools=tools)

    async def _list_resources(self, _ctx: Any, _params: types.PaginatedRequestParams | None) -> types.ListResourcesResult:
        return types.ListResourcesResult(resources=[
            types.Resource(uri=r.uri, name=r.name, title=r.title, description=r.description, mime_type="application/json")
            for r in self.resources.values()])

    async def _read_resource(self, _ctx: Any, params: types.ReadResourceRequestParams) -> types.ReadResourceResult:
        from mcp.shared.exceptions import MCPError

        spec = self.resources.get(str(params.uri))
        if spec is None:
            known = ", ".join(self.resources) or f"none: {self.companion} lives nowhere to be seen"
            raise MCPError(types.INVALID_PARAMS, f"no resource {params.uri} (resources: {known})")
        prefix = keys.storage_key(self.client.mesh, spec.embodiment, spec.store, ())
        try:
            entries = await self._thread(partial(self.client.read_store, spec.embodiment, spec.store, timeout=READ_TIMEOUT))
        except MeshError as exc:
            raise MCPError(types.INTERNAL_ERROR, f"{spec.embodiment} did not answer: {exc}") from None
        text = store_document(spec.embodiment, spec.store, entries, prefix)
        return types.ReadResourceResult(contents=[types.TextResourceContents(uri=spec.uri, mime_type="application/json", text=text)])

    async def _subscribe(self, ctx: Any, params: types.SubscribeRequestParams) -> types.EmptyResult:
        connection = _connection_of(ctx.session)
        self._sessions.setdefault(connection, ctx.session)
        self._subscribed.setdefault(str(params.uri), set()).add(connection)
        return types.EmptyResult()

    async def _unsubscribe(self, ctx: Any, params: types.UnsubscribeRequestParams) -> types.EmptyResult:
        self._subscribed.get(str(params.uri), set()).discard(_connection_of(ctx.session))
        return types.EmptyResult()

    async def _call_tool(self, ctx: Any, params: types.CallToolRequestParams) -> types.CallToolResult:
        spec = self.tools.get(params.name)
        if spec is None:
            where = f"in {self.host} now, which offers" if self.host else "nowhere to be seen now: it has only"
            return text_result(f"no tool {params.name!r}: {self.companion} lives {where} {', '.join(self.tools)}", error=True)
        if not spec.read_only and not self.allow_actions:
            return text_result(f"refused: this MCP server is read-only ({spec.name} would act on {self.host}); "
                                "start it with --allow-actions to let clients act", error=True)
        try:
            arguments = spec.arguments(params.arguments)
        except InvalidArguments as exc:
            return text_result(str(exc), error=True)
        return await self.calls.call(ctx.session, spec, arguments, self.host)

class _HttpServer(UvicornServer):
    """uvicorn's server, stopped by ``_on_signal`` rather than by handlers of its own (which would
    raise the signal again once stopped: a Ctrl-C would end in a traceback-free but failed exit)."""

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield


async def _on_signal(then: Callable[[], None], *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
    with anyio.open_signal_receiver(signal.SIGINT, signal.SIGTERM) as signals:
        task_status.started()  # the handlers are in place: what the start line promises holds from now on
        async for _ in signals:
            then()
            return


def _close_all(handles: list[Closeable]) -> None:
    for handle in handles:
        try:
            handle.close()
        except MeshError:
            pass


def _log_failure(task: asyncio.Task[Any]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.warning("mcp: %s", task.exception())


def _version() -> str:
    from cmion_mesh import __version__

    return __version__


__all__ = ["CompanionServer"]
