"""Remote competencies: a competency that lives in another process, over a key-space protocol.

Any zenoh client in any language can implement one. For embodiment ``E`` in mesh ``M``, a remote
competency named ``N`` of type ``T``:

1. declares the liveliness token ``cmion/M/@competency/E/T/N``: while it exists the embodiment's
   execution system counts ``N`` as an available competency of type ``T``; when it vanishes
   (process died, link lost) a run in progress fails with "vanished";
2. answers queries on ``cmion/M/E/rq/N/start`` (payload ``start_run``: ``run_id``, ``parameters``)
   and ``cmion/M/E/rq/N/cancel`` (``cancel_run``: ``run_id``) with an ``outcome`` (accepted, or
   rejected with a reason, e.g. busy);
3. may publish ``cmion/M/E/ev/N/Progress`` (an ``event`` whose data holds ``run_id``), and must end
   every accepted run by publishing ``cmion/M/E/ev/N/RunSucceeded``, ``RunFailed`` or
   ``RunCancelled`` (an ``event`` whose ``data`` is a ``run_ended`` map: ``run_id``, ``status``, ``reason``).

``RemoteCompetency`` is the proxy on the embodiment's side (created automatically from the
liveliness tokens); ``ion.serve(CompetencyHost(competency), ...)`` hosts any ``Competency``
subclass in another Python process (``cmion-mesh serve-competency``).
"""

from __future__ import annotations

import logging
import queue
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.competency import Competency, RunContext, RunResult
from cmion_mesh.errors import MeshError, OutcomeUnknown, ProtocolError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import CancelRun, Code, Event, RunEnded, RunStatus, StartRun, decode
from cmion_mesh.requests import IncomingRequest, send_request
from cmion_mesh.transport.base import Closeable, Sample

log = logging.getLogger(__name__)

#: The event that ends a run, by how it ended.
END_EVENT: dict[RunStatus, str] = {"succeeded": "RunSucceeded", "failed": "RunFailed", "cancelled": "RunCancelled"}
END_EVENTS = {event: status for status, event in END_EVENT.items()}
#: How long a cancelled run waits for the remote side to confirm before giving up on it.
CANCEL_GRACE = 10.0
_INTERRUPT = object()


class RemoteCompetency(Competency):
    """Proxy for a competency served by another process (see the module doc for the protocol)."""

    def __init__(self, name: str, competency_type: str) -> None:
        super().__init__(name=name, type=competency_type)
        self._ends: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._events: Closeable | None = None

    def start(self, sim: Simulation) -> None:
        super().start(sim)
        if self._events is None:
            pattern = keys.event_pattern(sim.mesh, sim.embodiment, self.name, "*")
            self._events = sim.transport.subscribe(pattern, self._on_event)

    def stop(self, timeout: float = 10.0) -> None:
        super().stop(timeout)
        if self._events is not None:
            self._events.close()
            self._events = None

    def _interrupt(self) -> None:
        self._ends.put(_INTERRUPT)

    def _on_event(self, sample: Sample) -> None:
        name = sample.key.rsplit("/", 1)[-1]
        if name not in END_EVENTS or sample.deleted:
            return
        try:
            event = decode(sample.payload, Event, where=sample.key)
            self._ends.put(msgspec.convert(event.data, RunEnded))
        except (ProtocolError, msgspec.ValidationError) as exc:
            log.warning("ignored malformed end of run from %s: %s", self.name, exc)

    def _key(self, request: str) -> str:
        return keys.request_key(self.sim.mesh, self.sim.embodiment, self.name, request)

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        while not self._ends.empty():  # ends of earlier runs that arrived late
            self._ends.get_nowait()
        outcome = send_request(self.sim.transport, self._key("start"), StartRun(ctx.run_id, parameters))
        if outcome.status != "accepted":
            return ctx.fail(f"{self.name} refused to start: {outcome.reason}")
        cancel_sent = False
        while True:
            if ctx.cancelled.is_set() and not cancel_sent:
                cancel_sent = True
                try:
                    send_request(self.sim.transport, self._key("cancel"), CancelRun(ctx.run_id), timeout=CANCEL_GRACE)
                except OutcomeUnknown as exc:
                    return ctx.fail(f"cancel not confirmed: {exc}")
            try:
                item = self._ends.get(timeout=CANCEL_GRACE if cancel_sent else None)
            except queue.Empty:
                return ctx.fail(f"{self.name} did not confirm the cancel within {CANCEL_GRACE:g} s")
            if item is _INTERRUPT:
                if self._stopping.is_set() and not ctx.cancelled.is_set():
                    return ctx.fail(f"remote competency {self.name!r} vanished")
                continue
            if item.run_id != ctx.run_id:
                continue
            if item.status == "succeeded":
                return True
            return ctx.fail(item.reason or f"{self.name} {item.status}")


class CompetencyHost(Component):
    """Serves one ``Competency`` on the remote-competency protocol from this process."""

    requests = {"start": StartRun, "cancel": CancelRun}

    def __init__(self, competency: Competency) -> None:
        super().__init__(competency.name)
        self.competency = competency
        self._token: Closeable | None = None

    def attach(self, sim: Simulation) -> None:
        self.competency.start(sim)
        key = keys.competency_alive_key(sim.mesh, sim.embodiment, self.competency.type, self.competency.name)
        self._token = sim.transport.declare_token(key)

    def detach(self) -> None:
        if self._token is not None:
            self._token.close()
            self._token = None
        self.competency.stop()

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        started = False
        for request in batch:
            match request.payload:
                case CancelRun(run_id=run_id):
                    self.competency.cancel(run_id)
                    request.accept()
                case StartRun() if self.competency.busy or started:
                    request.reject(f"{self.competency.name} is busy", Code.BUSY)
                case StartRun(run_id=run_id, parameters=parameters):
                    started = True
                    self.competency.execute(run_id, dict(parameters), self._ended)
                    request.accept()

    def _ended(self, result: RunResult) -> None:
        # On the competency's thread; raise_event hands the event to the loop.
        try:
            self.sim.raise_event(self.name, END_EVENT[result.status],
                                 msgspec.to_builtins(RunEnded(result.run_id, result.status, result.reason)))
        except MeshError:
            pass  # closing
