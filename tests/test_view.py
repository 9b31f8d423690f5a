"""``cmion-mesh view`` in a real browser (headless Chromium), beside daemons in processes of their own.

The view is a process (``cmion-mesh view``) joined to the daemons' loopback endpoints; this
process drives the page with Playwright and writes to the mesh with a ``MeshClient`` of its own.
Every wait is on a condition in the page, with a deadline. Screenshots go to tests/screenshots/.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.procs import Daemon
from cmion_mesh.testing.wait import migrate_once_seen
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport
from cmion_mesh.web.view import spawn_view

from .conftest import start_daemon
from .helpers.browser import screenshot
from .helpers.mesh_setups import three_daemons

pytestmark = pytest.mark.timeout(120)

#: What the issue asks of the view: a blackboard change shown within this (seconds).
SHOWN_WITHIN = 0.2
PAGE_WAIT_MS = 20_000


def start_view(mesh: str, endpoints: list[str], *extra: str) -> tuple[Daemon, str]:
    return spawn_view(mesh, endpoints, *extra, timeout=20)


@pytest.fixture
def mesh3(mesh: str, tmp_path: Path) -> Iterator[list[str]]:
    """robot (where the companion spirit is born), screen and phone, each a daemon."""
    with three_daemons(mesh, tmp_path) as endpoints:
        yield endpoints


@pytest.fixture
def client(mesh: str, mesh3: list[str]) -> Iterator[MeshClient]:
    config = TransportConfig(connect=tuple(mesh3), multicast=False, overrides=(("listen/endpoints", "[]"),))
    with ZenohTransport(config) as transport, MeshClient(transport, mesh) as c:
        yield c


def wait_page(page: Any, expression: str, what: str, arg: Any = None) -> Any:
    try:
        return page.wait_for_function(expression, arg=arg, timeout=PAGE_WAIT_MS).json_value()
    except Exception as exc:  # Playwright's TimeoutError: say what was awaited
        raise AssertionError(f"the view page never showed {what} within {PAGE_WAIT_MS} ms") from exc


def card(page: Any, name: str) -> Any:
    return page.locator(f'.card[data-embodiment="{name}"]')


def test_view_shows_daemons_blackboard_changes_and_a_migration(
    chromium_browser: Any, mesh: str, mesh3: list[str], client: MeshClient
) -> None:
    view, url = start_view(mesh, mesh3)
    with view:
        page = chromium_browser.new_page(viewport={"width": 1400, "height": 900})
        try:
            page.goto(url)
            wait_page(page, "() => ['robot', 'screen', 'phone'].every(n => document.querySelector("
                            "`.card[data-embodiment=\"${n}\"][data-alive=\"true\"]`))", "all three daemons alive")
            wait_page(page, "() => document.querySelector('.card[data-embodiment=\"robot\"][data-inhabitant=\"spirit\"]')",
                      "spirit living on robot")
            assert page.locator("#mode").inner_text() == "read-only"
            assert page.locator(".card form").count() == 0, "a read-only view offers no actions"

            # One embodiment's trees: a blackboard write shows within SHOWN_WITHIN.
            card(page, "robot").click()
            wait_page(page, "() => document.getElementById('tree-note').textContent === ''", "robot's trees read")
            latencies = []
            for value in range(3):
                written = time.time()
                client.set_property("robot", "bb", "", "probe", value)
                drawn_ms = wait_page(page, "v => { const d = cmionView.stats.treeDrawn.get('bb/probe'); "
                                           "return d && d.value === v && d.at; }", f"bb/probe = {value}", value)
                latencies.append(drawn_ms / 1000 - written)
            assert page.locator('#tree-bb li[data-path="probe"] > .value').inner_text() == "2"
            print(f"blackboard write -> drawn in the page: {[round(x * 1000, 1) for x in latencies]} ms")
            assert statistics.median(latencies) <= SHOWN_WITHIN, f"blackboard write -> drawn: {latencies}"

            # A migration as it happens, step by step.
            migrate_once_seen(client, "spirit", "screen")
            steps = wait_page(page, "() => { const m = [...cmionView.state.migrations.values()].find(m => "
                                    "m.companion === 'spirit' && m.status === 'succeeded' && m.steps.length === 6); "
                                    "return m && m.steps.map(s => `${s.step}@${s.embodiment}`); }", "the migration succeeded")
            assert steps == ["starting@robot", "prepared@robot", "incoming@screen", "handed@robot", "active@screen",
                             "released@robot"], steps
            wait_page(page, "() => document.querySelector('.card[data-embodiment=\"screen\"][data-inhabitant=\"spirit\"]')"
                            " && document.querySelector('.card[data-embodiment=\"robot\"][data-inhabitant=\"\"]')",
                      "spirit living on screen, robot empty")
            assert page.locator('.migration[data-status="succeeded"] .step').count() == 6
            wait_page(page, "() => document.querySelector('#companions li[data-companion=\"spirit\"][data-host=\"screen\"]')",
                      "the companions list saying spirit lives on screen")

            # A plan and its steps: the mind action ``Migrate robot`` runs the migration competency.
            report = client.act("screen", "Migrate", ["robot"], timeout=30)
            assert report.status == "succeeded", report
            plan = wait_page(page, "() => { const p = [...cmionView.state.plans.values()].find(p => p.embodiment === 'screen' "
                                   "&& p.state === 'succeeded'); return p && Object.values(p.steps).map(s => s.status); }",
                             "screen's plan succeeded")
            assert plan and all(status == "succeeded" for status in plan), plan
            assert page.locator('.plan[data-state="succeeded"] .step[data-status="succeeded"]').count() >= 1
            wait_page(page, "() => document.querySelector('.card[data-embodiment=\"robot\"][data-inhabitant=\"spirit\"]')",
                      "spirit back on robot")

            # The event stream and its filters.
            page.fill("#filter-component", "migration")
            names = page.locator("#events tbody tr").evaluate_all("rows => rows.map(r => r.dataset.name)")
            assert names and all(n.startswith("Migration") for n in names), names
            assert "MigrationStep" in names
            page.fill("#filter-component", "")
            screenshot(page, "view-mesh")

            # Read-only: the server refuses actions, whatever the page sends.
            page.evaluate("() => { cmionView.migrate('spirit', 'phone'); cmionView.act('screen', 'Greet', []); }")
            refused = wait_page(page, "() => { const r = [...document.querySelectorAll('.action-result[data-status=\"refused\"]')];"
                                      " return r.length === 2 && r.map(n => n.textContent); }", "both actions refused")
            assert all("read-only" in text for text in refused), refused
            assert client.find_companion("spirit") == "robot"
        finally:
            page.close()
    assert view.proc.returncode == 0, "\n".join(view.lines[-20:])


def test_view_with_actions_allowed_migrates_from_a_button(chromium_browser: Any, mesh: str, tmp_path: Path) -> None:
    with ExitStack() as stack:
        robot, first = start_daemon(mesh, "robot", "--companion", "spirit", "--state-dir", str(tmp_path / "robot"))
        stack.enter_context(robot)
        screen, second = start_daemon(mesh, "screen", "--connect", first, "--state-dir", str(tmp_path / "screen"))
        stack.enter_context(screen)
        view, url = start_view(mesh, [first, second], "--allow-actions")
        stack.enter_context(view)
        page = chromium_browser.new_page(viewport={"width": 1400, "height": 900})
        stack.callback(page.close)
        page.goto(url)
        assert wait_page(page, "() => document.getElementById('mode').textContent", "the mode") == "actions allowed"
        wait_page(page, "() => document.querySelector('.card[data-embodiment=\"robot\"][data-inhabitant=\"spirit\"]') && "
                        "document.querySelector('.card[data-embodiment=\"screen\"][data-alive=\"true\"] button.migrate')",
                  "a button to bring spirit to screen")
        # The screen may not see the robot yet (their own link comes up after the view's): ask until it does.
        for _ in range(20):
            card(page, "screen").locator("button.migrate").click()
            status = wait_page(page, "() => { const r = document.querySelector('.action-result'); "
                                     "return r && !['asked', 'sent'].includes(r.dataset.status) && r.dataset.status; }",
                               "the migration's outcome")
            if status == "succeeded" or "is not alive" not in page.locator(".action-result").first.inner_text():
                break
            page.wait_for_timeout(200)  # not a wait for the outcome: a pause before asking again
        assert status == "succeeded", page.locator(".action-result").first.inner_text()
        wait_page(page, "() => document.querySelector('.card[data-embodiment=\"screen\"][data-inhabitant=\"spirit\"]')",
                  "spirit living on screen")
        screenshot(page, "view-actions")
