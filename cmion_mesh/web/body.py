"""A body in the browser: the companion's face, voice and senses on a web page.

``WebBody`` is an ION component (named ``web``) that serves a page (``cmion_mesh/web/static/body/``, plain
static files) from the daemon: ``cmion-mesh up screen --web 127.0.0.1:8080``, or an
``ArchitectureComponent ClassName="cmion_mesh.web.body:WebBody" ConstructorParameters="127.0.0.1:8080"``
in the configuration. The page is the body's actuators and sensors; the competencies that drive
it are the web competencies (``web/competencies.py``), which look the body up in their
embodiment and behave as the simulated ones when there is none.

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

Threads: events reach the body on the update loop, competencies call it from their threads, the
page talks to it on the web server's asyncio loop. State is guarded by one lock held only to
copy or change it; the loops are crossed with ``WebServer.call_soon`` (never blocking).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import itertools
import json
import logging
import threading
import time
from collections import OrderedDict
from importlib import resources
from typing import Any, ClassVar

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from cmion_mesh import keys, logs
from cmion_mesh.errors import InvalidName, MeshError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event
from cmion_mesh.web.server import LOOPBACK_NAMES, WebServer, host_allowed, parse_bind, same_origin

log = logging.getLogger(__name__)

#: Utterances whose audio stays available (a page that joins late still gets the current one).
KEEP_UTTERANCES = 8
#: Longest typed command accepted from a page (characters).
MAX_COMMAND = 200
#: Valence beyond which the face shows the mind's mood rather than a neutral look.
MOOD_THRESHOLD = 0.15
#: How long an arrival is news (seconds): after it, the state says the companion is simply here,
#: so a page opened later shows the face at rest, not the arrival again.
ARRIVAL_SHOWN = 4.0
LAYOUTS = ("auto", "screen", "phone")
MIGRATION_EVENTS = frozenset({"MigrationOccurred", "CompanionResumed", "MigrationStarting", "MigrationSucceeded",
                              "MigrationFailed", "CompanionDamaged", "CustodyFork", "CustodySuperseded",
                              "CustodyStoodDown", "CustodyResolved"})


def static_dir() -> Any:
    return resources.files("cmion_mesh") / "web" / "static" / "body"


class WebSense:
    """What a competency fed by the page is to the body: ``sense`` names the input it takes (answer,
    visitor, command), and the body calls ``poke`` (from the server's loop: it only sets an event)
    when one arrives. The web competencies (``web/competencies.py``) are such senses; the body
    finds them among the embodiment's competencies, and so needs no import of them."""

    sense: ClassVar[str] = ""
    _wake: Any

    def poke(self) -> None:
        self._wake.set()


class _Page:
    """One open page: the latest state not yet sent, and what wakes its sender."""

    def __init__(self) -> None:
        self.latest: dict[str, Any] | None = None
        self.replies: list[dict[str, Any]] = []
        self.ready = asyncio.Event()


class WebBody(Component):
    """The web page body of an embodiment. A context manager: ``__enter__`` serves the page."""

    def __init__(self, address: str = "127.0.0.1:0", layout: str = "auto", *, name: str = "web", key: str | None = None) -> None:
        super().__init__(name)
        self.key = key
        self.host, self.port = parse_bind(address)
        if layout not in LAYOUTS:
            raise MeshError(f"web body layout {layout!r}: expected one of {', '.join(LAYOUTS)}")
        self.layout = layout
        self._lock = threading.Lock()
        self._seq = itertools.count(1)
        self._utterance_ids = itertools.count(1)
        self._audio: OrderedDict[str, bytes] = OrderedDict()
        self._answers: list[str] = []
        self._commands: list[str] = []
        self._visitors: set[str] = set()
        self._state: dict[str, Any] = {
            "embodiment": None, "companion": None, "transition": None, "face": "idle", "animation": None,
            "emotion": {"valence": 0.0, "arousal": 0.0}, "expression": "neutral", "speech": None, "said": [],
            "asking": None, "visitors": [], "senses": [], "layout": layout,
        }
        self._pages: set[_Page] = set()  # on the server's loop only
        self._connects = logs.Throttle(log, "page connections")
        self._disconnects = logs.Throttle(log, "page disconnections")
        self._server: WebServer | None = None
        self._subscription: Any = None
        self._closed = False

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

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._subscription is not None:
            self._subscription.close()
        if self._server is not None:
            self._server.close()
        self._connects.flush()
        self._disconnects.flush()

    def detach(self) -> None:
        self.close()

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

    def snapshot(self) -> dict[str, Any]:
        now = time.time()
        with self._lock:
            # A deep copy through JSON: what a page gets is what JSON can carry, and never shared state.
            copied: dict[str, Any] = json.loads(json.dumps({"type": "state", "seq": next(self._seq), "time": now, **self._state}))
        transition = copied["transition"]
        if transition is not None and transition.get("kind") == "arriving":
            until = float(transition.get("at", 0.0)) + ARRIVAL_SHOWN
            if now >= until:
                copied["transition"] = None  # the arrival is over: the companion is here
            else:
                transition["until"] = until
        return copied

    def _changed(self, **changes: Any) -> None:
        with self._lock:
            self._state.update(changes)
            self._state["face"] = "speaking" if self._state["speech"] else "listening" if self._state["asking"] else "idle"
            self._state["expression"] = self._state["animation"] or _mood(self._state["emotion"])
        server = self._server
        if server is not None:
            server.call_soon(self._push, self.snapshot())

    # --- the embodiment ---------------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        self._subscription = sim.on_event(self._on_event)
        self._changed(embodiment=sim.embodiment, companion=self._inhabitant(), senses=self._senses())

    def _inhabitant(self) -> str | None:
        migration = self.sim.components_by_name().get("migration")
        inhabitant = getattr(migration, "inhabitant", None)
        return inhabitant if isinstance(inhabitant, str) else None

    def _senses(self) -> list[str]:
        execution = self.sim.components_by_name().get("execution")
        return sorted({c.sense for c in getattr(execution, "competencies", ()) if isinstance(c, WebSense)})

    def sensing(self) -> list[WebSense]:
        execution = self.sim.components_by_name().get("execution")
        return [c for c in getattr(execution, "competencies", ()) if isinstance(c, WebSense)]

    def _on_event(self, event: Event) -> None:
        """On the update loop: cheap, never blocking."""
        data = event.data if isinstance(event.data, dict) else {}
        if event.name in MIGRATION_EVENTS or event.name == "EmbodimentReady":
            transition = None
            if event.name == "MigrationOccurred":
                transition = {"kind": "arriving", "from": str(data.get("why", "")).removeprefix("arrived from "), "at": time.time()}
            elif event.name == "MigrationStarting":
                transition = {"kind": "leaving", "to": data.get("target"), "at": time.time()}
            elif event.name == "MigrationSucceeded":
                transition = {"kind": "left", "to": data.get("target"), "at": time.time()}
            companion = self._inhabitant()
            if event.name == "MigrationStarting":
                companion = data.get("companion") or companion  # still here, leaving
            changes: dict[str, Any] = {"companion": companion, "senses": self._senses()}
            if transition is not None or event.name in ("CompanionResumed", "MigrationFailed"):
                changes["transition"] = transition
            if companion is None:  # an empty body: nothing of the companion stays on it
                changes.update(speech=None, asking=None, animation=None, said=[])
            self._changed(**changes)
        elif event.name == "Emotion":
            try:
                emotion = {"valence": float(data.get("valence", 0.0)), "arousal": float(data.get("arousal", 0.0))}
            except (TypeError, ValueError):
                return
            self._changed(emotion=emotion)

    # --- what the competencies do to the page (their threads) ---------------------------------------

    def begin_speech(self, text: str, wav: bytes | None, seconds: float) -> str:
        utterance = f"u{next(self._utterance_ids)}-{int(time.time() * 1000) % 100000}"
        with self._lock:
            if wav is not None:
                self._audio[utterance] = wav
                while len(self._audio) > KEEP_UTTERANCES:
                    self._audio.popitem(last=False)
            said = [*self._state["said"], text][-KEEP_UTTERANCES:]
        audio = f"/speech/{utterance}.wav" if wav is not None else None
        self._changed(speech={"id": utterance, "text": text, "audio": audio, "seconds": round(seconds, 3)}, said=said)
        return utterance

    def end_speech(self, utterance: str) -> None:
        with self._lock:
            current = self._state["speech"]
        if current is not None and current.get("id") == utterance:
            self._changed(speech=None)

    def audio(self, utterance: str) -> bytes | None:
        with self._lock:
            return self._audio.get(utterance)

    def begin_animation(self, animation: str) -> None:
        self._changed(animation=animation)

    def end_animation(self, animation: str) -> None:
        with self._lock:
            current = self._state["animation"]
        if current == animation:
            self._changed(animation=None)

    def begin_ask(self, user: str) -> None:
        with self._lock:
            self._answers.clear()  # a new question voids answers to the last
        self._changed(asking=user)

    def end_ask(self) -> None:
        self._changed(asking=None)

    def take_answer(self) -> str | None:
        with self._lock:
            return self._answers.pop(0) if self._answers else None

    def take_command(self) -> str | None:
        with self._lock:
            return self._commands.pop(0) if self._commands else None

    def visitors(self) -> set[str]:
        with self._lock:
            return set(self._visitors)

    # --- what the page senses (the server's loop) --------------------------------------------------------

    def _on_input(self, text: str) -> dict[str, Any] | None:
        """One message from a page; the reply (an error, or what became of it) goes back to that page."""
        try:
            message = json.loads(text)
            kind = message.get("type") if isinstance(message, dict) else None
        except ValueError:
            kind, message = None, None
        if not isinstance(message, dict) or kind not in ("answer", "visitor", "command"):
            return {"type": "error", "error": "expected a JSON object with type answer, visitor or command"}
        with self._lock:
            senses = list(self._state["senses"])
        if kind not in senses:
            return {"type": "error", "error": f"this body does not sense {kind}s (it senses: {', '.join(senses) or 'nothing'})"}
        if kind == "answer":
            value = str(message.get("value", "")).strip().lower()
            if value not in ("yes", "no"):
                return {"type": "error", "error": f"an answer is yes or no, not {value!r}"}
            with self._lock:
                if self._state["asking"] is None:
                    return {"type": "error", "error": "nobody asked a question"}
                self._answers.append(value)
        elif kind == "visitor":
            name = str(message.get("name", "")).strip()
            try:
                keys.check_name(name, "visitor")
            except InvalidName as exc:
                return {"type": "error", "error": str(exc)}
            with self._lock:
                (self._visitors.add if message.get("present", True) else self._visitors.discard)(name)
                visitors = sorted(self._visitors)
            self._changed(visitors=visitors)
        else:
            command = " ".join(str(message.get("text", "")).split())
            if not command or len(command) > MAX_COMMAND:
                return {"type": "error", "error": f"a command is 1 to {MAX_COMMAND} characters"}
            with self._lock:
                self._commands.append(command)
        for competency in self.sensing():
            if competency.sense == kind:
                competency.poke()
        return {"type": "ok", "input": kind}


def _mood(emotion: dict[str, float]) -> str:
    valence, arousal = emotion.get("valence", 0.0), emotion.get("arousal", 0.0)
    if valence >= MOOD_THRESHOLD:
        return "happy"
    if valence <= -MOOD_THRESHOLD:
        return "sad" if arousal < 0.3 else "worried"
    return "neutral"


def web_body(sim: Simulation) -> WebBody | None:
    """The web body of the embodiment ``sim`` runs, if it has one serving a page."""
    for component in sim.components:
        if isinstance(component, WebBody) and component._server is not None and not component._closed:
            return component
    return None

