"""The MCP server's tool calls (``tools/mcp_server.py``): each one ends as a tool result, never a
traceback.

* an action of the body: ``MeshClient.start_action`` on the host; its run's events become progress
  notifications (when the client asked with a progress token); a cancelled call cancels the action
  in the body and waits, bounded, for its end; the outcome is the result (``isError`` unless it
  succeeded), the body leaving first is "outcome unknown" naming it;
* ``migrate``: ``MeshClient.migrate``, which cannot be called back once its handshake started;
* ``peers``: ``MeshClient.describe_all``, in short.

Runs on the server's loop; what waits for the mesh runs in worker threads.
"""

from __future__ import annotations

import asyncio
import json
import logging
import uuid
from collections.abc import Callable
from functools import partial
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import mcp_types as types
import msgspec

from cmion_mesh.action_runs import ActionRun
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError, NotAlive, NotReached, OutcomeUnknown, RequestRejected, Vanished
from cmion_mesh.messages import ActionReport, Event
from cmion_mesh.tools.companion_view import ToolSpec, belongs_to, progress_message

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Longest wait for an action's outcome.
ACTION_TIMEOUT = 600.0
#: After a cancelled call, how long the body is given to end the action before it is left.
CANCEL_WAIT = 10.0
MIGRATE_TIMEOUT = 60.0
DESCRIBE_TIMEOUT = 3.0


def text_result(text: str, *, error: bool, structured: dict[str, Any] | None = None) -> types.CallToolResult:
    return types.CallToolResult(content=[types.TextContent(text=text)], structured_content=structured, is_error=error)


class ToolCalls:
    """Runs the calls of ``companion``'s tools through ``client`` (on the server's loop)."""

    def __init__(self, client: MeshClient, companion: str, *, secure: bool = False) -> None:
        self.client = client
        self.companion = companion
        self.secure = secure
        self._runs: dict[str, Callable[[str, str, dict[str, Any]], None]] = {}  # action id -> its progress hook

    async def call(self, session: Any, spec: ToolSpec, arguments: tuple[str, ...], host: str | None) -> types.CallToolResult:
        """``spec`` called with ``arguments`` (already checked) while the companion lives on ``host``."""
        try:
            if spec.kind == "peers":
                return await self._peers()
            if spec.kind == "migrate":
                return await self._migrate(arguments[0])
            if host is None:
                raise NotAlive(f"{self.companion} lives nowhere to be seen now: no body to act with")
            assert spec.ability is not None
            return await self._act(session, host, spec.ability.action, arguments)
        except NotReached as exc:  # a request that reached nobody was not delivered: nothing was done
            hint = " (in secure mode the access rules refuse what this identity may not do: an operator's certificate " \
                   "may act)" if self.secure else ""
            return text_result(f"not delivered, nothing was done: {exc}{hint}", error=True,
                               structured={"status": "not_reached", "reason": str(exc)})
        except (Vanished, OutcomeUnknown) as exc:
            return text_result(f"outcome unknown: {exc}", error=True, structured={"status": "unknown", "reason": str(exc)})
        except RequestRejected as exc:
            return text_result(f"refused: {exc}", error=True, structured={"status": "refused", "reason": str(exc)})
        except MeshError as exc:
            return text_result(str(exc), error=True, structured={"status": "failed", "reason": str(exc)})

    def run_event(self, action_id: str, event: Event) -> None:
        """An event of a run of action ``action_id`` (loop): to its call's progress, if it is ours."""
        hook = self._runs.get(action_id)
        if hook is not None and belongs_to(action_id, event.data):
            hook(event.name, event.component, dict(event.data))

    async def _thread(self, fn: Callable[..., T], *args: Any) -> T:
        return await anyio.to_thread.run_sync(partial(fn, *args))

    async def _peers(self) -> types.CallToolResult:
        described = await self._thread(partial(self.client.describe_all, timeout=DESCRIBE_TIMEOUT))
        peers = [{"name": d.get("name"), "inhabitant": d.get("inhabitant"), "actions": d.get("actions", []),
                  **({"error": d["error"]} if d.get("error") else {})} for d in described]
        return text_result(json.dumps(peers), error=False, structured={"peers": peers})

    async def _migrate(self, target: str) -> types.CallToolResult:
        # A handshake, once started, cannot be called back (the companion must end up in exactly one
        # place): a cancelled call leaves it to finish, in its worker thread.
        result = await self._thread(partial(self.client.migrate, self.companion, target, timeout=MIGRATE_TIMEOUT))
        text = f"{self.companion} migrated from {result.get('source')} to {target}; the tools are now {target}'s"
        plain = {k: v for k, v in result.items() if isinstance(v, str | int)}
        return text_result(text, error=False, structured={"status": "succeeded", **plain})

    async def _act(self, session: Any, host: str, action: str, arguments: tuple[str, ...]) -> types.CallToolResult:
        action_id = f"mcp-{uuid.uuid4().hex[:12]}"
        loop = asyncio.get_running_loop()
        ended = asyncio.Event()
        progress: asyncio.Queue[str] = asyncio.Queue()
        started: list[ActionRun] = []

        def on_end() -> None:  # a transport worker: the loop sets it
            loop.call_soon_threadsafe(ended.set)

        def start() -> None:  # a worker thread; the run is kept even if the call is cancelled meanwhile
            started.append(self.client.start_action(host, action, arguments, action_id=action_id,
                                                    join_timeout=DESCRIBE_TIMEOUT, on_end=on_end))

        def hook(name: str, component: str, data: dict[str, Any]) -> None:
            message = progress_message(name, component, data)
            if message is not None:
                progress.put_nowait(message)

        self._runs[action_id] = hook
        try:
            try:
                await self._thread(start)
                await self._follow(session, ended, progress)
            except anyio.get_cancelled_exc_class():
                if started:  # the action is on its way: the body is told, and given a moment to end it
                    with anyio.CancelScope(shield=True):
                        await self._cancel(host, action_id, ended)
                raise
            run = started[0]
            # The end heard (the common case): no request, so no worker thread; else the manager is asked.
            report = run.report if run.report is not None else await self._thread(run.result, ACTION_TIMEOUT)
        finally:
            self._runs.pop(action_id, None)
            for run in started:
                run.close()
        return self._outcome(host, report)

    async def _follow(self, session: Any, ended: asyncio.Event, progress: asyncio.Queue[str]) -> None:
        """Until the action ends (or ``ACTION_TIMEOUT``): each progress line to the client."""
        steps = 0
        with anyio.move_on_after(ACTION_TIMEOUT):
            while not ended.is_set():
                waiter = asyncio.ensure_future(progress.get())
                ending = asyncio.ensure_future(ended.wait())
                try:
                    await asyncio.wait({waiter, ending}, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    waiter.cancel()
                    ending.cancel()
                if waiter.done() and not waiter.cancelled():
                    steps += 1
                    await session.report_progress(steps, None, waiter.result())  # a no-op without a progress token

    async def _cancel(self, host: str, action_id: str, ended: asyncio.Event) -> None:
        try:
            await self._thread(self.client.cancel, host, action_id)
        except MeshError as exc:
            log.warning("cancelling %s on %s: %s", action_id, host, exc)
            return
        with anyio.move_on_after(CANCEL_WAIT):
            await ended.wait()

    def _outcome(self, host: str, report: ActionReport) -> types.CallToolResult:
        data = msgspec.to_builtins(report)
        data["embodiment"] = host
        action = " ".join([report.name, *report.parameters])
        if report.status == "succeeded":
            return text_result(f"{action} succeeded on {host}", error=False, structured=data)
        reason = f": {report.reason}" if report.reason else ""
        return text_result(f"{action} {report.status} on {host}{reason}", error=True, structured=data)


__all__ = ["ToolCalls", "text_result"]
