"""The thread that talks to the endpoint, so the update loop never waits on HTTP.

The mind hands it one ``Job`` at a time (the messages, the tools); the worker waits as long as the
budget says (``budget.Budget``: it alone counts what was sent), sends the request through the
``Chat`` adapter and hands the ``Reply`` or the ``EndpointError`` to ``Job.done``, on its own
thread (the mind posts it to the loop).

The thread runs an asyncio event loop of its own with the library's asynchronous client: ``close``
(idempotent) cancels what it is doing, a budget wait or a request in flight, at once, closes the
client and joins the thread; a job it was doing then never reports (the mind is closing).
A context manager.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh.minds.llm.budget import Budget, Limits, estimate_tokens
from cmion_mesh.minds.llm.chat import Chat, EndpointError, Reply
from cmion_mesh.minds.llm.settings import LlmSettings

JOIN_TIMEOUT = 5.0
_json = msgspec.json.Encoder()


@dataclass(slots=True)
class Job:
    messages: list[dict[str, Any]]
    done: Callable[[Reply | EndpointError], None]
    tools: list[dict[str, Any]] = field(default_factory=list)
    max_tokens: int | None = None


class Worker:
    def __init__(self, settings: LlmSettings, *, name: str, on_wait: Callable[[float], None] | None = None,
                 limits: Limits | None = None) -> None:
        self.settings = settings
        self.budget = Budget(limits or settings.limits)
        self._on_wait = on_wait
        self._loop = asyncio.new_event_loop()
        self._jobs: asyncio.Queue[Job] | None = None
        self._main: asyncio.Task[None] | None = None
        self._closed = False
        self._lock = threading.Lock()
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"llm-{name}", daemon=True)
        self._thread.start()
        self._started.wait(JOIN_TIMEOUT)

    def __enter__(self) -> Worker:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def submit(self, job: Job) -> None:
        with self._lock:
            jobs = None if self._closed else self._jobs
            if jobs is not None:
                self._loop.call_soon_threadsafe(jobs.put_nowait, job)
                return
        job.done(EndpointError("the mind is closing"))

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            main = self._main
            if main is not None:
                self._loop.call_soon_threadsafe(main.cancel)
        if self._thread is not threading.current_thread():
            self._thread.join(JOIN_TIMEOUT)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._serve())
        finally:
            self._loop.close()

    async def _serve(self) -> None:
        chat = Chat(self.settings)
        with self._lock:
            self._jobs = asyncio.Queue()
            self._main = asyncio.current_task()
            closed = self._closed
        self._started.set()
        try:
            while not closed:
                job = await self._jobs.get()
                job.done(await self._send(chat, job))
        except asyncio.CancelledError:
            pass
        finally:
            await chat.aclose()

    async def _send(self, chat: Chat, job: Job) -> Reply | EndpointError:
        tokens = estimate_tokens(len(_json.encode(job.messages)) + len(_json.encode(job.tools))) + (job.max_tokens or 0)
        while True:
            wait = self.budget.wait(time.monotonic(), tokens)
            if wait <= 0:
                break
            if self._on_wait is not None:
                self._on_wait(wait)
            await asyncio.sleep(wait)
        handle = self.budget.spend(time.monotonic(), tokens)
        try:
            reply = await chat.complete(job.messages, job.tools, max_tokens=job.max_tokens)
        except EndpointError as exc:
            return exc
        if reply.tokens is not None:
            self.budget.settle(handle, reply.tokens)
        return reply
