"""A body in the browser: the companion's face, voice and senses on a web page.

``WebBody`` is an ION component (named ``web``) that serves a page (``cmion_mesh/web/static/body/``, plain
static files) from the daemon: ``cmion-mesh up screen --web 127.0.0.1:8080``, or an
``ArchitectureComponent ClassName="cmion_mesh.web.body:WebBody" ConstructorParameters="127.0.0.1:8080"``
in the configuration. The page is the body's actuators and sensors; the competencies that drive
it are the web competencies (``web/competencies.py``), which look the body up in their
embodiment and behave as the simulated ones when there is none serving a page.

What the page shows is one state (``snapshot()``): who inhabits the body (an empty, waiting body
when nobody does; arriving and leaving as migration events say), the face (idle, listening,
speaking), the expression (an animation being played, else the mind's ``Emotion``), the line being
spoken with its audio (``/speech/<id>.wav``, synthesized on the server), the question waiting for
a yes or no, the visitors the page has reported. Each change is pushed over a WebSocket to every
open page (the latest state only: a slow page skips states, never queues them); nothing polls, so
an idle page costs the daemon nothing.

What the page senses comes back on the same WebSocket: a visitor present or gone, a yes/no answer,
a typed command. Each goes to the competencies that sense it (they wake at once) and from there
into the same world-model and blackboard writes the simulated sensors make.

Which pages: only the body's own. A WebSocket opened by a page of another site (its ``Origin``), or
on a loopback body by a name that is not loopback (its ``Host``: a site made to resolve to
127.0.0.1, DNS rebinding), is refused before it is accepted, and so are such names asking for the
state or the speech: another page in the same browser neither drives the senses nor hears what the
companion says. It is the live view's check (``web.server.same_origin``).

Who may act: anyone who can open the page, in plain mode (it is bound to loopback unless told
otherwise). With a ``key`` (``up --certs`` makes one, and prints the page's address with it), the
page is read-only unless opened with ``?key=<key>``: watching stays open, but only the holder of
the printed address may play a visitor, answer or type a command, since these become world-model
writes on an authenticated mesh.

Pages opening and closing are log lines at info (``web page connected`` / ``web page disconnected``;
fields ``body``, ``client`` (its address), ``acts`` (whether it may act), ``pages`` (open now),
``duration_s`` at the end), through throttles keyed by the client's address: a client opening
sockets in a loop writes a line and a count per window. The page's key is never written.

The state, what the competencies do to it and what the page's inputs become are the body's
component half, ``web.face.Face``, which this module serves: the web competencies import that half
alone, so an embodiment that serves no page never imports the HTTP server.

Threads: events reach the body on the update loop, competencies call it from their threads, the
page talks to it on the web server's asyncio loop. State is guarded by one lock held only to
copy or change it; the loops are crossed with ``WebServer.call_soon`` (never blocking).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import time
from importlib import resources
from typing import Any

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from cmion_mesh import logs
from cmion_mesh.errors import MeshError
from cmion_mesh.web.face import Face
from cmion_mesh.web.server import LOOPBACK_NAMES, WebServer, host_allowed, parse_bind, same_origin

log = logging.getLogger(__name__)


def static_dir() -> Any:
    return resources.files("cmion_mesh") / "web" / "static" / "body"


class _Page:
    """One open page: the latest state not yet sent, and what wakes its sender."""

    def __init__(self) -> None:
        self.latest: dict[str, Any] | None = None
        self.replies: list[dict[str, Any]] = []
        self.ready = asyncio.Event()


class WebBody(Face):
    """The web page body of an embodiment. A context manager: ``__enter__`` serves the page."""

    def __init__(self, address: str = "127.0.0.1:0", layout: str = "auto", *, name: str = "web", key: str | None = None) -> None:
        super().__init__(layout, name=name)
        self.key = key
        self.host, self.port = parse_bind(address)
        self._pages: set[_Page] = set()  # on the server's loop only
        self._connects = logs.Throttle(log, "page connections")
        self._disconnects = logs.Throttle(log, "page disconnections")
        self._server: WebServer | None = None

    # --- serving ----------------------------------------------------------------------------------

    @property
    def loopback(self) -> bool:
        """Served on loopback (``up --web`` may set ``host`` after construction): then only loopback
        names may ask for the page's state or open its socket."""
        return self.host in LOOPBACK_NAMES

    @property
    def url(self) -> str:
        if self._server is None:
            raise MeshError(f"web body {self.name!r} is not serving (enter it first)")
        return self._server.url

    @property
    def address(self) -> str:
        """The page's address to give a person: with its key, when it has one."""
        return self.url + (f"/?key={self.key}" if self.key else "")

    def __enter__(self) -> WebBody:
        if self._server is None:
            self._server = WebServer(self._app(), self.host, self.port, name=self.name).__enter__()
            self.port = self._server.port
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    @property
    def serving(self) -> bool:
        return self._server is not None and not self._closed

    def _stopped(self) -> None:
        if self._server is not None:
            self._server.close()
        self._connects.flush()
        self._disconnects.flush()

    def _app(self) -> Starlette:
        folder = static_dir()
        return Starlette(routes=[
            Route("/", self._index),
            Route("/state", self._state_json),
            Route("/speech/{utterance}.wav", self._speech),
            WebSocketRoute("/ws", self._socket),
            Mount("/static", StaticFiles(directory=str(folder)), name="static"),
        ])

    async def _index(self, request: Request) -> Response:
        return FileResponse(str(static_dir() / "index.html"), headers={"cache-control": "no-cache"})

    def _foreign(self, request: Request) -> Response | None:
        """The refusal of a request for what the companion says by a rebound name, else None."""
        if host_allowed(request.headers, loopback=self.loopback):
            return None
        return Response("this body answers to loopback names only", status_code=403, media_type="text/plain")

    async def _state_json(self, request: Request) -> Response:
        refused = self._foreign(request)
        return refused if refused is not None else JSONResponse(self.snapshot())

    async def _speech(self, request: Request) -> Response:
        refused = self._foreign(request)
        if refused is not None:
            return refused
        with self._lock:
            wav = self._audio.get(request.path_params["utterance"])
        if wav is None:
            return Response("no such utterance (only the last few are kept)", status_code=404, media_type="text/plain")
        return Response(wav, media_type="audio/wav", headers={"cache-control": "no-store"})

    async def _socket(self, socket: WebSocket) -> None:
        client = f"{socket.client.host}:{socket.client.port}" if socket.client is not None else "?"
        host = socket.client.host if socket.client is not None else "?"
        if not same_origin(socket.headers, loopback=self.loopback):
            self._connects(host, "web page refused on %s: cross-origin", self.name, body=self.name, client=client,
                           reason="cross-origin page")
            await socket.close(code=1008, reason="cross-origin page")
            return
        await socket.accept()
        may_act = self.key is None or hmac.compare_digest(socket.query_params.get("key", ""), self.key)
        page = _Page()
        page.replies.append({"type": "access", "act": may_act})
        page.latest = self.snapshot()
        page.ready.set()
        self._pages.add(page)
        opened = time.monotonic()
        self._connects(host, "web page connected to %s", self.name, body=self.name, client=client, acts=may_act,
                       pages=len(self._pages))
        sender = asyncio.create_task(self._send_to(socket, page))
        try:
            while True:
                text = await socket.receive_text()
                reply = self._on_input(text) if may_act else {
                    "type": "error", "error": "this page is read-only: open the address the daemon printed, with its key"}
                if reply is not None:
                    page.replies.append(reply)
                    page.ready.set()
        except WebSocketDisconnect:
            pass
        finally:
            self._pages.discard(page)
            self._disconnects(host, "web page disconnected from %s", self.name, body=self.name, client=client,
                              pages=len(self._pages), duration_s=round(time.monotonic() - opened, 3))
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender

    async def _send_to(self, socket: WebSocket, page: _Page) -> None:
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            while True:
                await page.ready.wait()
                page.ready.clear()
                replies, page.replies = page.replies, []
                for reply in replies:
                    await socket.send_text(json.dumps(reply))
                latest, page.latest = page.latest, None
                if latest is not None:
                    await socket.send_text(json.dumps(latest))

    def _push(self, snapshot: dict[str, Any]) -> None:
        """On the server's loop: the newest state replaces whatever a page has not been sent yet."""
        for page in self._pages:
            if page.latest is None or page.latest["seq"] < snapshot["seq"]:
                page.latest = snapshot
                page.ready.set()

    def _publish(self) -> None:
        server = self._server
        if server is not None:
            server.call_soon(self._push, self.snapshot())
