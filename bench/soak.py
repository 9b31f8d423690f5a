"""The soak: ``python -m bench soak --seconds N`` (also ``--only soak --soak-seconds N``).

Three daemons ``cmion-mesh up`` of the bench embodiment (``soak-a``, where the companion ``soak``
is born, ``soak-b``, ``soak-c``; all on loopback, each with its records in a temporary
``--state-dir``) and, in the measuring process, for ``N`` seconds (default 20):

* a migrator moving the companion round robin (a -> b -> c -> a...), one ``MeshClient.migrate``
  after another with a short pause, its mind carrying a 10 KiB blob and the list of embodiments
  it arrived on;
* an actor sending mind actions (``One`` and ``Multi`` in turn) to each daemon in turn;
* a writer setting blackboard properties ``w00``..``w31`` of each daemon in turn to increasing
  numbers;
* a listener subscribed to every event of the mesh, checking each daemon's sequence numbers;
* a census asking every daemon for its inhabitant every quarter second (the daemons answer one
  after the other, so a handover between two answers can show the companion twice: a double is
  re-checked at once and counts as a duplicate only if it persists);
* a sampler reading each daemon's resident memory and threads from ``/proc``.

Then, traffic stopped, the checks (any failure makes ``python -m bench`` exit 1): every action
succeeded and every migration too; for every daemon and property the final value is the last
accepted write (no write lost); no event missing or out of order in any daemon's sequence; the
census never confirmed two inhabitants and at the end exactly one daemon holds the companion,
whose mind remembers exactly the arrivals the migrator caused; resident memory did not grow by
more than max(4 MiB, 5 %) between the first samples after the warm-up (a fifth of the run, at
least 2 s) and the last ones, and threads not by more than 2 (the rows give the slope, MiB per
minute). Growth is judged only when at least 10 s remain after the warm-up: a shorter soak (the
smoke test's 5 s) reports it without judging it.
"""

from __future__ import annotations

import itertools
import tempfile
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median
from typing import Any

from bench.daemons import Node, ProcSample, Sampler, client_config, stop_all
from bench.registry import Options, Row
from bench.stats import summarize
from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Event, MindMessage, MindState, Property, SetProperty
from cmion_mesh.procs import unique_mesh
from cmion_mesh.testing.wait import migrate_once_seen, wait_for
from cmion_mesh.transport.zenoh import ZenohTransport

COMPANION = "soak"
NAMES = ("soak-a", "soak-b", "soak-c")
KEYS = 32
BLOB = 10 * 1024
#: Growth is judged only over at least this many seconds after the warm-up (shorter: reported only).
MIN_JUDGED_WINDOW = 10.0
#: Resident memory may grow by at most max(this many MiB, this share of the start) after the warm-up.
RSS_GROWTH_MIB = 4.0
RSS_GROWTH_SHARE = 0.05


def log(text: str) -> None:
    print(f"  [soak] {text}", flush=True)


@dataclass
class Sequences:
    """Per-embodiment event sequence numbers as the listener saw them."""

    last: dict[str, int] = field(default_factory=dict)
    received: int = 0
    missing: int = 0
    out_of_order: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_event(self, event: Event) -> None:
        with self.lock:
            self.received += 1
            last = self.last.get(event.embodiment)
            if last is not None:
                if event.seq > last + 1:
                    self.missing += event.seq - last - 1
                elif event.seq <= last:
                    self.out_of_order += 1
                    return
            self.last[event.embodiment] = event.seq


@dataclass
class Traffic:
    stop: threading.Event = field(default_factory=threading.Event)
    errors: list[str] = field(default_factory=list)
    act_times: list[float] = field(default_factory=list)
    act_failed: int = 0
    write_times: list[float] = field(default_factory=list)
    write_refused: int = 0
    accepted: dict[tuple[str, str], int] = field(default_factory=dict)
    migrate_times: list[float] = field(default_factory=list)
    migrate_failed: int = 0
    arrivals: list[str] = field(default_factory=lambda: [NAMES[0]])
    census: list[int] = field(default_factory=list)
    doubles_transient: int = 0  # two seen, one again on an immediate re-check (a handover in progress)
    doubles_confirmed: list[str] = field(default_factory=list)

    def loop(self, name: str, step: Callable[[], None], pause: float = 0.0) -> None:
        """Run ``step`` until stopped; an exception is recorded (the check fails) and the loop goes on."""
        while not self.stop.is_set():
            try:
                step()
            except Exception as exc:
                if len(self.errors) < 50:
                    self.errors.append(f"{name}: {type(exc).__name__}: {exc}")
                self.stop.wait(0.1)
            if pause:
                self.stop.wait(pause)


def slope_mib_per_min(samples: list[ProcSample]) -> float:
    if len(samples) < 2:
        return 0.0
    xs = [s.at for s in samples]
    ys = [s.rss_mb for s in samples]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    den = sum((x - mx) ** 2 for x in xs)
    return 60.0 * sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / den if den else 0.0


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    seconds = options.soak_seconds
    warmup = max(2.0, seconds / 5)
    mesh = unique_mesh("soak")
    traffic = Traffic()
    sequences = Sequences()
    rows: list[Row] = []
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-soak-")))
        nodes: dict[str, Node] = {}
        for i, name in enumerate(NAMES):
            nodes[name] = Node(name, mesh, tmp / name, connect=tuple(n.listen for n in list(nodes.values())[:i]),
                               companion=COMPANION if i == 0 else None)
        for node in nodes.values():
            node.start()
        stop_problems: list[str] = []
        stack.callback(lambda: stop_problems.extend(stop_all(nodes.values())))
        for node in nodes.values():
            node.wait_up(60.0)
        transport = ZenohTransport(client_config(*(n.listen for n in nodes.values())))
        stack.callback(transport.close)
        client = MeshClient(transport, mesh)
        for name in NAMES:
            client.wait_for_embodiment(name, timeout=20.0)
        wait_for(lambda: client.describe(NAMES[0], timeout=2.0).get("inhabitant") == COMPANION, 20.0, "the companion born")
        for target in NAMES[1:] + NAMES[:1]:  # one round before the traffic: each host has seen its next target alive
            migrate_once_seen(client, COMPANION, target)
            traffic.arrivals.append(target)  # an arrival the mind remembers like any other
        outcome = client.request(NAMES[0], "mind", "message", MindMessage({"size": BLOB}), timeout=10.0)
        if outcome.status != "accepted":
            raise MeshError(f"the companion's mind refused its blob: {outcome.reason}")
        stack.enter_context(client.events(sequences.on_event))

        targets = itertools.cycle(NAMES[1:] + NAMES[:1])
        daemons = itertools.cycle(NAMES)
        actions = itertools.cycle(("One", "Multi"))
        writes = itertools.count(1)

        def migrate() -> None:
            target = next(targets)
            t0 = time.perf_counter()
            try:
                client.migrate(COMPANION, target, timeout=30.0)
            except MeshError:
                traffic.migrate_failed += 1
                raise
            traffic.migrate_times.append(time.perf_counter() - t0)
            traffic.arrivals.append(target)

        def act() -> None:
            t0 = time.perf_counter()
            report = client.act(next(daemons), next(actions), timeout=30.0)
            traffic.act_times.append(time.perf_counter() - t0)
            if report.status != "succeeded":
                traffic.act_failed += 1
                raise MeshError(f"action {report.name} {report.status}: {report.reason}")

        def write() -> None:
            seq = next(writes)
            embodiment, name = NAMES[seq % len(NAMES)], f"w{seq % KEYS:02d}"
            t0 = time.perf_counter()
            result = client.write(embodiment, keys.BLACKBOARD, SetProperty("", name, seq), timeout=10.0)
            traffic.write_times.append(time.perf_counter() - t0)
            if result.status == "accepted":
                traffic.accepted[(embodiment, name)] = seq
            else:
                traffic.write_refused += 1
                raise MeshError(f"write {embodiment}/{name}: {result.status}: {result.reason}")

        def census() -> None:
            homes = [d["name"] for d in client.describe_all(timeout=2.0) if d.get("inhabitant") == COMPANION]
            traffic.census.append(len(homes))
            if len(homes) > 1:
                # The daemons answer one after the other, not at one instant: a handover between two
                # answers shows the companion twice. Only a double that persists is a duplicate.
                traffic.stop.wait(0.05)
                again = [name for name in homes if client.describe(name, timeout=2.0).get("inhabitant") == COMPANION]
                if len(again) > 1:
                    traffic.doubles_confirmed.append(", ".join(again))
                else:
                    traffic.doubles_transient += 1

        sampler = Sampler({name: node.pid for name, node in nodes.items()}, max(0.25, seconds / 40)).start()
        stack.callback(sampler.stop)
        threads = [threading.Thread(target=traffic.loop, args=(name, fn, pause), name=f"soak-{name}", daemon=True)
                   for name, fn, pause in (("migrator", migrate, 0.3), ("actor", act, 0.0), ("writer", write, 0.0),
                                           ("census", census, 0.25))]
        started = time.monotonic()
        for thread in threads:
            thread.start()
        log(f"three daemons, traffic for {seconds:g} s (warm-up {warmup:g} s)")
        traffic.stop.wait(seconds)
        traffic.stop.set()
        for thread in threads:
            thread.join(60.0)
        elapsed = time.monotonic() - started
        sampler.stop()
        threading.Event().wait(0.5)  # the last events in flight

        # --- checks -----------------------------------------------------------------------------
        lost_writes = []
        for name in NAMES:
            entries = client.read_store(name, keys.BLACKBOARD, timeout=10.0)
            for (embodiment, prop), seq in traffic.accepted.items():
                if embodiment != name:
                    continue
                entry = entries.get(keys.storage_key(mesh, name, keys.BLACKBOARD, (), prop))
                value = entry.value if isinstance(entry, Property) else None
                if value != seq:
                    lost_writes.append(f"{name}/{prop}: {value!r}, last accepted {seq}")
        homes = [d["name"] for d in client.describe_all(timeout=5.0) if d.get("inhabitant") == COMPANION]
        arrivals: Any = None
        if len(homes) == 1:
            state = client.request(homes[0], "mind", "state", MindState(), timeout=10.0).value
            arrivals = state.get("arrivals") if isinstance(state, dict) else None
        log(f"{elapsed:.1f} s: {len(traffic.migrate_times)} migrations, {len(traffic.act_times)} actions, "
            f"{len(traffic.write_times)} writes, {sequences.received} events")

    def row(metric: str, label: str, samples: list[float], failures: list[str], unit: str = "ms", scale: float = 1000.0,
            extra: dict[str, Any] | None = None) -> Row:
        return Row(metric, label, summarize(samples or [0.0], scale), unit=unit, failures=failures, extra=extra or {})

    rows.append(row("soak_migrations", "migrate (round robin over 3 daemons)", traffic.migrate_times,
                    [f"{traffic.migrate_failed} migrations failed"] if traffic.migrate_failed else []))
    rows.append(row("soak_actions", "MeshClient.act One/Multi (3 daemons in turn)", traffic.act_times,
                    [f"{traffic.act_failed} actions did not succeed"] if traffic.act_failed else []))
    write_failures = [f"{len(lost_writes)} writes lost: {lost_writes[:3]}"] if lost_writes else []
    if traffic.write_refused:
        write_failures.append(f"{traffic.write_refused} writes refused")
    rows.append(row("soak_writes", "blackboard set_property (accepted, checked at the end)", traffic.write_times, write_failures,
                    extra={"accepted": len(traffic.write_times) - traffic.write_refused, "keys": len(traffic.accepted)}))
    event_failures = []
    if sequences.missing:
        event_failures.append(f"{sequences.missing} events missing")
    if sequences.out_of_order:
        event_failures.append(f"{sequences.out_of_order} events repeated or out of order")
    rows.append(row("soak_events", "events received by the listener (sequence-checked)", [float(sequences.received)], event_failures,
                    unit="events", scale=1.0, extra={"per_embodiment_last_seq": dict(sequences.last)}))
    census_failures = []
    if traffic.doubles_confirmed:
        census_failures.append(f"two inhabitants, confirmed on a re-check: {traffic.doubles_confirmed[:3]}")
    if len(homes) != 1:
        census_failures.append(f"at the end the companion lives on {homes or 'no embodiment'}")
    elif arrivals != traffic.arrivals:
        census_failures.append(f"its mind remembers arrivals {arrivals}, the migrator caused {traffic.arrivals}")
    rows.append(row("soak_inhabitants", "embodiments hosting the companion (census)", [float(c) for c in traffic.census],
                    census_failures, unit="companions", scale=1.0,
                    extra={"final_home": homes, "arrivals": len(traffic.arrivals), "doubles_transient": traffic.doubles_transient,
                           "zero_seen": sum(1 for c in traffic.census if c == 0)}))
    for name in NAMES:
        samples = [s for s in sampler.samples[name] if s.at >= sampler.samples[name][0].at + warmup]
        if len(samples) < 2:
            samples = sampler.samples[name]
        head, tail = samples[:3], samples[-3:]
        rss0, rss1 = median(s.rss_mb for s in head), median(s.rss_mb for s in tail)
        th0, th1 = min(s.threads for s in head), min(s.threads for s in tail)
        slope = slope_mib_per_min(samples)
        failures = []
        window = samples[-1].at - samples[0].at
        judged = window >= MIN_JUDGED_WINDOW
        if judged and rss1 - rss0 > max(RSS_GROWTH_MIB, RSS_GROWTH_SHARE * rss0):
            failures.append(f"memory grew {rss0:.1f} -> {rss1:.1f} MiB in {window:.0f} s ({slope:+.1f} MiB/min)")
        if judged and th1 > th0 + 2:
            failures.append(f"threads grew {th0} -> {th1}")
        rows.append(row(f"soak_rss_{name}", f"{name}: resident memory after warm-up", [s.rss_mb for s in samples], failures,
                        unit="MiB", scale=1.0, extra={"start_mib": rss0, "end_mib": rss1, "slope_mib_per_min": slope,
                                                      "threads_start": th0, "threads_end": th1, "window_s": window,
                                                      "growth_judged": judged}))
        rows.append(row(f"soak_threads_{name}", f"{name}: threads after warm-up (slope {slope:+.2f} MiB/min)",
                        [float(s.threads) for s in samples], [], unit="threads", scale=1.0))
    if traffic.errors:
        rows[0].failures.append(f"{len(traffic.errors)} traffic errors, first: {traffic.errors[0]}")
    if stop_problems:
        rows[0].failures.append("daemons did not stop cleanly: " + "; ".join(stop_problems))
    return rows
