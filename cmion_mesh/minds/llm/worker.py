"""The thread that talks to the endpoint, so the update loop never waits on HTTP.

The mind hands it one ``Job`` at a time (the messages, the tools); the worker waits as long as the
budget says (``budget.Budget``: it alone counts what was sent), sends the request through the
``Chat`` adapter and hands the ``Reply`` or the ``EndpointError`` to ``Job.done``, on its own
thread (the mind posts it to the loop). A context manager; ``close`` (idempotent) ends a budget
wait at once and a request in flight by closing the client, then joins the thread.
"""

from __future__ import annotations

import queue
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
        self.chat = Chat(settings)
        self.budget = Budget(limits or settings.limits)
        self._on_wait = on_wait
        self._jobs: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"llm-{name}", daemon=True)
        self._thread.start()

    def __enter__(self) -> Worker:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def submit(self, job: Job) -> None:
        if self._stop.is_set():
            job.done(EndpointError("the mind is closing"))
            return
        self._jobs.put(job)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._jobs.put(None)
        self.chat.close()
        if self._thread is not threading.current_thread():
            self._thread.join(JOIN_TIMEOUT)

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None or self._stop.is_set():
                return
            job.done(self._send(job))

    def _send(self, job: Job) -> Reply | EndpointError:
        tokens = estimate_tokens(len(_json.encode(job.messages)) + len(_json.encode(job.tools))) + (job.max_tokens or 0)
        while True:
            wait = self.budget.wait(time.monotonic(), tokens)
            if wait <= 0:
                break
            if self._on_wait is not None:
                self._on_wait(wait)
            if self._stop.wait(wait):
                return EndpointError("the mind is closing")
        handle = self.budget.spend(time.monotonic(), tokens)
        try:
            reply = self.chat.complete(job.messages, job.tools, stop=self._stop, max_tokens=job.max_tokens)
        except EndpointError as exc:
            return exc
        if reply.tokens is not None:
            self.budget.settle(handle, reply.tokens)
        return reply
