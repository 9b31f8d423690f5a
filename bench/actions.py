"""Mind action -> succeeded: a one-step and a four-step plan, timed in the daemon and from outside.

Processes (all on loopback): a daemon ``cmion-mesh up`` of the bench embodiment
(``bench/embodiment``: rules ``One`` -> one ``Instant`` step, ``Multi`` -> steps 1 and 2 in
parallel, then 3, then 4; competencies that succeed at once) with the companion living there, so
its minds are awake; ``python -m bench.core serve-raw`` (a raw zenoh queryable); the measuring
process, connected to both.

Metrics:

* ``act_one_daemon`` / ``act_multi_daemon``: inside the daemon, the mind ``bench.minds:TimingMind``
  sends the action back to back (each from the handler of the previous one's end) and times
  ``Mind.act()`` -> ``on_action_succeeded`` with ``time.perf_counter``; the samples come back in
  its ``Measured`` event. This is the issue's target: under 2 ms for a one-step plan on one
  embodiment.
* ``act_one_client`` / ``act_multi_client``: ``MeshClient.act`` from the measuring process
  (another process): it joins, sends the ``Act`` request and waits for the end event, which the
  client's ``watch_actions`` subscription (opened by the first call, kept) hands to it.
* ``act_one_wire``: the same protocol with one long-lived subscription (what a remote mind or a
  long-running tool pays): the ``Act`` request, then the ``ActionSucceeded`` event.
* ``raw_get``: a raw zenoh get round trip between the same two kinds of process, for context
  (the ratios are given against it, with no target: an action is more than one round trip).
"""

from __future__ import annotations

import itertools
import queue
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import msgspec

from bench.core import RawGet, open_session
from bench.daemons import Node, stop_and_report
from bench.harness import Probe, interleaved, loopback_config, loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh import keys
from cmion_mesh.action_runs import ACTION_END_EVENTS
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Act, ActionReport, Event, MindMessage
from cmion_mesh.procs import unique_mesh
from cmion_mesh.requests import send_request
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.zenoh import ZenohTransport

EMBODIMENT = "bench-act"
COMPANION = "bench"

LABELS = {
    "raw_get": "raw zenoh get, round trip (context)",
    "act_one_daemon": "action One (1 step) -> succeeded, mind in the daemon",
    "act_multi_daemon": "action Multi (4 steps) -> succeeded, mind in the daemon",
    "act_one_client": "MeshClient.act One -> succeeded, other process",
    "act_multi_client": "MeshClient.act Multi -> succeeded, other process",
    "act_one_wire": "Act request -> end event (kept subscription) One, other process",
}
CONTEXT = {m: "raw_get" for m in LABELS if m != "raw_get"}


def log(text: str) -> None:
    print(f"  [actions] {text}", flush=True)


class DaemonMind:
    """Asks the daemon's ``TimingMind`` for ``count`` back-to-back actions; its samples are the metric."""

    def __init__(self, client: MeshClient, action: str, metric: str) -> None:
        self.client = client
        self.action = action
        self.metric = metric
        self.tags = itertools.count(1)
        self.measured: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()
        self.subscription = client.events(self._on_event, embodiment=EMBODIMENT, component="timer", event="Measured")

    def _on_event(self, event: Event) -> None:
        if isinstance(event.data, dict):
            self.measured.put(event.data)

    def close(self) -> None:
        self.subscription.close()

    def _run(self, count: int, timeout: float) -> list[float]:
        tag = f"{self.metric}-{next(self.tags)}"
        outcome = self.client.request(EMBODIMENT, "timer", "message", MindMessage({"action": self.action, "count": count, "tag": tag}))
        if outcome.status != "accepted":
            raise MeshError(f"timer mind refused: {outcome.reason}")
        deadline = time.monotonic() + timeout
        while True:
            data = self.measured.get(timeout=max(0.01, deadline - time.monotonic()))
            if data.get("tag") != tag:
                continue  # a late answer of an earlier contact attempt
            if "error" in data:
                raise MeshError(str(data["error"]))
            return [float(x) for x in data["samples"]]

    def contact(self) -> None:
        def answered() -> bool:
            try:
                return bool(self._run(1, 2.0))
            except (MeshError, queue.Empty):
                return False

        wait_for(answered, 20.0, f"{self.metric}: the daemon's timer mind answering")

    def measure(self, count: int) -> list[float]:
        return self._run(count, 30.0 + 0.05 * count)


class _TimedOnce:
    """An action sent from this process, timed round trip by round trip (subclasses define ``once``)."""

    def once(self) -> None:
        raise NotImplementedError

    def contact(self) -> None:
        self.once()

    def measure(self, count: int) -> list[float]:
        out = []
        for _ in range(count):
            t0 = time.perf_counter()
            self.once()
            out.append(time.perf_counter() - t0)
        return out


class ClientAct(_TimedOnce):
    def __init__(self, client: MeshClient, action: str, metric: str) -> None:
        self.client = client
        self.action = action
        self.metric = metric

    def once(self) -> None:
        report = self.client.act(EMBODIMENT, self.action, timeout=10.0)
        if report.status != "succeeded":
            raise MeshError(f"{self.action}: {report.status}: {report.reason}")



class WireAct(_TimedOnce):
    """The act protocol with one subscription kept for the whole run."""

    def __init__(self, client: MeshClient, action: str, metric: str) -> None:
        self.client = client
        self.action = action
        self.metric = metric
        self.ids = itertools.count(1)
        self.ended: queue.SimpleQueue[ActionReport] = queue.SimpleQueue()
        self.key = keys.request_key(client.mesh, EMBODIMENT, "manager", "act")
        self.subscription = client.events(self._on_event, embodiment=EMBODIMENT, component="manager")

    def _on_event(self, event: Event) -> None:
        if event.name in ACTION_END_EVENTS and isinstance(event.data, dict):
            self.ended.put(msgspec.convert(event.data, ActionReport))

    def close(self) -> None:
        self.subscription.close()

    def once(self) -> None:
        action_id = f"wire-{next(self.ids)}"
        outcome = send_request(self.client.transport, self.key, Act(self.action, [], "", action_id))
        if outcome.status != "accepted":
            raise MeshError(f"act refused: {outcome.reason}")
        while True:
            report = self.ended.get(timeout=10.0)
            if report.action_id == action_id:
                if report.status != "succeeded":
                    raise MeshError(f"{self.action}: {report.status}: {report.reason}")
                return



def run(options: Options, groups: frozenset[str]) -> list[Row]:
    mesh = unique_mesh("bench")
    raw_ep = loopback_endpoint()
    started = time.monotonic()
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-actions-")))
        raw_child = start_child("bench.core", "serve-raw", "--listen", raw_ep, "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw_child)
        node = Node(EMBODIMENT, mesh, tmp / EMBODIMENT, companion=COMPANION)
        node.start()
        stack.callback(stop_and_report, [node], log)
        raw_child.wait_line("ready", 30.0)
        node.wait_up(60.0)
        log(f"daemon and raw peer up after {time.monotonic() - started:.2f} s (mesh {mesh})")

        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        transport = ZenohTransport(loopback_config(connect=node.listen))
        stack.callback(transport.close)
        client = MeshClient(transport, mesh)
        client.wait_for_embodiment(EMBODIMENT, timeout=20.0)

        one, multi = DaemonMind(client, "One", "act_one_daemon"), DaemonMind(client, "Multi", "act_multi_daemon")
        wire = WireAct(client, "One", "act_one_wire")
        for closeable in (one, multi, wire):
            stack.callback(closeable.close)
        probes: list[Probe] = [RawGet(session, mesh), one, multi, ClientAct(client, "One", "act_one_client"),
                  ClientAct(client, "Multi", "act_multi_client"), wire]
        pooled = interleaved(probes, samples=options.samples, warmup=options.warmup, rounds=options.rounds,
                             rewarm=options.rewarm, log=log)
        log(f"measured in {time.monotonic() - started:.1f} s")
    rows = [Row(m, LABELS[m], summarize(pooled[m]), extra={"rounds": options.rounds}) for m in LABELS]
    compare(rows, CONTEXT, None)  # targets: bench.targets
    return rows
