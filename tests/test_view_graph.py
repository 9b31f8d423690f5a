"""The view's picture of the mesh, its timeline and a recording played through it, in headless Chromium.

Daemons and the view are processes of their own (``cmion-mesh up``, ``cmion-mesh view``); what
the page shows is read from its DOM (the graph's ``data-*`` attributes), every wait a condition
with a deadline. Screenshots go to tests/screenshots/ for a person to look at.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.testing.wait import migrate_once_seen
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport
from cmion_mesh.web.view import spawn_view

from .helpers.browser import screenshot
from .helpers.mesh_setups import record_demo, three_daemons

pytestmark = pytest.mark.timeout(180)

PAGE_WAIT_MS = 20_000
#: A quiet interval, on the page's own clock: long enough for anything pending to have come.
QUIET_MS = 1500


def wait_page(page: Any, expression: str, what: str, arg: Any = None) -> Any:
    try:
        return page.wait_for_function(expression, arg=arg, timeout=PAGE_WAIT_MS).json_value()
    except Exception as exc:  # Playwright's TimeoutError: say what was awaited
        raise AssertionError(f"the view page never showed {what} within {PAGE_WAIT_MS} ms") from exc


def token(page: Any, companion: str) -> dict[str, str]:
    attrs: dict[str, str] = page.evaluate(
        "c => { const t = document.querySelector(`#graph .token[data-companion=\"${c}\"]`); "
        "return t ? Object.fromEntries(Object.entries(t.dataset)) : null; }", companion)
    return attrs


def node(page: Any, name: str) -> dict[str, str]:
    attrs: dict[str, str] = page.evaluate(
        "n => { const g = document.querySelector(`#graph .node[data-embodiment=\"${n}\"]`); "
        "return g ? Object.fromEntries(Object.entries(g.dataset)) : null; }", name)
    return attrs


def resting_on(page: Any, companion: str, host: str, what: str) -> None:
    try:
        wait_for_resting(page, companion, host, what)
    except AssertionError as exc:
        seen = page.evaluate("() => [...document.querySelectorAll('#graph .token, #graph .node')].map(n => Object.assign({}, n.dataset))")
        raise AssertionError(f"{exc}; the graph shows {seen}") from None


def wait_for_resting(page: Any, companion: str, host: str, what: str) -> None:
    wait_page(page, "([c, h]) => { const t = document.querySelector(`#graph .token[data-companion=\"${c}\"]`); "
                    "const n = document.querySelector(`#graph .node[data-embodiment=\"${h}\"]`); "
                    "return t && n && t.dataset.state === 'resting' && t.dataset.at === h "
                    "&& t.dataset.x === n.dataset.x && t.dataset.y === n.dataset.y; }", what, [companion, host])


@pytest.fixture
def mesh3(mesh: str, tmp_path: Path) -> Iterator[list[str]]:
    """robot (where the companion spirit is born), screen and phone, each a daemon."""
    with three_daemons(mesh, tmp_path) as endpoints:
        yield endpoints


def test_the_graph_shows_the_mesh_the_companion_travels_and_scrubbing_back_shows_it_as_it_was(
        chromium_browser: Any, mesh: str, mesh3: list[str]) -> None:
    config = TransportConfig(connect=tuple(mesh3), multicast=False, overrides=(("listen/endpoints", "[]"),))
    view, url = spawn_view(mesh, mesh3, timeout=20)
    with view, ZenohTransport(config) as transport, MeshClient(transport, mesh) as client:
        page = chromium_browser.new_page(viewport={"width": 1400, "height": 1000})
        try:
            page.goto(url)
            # Three nodes alive, each seeing the two others (the links), spirit resting on the robot.
            wait_page(page, "() => ['robot', 'screen', 'phone'].every(n => document.querySelector("
                            "`#graph .node[data-embodiment=\"${n}\"][data-alive=\"true\"]`))", "three nodes alive")
            wait_page(page, "() => document.querySelectorAll('#graph .link[data-mutual=\"true\"]').length === 3",
                      "three links, each embodiment seeing the others")
            resting_on(page, "spirit", "robot", "spirit resting on the robot")
            assert node(page, "robot")["inhabitant"] == "spirit" and node(page, "robot")["custody"] == "spirit:1"
            assert node(page, "screen")["inhabitant"] == ""

            # The migration takes ~100 ms; the token travels its edge for a person to see, the steps on the way.
            migrate_once_seen(client, "spirit", "screen")
            during = wait_page(page, "() => { const t = document.querySelector('#graph .token[data-companion=\"spirit\"]'); "
                                     "return t && t.dataset.state === 'travelling' && Number(t.dataset.progress) > 0.3 "
                                     "&& Number(t.dataset.progress) < 0.9 && Object.assign({}, t.dataset); }",
                               "spirit travelling from robot to screen")
            assert (during["from"], during["to"]) == ("robot", "screen")
            robot, screen = node(page, "robot"), node(page, "screen")
            # On the edge: between the two nodes, at the fraction it reached.
            p = float(during["progress"])
            for axis in ("x", "y"):
                expected = float(robot[axis]) + (float(screen[axis]) - float(robot[axis])) * p
                assert abs(float(during[axis]) - expected) < 1.0, (axis, during, robot, screen)
            marks = page.locator("#graph .step-mark").evaluate_all("m => m.map(g => g.dataset.step)")
            assert marks and marks[0] == "starting", marks
            screenshot(page, "view-graph-travelling")
            resting_on(page, "spirit", "screen", "spirit resting on the screen after the migration")
            assert page.evaluate("cmionView.stats.travels.map(t => [t.from, t.to])") == [["robot", "screen"]]
            assert page.locator("#graph .step-mark").count() == 0
            screenshot(page, "view-graph-after")

            # Scrubbing back: before the migration, spirit is on the robot; during it, on the edge.
            begun = page.evaluate("() => { const m = [...cmionView.state.migrations.values()][0]; "
                                  "return [m.steps[0].received, m.steps[m.steps.length - 1].received]; }")
            page.evaluate("t => cmionView.pick(t)", begun[0] - 0.001)
            resting_on(page, "spirit", "robot", "spirit on the robot, scrubbed back to before the migration")
            assert node(page, "robot")["inhabitant"] == "spirit" and node(page, "screen")["inhabitant"] == ""
            assert page.locator("#graph-when").inner_text().startswith("as it was at")
            screenshot(page, "view-graph-scrubbed")
            if begun[1] > begun[0]:  # a moment inside the handshake: on the edge
                page.evaluate("t => cmionView.pick(t)", (begun[0] + begun[1]) / 2)
                inside = token(page, "spirit")
                assert inside["state"] == "travelling" and (inside["from"], inside["to"]) == ("robot", "screen"), inside
            page.click("#live")
            resting_on(page, "spirit", "screen", "spirit on the screen again, live")

            # Events for people, the JSON one click away.
            line = wait_page(page, "() => { const r = document.querySelector('#events tr[data-name=\"MigrationStarting\"]'); "
                                   "return r && r.querySelector('td.line').textContent; }", "the migration's start as a line")
            assert line == "robot: spirit leaves for screen"
            report = client.act("screen", "Migrate", ["robot"], timeout=30)
            assert report.status == "succeeded", report
            done = wait_page(page, "() => { const r = [...document.querySelectorAll('#events tr[data-name=\"ActionSucceeded\"]')]"
                                   ".find(r => r.dataset.embodiment === 'screen'); return r && r.querySelector('td.line').textContent; }",
                             "the action's end as a line")
            assert done.startswith("screen: Migrate robot succeeded in ") and done.endswith("(built-in rule)"), done
            row = page.locator('#events tr[data-name="ActionSucceeded"]').first
            row.locator("summary").click()
            assert '"name": "ActionSucceeded"' in row.locator("pre").inner_text()
            page.fill("#filter-component", "migration")
            names = page.locator("#events tbody tr").evaluate_all("rows => rows.map(r => r.dataset.name)")
            assert names and all(n.startswith("Migration") for n in names), names
            page.fill("#filter-component", "")
            resting_on(page, "spirit", "robot", "spirit back on the robot")
            wait_page(page, "() => !cmionView.graph.travels.size", "every travel over")

            # Nothing happens: nothing is sent. A quiet interval on the page's clock, then the count.
            wait_page(page, "() => document.querySelectorAll('#graph .link[data-mutual=\"true\"]').length === 3", "links settled")
            before = page.evaluate("cmionView.stats.messages")
            start = page.evaluate("performance.now()")
            wait_page(page, "t => performance.now() > t", "a quiet interval", start + QUIET_MS)
            assert page.evaluate("cmionView.stats.messages") == before, "the view sent messages while nothing happened"
            screenshot(page, "view-graph-events")
        finally:
            page.close()


#: The graph's drawing, checked for overlap: node discs against each other, labels against each
#: other and against discs (labels may be turned along their radius: their corners are turned too).
OVERLAPS = """
n => {
  const cards = new Map();
  for (let i = 0; i < n; i++) {
    const name = `embodiment-${String(i + 1).padStart(2, "0")}`;
    cards.set(name, {name, alive: true, description: {inhabitant: i === 0 ? "spirit" : null, alive: []}});
  }
  cmionView.state.embodiments = cards;
  cmionView.drawGraph();
  const discs = [...document.querySelectorAll("#graph .node .disc")]
    .map(c => ["cx", "cy", "r"].map(a => +c.getAttribute(a)));
  const quads = [...document.querySelectorAll("#graph .node .name")].map(t => {
    const b = t.getBBox(), m = t.getCTM(), svg = t.ownerSVGElement.getCTM().inverse();
    const k = svg.multiply(m);
    return [[b.x, b.y], [b.x + b.width, b.y], [b.x + b.width, b.y + b.height], [b.x, b.y + b.height]]
      .map(([x, y]) => [k.a * x + k.c * y + k.e, k.b * x + k.d * y + k.f]);
  });
  const bad = [];
  for (let i = 0; i < discs.length; i++) for (let j = i + 1; j < discs.length; j++) {
    const [x1, y1, r1] = discs[i], [x2, y2, r2] = discs[j];
    if (Math.hypot(x1 - x2, y1 - y2) < r1 + r2) bad.push(`discs ${i} ${j}`);
  }
  const project = (q, ax) => { const v = q.map(([x, y]) => x * ax[0] + y * ax[1]); return [Math.min(...v), Math.max(...v)]; };
  const axes = q => [0, 1].map(i => { const [a, b] = [q[i], q[i + 1]]; return [b[1] - a[1], a[0] - b[0]]; });
  const apart = (p, q) => [...axes(p), ...axes(q)].some(ax => {
    const [a, b] = project(p, ax), [c, d] = project(q, ax);
    return b <= c || d <= a;
  });
  const reach = (q, [x, y, r]) => {  // the disc meets the quad: its centre inside, or an edge nearer than r
    const edges = q.map((a, k) => [a, q[(k + 1) % 4]]);
    const near = edges.some(([[ax, ay], [bx, by]]) => {
      const t = Math.max(0, Math.min(1, ((x - ax) * (bx - ax) + (y - ay) * (by - ay)) / ((bx - ax) ** 2 + (by - ay) ** 2 || 1)));
      return Math.hypot(ax + t * (bx - ax) - x, ay + t * (by - ay) - y) < r;
    });
    const sides = edges.map(([[ax, ay], [bx, by]]) => Math.sign((bx - ax) * (y - ay) - (by - ay) * (x - ax)));
    return near || sides.every(s => s >= 0) || sides.every(s => s <= 0);
  };
  for (let i = 0; i < quads.length; i++) {
    for (let j = i + 1; j < quads.length; j++) if (!apart(quads[i], quads[j])) bad.push(`labels ${i} ${j}`);
    for (let j = 0; j < discs.length; j++) if (reach(quads[i], discs[j])) bad.push(`label ${i} disc ${j}`);
  }
  const [, , width, height] = document.getElementById("graph").getAttribute("viewBox").split(" ").map(Number);
  const inside = [...discs.map(([x, y, r]) => [x - r, y - r, x + r, y + r]), ...quads.flat().map(([x, y]) => [x, y, x, y])]
    .every(([a, b, c, d]) => a >= 0 && b >= 0 && c <= width && d <= height);
  return {nodes: discs.length, bad, inside};
}
"""


def test_one_to_thirty_two_embodiments_are_drawn_without_overlap(chromium_browser: Any, mesh: str) -> None:
    view, url = spawn_view(mesh, [], timeout=20)
    with view:
        page = chromium_browser.new_page(viewport={"width": 1400, "height": 1000})
        try:
            page.goto(url)
            wait_page(page, "() => document.getElementById('connection').dataset.state === 'open'", "the page connected")
            for n in (1, 2, 3, 5, 8, 12, 16, 24, 32):
                drawn = page.evaluate(OVERLAPS, n)
                assert drawn == {"nodes": n, "bad": [], "inside": True}, (n, drawn)
            screenshot(page, "view-graph-32")
        finally:
            page.close()


@pytest.fixture(scope="module")
def demo_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_demo(tmp_path_factory.mktemp("view") / "demo.mcap")


def test_a_recording_of_the_demo_plays_through_the_view_its_three_migrations_in_order(
        chromium_browser: Any, demo_recording: Path) -> None:
    view, url = spawn_view("unused", [], "--recording", str(demo_recording), timeout=20)
    with view:
        page = chromium_browser.new_page(viewport={"width": 1400, "height": 1000})
        try:
            page.goto(url)
            travels = wait_page(page, "() => cmionView.stats.travels.length === 3 && cmionView.stats.travels.map(t => [t.from, t.to])",
                                "three travels")
            assert travels == [["robot", "screen"], ["screen", "phone"], ["phone", "robot"]], travels
            resting_on(page, "spirit", "robot", "spirit back on the robot at the recording's end")
            wait_page(page, "() => document.getElementById('playback').dataset.playing === 'false'", "the recording played to its end")
            assert page.locator("#timeline .mark.migration").count() == 3
            assert page.locator("#timeline .mark.person").count() >= 1, "Guest arriving at the entrance"
            screenshot(page, "view-recording-played")

            # Seek back to just before the second migration: the mesh as it was then, spirit on the screen.
            second = page.evaluate("() => [...cmionView.state.migrations.values()].find(m => m.source === 'screen')"
                                   ".steps[0].received")
            page.evaluate("t => cmionView.pick(t)", second - 0.001)
            wait_page(page, "t => Math.abs(Number(document.getElementById('playback').dataset.position) - t) < 0.0005",
                      "the player at the moment picked", second - 0.001)
            resting_on(page, "spirit", "screen", "spirit on the screen before its second migration")
            assert page.evaluate("cmionView.state.migrations.size") == 1
            # Speed and play: on to the end again, the two migrations left travelled in order.
            page.select_option("#speed", "2")
            wait_page(page, "() => cmionView.graph.playback.speed === 2", "speed 2")
            page.click("#play")
            travels = wait_page(page, "() => cmionView.stats.travels.length === 5 "
                                      "&& cmionView.stats.travels.slice(3).map(t => [t.from, t.to])",
                                "the two migrations after the moment picked")
            assert travels == [["screen", "phone"], ["phone", "robot"]], travels
            resting_on(page, "spirit", "robot", "spirit back on the robot")
        finally:
            page.close()
    assert view.proc.returncode == 0, "\n".join(view.lines[-20:])
