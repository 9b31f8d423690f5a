"""The live view (``cmion-mesh view``): an event at a daemon -> drawn in the page, and what an idle
page costs the daemon.

One daemon (the bench embodiment), the view in a process of its own connected to it, and the
page in headless Chromium (the system's ``chromium``, or ``CMION_MESH_CHROMIUM``) driven by
Playwright. This process writes a blackboard property of the daemon, one write at a time, each
after the page has drawn the previous one's event. Each write makes the daemon raise a
``PropertyChanged`` event stamped with its wall clock (``Event.time``); the page notes when it
put that event's row in its table (``performance.timeOrigin + performance.now()``, the same
clock), and the difference is the latency. The baseline is the same events received by a plain
subscriber in this process (``MeshClient.events``: zenoh plus decoding), in the same run.

Idle cost: the daemon's CPU over a window alone, then with a plain session connected (what any
one more peer costs it), then with that session, the view connected and its page open but
nothing happening (the page never polls, nor does the view: the daemon should see no difference
from the plain session), and the view process's own CPU meanwhile.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from bench.daemons import Node, Sampler, client_config, cpu_percent, stop_and_report
from bench.harness import stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event
from cmion_mesh.procs import unique_mesh
from cmion_mesh.transport.zenoh import ZenohTransport
from cmion_mesh.web.view import spawn_view

PAGE_WAIT_MS = 20_000


def log(text: str) -> None:
    print(f"  [view] {text}", flush=True)


def chromium() -> str:
    path = os.environ.get("CMION_MESH_CHROMIUM") or "/usr/bin/chromium"
    if not os.access(path, os.X_OK):
        raise RuntimeError(f"no Chromium at {path}: `apt-get install chromium` (or set CMION_MESH_CHROMIUM)")
    return path


def cpu_rows(prefix: str, who: str, samples: list[Any]) -> Row:
    values = [cpu_percent(a, b) for a, b in itertools.pairwise(samples)]
    return Row(prefix, who, summarize(values or [0.0], 1.0), unit="%",
               extra={"window_cpu_percent": cpu_percent(samples[0], samples[-1]) if len(samples) > 1 else 0.0})


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    from playwright.sync_api import sync_playwright

    writes = 40 if options.quick else 300
    settle, window, interval = (1.0, 2.0, 0.5) if options.quick else (2.0, 5.0, 1.0)
    mesh = unique_mesh("bench")
    raw: dict[int, float] = {}  # seq -> received here - raised at the daemon (s)
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-view-")))
        node = Node("robot", mesh, tmp / "robot")
        node.start()
        stack.callback(stop_and_report, [node], log)
        node.wait_up(60.0)
        assert node.daemon is not None

        threading.Event().wait(settle)
        alone = Sampler({"daemon": node.daemon.proc.pid}, interval).start()
        threading.Event().wait(window)
        alone.stop()

        # A plain session connected to the daemon: what any one more peer costs it (keep-alives),
        # so that the view's own cost is told apart from that.
        transport = stack.enter_context(ZenohTransport(client_config(node.listen)))
        client = stack.enter_context(MeshClient(transport, mesh))
        client.join("robot")
        threading.Event().wait(settle)
        peer = Sampler({"daemon": node.daemon.proc.pid}, interval).start()
        threading.Event().wait(window)
        peer.stop()

        view, url = spawn_view(mesh, [node.listen])
        stack.callback(stop_child, view)

        playwright = stack.enter_context(sync_playwright())
        browser = playwright.chromium.launch(executable_path=chromium(), headless=True)
        stack.callback(browser.close)
        page = browser.new_page()
        page.goto(url)
        page.wait_for_function("() => document.querySelector('.card[data-embodiment=\"robot\"][data-alive=\"true\"]')",
                               timeout=PAGE_WAIT_MS)
        log(f"daemon (pid {node.daemon.proc.pid}), view (pid {view.proc.pid}) at {url}, page open; idle {window:g} s")

        threading.Event().wait(settle)
        idle = Sampler({"daemon": node.daemon.proc.pid, "view": view.proc.pid}, interval).start()
        threading.Event().wait(window)
        idle.stop()

        def on_event(event: Event) -> None:
            if event.name == "PropertyChanged":
                raw[event.seq] = time.time() - event.time

        stack.enter_context(client.events(on_event, embodiment="robot", component="bb"))
        log(f"{writes} blackboard writes, each once the page drew the previous one")
        for i in range(writes):
            client.set_property("robot", "bb", "", "bench_view", i)
            page.wait_for_function("n => cmionView.stats.drawn.filter(d => d.name === 'PropertyChanged').length >= n",
                                   arg=i + 1, timeout=PAGE_WAIT_MS)
        drawn = page.evaluate("() => cmionView.stats.drawn.filter(d => d.name === 'PropertyChanged')"
                              ".map(d => [d.seq, d.drawn / 1000 - d.time, d.received - d.time])")
    page_latency = [float(d[1]) for d in drawn]
    view_latency = [float(d[2]) for d in drawn]
    failures = [] if len(drawn) == writes else [f"the page drew {len(drawn)} of {writes} events"]
    rows = [
        Row("view_event_drawn", "event at the daemon -> drawn in the view page", summarize(page_latency),
            extra={"writes": writes}, failures=failures),
        Row("view_event_received", "event at the daemon -> received by the view process", summarize(view_latency)),
        Row("raw_event_received", "event at the daemon -> received by a plain subscriber here", summarize(list(raw.values()))),
        cpu_rows("daemon_cpu_alone", "daemon idle, no view (CPU % of one core)", alone.samples["daemon"]),
        cpu_rows("daemon_cpu_peer", "daemon idle, a plain session connected", peer.samples["daemon"]),
        cpu_rows("daemon_cpu_idle_page", "daemon idle, that session, the view and its page", idle.samples["daemon"]),
        cpu_rows("view_cpu_idle_page", "view process, page open, mesh idle", idle.samples["view"]),
    ]
    compare(rows, {"view_event_drawn": "raw_event_received", "view_event_received": "raw_event_received"}, None)
    compare(rows, {"daemon_cpu_peer": "daemon_cpu_alone", "daemon_cpu_idle_page": "daemon_cpu_peer"}, None)
    return rows
