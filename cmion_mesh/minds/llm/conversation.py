"""The language-model mind's memory, pure: a rolling window of chat messages, a summary the model
wrote of what fell out of it, perceptions waiting to be told, and the tool calls still running.

What the model is sent each turn (``request``): one system message (the persona, then the summary),
the window, then the perceptions gathered since the last turn as one user message. Messages are the
chat-completions API's own (``role`` user / assistant / tool), as plain data, so the state is
what the endpoint saw, byte for byte. Nothing is taken from the inbox until the model's answer is
committed (``commit``): a turn that fails (the endpoint is down, the mind migrated meanwhile) is
asked again with the same perceptions and nothing is lost.

The window is bounded (``overflow``): the oldest messages, cut where a user message starts, else
an assistant message (its tool calls are never parted from their results), are summarised by the model
(``apply_summary``); when the model cannot be reached for long, beyond twice the bound, the oldest
are dropped, and the summary says so (``drop_oldest``).

``state`` / ``from_state`` are the identity section that migrates: the summary, the window, the
inbox, the tool calls in flight with the results known so far, and the body it was last in.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgspec

STATE_VERSION = 1
#: Most perceptions waiting: beyond, the oldest are counted, not kept (one line says how many).
MAX_INBOX = 200
#: Longest perception line (a property holding a long text is cut).
MAX_LINE = 600

_json = msgspec.json.Encoder()


@dataclass(slots=True)
class OpenCall:
    """A tool call of the last assistant message whose result is not yet in the window."""

    id: str
    tool: str
    action_id: str = ""  # the mind action it became ("" when it was answered at once)
    result: str | None = None
    arguments: str = ""  # the JSON text the model sent
    action: str = ""  # the body's action it names, once looked up

    def to_data(self) -> dict[str, Any]:
        return {"id": self.id, "tool": self.tool, "action_id": self.action_id, "result": self.result,
                "arguments": self.arguments, "action": self.action}


@dataclass(slots=True)
class Conversation:
    summary: str = ""
    messages: list[dict[str, Any]] = field(default_factory=list)
    inbox: list[str] = field(default_factory=list)
    dropped: int = 0  # perceptions beyond ``MAX_INBOX`` not kept since the last turn
    calls: list[OpenCall] = field(default_factory=list)
    body: str = ""
    #: Bumped whenever the window changes other than by appending: an answer to a request made
    #: before is not committed (runtime only).
    generation: int = 0

    # --- perceptions --------------------------------------------------------------------------

    def perceive(self, line: str, at: int | None = None) -> None:
        """Add a perception (at the end, or before the inbox's line ``at``)."""
        if len(line) > MAX_LINE and at is None:
            line = line[: MAX_LINE - 1] + "…"
        if len(self.inbox) >= MAX_INBOX:
            self.inbox.pop(0)
            self.dropped += 1
            at = None if at is None else max(0, at - 1)
        if at is None:
            self.inbox.append(line)
        else:
            self.inbox.insert(min(at, len(self.inbox)), line)

    # --- a turn -------------------------------------------------------------------------------

    def request(self, system: str) -> tuple[list[dict[str, Any]], int]:
        """The messages of the next request, and how many inbox lines they include."""
        prompt = system if not self.summary else f"{system}\n\nWhat happened before (your own summary):\n{self.summary}"
        out: list[dict[str, Any]] = [{"role": "system", "content": prompt}, *self.messages]
        taken = len(self.inbox)
        if taken or self.dropped:
            out.append(self._perceptions(taken))
        return out, taken

    def _perceptions(self, taken: int) -> dict[str, Any]:
        lines = list(self.inbox[:taken])
        if self.dropped:
            lines.insert(0, f"({self.dropped} earlier perceptions were not kept)")
        return {"role": "user", "content": "\n".join(lines)}

    def commit(self, taken: int, reply: Mapping[str, Any]) -> None:
        """The model answered a request that included ``taken`` inbox lines: they and the answer
        join the window; its tool calls (if any) are open until ``close_calls``."""
        if taken or self.dropped:
            self.messages.append(self._perceptions(taken))
            del self.inbox[:taken]
            self.dropped = 0
        self.messages.append(dict(reply))
        self.calls = [OpenCall(str(c.get("id", "")), str(c.get("function", {}).get("name", "")),
                               arguments=str(c.get("function", {}).get("arguments", "")))
                      for c in reply.get("tool_calls") or ()]

    def resolve(self, call_id: str, result: str) -> bool:
        """Record a tool call's result; False when no open call has that id."""
        for call in self.calls:
            if call.id == call_id and call.result is None:
                call.result = result
                return True
        return False

    def call_for_action(self, action_id: str) -> OpenCall | None:
        return next((c for c in self.calls if c.action_id == action_id and c.result is None), None)

    @property
    def waiting(self) -> bool:
        """Whether a tool call of the last answer has no result yet."""
        return any(c.result is None for c in self.calls)

    def close_calls(self) -> bool:
        """Once every open call has its result, they join the window as tool messages, in the
        order the model made them; True if there were calls."""
        if not self.calls or self.waiting:
            return False
        for call in self.calls:
            self.messages.append({"role": "tool", "tool_call_id": call.id, "content": call.result or ""})
        self.calls = []
        return True

    # --- the bound ----------------------------------------------------------------------------

    def size(self) -> int:
        return sum(len(_json.encode(m)) for m in self.messages)

    def overflow(self, max_messages: int, max_chars: int) -> int:
        """How many of the oldest messages to summarise once the window is over its bound (0: it is
        not), so that what is left fits in half of it. The window starts at a user message when one
        makes it fit, else at an assistant message (a long run of tool calls has no user message in
        it); never at a tool result, which must follow its call. The last exchange is kept whole
        even when alone it is over the bound."""
        sizes = [len(_json.encode(m)) for m in self.messages]
        count = len(self.messages)
        if count <= max_messages and sum(sizes) <= max_chars:
            return 0
        # Down to half the bound: a summary every few turns, not one per message once full.
        keep_messages, keep_chars = max(1, max_messages // 2), max_chars // 2
        fits = [i for i in range(1, count) if count - i <= keep_messages and sum(sizes[i:]) <= keep_chars]
        starts = [i for i in fits if self.messages[i].get("role") == "user"] or \
                 [i for i in fits if self.messages[i].get("role") == "assistant"]
        if starts:
            return starts[0]
        last = [i for i in range(1, count) if self.messages[i].get("role") in ("user", "assistant")]
        return last[-1] if last else 0

    def summary_request(self, cut: int, words: int) -> list[dict[str, Any]]:
        """The messages asking the model to fold the ``cut`` oldest messages into its summary."""
        told = "\n".join(render(m) for m in self.messages[:cut])
        earlier = f"Your summary so far:\n{self.summary}\n\n" if self.summary else ""
        return [
            {"role": "system", "content": "You keep the memory of an embodied companion. Write its summary of what "
                                          f"happened, at most {words} words, in the first person: the people, places and "
                                          "facts it learned, what it did and where, what it promised or still has to "
                                          "do. Write only the summary."},
            {"role": "user", "content": f"{earlier}What happened next:\n{told}"},
        ]

    def apply_summary(self, cut: int, text: str, max_chars: int) -> None:
        self.summary = text.strip()[:max_chars]
        del self.messages[:cut]
        self.generation += 1

    def drop_oldest(self, cut: int) -> None:
        """Drop the ``cut`` oldest messages unsummarised (the model could not be asked for long)."""
        del self.messages[:cut]
        note = f"({cut} older messages were dropped without a summary: the model could not be reached)"
        self.summary = f"{self.summary}\n{note}".strip()
        self.generation += 1

    # --- what migrates ------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """A copy (the identity is packed off the loop while the window goes on)."""
        return {
            "version": STATE_VERSION,
            "summary": self.summary,
            "messages": copy.deepcopy(self.messages),
            "inbox": list(self.inbox),
            "dropped": self.dropped,
            "calls": [c.to_data() for c in self.calls],
            "body": self.body,
        }

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> Conversation:
        """``ValueError`` naming the field when ``state`` is not a conversation of this version."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"conversation version {state.get('version')!r}, expected {STATE_VERSION}")
        messages = state.get("messages")
        if not isinstance(messages, list) or not all(isinstance(m, dict) and isinstance(m.get("role"), str) for m in messages):
            raise ValueError("messages: not a list of chat messages")
        inbox = state.get("inbox")
        if not isinstance(inbox, list) or not all(isinstance(x, str) for x in inbox):
            raise ValueError("inbox: not a list of lines")
        calls = []
        for c in state.get("calls") or []:
            if not isinstance(c, dict) or not isinstance(c.get("id"), str):
                raise ValueError("calls: not a list of tool calls")
            result = c.get("result")
            calls.append(OpenCall(c["id"], str(c.get("tool", "")), str(c.get("action_id", "")),
                                  result if isinstance(result, str) else None, str(c.get("arguments", "")),
                                  str(c.get("action", ""))))
        return cls(str(state.get("summary") or ""), copy.deepcopy(messages), list(inbox), int(state.get("dropped") or 0),
                   calls, str(state.get("body") or ""))


# --- perceptions as text (what the model reads) ------------------------------------------------


def value_text(value: Any) -> str:
    return value if isinstance(value, str) else _json.encode(value).decode()


def render(message: Mapping[str, Any]) -> str:
    """One message as a line of text (what a summary request shows the model)."""
    role = message.get("role")
    content = message.get("content") or ""
    if role == "assistant":
        calls = [f"{c.get('function', {}).get('name')}({c.get('function', {}).get('arguments')})" for c in message.get("tool_calls") or ()]
        said = f"I said: {content}" if content else ""
        did = f"I called: {', '.join(calls)}" if calls else ""
        return " ".join(p for p in (said, did) if p) or "I said nothing."
    if role == "tool":
        return f"Result: {content}"
    return f"I perceived: {content}"


def world_text(tree: Mapping[str, Any], max_chars: int) -> str:
    """A world model (``Store.tree()`` form) as one line per entity: ``Name (kind): prop=value, ...``,
    at most ``max_chars`` (then how many entities were left out)."""
    lines: list[str] = []

    def walk(node: Mapping[str, Any], path: str) -> None:
        for name, child in (node.get("children") or {}).items():
            if not isinstance(child, Mapping):
                continue
            full = f"{path}/{name}" if path else str(name)
            props = child.get("properties") or {}
            shown = ", ".join(f"{p}={value_text(v.get('value') if isinstance(v, Mapping) else v)}" for p, v in props.items())
            lines.append(f"{full} ({child.get('kind') or 'entity'}): {shown}" if shown else f"{full} ({child.get('kind') or 'entity'})")
            walk(child, full)

    walk(tree, "")
    out: list[str] = []
    used = 0
    for i, line in enumerate(lines):
        if used + len(line) + 1 > max_chars:
            out.append(f"... and {len(lines) - i} more entities")
            break
        out.append(line)
        used += len(line) + 1
    return "\n".join(out) if out else "(empty)"


def tools_text(tools: Sequence[Mapping[str, Any]]) -> str:
    """The tools offered, one line each (name and parameters), as an arrival note lists them."""
    out = []
    for tool in tools:
        function = tool.get("function") or {}
        params = ", ".join((function.get("parameters") or {}).get("properties") or {})
        out.append(f"{function.get('name')}({params})")
    return "; ".join(out) if out else "(none)"
