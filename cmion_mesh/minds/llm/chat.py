"""The one door to a chat-completions endpoint: the official ``openai`` client library, which
speaks to any OpenAI-compatible server (llama.cpp's ``llama-server``, Ollama, vLLM, hosted ones).

``Chat.complete(messages, tools)`` sends one request and returns the assistant's message as plain
data (``role``, ``content``, ``tool_calls`` with ``id``, ``type`` and ``function`` ``name`` and
``arguments`` text) and the tokens the endpoint says it cost. Every failure is one
``EndpointError`` with a reason fit for a log line (never the key: the library sends it in a
header, and no reason here quotes a request) and, when the endpoint sent one, its ``Retry-After``.
The library's own retries are off (``max_retries=0``): the mind retries on its own schedule, so
its budget counts every request.

With ``stream``, the answer comes as server-sent events, assembled here (the content's pieces,
each tool call's pieces by index); ``timeout`` then bounds the wait for each chunk, so a slow model
that keeps talking is not cut off while one that stalls is, and four times ``timeout`` bounds
the whole answer.

The client is the library's asynchronous one, run by the mind's worker thread on an event loop of
its own (``worker``): cancelling the task ends a request in flight at once, which a blocking
client cannot do from another thread (closing it leaves a read waiting for the server).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import openai
from openai.types.chat import ChatCompletion, ChatCompletionChunk

from cmion_mesh.errors import MeshError
from cmion_mesh.minds.llm.settings import LlmSettings, api_key

#: Placeholder key for servers that need none (the library refuses to start without one).
NO_KEY = "none"


class EndpointError(MeshError):
    """The endpoint could not give an answer: ``reason`` says why; ``retry_after`` in seconds when
    it asked for a pause; ``status`` the HTTP status, if one came."""

    def __init__(self, reason: str, *, retry_after: float | None = None, status: int | None = None) -> None:
        super().__init__(reason)
        self.reason, self.retry_after, self.status = reason, retry_after, status


@dataclass(frozen=True, slots=True)
class Reply:
    message: dict[str, Any]
    tokens: int | None  # usage.total_tokens, when the endpoint reported it


class Chat:
    """A client of one endpoint, made and used on one event loop; ``aclose`` is idempotent."""

    def __init__(self, settings: LlmSettings) -> None:
        self.settings = settings
        self._client = openai.AsyncOpenAI(base_url=settings.base_url, api_key=api_key() or NO_KEY, timeout=settings.timeout,
                                          max_retries=0)
        self._closed = False

    async def aclose(self) -> None:
        if not self._closed:
            self._closed = True
            await self._client.close()

    async def complete(self, messages: Sequence[dict[str, Any]], tools: Sequence[dict[str, Any]] = (), *,
                       stream: bool | None = None, max_tokens: int | None = None) -> Reply:
        s = self.settings
        streaming = s.stream if stream is None else stream
        body: dict[str, Any] = {"model": s.model, "messages": list(messages), "max_tokens": max_tokens or s.max_tokens}
        if tools:
            body["tools"] = list(tools)
        if s.temperature is not None:
            body["temperature"] = s.temperature
        # The client's generic ``post`` (its documented way to send a body as it is), not
        # ``chat.completions.create``: ``create`` walks every message through its TypedDict
        # transforms first, 10 ms for a window of 40 messages, and the messages here are already
        # the API's plain JSON. Timeouts, errors, the key and streaming are the client's; a whole
        # answer's bytes are decoded here by their schema (``_Completion``).
        try:
            if streaming:
                body["stream"], body["stream_options"] = True, {"include_usage": True}
                chunks = await self._client.post("/chat/completions", cast_to=ChatCompletion, body=body, stream=True,
                                                 stream_cls=openai.AsyncStream[ChatCompletionChunk])
                try:
                    async with asyncio.timeout(4 * s.timeout):
                        return await _assemble(chunks)
                except TimeoutError:
                    raise EndpointError(f"the answer took more than {4 * s.timeout:g} s") from None
                finally:
                    await chunks.close()
            raw = await self._client.post("/chat/completions", cast_to=bytes, body=body)
        except EndpointError:
            raise
        except openai.APITimeoutError:
            raise EndpointError(f"no answer within {s.timeout:g} s") from None
        except openai.APIConnectionError as exc:
            raise EndpointError(f"cannot reach it: {_cause(exc)}") from None
        except openai.APIStatusError as exc:
            raise EndpointError(f"HTTP {exc.status_code}: {_status_text(exc)}", retry_after=_retry_after(exc),
                                status=exc.status_code) from None
        except Exception as exc:  # the library's others, and the HTTP layer's while a stream is read
            raise EndpointError(f"{type(exc).__name__}: {str(exc)[:200]}") from None
        return _reply(raw)


class _Function(msgspec.Struct):
    name: str = ""
    arguments: str = ""


class _ToolCall(msgspec.Struct):
    id: str = ""
    function: _Function | None = None  # a function call; other kinds of tool call are not ours


class _Message(msgspec.Struct):
    content: str | None = None
    tool_calls: list[_ToolCall] | None = None


class _Choice(msgspec.Struct):
    message: _Message


class _Usage(msgspec.Struct):
    total_tokens: int | None = None


class _Completion(msgspec.Struct):
    """The fields of a ``chat.completion`` object the mind reads (the others are ignored)."""

    choices: list[_Choice]
    usage: _Usage | None = None


_completion = msgspec.json.Decoder(_Completion)


def _reply(raw: bytes) -> Reply:
    """The answer's body, decoded by its schema (faster than the library's models, and as strict:
    a body that is not a chat completion is an ``EndpointError``)."""
    try:
        completion = _completion.decode(raw)
    except msgspec.DecodeError as exc:
        raise EndpointError(f"an answer that is not a chat completion: {exc}") from None
    if not completion.choices:
        raise EndpointError("an answer with no choices")
    message = completion.choices[0].message
    calls = [{"id": call.id or f"call_{i}", "type": "function",
              "function": {"name": call.function.name, "arguments": call.function.arguments}}
             for i, call in enumerate(message.tool_calls or ()) if call.function is not None]
    tokens = completion.usage.total_tokens if completion.usage is not None else None
    return Reply(assistant(message.content, calls), tokens)


def assistant(content: str | None, calls: list[dict[str, Any]]) -> dict[str, Any]:
    """The assistant message as the window keeps it (and sends it back in every later request)."""
    # ``null`` content only beside tool calls: an assistant message with neither is refused by the API.
    out: dict[str, Any] = {"role": "assistant", "content": content if content else (None if calls else "")}
    if calls:
        out["tool_calls"] = calls
    return out


async def _assemble(chunks: AsyncIterator[Any]) -> Reply:
    content: list[str] = []
    calls: dict[int, dict[str, Any]] = {}
    tokens: int | None = None
    async for chunk in chunks:
        if getattr(chunk, "usage", None) is not None:
            tokens = chunk.usage.total_tokens
        for choice in chunk.choices or ():
            delta = choice.delta
            if delta.content:
                content.append(delta.content)
            for call in delta.tool_calls or ():
                slot = calls.setdefault(call.index, {"id": "", "name": "", "arguments": []})
                if call.id:
                    slot["id"] = call.id
                if call.function is not None:
                    if call.function.name:
                        slot["name"] += call.function.name
                    if call.function.arguments:
                        slot["arguments"].append(call.function.arguments)
    assembled = [{"id": slot["id"] or f"call_{i}", "type": "function",
                  "function": {"name": slot["name"], "arguments": "".join(slot["arguments"])}}
                 for i, slot in sorted(calls.items())]
    return Reply(assistant("".join(content), assembled), tokens)


def _cause(exc: BaseException) -> str:
    inner = exc.__cause__ or exc.__context__
    text = str(inner) if inner is not None else str(exc)
    return text[:200] or type(inner or exc).__name__


def _status_text(exc: openai.APIStatusError) -> str:
    body = exc.body
    if isinstance(body, dict):
        inner = body.get("error")
        message = inner.get("message") if isinstance(inner, dict) else body.get("message")
        if isinstance(message, str):
            return message[:200]
    return str(exc.message)[:200]


def _retry_after(exc: openai.APIStatusError) -> float | None:
    raw = exc.response.headers.get("retry-after") if exc.response is not None else None
    try:
        return max(0.0, float(raw)) if raw is not None else None
    except ValueError:
        return None
