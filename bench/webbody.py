"""The body in the browser: migration -> the companion's face shown on the target's page, and what
an open, idle page costs the daemon serving it.

Two daemons: the shipped robot (the companion ``spirit`` is born there) and the shipped screen
serving its page (``--web 127.0.0.1:0``), both on loopback. Headless Chromium (the system's, as
the tests use it; ``$CMION_MESH_CHROMIUM`` names another) opens the screen's page; a
``MutationObserver`` in the page stamps the moment its body's ``data-companion`` changes
(``performance.timeOrigin + performance.now()``, the machine's wall clock in ms, as
``time.time()`` in the measuring process).

Each round: ``MeshClient.migrate(spirit, screen)`` is called at t0; the rows time t0 -> the
``MigrationOccurred`` event of the screen received by the measuring process (the companion awake
at the target, the baseline) and t0 -> the face shown on the page (ratio against the baseline:
what the page adds). Then the companion goes back to the robot and t0 -> the empty body shown is
timed the same way. 20 rounds (quick 5).

Idle: with the page still open and nothing happening, the screen daemon's CPU (``/proc``, every
second for 5 s; quick every half second for 2 s) beside the idle robot daemon's, which serves no
page; and the number of WebSocket messages the page received in that window, which must be 0 (a
failure otherwise: something polls or pushes while nothing happens).
"""

from __future__ import annotations

import itertools
import os
import queue
import shutil
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path

from bench.daemons import Node, Sampler, client_config, cpu_percent, stop_and_report
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event
from cmion_mesh.procs import unique_mesh
from cmion_mesh.transport.zenoh import ZenohTransport

COMPANION = "spirit"
WATCH = """() => {
  window.benchMessages = 0;
  window.benchChanges = [];
  new MutationObserver(() => {
    window.benchChanges.push([document.body.dataset.companion || "", performance.timeOrigin + performance.now()]);
  }).observe(document.body, { attributes: true, attributeFilter: ["data-companion"] });
  socket.addEventListener("message", () => { window.benchMessages += 1; });
}"""


def log(text: str) -> None:
    print(f"  [webbody] {text}", flush=True)


def chromium() -> str:
    configured = os.environ.get("CMION_MESH_CHROMIUM")
    found = configured or shutil.which("chromium") or shutil.which("chromium-browser")
    if not found:
        raise RuntimeError("the webbody benchmark needs Chromium: apt-get install chromium (or name it in $CMION_MESH_CHROMIUM)")
    return found


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    from playwright.sync_api import sync_playwright

    rounds = 5 if options.quick else 20
    settle, window, interval = (1.0, 2.0, 0.5) if options.quick else (2.0, 5.0, 1.0)
    mesh = unique_mesh("bench")
    samples: dict[str, list[float]] = {"occurred": [], "face": [], "empty": []}
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-web-")))
        robot = Node("robot", mesh, tmp / "robot", architecture="robot")
        screen = Node("screen", mesh, tmp / "screen", architecture="screen", extra_args=("--web", "127.0.0.1:0"))
        robot.connect, screen.connect = (screen.listen,), (robot.listen,)
        nodes = [robot, screen]
        for node in nodes:
            node.start()
        stack.callback(stop_and_report, nodes, log)
        for node in nodes:
            node.wait_up(60.0)
        assert screen.daemon is not None
        url = screen.daemon.wait_line("web body of", 10.0).split(" at ", 1)[1].split()[0]
        transport = stack.enter_context(ZenohTransport(client_config(robot.listen, screen.listen)))
        client = MeshClient(transport, mesh)
        client.join("robot", timeout=30.0)
        client.join("screen", timeout=30.0)
        occurred: queue.SimpleQueue[float] = queue.SimpleQueue()

        def on_event(event: Event) -> None:
            if event.name == "MigrationOccurred":
                occurred.put(time.time())

        stack.enter_context(client.events(on_event, embodiment="screen", component="migration"))
        playwright = stack.enter_context(sync_playwright())
        browser = playwright.chromium.launch(executable_path=chromium(), headless=True)
        stack.callback(browser.close)
        page = browser.new_page()
        page.goto(url)
        page.wait_for_selector('body[data-connected="true"][data-companion=""]', timeout=30_000)
        page.evaluate(WATCH)
        log(f"robot and screen up; the screen's page {url} open in headless Chromium; {rounds} rounds")

        def shown(companion: str, since: float) -> float:
            page.wait_for_function(f"window.benchChanges.some(c => c[0] === {companion!r} && c[1] >= {since * 1000!r})",
                                   timeout=30_000)
            stamps = page.evaluate(f"window.benchChanges.filter(c => c[0] === {companion!r}).map(c => c[1])")
            return float(max(stamps)) / 1000.0 - since

        for _ in range(rounds):
            t0 = time.time()
            client.migrate(COMPANION, "screen")
            samples["face"].append(shown(COMPANION, t0))
            samples["occurred"].append(occurred.get(timeout=30.0) - t0)
            t0 = time.time()
            client.migrate(COMPANION, "robot")
            samples["empty"].append(shown("", t0))

        threading.Event().wait(settle)
        before = int(page.evaluate("window.benchMessages"))
        sampler = Sampler({"screen": screen.pid, "robot": robot.pid}, interval).start()
        threading.Event().wait(window)
        sampler.stop()
        pushed = int(page.evaluate("window.benchMessages")) - before

    def cpu(name: str) -> list[float]:
        return [cpu_percent(a, b) for a, b in itertools.pairwise(sampler.samples[name])]

    rows = [
        Row("web_occurred", "migration command -> companion awake at the target (event heard)", summarize(samples["occurred"])),
        Row("web_face", "migration command -> face shown on the target's page", summarize(samples["face"])),
        Row("web_empty", "migration away -> empty body shown on the source's page", summarize(samples["empty"])),
        Row("web_idle_cpu", "screen daemon, its page open, idle: CPU (% of one core)", summarize(cpu("screen"), 1.0), unit="%",
            extra={"messages_pushed": pushed, "window_s": window},
            failures=[f"{pushed} messages pushed to an idle page"] if pushed else []),
        Row("web_idle_cpu_robot", "robot daemon, no page, idle: CPU (% of one core)", summarize(cpu("robot"), 1.0), unit="%"),
    ]
    compare(rows, {"web_face": "web_occurred", "web_idle_cpu": "web_idle_cpu_robot"}, None)
    return rows
