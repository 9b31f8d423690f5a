"""The live view of a mesh (``cmion-mesh view``): a page that shows the mesh as it happens.

The view is a mesh client like any other (it serves nothing in the key-space): it watches the
liveliness tokens (embodiments alive, custody of companions), subscribes to every event of the
mesh, and to the blackboard and world model of the embodiments that pages have selected. What it
learns is kept in a ``Model`` on the web server's event loop and pushed to every page over a
WebSocket as it happens; a page never polls, and nothing here polls the mesh either: an idle
mesh with a page open costs its daemons nothing.

Threads: the transport's workers run the subscription and liveliness handlers; each hands its
sample to the loop with ``call_soon`` (never blocking, never calling zenoh) and returns. Requests
that wait for answers (``describe``, ``execution/status``, store reads, actions) run on a small
thread pool, whose results are handed to the loop the same way. Only the loop touches the model
and the pages.

Memory is bounded (``view_model``'s doc says how): a slow page never holds up the mesh, the
other pages, or the view's memory.

Read-only unless ``allow_actions``: a page may then send mind actions and migrations, which the
view sends as its own requests (with ``--certs``, under its own identity and access rules); when
not allowed they are refused here, whatever the page sends.

A recording played through the view (``view --recording``) is the same view with no mesh: a
``Playback`` (``tools/view_player.py``) feeds it what the recording holds, through the same
handlers (``feed_*``), at the recording's pace; the pages pause, speed it up and seek.

Here: ``MeshView`` (the Starlette application, joining the mesh, the WebSocket to each page, the
actions) and ``spawn_view``. What the view knows and what waits for each page (``Model``, ``Page``,
``TreeWatch``), plain state with no I/O: ``web/view_model.py``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import msgspec
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError, ProtocolError
from cmion_mesh.messages import Container, Event, ExecutionStatus, Property, decode
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.transport.base import Closeable, Sample
from cmion_mesh.web.server import host_allowed, same_origin
from cmion_mesh.web.view_model import STORES, Model, Page, Playback, TreeWatch, entry_json, event_json

log = logging.getLogger(__name__)

#: Most events in one message to a page: a page reading slowly holds at most this much in its
#: socket's buffers beyond its queue, and a page catching up draws in steps.
BATCH_EVENTS = 200
DESCRIBE_TIMEOUT = 3.0
ACTION_TIMEOUT = 60.0
ACTION_JOIN = 2.0
#: Actions in flight at once from all pages; more are refused as busy.
ACTIONS_IN_FLIGHT = 8
#: Events after which an embodiment's description is asked again (what ``describe`` says changed).
REDESCRIBE = frozenset({
    "MigrationOccurred", "MigrationSucceeded", "MigrationFailed", "MigrationDropped", "CompanionResumed", "CompanionBorn",
    "CompanionDamaged", "CustodyFork", "CustodySuperseded", "CustodyStoodDown", "CustodyResolved", "CompetencyAppeared",
    "CompetencyVanished", "MindConnected", "MindDisconnected",
})

#: Descriptions asked again, at most, while an embodiment does not yet see every embodiment the
#: view sees (their links come up after the view's): then the graph's links are right.
RECHECKS = 5
RECHECK_FIRST = 0.3

Schedule = Callable[..., None]


def spawn_view(mesh: str, connect: Iterable[str], *extra: str, web: str = "127.0.0.1:0", timeout: float = 30.0,
               die_with_parent: bool = False) -> tuple[Daemon, str]:
    """``cmion-mesh view`` in a process of its own, connected to the ``connect`` endpoints only
    (no multicast): the process (a context manager that stops it) and the page's address, once
    it serves. For the demo's pages and the tests. ``die_with_parent``: as ``procs.Daemon``'s
    (from the main thread only)."""
    endpoints = [arg for endpoint in connect for arg in ("--connect", endpoint)]
    view = Daemon(cli_argv("view", "--mesh", mesh, "--web", web, "--no-multicast", *endpoints, *extra), name="view",
                  die_with_parent=die_with_parent)
    try:
        line = view.wait_line("view of mesh", timeout)
    except BaseException:
        view.kill()
        raise
    match = re.search(r" at (http://\S+)/ ", line)
    if match is None:
        view.kill()
        raise MeshError(f"cmion-mesh view printed no address: {line!r}")
    return view, match.group(1)


def static_dir() -> Path:
    return Path(__file__).resolve().parent / "static" / "view"


class MeshView:
    """The view's server side: ``app`` is the Starlette application; ``start(schedule)`` joins the
    mesh once the web server's loop runs (``schedule`` is ``WebServer.call_soon``). A context
    manager; ``close`` (idempotent) leaves the mesh and stops the thread pools."""

    def __init__(self, client: MeshClient | None, *, allow_actions: bool = False, loopback: bool = False,
                 mesh: str = "") -> None:
        self.client = client
        self.loopback = loopback
        self.mesh = client.mesh if client is not None else mesh
        self.allow_actions = allow_actions and client is not None
        self.model = Model(self.mesh)
        self.playback: Playback | None = None
        self._muted = False  # a seek replays many things at once: the pages get one snapshot after
        self._rechecks: dict[str, int] = {}
        self.pages: set[Page] = set()
        self.trees: dict[str, TreeWatch] = {}
        self._pages_made = 0
        self._describing: dict[str, bool] = {}  # name -> asked again while a describe was in flight
        self._running: dict[threading.Thread, threading.Event] = {}  # actions under way, and what ends their wait
        self._schedule: Schedule | None = None
        self._handles: list[Closeable] = []
        self._lock = threading.Lock()
        self._closed = False
        self._pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="view-ask")
        self.app = Starlette(routes=[
            Route("/", self._index),
            Route("/api/snapshot", self._snapshot_route),
            WebSocketRoute("/ws", self._websocket),
            Mount("/static", app=StaticFiles(directory=static_dir()), name="static"),
        ])

    def __enter__(self) -> MeshView:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # --- joining the mesh (any thread) ------------------------------------------------------

    def start(self, schedule: Schedule) -> None:
        """Watch the mesh; every handler hands what it got to the loop with ``schedule``."""
        self._schedule = schedule
        if self.client is None:
            return  # a recording: ``feed_*`` says what happens
        transport = self.client.transport
        prefix = keys.mesh_prefix(self.mesh)
        with self._lock:
            if self._closed:
                return
            self._handles.append(self.client.events(lambda e: self._later(self._on_event, e, time.time())))
            self._handles.append(transport.watch_liveliness(
                f"{prefix}/{keys.ALIVE}/*", lambda k, a: self._later(self._on_alive, k.rsplit("/", 1)[-1], a, time.time())))
            self._handles.append(transport.watch_liveliness(keys.custody_pattern(self.mesh),
                                                            lambda k, a: self._later(self._on_custody, k, a, time.time())))

    # --- a recording played through the view (any thread) -----------------------------------

    def feed_alive(self, name: str, alive: bool, when: float) -> None:
        self._later(self._on_alive, name, alive, when)

    def feed_custody(self, key: str, alive: bool, when: float) -> None:
        self._later(self._on_custody, key, alive, when)

    def feed_event(self, event: Event, when: float) -> None:
        self._later(self._on_event, event, when)

    def feed_description(self, name: str, description: dict[str, Any], when: float) -> None:
        self._later(self._on_described, name, description, None, when)

    def feed_playback(self, status: dict[str, Any]) -> None:
        self._later(self._change, {"type": "playback", "playback": status})

    def feed_replay(self, items: list[tuple[str, tuple[Any, ...]]], *, reset: bool) -> None:
        """Apply many feeds at once (a seek), each ``(kind, args)`` with kind ``alive``, ``custody``,
        ``event`` or ``description`` (the ``feed_*`` of that name); ``reset``: from an empty view.
        The pages then get one snapshot, not each change."""
        self._later(self._replay, items, reset)

    def _replay(self, items: list[tuple[str, tuple[Any, ...]]], reset: bool) -> None:
        handlers: dict[str, Callable[..., None]] = {
            "alive": self._on_alive, "custody": self._on_custody, "event": self._on_event,
            "description": lambda name, d, when: self._on_described(name, d, None, when)}
        if reset:
            self.model = Model(self.mesh)
        self._muted = True
        try:
            for kind, args in items:
                handlers[kind](*args)
        finally:
            self._muted = False
        for page in self.pages:
            page.resync = True
            page.wake.set()

    def _later(self, fn: Callable[..., None], *args: Any) -> None:
        """From any thread: run ``fn`` on the loop; never blocks."""
        schedule = self._schedule
        if schedule is not None and not self._closed:
            schedule(fn, *args)

    def _ask(self, fn: Callable[[], Any], then: Callable[[Any, str | None], None]) -> None:
        """Run ``fn`` (which waits for the mesh) on the pool; ``then(result, error)`` on the loop."""
        def run() -> None:
            try:
                result, error = fn(), None
            except MeshError as exc:
                result, error = None, str(exc)
            self._later(then, result, error)

        with self._lock:
            if not self._closed:
                self._pool.submit(run)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles, self._handles = self._handles, []
            trees, self.trees = list(self.trees.values()), {}
            running = dict(self._running)
        for stop in running.values():
            stop.set()
        for handle in handles + [h for t in trees for h in t.handles]:
            try:
                handle.close()
            except MeshError:
                pass
        self._pool.shutdown(wait=True, cancel_futures=True)
        for thread in running:
            thread.join(ACTION_JOIN)  # a migration cannot be interrupted: it is not waited for longer

    # --- what the mesh says (loop) ----------------------------------------------------------

    def _change(self, item: dict[str, Any], pages: set[Page] | None = None) -> None:
        if self._muted:
            return
        for page in self.pages if pages is None else pages:
            page.change(item)

    def _card(self, card: dict[str, Any] | None, when: float) -> None:
        if card is not None:
            self._change({"type": "embodiment", "card": card})
            self._frame(when)

    def _frame(self, when: float) -> None:
        frame = self.model.frame(when)
        if frame is not None:
            self._change({"type": "frame", "frame": frame})

    def _on_alive(self, name: str, alive: bool, when: float) -> None:
        self._card(self.model.alive(name, alive), when)
        if self.client is None:
            return
        # Who sees whom (the graph's links) changed for the others too: ask them again.
        for other, card in self.model.embodiments.items():
            if other != name and card["alive"]:
                self._rechecks.pop(other, None)
                self._describe(other)
        if alive:
            client = self.client
            self._describe(name)
            self._ask(lambda: client.request(name, "execution", "status", ExecutionStatus(), timeout=DESCRIBE_TIMEOUT),
                      lambda outcome, error: self._on_status(name, outcome))

    def _describe(self, name: str) -> None:
        client = self.client
        if client is None:
            return
        if name in self._describing:
            self._describing[name] = True  # ask once more when this one answers
            return
        self._describing[name] = False
        self._ask(lambda: client.describe(name, timeout=DESCRIBE_TIMEOUT),
                  lambda description, error: self._on_described(name, description, error, time.time()))

    def _on_described(self, name: str, description: dict[str, Any] | None, error: str | None, when: float) -> None:
        again = self._describing.pop(name, False)
        card = self.model.embodiments.get(name)
        if card is not None and card["alive"]:
            self._card(self.model.described(name, description, error), when)
            if again:
                self._describe(name)
            elif description is not None and self.client is not None:
                self._recheck(name, description)

    def _recheck(self, name: str, description: dict[str, Any]) -> None:
        """Ask ``name`` again, a little later, while it does not see every embodiment the view sees
        (its own links may come up after the view's); a few times at most, then the graph says
        what it said. Nothing is asked once they agree: an idle mesh stays idle."""
        seen = set(description.get("alive") or ())
        alive = {n for n, c in self.model.embodiments.items() if c["alive"]}
        if alive <= seen:
            self._rechecks.pop(name, None)
            return
        tries = self._rechecks.get(name, 0)
        if tries >= RECHECKS:
            return
        self._rechecks[name] = tries + 1
        asyncio.get_running_loop().call_later(RECHECK_FIRST * 2 ** tries, self._describe, name)

    def _on_status(self, name: str, outcome: Any) -> None:
        if outcome is not None and getattr(outcome, "status", "") == "accepted" and not self._muted:
            for plan in self.model.status(name, outcome.value):
                self._change({"type": "plan", "plan": plan})

    def _on_custody(self, key: str, alive: bool, when: float) -> None:
        try:
            holder, companion, epoch = key.split("/")[-3:]
            change = self.model.custody_token(holder, companion, int(epoch), alive)
        except ValueError:
            return  # not a custody token of this grammar
        self._change(change)
        self._frame(when)

    def _on_event(self, event: Event, received: float) -> None:
        item = event_json(event, received)
        self.model.ring.append(item)
        if not self._muted:
            for page in self.pages:
                page.event(item)
        if event.component == "migration":
            migration = self.model.migration_event(event, received)
            if migration is not None:
                self._change({"type": "migration", "migration": migration})
        elif event.component == "execution":
            plan = self.model.plan_event(event)
            if plan is not None:
                self._change({"type": "plan", "plan": plan})
        data = event.data if isinstance(event.data, dict) else {}
        if event.name in ("MigrationOccurred", "CompanionResumed", "CompanionBorn"):
            self._card(self.model.inhabit(event.embodiment, str(data.get("companion") or "") or None), received)
        elif event.name == "MigrationSucceeded" or (event.name == "MigrationStep" and data.get("step") == "handed"):
            # ``handed`` is the source's commit: the companion is no longer its own, whether or not
            # its ``MigrationSucceeded`` follows (a recording may end before).
            self._card(self.model.inhabit(event.embodiment, None), received)
        if event.name in REDESCRIBE and self.model.embodiments.get(event.embodiment, {}).get("alive"):
            self._describe(event.embodiment)

    # --- trees (loop) -----------------------------------------------------------------------

    def _select(self, page: Page, name: str | None) -> None:
        if page.selected == name:
            return
        self._unselect(page)
        if not name or not keys.is_name(name):
            return
        page.selected = name
        if self.client is None:
            page.change({"type": "trees", "embodiment": name, "ready": True, "truncated": False,
                         "stores": {s: [] for s in STORES}, "error": "a recording: its stores are not shown here"})
            return
        watch = self.trees.get(name)
        if watch is None:
            watch = TreeWatch(name)
            self.trees[name] = watch
            self._watch_trees(watch)
        watch.pages.add(page)
        page.change(watch.message())

    def _unselect(self, page: Page) -> None:
        name, page.selected = page.selected, None
        watch = self.trees.get(name) if name else None
        if watch is None:
            return
        watch.pages.discard(page)
        if not watch.pages:
            del self.trees[watch.embodiment]
            handles, watch.handles = watch.handles, []
            self._close_off_loop(handles)

    def _close_off_loop(self, handles: list[Closeable]) -> None:
        """Close subscriptions on the pool: closing one calls zenoh, which the loop never waits on."""
        def close() -> None:
            for handle in handles:
                handle.close()

        self._ask(close, lambda *_: None)

    def _watch_trees(self, watch: TreeWatch) -> None:
        name = watch.embodiment
        client = self.client
        assert client is not None  # a recording's view watches no trees (``_select``)
        transport = client.transport

        def subscribe() -> dict[str, Any]:
            handles = []
            for store in STORES:
                prefix = keys.storage_key(self.mesh, name, store, ())
                skip = len(prefix.split("/"))

                def on_sample(sample: Sample, store: str = store, skip: int = skip) -> None:
                    path = tuple(sample.key.split("/")[skip:])
                    if not path:
                        return
                    entry = None
                    if not sample.deleted:
                        try:
                            entry = entry_json(decode(sample.payload, Property | Container, where=sample.key))
                        except ProtocolError:
                            return
                    self._later(self._on_tree, name, store, path, entry, time.time())

                handles.append(transport.subscribe(f"{prefix}/**", on_sample))
            self._later(self._adopt_handles, watch, handles)
            # Subscribed first, read second: a change between the two is not lost (``touched``).
            return {store: client.read_store(name, store, timeout=DESCRIBE_TIMEOUT) for store in STORES}

        self._ask(subscribe, lambda stores, error: self._on_trees_read(watch, stores, error))

    def _adopt_handles(self, watch: TreeWatch, handles: list[Closeable]) -> None:
        if self.trees.get(watch.embodiment) is watch:
            watch.handles.extend(handles)
        else:  # unselected meanwhile
            self._close_off_loop(handles)

    def _on_trees_read(self, watch: TreeWatch, stores: dict[str, dict[str, Any]] | None, error: str | None) -> None:
        if self.trees.get(watch.embodiment) is not watch:
            return
        for store, entries in (stores or {}).items():
            skip = len(keys.storage_key(self.mesh, watch.embodiment, store, ()).split("/"))
            for key, entry in entries.items():
                path = tuple(key.split("/")[skip:])
                if path and (store, path) not in watch.touched:
                    watch.apply(store, path, entry_json(entry))
        watch.touched.clear()
        watch.ready = True
        message = watch.message()
        if error:
            message["error"] = error
        self._change(message, watch.pages)

    def _on_tree(self, name: str, store: str, path: tuple[str, ...], entry: dict[str, Any] | None, received: float) -> None:
        watch = self.trees.get(name)
        if watch is None:
            return
        if not watch.ready:
            watch.touched.add((store, path))
        if watch.apply(store, path, entry):
            self._change({"type": "tree", "embodiment": name, "store": store, "path": "/".join(path), "entry": entry,
                          "received": received}, watch.pages)

    # --- actions (loop) ---------------------------------------------------------------------

    def _action(self, page: Page, message: dict[str, Any]) -> None:
        kind = message.get("type")
        token = message.get("id")

        def answer(status: str, reason: str = "", value: Any = None) -> None:
            page.change({"type": "action_result", "id": token, "action": kind, "status": status, "reason": reason, "value": value})

        client = self.client
        if client is None:
            answer("refused", "this view plays a recording: there is no mesh to act on")
            return
        if not self.allow_actions:
            answer("refused", "this view is read-only: start `cmion-mesh view --allow-actions` to act on the mesh")
            return
        stop = threading.Event()
        try:
            if kind == "act":
                embodiment = keys.check_name(str(message.get("embodiment", "")), "embodiment")
                name = keys.check_name(str(message.get("name", "")), "action")
                parameters = [str(p) for p in message.get("parameters") or []]

                def run() -> Any:
                    with client.start_action(embodiment, name, parameters, on_end=stop.set) as action:
                        stop.wait(ACTION_TIMEOUT)  # set by the action's end, or by ``close``
                        return msgspec.to_builtins(action.result(ACTION_TIMEOUT))
            else:
                companion = keys.check_name(str(message.get("companion", "")), "companion")
                target = keys.check_name(str(message.get("target", "")), "target")

                def run() -> Any:
                    return client.migrate(companion, target, timeout=ACTION_TIMEOUT)
        except MeshError as exc:
            answer("refused", str(exc))
            return

        def done(result: Any, error: str | None) -> None:
            if error is not None:
                answer("failed", error)
            else:
                answer(str(result.get("status", "succeeded")) if kind == "act" else "succeeded", str(result.get("reason", "")), result)

        def work() -> None:
            try:
                result, error = run(), None
            except MeshError as exc:
                result, error = None, str(exc)
            finally:
                with self._lock:
                    self._running.pop(thread, None)
            self._later(done, result, error)

        # Threads of their own, not a pool: ``close`` ends an action's wait (``stop``) rather than
        # waiting up to ACTION_TIMEOUT for it.
        thread = threading.Thread(target=work, name=f"view-{kind}", daemon=True)
        with self._lock:
            if self._closed:
                return
            if len(self._running) >= ACTIONS_IN_FLIGHT:
                answer("refused", f"busy: {ACTIONS_IN_FLIGHT} actions are already under way")
                return
            self._running[thread] = stop
        thread.start()
        answer("sent")

    # --- the web side (loop) ----------------------------------------------------------------

    async def _index(self, request: Request) -> Response:
        return FileResponse(static_dir() / "index.html", headers={"Cache-Control": "no-store"})

    async def _snapshot_route(self, request: Request) -> Response:
        # The snapshot is the whole mesh: a rebound name must not read it any more than the socket.
        if not host_allowed(request.headers, loopback=self.loopback):
            return Response("this view answers to loopback names only", status_code=403, media_type="text/plain")
        return JSONResponse(msgspec.to_builtins({**self.model.snapshot(), "allow_actions": self.allow_actions}))

    def _snapshot(self, page: Page) -> dict[str, Any]:
        out = {**self.model.snapshot(), "allow_actions": self.allow_actions, "dropped": page.dropped, "page": page.number,
               "playback": self.playback.status() if self.playback is not None else None}
        watch = self.trees.get(page.selected) if page.selected else None
        if watch is not None:
            out["trees"] = watch.message()
        return out

    def same_origin(self, websocket: WebSocket) -> bool:
        """Whether a page from this server opened the socket: a foreign page must not read the
        mesh (or act on it). The check the web body makes too (``web.server.same_origin``)."""
        return same_origin(websocket.headers, loopback=self.loopback)

    async def _websocket(self, websocket: WebSocket) -> None:
        if not self.same_origin(websocket):
            await websocket.close(code=1008, reason="cross-origin page")
            return
        await websocket.accept()
        self._pages_made += 1
        page = Page(self._pages_made)
        page.resync = True  # the first thing sent is a snapshot
        page.wake.set()
        self.pages.add(page)
        if self.playback is not None:
            self.playback.page_opened()
        sender = asyncio.create_task(self._send_to(websocket, page))
        try:
            while True:
                received = await websocket.receive()
                if received["type"] == "websocket.disconnect":
                    break
                try:
                    message = json.loads(received.get("text") or "")
                    if not isinstance(message, dict):
                        raise ValueError("not a JSON object")
                except ValueError as exc:
                    page.change({"type": "error", "reason": f"message from the page refused: {exc}"})
                    continue
                kind = message.get("type")
                if kind == "select":
                    self._select(page, message.get("embodiment") or None)
                elif kind in ("act", "migrate"):
                    self._action(page, message)
                elif kind == "playback":
                    error = self.playback.control(message) if self.playback is not None else "this view is live: nothing to play"
                    if error:
                        page.change({"type": "error", "reason": error})
                else:
                    page.change({"type": "error", "reason": f"unknown message type {kind!r}"})
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            self.pages.discard(page)
            self._unselect(page)
            sender.cancel()

    async def _send_to(self, websocket: WebSocket, page: Page) -> None:
        """Send what waits for ``page`` in batches; while a send waits on a slow page, more
        waits in the page's bounded queues (see ``Page``)."""
        try:
            while True:
                await page.wake.wait()
                page.wake.clear()
                if page.resync:
                    page.resync = False
                    page.changes.clear()
                    page.events.clear()
                    payload: dict[str, Any] = self._snapshot(page)
                else:
                    events = [page.events.popleft() for _ in range(min(BATCH_EVENTS, len(page.events)))]
                    payload = {"type": "batch", "changes": page.changes, "events": events, "dropped": page.dropped,
                               "sent": time.time()}
                    page.changes = []
                    if page.events:
                        page.wake.set()  # the rest in the next message
                await websocket.send_text(msgspec.json.encode(payload).decode())
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass
