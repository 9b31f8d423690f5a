"""The web body without its page: the state a page shows, what the competencies do to it, what the
page senses.

``Face`` is the component half of ``web.body.WebBody``: who inhabits the body, the face, the
expression, the line being spoken and its audio, the question waiting, the visitors and commands
the page reported (the state and its fields are described in ``docs/web.md``). It serves nothing:
``WebBody`` (``web/body.py``) adds the page, its HTTP server and WebSocket, and pushes each change
there. The web competencies (``web/competencies.py``) import this module alone, so an embodiment
whose competency library holds them, but serves no page (the robot), does not import the HTTP
server (starlette, uvicorn, asyncio: about 8 MB and 60 ms of start).

Threads: events reach the body on the update loop, competencies call it from their threads, the
page from its server's loop. State is guarded by one lock held only to copy or change it.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from collections import OrderedDict
from typing import Any, ClassVar

from cmion_mesh import keys
from cmion_mesh.errors import InvalidName, MeshError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event

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


class WebSense:
    """What a competency fed by the page is to the body: ``sense`` names the input it takes (answer,
    visitor, command), and the body calls ``poke`` (from the server's loop: it only sets an event)
    when one arrives. The web competencies (``web/competencies.py``) are such senses; the body
    finds them among the embodiment's competencies, and so needs no import of them."""

    sense: ClassVar[str] = ""
    _wake: Any

    def poke(self) -> None:
        self._wake.set()


class Face(Component):
    """The state of a web body and its senses; ``WebBody`` serves it on a page."""

    def __init__(self, layout: str = "auto", *, name: str = "web") -> None:
        super().__init__(name)
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
        self._subscription: Any = None
        self._closed = False

    @property
    def serving(self) -> bool:
        """Whether a page shows this body now (``WebBody`` once entered, until closed): only then do
        the web competencies act on it rather than as their simulated selves."""
        return False

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._subscription is not None:
            self._subscription.close()
        self._stopped()

    def _stopped(self) -> None:
        """After ``close`` (once): what serves the page stops here."""

    def detach(self) -> None:
        self.close()

    def _publish(self) -> None:
        """The state changed: a page showing it is sent the new one (nothing to do without a page)."""

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
        self._publish()

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


def web_body(sim: Simulation) -> Face | None:
    """The web body of the embodiment ``sim`` runs, if it has one serving a page."""
    for component in sim.components:
        if isinstance(component, Face) and component.serving:
            return component
    return None
