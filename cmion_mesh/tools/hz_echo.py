"""``cmion-mesh hz KEY`` and ``cmion-mesh echo KEY``: the rate and the content of any key expression
of the mesh, as ``ros2 topic hz`` and ``ros2 topic echo`` show a topic's.

Keys: one that starts with ``cmion/`` (or ``/``, which is dropped) is absolute, any zenoh key
expression; any other is relative to the mesh: ``robot/ev/**`` is ``cmion/<mesh>/robot/ev/**``,
``**`` is everything the mesh publishes. A key expression with a chunk that starts with ``@``
(``@alive/*``, ``@competency/robot/**``) names liveliness tokens, watched as they appear and go
(zenoh's ``**`` never matches such a chunk); ``@outcome`` is the exception: requests' answers are
published there (``*/@outcome/**``). What is seen is what is *published*: events, storage
changes, liveliness; requests are queries, which zenoh hands to queryables, not to subscribers.

Times are taken when a sample reaches the subscription's worker (``time.monotonic``), as
``ros2 topic hz`` takes them on receipt: the rate is the mesh's as a subscriber sees it.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import InvalidName, ProtocolError
from cmion_mesh.messages import decode
from cmion_mesh.transport.base import Closeable, Handle, Sample, Transport

#: ``ros2 topic hz``'s default window.
DEFAULT_WINDOW = 10_000
#: Bytes of a binary payload ``echo`` shows (as hex); text is shown up to ``TEXT_PREVIEW`` characters.
HEX_PREVIEW = 64
TEXT_PREVIEW = 2000


def resolve(mesh: str, key: str) -> str:
    """The key expression ``KEY`` names (see the module's doc); ``InvalidName`` when it is unusable."""
    text = key.strip()
    if text.startswith("/"):
        text = text[1:]
    elif not text.startswith(keys.ROOT + "/") and text != keys.ROOT:
        text = f"{keys.mesh_prefix(mesh)}/{text}" if text else ""
    if not text or any(chunk == "" for chunk in text.split("/")) or re.search(r"[\s#?$]", text):
        raise InvalidName(f"key expression {key!r} is not usable: chunks are separated by single '/', and may not be empty "
                          "or hold white space, '#', '?' or '$'")
    return text


def is_liveliness(expression: str) -> bool:
    """Whether ``expression`` names liveliness tokens: a chunk starts with ``@``, except ``@outcome``,
    where requests' answers are *published* (``keys.OUTCOMES``)."""
    return any(chunk.startswith("@") and chunk != keys.OUTCOMES for chunk in expression.split("/"))


@dataclass(frozen=True, slots=True)
class Seen:
    """One thing seen on the key expression: ``kind`` is ``put``, ``delete``, ``alive`` or ``gone``."""

    key: str
    payload: bytes
    kind: str
    time: float  # wall clock, for people
    stamp: float  # monotonic, for rates


class Tap(Handle):
    """A subscription (or a liveliness watch) on ``expression``; ``handler`` gets every ``Seen``, in
    order, on the transport's worker thread."""

    def __init__(self, transport: Transport, expression: str, handler: Callable[[Seen], None], *, liveliness: bool | None = None) -> None:
        self.expression = expression
        self.liveliness = is_liveliness(expression) if liveliness is None else liveliness

        def on_sample(sample: Sample) -> None:
            handler(Seen(sample.key, sample.payload, "delete" if sample.deleted else "put", time.time(), time.monotonic()))

        def on_token(key: str, alive: bool) -> None:
            handler(Seen(key, b"", "alive" if alive else "gone", time.time(), time.monotonic()))

        self._entity: Closeable = (transport.watch_liveliness(expression, on_token) if self.liveliness
                                   else transport.subscribe(expression, on_sample))

    def close(self) -> None:
        self._entity.close()


# --- hz -------------------------------------------------------------------------------------------


class Rate:
    """Arrival times of the last ``window`` periods, and their statistics (thread-safe)."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        self.stamps: deque[float] = deque(maxlen=window + 1)
        self.count = 0
        self.lock = threading.Lock()

    def add(self, stamp: float) -> None:
        with self.lock:
            self.stamps.append(stamp)
            self.count += 1

    def stats(self) -> dict[str, Any] | None:
        """``rate`` (Hz: periods / their total), the periods' ``min``/``max``/``std_dev`` (s),
        ``window`` (periods used) and ``count`` (messages so far); None before two messages."""
        with self.lock:
            stamps, count = list(self.stamps), self.count
        if len(stamps) < 2:
            return None
        periods = [b - a for a, b in itertools.pairwise(stamps)]
        mean = (stamps[-1] - stamps[0]) / len(periods)
        std = math.sqrt(sum((p - mean) ** 2 for p in periods) / len(periods))
        return {"rate": 1.0 / mean if mean > 0 else math.inf, "min": min(periods), "max": max(periods), "std_dev": std,
                "window": len(periods), "count": count}


class Hz:
    """Rates on a key expression: overall, or per key (``per_key``)."""

    def __init__(self, window: int = DEFAULT_WINDOW, *, per_key: bool = False) -> None:
        self.window, self.per_key = window, per_key
        self.rates: dict[str, Rate] = {}
        self.lock = threading.Lock()
        self.total = 0

    def add(self, seen: Seen, group: str) -> int:
        """Count ``seen`` (under ``group``: the expression, or its key); the total so far."""
        name = seen.key if self.per_key else group
        with self.lock:
            rate = self.rates.get(name)
            if rate is None:
                rate = self.rates[name] = Rate(self.window)
            self.total += 1
            total = self.total
        rate.add(seen.stamp)
        return total

    def report(self) -> dict[str, dict[str, Any]]:
        with self.lock:
            rates = dict(self.rates)
        return {name: stats for name, rate in sorted(rates.items()) if (stats := rate.stats()) is not None}


def format_rate(name: str, stats: dict[str, Any], *, with_name: bool) -> str:
    """As ``ros2 topic hz`` prints it."""
    head = f"{name}: " if with_name else ""
    return (f"{head}average rate: {stats['rate']:.3f}\n"
            f"\tmin: {stats['min']:.3f}s max: {stats['max']:.3f}s std dev: {stats['std_dev']:.5f}s window: {stats['window']}")


# --- echo -----------------------------------------------------------------------------------------


def describe(seen: Seen, *, raw: bool = False) -> dict[str, Any]:
    """What ``echo`` shows of ``seen``: the decoded mesh message (``type``, ``message``), or the raw
    payload (``raw``: its ``size`` and its ``text`` when it is UTF-8 text, else ``hex`` of the first bytes)."""
    out: dict[str, Any] = {"key": seen.key, "time": seen.time, "kind": seen.kind}
    if seen.kind != "put":
        return out
    if not raw:
        try:
            message = decode(seen.payload, where=seen.key)
        except ProtocolError:
            pass
        else:
            builtins = msgspec.to_builtins(message)
            out["type"] = builtins.get("type") if isinstance(builtins, dict) else None
            out["message"] = builtins
            return out
    preview: dict[str, Any] = {"size": len(seen.payload)}
    try:
        text = seen.payload.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is not None and all(c.isprintable() or c in "\n\t\r" for c in text):
        preview["text"] = text[:TEXT_PREVIEW]
    else:
        preview["hex"] = seen.payload[:HEX_PREVIEW].hex(" ")
    if len(seen.payload) > (TEXT_PREVIEW if "text" in preview else HEX_PREVIEW):
        preview["truncated"] = True
    out["raw"] = preview
    return out


_PLAIN = re.compile(r"[A-Za-z_/][\w./@*+-]*( [\w./@*+-]+)*")


def _scalar(value: Any) -> str:
    if isinstance(value, str) and _PLAIN.fullmatch(value) and value not in ("true", "false", "null", "yes", "no", "on", "off"):
        return value
    return json.dumps(value, ensure_ascii=False)


def yamlish(value: Any, indent: int = 0) -> list[str]:
    """``value`` as YAML-like lines: maps as ``key: value``, lists of scalars inline, nested blocks indented."""
    pad = "  " * indent
    if isinstance(value, dict):
        if not value:
            return [pad + "{}"]
        lines = []
        for key, item in value.items():
            if isinstance(item, dict | list) and item and not _inline(item):
                lines.append(f"{pad}{key}:")
                lines += yamlish(item, indent + 1)
            else:
                lines.append(f"{pad}{key}: {_inline_text(item)}")
        return lines
    if isinstance(value, list):
        if _inline(value):
            return [pad + _inline_text(value)]
        lines = []
        for item in value:
            block = yamlish(item, indent + 1)
            lines.append(f"{pad}- {block[0].lstrip()}")
            lines += block[1:]
        return lines
    return [pad + _scalar(value)]


def _inline(value: Any) -> bool:
    return isinstance(value, list) and all(not isinstance(v, dict | list) for v in value)


def _inline_text(value: Any) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(_scalar(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{}"
    return _scalar(value)


def render(shown: dict[str, Any]) -> str:
    """``echo``'s text for one thing seen: a ``---`` line naming the key, time and kind, then the content."""
    stamp = time.strftime("%H:%M:%S", time.localtime(shown["time"])) + f".{int(shown['time'] * 1000) % 1000:03d}"
    kind = shown.get("type") or shown["kind"]
    lines = [f"--- {shown['key']}  ({stamp}, {kind})"]
    if "message" in shown:
        lines += yamlish(shown["message"])
    elif "raw" in shown:
        raw = shown["raw"]
        more = ", truncated" if raw.get("truncated") else ""
        if "text" in raw:
            lines.append(f"raw text ({raw['size']} bytes{more}): {raw['text']}")
        else:
            lines.append(f"raw bytes ({raw['size']}{more}): {raw['hex']}")
    return "\n".join(lines)


class Printer:
    """Writes what ``echo`` shows, one thing at a time (the worker thread writes while the main waits)."""

    def __init__(self, *, as_json: bool, raw: bool = False, stream: TextIO | None = None) -> None:
        self.as_json, self.raw = as_json, raw
        self.stream = stream or sys.stdout
        self.lock = threading.Lock()

    def show(self, seen: Seen) -> None:
        shown = describe(seen, raw=self.raw)
        text = json.dumps(shown, ensure_ascii=False) if self.as_json else render(shown)
        with self.lock:
            self.stream.write(text + "\n")
            self.stream.flush()
