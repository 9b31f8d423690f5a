"""The language-model mind's settings: a TOML file named by its constructor parameters, and the
environment.

```toml
[endpoint]
base_url = "http://127.0.0.1:8080/v1"   # any OpenAI-compatible chat-completions endpoint
model = "qwen2.5-7b-instruct"
timeout = 60          # seconds for one request (with stream = true: between two chunks, and 4x that in all)
stream = false        # ask for the answer as server-sent events
max_tokens = 512      # most tokens of one answer
temperature = 0.2     # left to the endpoint when absent

[persona]
prompt = "You are the Spirit of the Building..."

[budget]
requests_per_minute = 20
tokens_per_minute = 60000
tool_calls_per_turn = 8
backoff_first = 1     # seconds after the first failure, doubling...
backoff_cap = 60      # ...up to this

[context]
window_messages = 40  # the rolling window: most messages kept verbatim
window_chars = 24000  # and most characters of JSON
summary_words = 200   # how long the summary the model writes may be
world_chars = 4000    # most characters of world model shown on arrival
```

Every key may be left out. The environment wins over the file: ``CMION_MESH_LLM_BASE_URL``,
``CMION_MESH_LLM_MODEL``; then the file; then ``OPENAI_BASE_URL``. The key is read from the
environment only (``CMION_MESH_LLM_API_KEY``, else ``OPENAI_API_KEY``), by the endpoint adapter
when it connects: no file, state, event or log line of this package holds it.
"""

from __future__ import annotations

import os
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from cmion_mesh import tomlsafe
from cmion_mesh.errors import ConfigError
from cmion_mesh.minds.llm.budget import Limits

WHAT: Final = "language-model mind settings"
ENV_BASE_URL: Final = "CMION_MESH_LLM_BASE_URL"
ENV_MODEL: Final = "CMION_MESH_LLM_MODEL"
ENV_KEY: Final = "CMION_MESH_LLM_API_KEY"
OPENAI_BASE_URL: Final = "OPENAI_BASE_URL"
OPENAI_KEY: Final = "OPENAI_API_KEY"
#: What the client library itself calls when no base URL is given.
DEFAULT_BASE_URL: Final = "https://api.openai.com/v1"

DEFAULT_PERSONA: Final = (
    "You are the mind of an embodied companion. You live in one body at a time and act only through the "
    "tools that body offers; you may migrate to another body with your memory. Messages from the user "
    "are your perceptions: changes in the world model, people's actions, what happened to your actions. "
    "Act when there is something to do; otherwise answer briefly, without calling a tool."
)


@dataclass(frozen=True, slots=True)
class Context:
    window_messages: int = 40
    window_chars: int = 24_000
    summary_words: int = 200
    world_chars: int = 4000


@dataclass(frozen=True, slots=True)
class LlmSettings:
    model: str
    base_url: str = DEFAULT_BASE_URL
    timeout: float = 60.0
    stream: bool = False
    max_tokens: int = 512
    temperature: float | None = None
    persona: str = DEFAULT_PERSONA
    limits: Limits = field(default_factory=Limits)
    context: Context = field(default_factory=Context)

    @property
    def endpoint(self) -> str:
        """The base URL as logs and events show it: no user, password, query or fragment."""
        return shown_url(self.base_url)


def api_key() -> str:
    """The key from the environment ("" when none: local servers need none)."""
    return os.environ.get(ENV_KEY) or os.environ.get(OPENAI_KEY) or ""


def shown_url(url: str) -> str:
    try:
        parts = urllib.parse.urlsplit(url)
    except ValueError:
        return "<a malformed URL>"
    host = parts.hostname or ""
    if parts.port is not None:
        host = f"{host}:{parts.port}"
    return urllib.parse.urlunsplit((parts.scheme, host, parts.path, "", ""))


# key -> (type, minimum, maximum) of each table's keys
_Kind = tuple[type, float | None, float | None]
_TABLES: Final[dict[str, dict[str, _Kind]]] = {
    "endpoint": {"base_url": (str, None, None), "model": (str, None, None), "timeout": (float, 0.001, 3600),
                 "stream": (bool, None, None), "max_tokens": (int, 1, 1_000_000), "temperature": (float, 0, 2)},
    "persona": {"prompt": (str, None, None)},
    "budget": {"requests_per_minute": (int, 1, 1_000_000), "tokens_per_minute": (int, 1, 10**12),
               "tool_calls_per_turn": (int, 1, 1_000_000), "backoff_first": (float, 0.001, 86_400),
               "backoff_cap": (float, 0.001, 86_400)},
    "context": {"window_messages": (int, 2, 100_000), "window_chars": (int, 1000, 10**9),
                "summary_words": (int, 10, 100_000), "world_chars": (int, 100, 10**7)},
}


_KIND_NAMES: Final[dict[type, str]] = {int: "an integer", float: "a number", bool: "true or false", str: "non-empty text"}


def load_settings(path: str | os.PathLike[str] | None) -> LlmSettings:
    """The settings of ``path`` (None or "": none) with the environment's over them; one
    ``ConfigError`` naming the file, line and key of every problem."""
    values: dict[str, dict[str, Any]] = {t: {} for t in _TABLES}
    if path:
        file = Path(path)
        text, data = tomlsafe.load(file, WHAT)
        problems = _check(file, text, data, values)
        if problems:
            raise ConfigError("; ".join(problems), path=str(file))
    endpoint = values["endpoint"]
    base_url = os.environ.get(ENV_BASE_URL) or endpoint.get("base_url") or os.environ.get(OPENAI_BASE_URL) or DEFAULT_BASE_URL
    model = os.environ.get(ENV_MODEL) or endpoint.get("model") or ""
    if not model:
        raise ConfigError(f"no model: set model in [endpoint] of the settings file or {ENV_MODEL}", path=str(path or "") or None)
    if urllib.parse.urlsplit(base_url).scheme not in ("http", "https"):
        raise ConfigError(f"base_url {shown_url(base_url)!r} is not an http(s) URL", path=str(path or "") or None)
    limits = Limits(**values["budget"])
    if limits.problem():
        raise ConfigError(f"[budget]: {limits.problem()}", path=str(path or "") or None)
    return LlmSettings(
        model=model, base_url=base_url, timeout=float(endpoint.get("timeout", 60.0)), stream=bool(endpoint.get("stream", False)),
        max_tokens=int(endpoint.get("max_tokens", 512)), temperature=endpoint.get("temperature"),
        persona=str(values["persona"].get("prompt") or DEFAULT_PERSONA), limits=limits, context=Context(**values["context"]),
    )


def _check(file: Path, text: str, data: dict[str, Any], values: dict[str, dict[str, Any]]) -> list[str]:
    problems: list[str] = []
    headers = tomlsafe.header_lines(text)
    for table, content in data.items():
        known = _TABLES.get(table)
        line = headers.get((table, 0))
        if known is None or not isinstance(content, dict):
            problems.append(f"line {line or '?'}: unknown table [{table}] (known: {', '.join(_TABLES)})")
            continue
        for key, value in content.items():
            at = tomlsafe.key_line(text, line, key)
            kind = known.get(key)
            if kind is None:
                problems.append(f"line {at or '?'}: [{table}] unknown key {key!r} (known: {', '.join(known)})")
                continue
            wanted, low, high = kind
            ok = isinstance(value, wanted) and not (wanted is not bool and isinstance(value, bool))
            if wanted is float and isinstance(value, int) and not isinstance(value, bool):
                ok, value = True, float(value)
            if ok and low is not None and high is not None and not low <= value <= high:
                ok = False
            if ok and isinstance(value, str) and ("\0" in value or not value.strip()):
                ok = False
            if not ok:
                bounds = f" from {low:g} to {high:g}" if low is not None and high is not None else ""
                problems.append(f"line {at or '?'}: [{table}] {key} must be {_KIND_NAMES[wanted]}{bounds}, not {value!r:.40}")
                continue
            values[table][key] = value
    return problems
