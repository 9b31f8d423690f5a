"""A legitimate action's latency while a flood of 20,000 action requests hits the same daemon.

Processes (loopback): a daemon of the bench embodiment with its companion, a raw zenoh queryable
for context, and the measuring process, which runs four flooding threads on a session of their
own (``Act One`` requests back to back, each with a fresh id, 20,000 in all or until measured)
while it times, on another session, ``Act`` request -> end event for one legitimate action at a
time, and a raw zenoh get. Metrics: ``act_during_flood`` (median and p99) beside the raw get in
the same moment; and the flood's own outcome counts (accepted / busy), so a run shows that the
daemon answered every request and refused what it could not take. Memory after the flood is in
the ``idle`` and ``soak`` benchmarks' domain; here the count of answers is checked.
"""

from __future__ import annotations

import itertools
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path

from bench.actions import COMPANION, EMBODIMENT, WireAct
from bench.core import RawGet, open_session
from bench.daemons import Node, stop_and_report
from bench.harness import loopback_config, loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError, OutcomeUnknown
from cmion_mesh.messages import Act
from cmion_mesh.procs import unique_mesh
from cmion_mesh.requests import send_request
from cmion_mesh.transport.zenoh import ZenohTransport

FLOOD = 20_000
FLOODERS = 4
LABELS = {
    "raw_get_flood": "raw zenoh get, round trip, during the flood (context)",
    "act_during_flood": "Act request -> end event (One), during a 20,000-request flood",
}


def log(text: str) -> None:
    print(f"  [flood] {text}", flush=True)


class Flood:
    def __init__(self, transport: ZenohTransport, mesh: str) -> None:
        self.transport = transport
        self.key = keys.request_key(mesh, EMBODIMENT, "manager", "act")
        self.ids = itertools.count(1)
        self.counts: dict[str, int] = {}
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._run, name=f"flood-{i}") for i in range(FLOODERS)]

    def _run(self) -> None:
        for _ in range(FLOOD // FLOODERS):
            if self.stop.is_set():
                return
            try:
                outcome = send_request(self.transport, self.key, Act("One", [], "", f"flood-{next(self.ids)}"), timeout=10.0)
                kind = "accepted" if outcome.status == "accepted" else outcome.reason.split(":")[0]
            except OutcomeUnknown:
                kind = "unknown"
            with self.lock:
                self.counts[kind] = self.counts.get(kind, 0) + 1

    def __enter__(self) -> Flood:
        for thread in self.threads:
            thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(60.0)


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    mesh = unique_mesh("bench")
    raw_ep = loopback_endpoint()
    samples = max(50, options.samples // 10)
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-flood-")))
        raw_child = start_child("bench.core", "serve-raw", "--listen", raw_ep, "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw_child)
        node = Node(EMBODIMENT, mesh, tmp / EMBODIMENT, companion=COMPANION)
        node.start()
        stack.callback(stop_and_report, [node], log)
        raw_child.wait_line("ready", 30.0)
        node.wait_up(60.0)
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        transport = ZenohTransport(loopback_config(connect=node.listen))
        stack.callback(transport.close)
        flooder = ZenohTransport(loopback_config(connect=node.listen))
        stack.callback(flooder.close)
        client = MeshClient(transport, mesh)
        client.wait_for_embodiment(EMBODIMENT, timeout=20.0)
        wire = WireAct(client, "One", "act_during_flood")
        stack.callback(wire.close)
        raw = RawGet(session, mesh)
        raw.contact()
        wire.contact()
        pooled: dict[str, list[float]] = {"raw_get_flood": [], "act_during_flood": []}
        with Flood(flooder, mesh) as flood:
            deadline = time.monotonic() + 120.0
            for _ in range(20 * samples):  # for as long as the flood lasts, bounded
                if (len(pooled["act_during_flood"]) >= samples and not any(t.is_alive() for t in flood.threads)) \
                        or time.monotonic() > deadline:
                    break
                pooled["raw_get_flood"] += raw.measure(1)
                try:
                    pooled["act_during_flood"] += wire.measure(1)
                except MeshError as exc:  # refused busy: the flood holds every slot; try the next one
                    pooled.setdefault("refused", []).append(0.0)
                    log(f"legitimate action refused: {exc}")
        log(f"flood outcomes: {dict(sorted(flood.counts.items()))}; legitimate actions refused: {len(pooled.get('refused', []))}")
    rows = [Row(m, LABELS[m], summarize(pooled[m]), extra={"flood": dict(flood.counts)}) for m in LABELS]
    compare(rows, {"act_during_flood": "raw_get_flood"}, None)
    rows[1].failures = [f"{k}: {v}" for k, v in flood.counts.items() if k == "unknown"]
    return rows
