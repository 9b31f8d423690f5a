"""A recording played through the live view (``cmion-mesh view --recording FILE.mcap``).

``RecordingPlayer`` reads what the view needs of a recording (``recording_reader``): embodiments
coming and going (``@alive``), custody tokens (``@custody``), every event, and the descriptions
the recorder wrote as metadata; then feeds them to a ``MeshView`` with no mesh, through the
handlers live samples go through, at the recording's pace times ``speed``. The pages pause, play,
change the speed and seek (``control``); a seek back replays from the start at once (the view is
rebuilt, the pages get one snapshot). Playback starts when the first page opens: a recording
played to nobody would be over before anyone looked.

Times on the view's axis are the recorder's (each message's ``log_time``): one clock for all.
What is kept in memory: only the messages the view uses, at most ``MAX_MESSAGES`` (beyond, the
rest is left out and ``status()["truncated"]`` says so).

One thread (``view-player``) waits for the next message's time or a control; it hands each
message to the view's loop (``MeshView.feed_*``, which never block). A context manager;
``close`` (idempotent) stops it.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, ProtocolError
from cmion_mesh.tools.recording_format import EVENT_SCHEMA, LIVELINESS_SCHEMA, recorded_event
from cmion_mesh.tools.recording_reader import RecordingReader
from cmion_mesh.web.view import MeshView

MAX_MESSAGES = 1_000_000
SEEK_SLACK_NS = 1_000
SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 10.0)
#: Metadata values the recorder wrote as JSON (it writes strings as they are).
_JSON_FIELDS = frozenset({"alive", "duplicates", "competency_types", "stand_ins", "competencies", "actions", "minds",
                          "mind_connections", "inhabitant", "companion_key", "admits", "damaged", "custody",
                          "migration_transfer", "devices", "pid", "started_at", "publications_dropped"})

Item = tuple[str, tuple[Any, ...]]  # a ``MeshView.feed_replay`` item: (kind, args)


def description_from(metadata: dict[str, str]) -> dict[str, Any]:
    """An embodiment's description as the recorder wrote it (``Recorder.describe``), decoded."""
    out: dict[str, Any] = {}
    for key, value in metadata.items():
        if key in _JSON_FIELDS:
            try:
                out[key] = json.loads(value)
                continue
            except ValueError:
                pass
        out[key] = value
    return out


def load(path: str | Path) -> tuple[str, list[tuple[int, Item]], bool]:
    """The recording's mesh, what the view needs of it (``(log_time ns, item)``, in the recorded
    order) and whether it was left out in part (truncated file, or over ``MAX_MESSAGES``)."""
    items: list[tuple[int, Item]] = []
    described: dict[str, dict[str, Any]] = {}
    mesh = ""
    cut = False
    with RecordingReader(path) as reader:
        for message in reader.messages():
            if len(items) >= MAX_MESSAGES:
                cut = True
                break
            seconds = message.log_time / 1e9
            if message.schema == LIVELINESS_SCHEMA:
                token = message.decoded()
                key = str(token.get("key", ""))
                if token.get("kind") == keys.ALIVE:
                    name = str(token.get("name", ""))
                    items.append((message.log_time, ("alive", (name, bool(token.get("alive")), seconds))))
                elif token.get("kind") == "@custody":
                    items.append((message.log_time, ("custody", (key, bool(token.get("alive")), seconds))))
                mesh = mesh or key.split("/")[1] if key.count("/") > 1 else mesh
            elif message.schema == EVENT_SCHEMA:
                try:
                    event = recorded_event(message.data)
                except ProtocolError:
                    continue  # what the recorder could not read is in its raw channel, not for the view
                items.append((message.log_time, ("event", (event, seconds))))
        for name, meta in reader.metadata:
            if name == "cmion-mesh":
                mesh = meta.get("mesh", "") or mesh
            elif name.startswith("embodiment:"):
                described[name.split(":", 1)[1]] = description_from(meta)
        cut = cut or reader.truncated
    # Each described embodiment is described as it appears (the recorder asked them at its start).
    out: list[tuple[int, Item]] = []
    for at, item in items:
        out.append((at, item))
        kind, args = item
        if kind == "alive" and args[1] and args[0] in described:
            out.append((at, ("description", (args[0], described[args[0]], args[2]))))
    if not mesh:
        raise ConfigError("not a recording of a mesh: no mesh named in it, nothing for the view", path=str(path))
    return mesh, out, cut


class RecordingPlayer:
    """Plays ``items`` (``load``) through ``view``; see the module's doc."""

    def __init__(self, view: MeshView, items: list[tuple[int, Item]], *, path: str = "", truncated: bool = False,
                 speed: float = 1.0) -> None:
        self.view = view
        self.items = items
        self.path = path
        self.truncated = truncated
        self.start = items[0][0] if items else 0
        self.end = items[-1][0] if items else 0
        self._cond = threading.Condition()
        self._index = 0
        self._position = self.start  # ns, where playback stands while paused (or stood at ``_anchor``)
        self._anchor = 0.0  # time.monotonic() when playing from ``_position`` began
        self._playing = False
        self._started = False  # by the first page
        self._speed = speed
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="view-player", daemon=True)
        view.playback = self

    def __enter__(self) -> RecordingPlayer:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join()

    # --- the pages (the view's loop) ---------------------------------------------------------

    def page_opened(self) -> None:
        with self._cond:
            if not self._started:
                self._started = True
                self._play()
                self._changed()
                self._cond.notify_all()

    def control(self, message: dict[str, Any]) -> str | None:
        action = message.get("action")
        with self._cond:
            if action == "pause":
                self._position = self._now()
                self._playing = False
            elif action == "play":
                if self._index >= len(self.items):  # at the end: from the start again
                    self._seek(self.start)
                self._play()
            elif action == "speed":
                try:
                    speed = float(message.get("speed", 0))
                except (TypeError, ValueError):
                    speed = 0.0
                if speed not in SPEEDS:
                    return f"speed: one of {', '.join(f'{s:g}' for s in SPEEDS)}"
                self._position = self._now()
                self._anchor = time.monotonic()
                self._speed = speed
            elif action == "seek":
                try:
                    at = round(float(message.get("position", "")) * 1e9)
                except (TypeError, ValueError):
                    return "seek: a position in seconds (the recording's clock)"
                self._seek(min(max(at, self.start), self.end))
            else:
                return "playback: action pause, play, speed or seek"
            self._changed()
            self._cond.notify_all()
        return None

    def status(self) -> dict[str, Any]:
        with self._cond:
            return self._status()

    # --- under the lock ----------------------------------------------------------------------

    def _status(self) -> dict[str, Any]:
        return {"file": self.path, "start": self.start / 1e9, "end": self.end / 1e9, "position": self._now() / 1e9,
                "playing": self._playing, "speed": self._speed, "at": time.time(), "truncated": self.truncated,
                "messages": len(self.items), "played": self._index}

    def _changed(self) -> None:
        self.view.feed_playback(self._status())

    def _now(self) -> int:
        if not self._playing:
            return self._position
        return min(self.end, self._position + int((time.monotonic() - self._anchor) * self._speed * 1e9))

    def _play(self) -> None:
        self._position = self._now()
        self._anchor = time.monotonic()
        self._playing = True

    def _seek(self, at: int) -> None:
        """Everything up to ``at`` at once; back means from the start, on an empty view."""
        back = at < self._now() or at < self._position
        start = 0 if back else self._index
        end = start
        # A position comes in seconds (a float: sub-microsecond digits lost), as the pages know
        # each message's time: what was at that moment, to the microsecond, is included.
        while end < len(self.items) and self.items[end][0] <= at + SEEK_SLACK_NS:
            end += 1
        self.view.feed_replay([item for _, item in self.items[start:end]], reset=back)
        self._index = end
        self._position = at
        self._anchor = time.monotonic()

    # --- the thread --------------------------------------------------------------------------

    def _run(self) -> None:
        feeds: dict[str, Callable[..., None]] = {"alive": self.view.feed_alive, "custody": self.view.feed_custody,
                                                 "event": self.view.feed_event, "description": self.view.feed_description}
        with self._cond:
            while not self._closed:
                if not self._playing or self._index >= len(self.items):
                    self._cond.wait()
                    continue
                due, (kind, args) = self.items[self._index]
                now = self._now()
                if due > now:
                    self._cond.wait((due - now) / 1e9 / self._speed)
                    continue
                feeds[kind](*args)  # hands it to the loop: never blocks
                self._index += 1
                if self._index >= len(self.items):
                    self._position = self.end
                    self._playing = False
                    self._changed()
