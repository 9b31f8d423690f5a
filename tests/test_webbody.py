"""The body in the browser, in a real browser: the screen and phone pages of the demo's mesh.

Three daemons in processes of their own (robot, screen and phone, the last two serving their
pages), headless Chromium on the pages. What a person would see: an empty, waiting screen; the
companion arriving on it; its question spoken (text and a real WAV) with yes/no buttons; a click
on "yes" answering the gesture competency, after which the mind's plan goes on (the greeting, then
the phone). Screenshots of each moment are written to tests/screenshots/.
"""

from __future__ import annotations

import http.client
import json
import signal
import socket
import subprocess
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect
from websockets.typing import Origin

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.testing.wait import migrate_once_seen, wait_for
from cmion_mesh.tools.demo import Scenario, start_bodies, stop_bodies, web_address
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport
from cmion_mesh.web import speech
from cmion_mesh.web.face import ARRIVAL_SHOWN
from tests.helpers.browser import screenshot

WAIT = 60.0
WAIT_MS = int(WAIT * 1000)


@pytest.fixture
def bodies(mesh: str, tmp_path: Path) -> Iterator[Scenario]:
    web = ("--web", "127.0.0.1:0")
    scenario = start_bodies(mesh, tmp_path, per_body={"screen": web, "phone": web})
    try:
        yield scenario
    finally:
        stop_bodies(scenario)


@pytest.fixture
def client(bodies: Scenario) -> Iterator[MeshClient]:
    with ZenohTransport(TransportConfig(connect=tuple(bodies.endpoints.values()), multicast=False)) as transport:
        yield MeshClient(transport, bodies.mesh)


def wm(client: MeshClient, embodiment: str, entity: str, prop: str) -> Any:
    try:
        return client.get_property(embodiment, keys.WORLD_MODEL, entity, prop).value
    except MeshError:
        return None


def test_the_screen_shows_the_companion_arriving_and_yes_answers_its_question(chromium_browser: Any, bodies: Scenario,
                                                                              client: MeshClient) -> None:
    if speech.engine() is None:
        pytest.skip("no speech engine for the speaking body: install espeak-ng (apt-get install espeak-ng; .ci/run does it when it can)")
    screen_url, phone_url = web_address(bodies.daemons["screen"]), web_address(bodies.daemons["phone"])
    wide = chromium_browser.new_context(viewport={"width": 1280, "height": 800})
    narrow = chromium_browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True, has_touch=True)
    try:
        screen, phone = wide.new_page(), narrow.new_page()
        screen.goto(screen_url)
        phone.goto(phone_url)
        # An empty body, waiting: no companion lives on the screen yet.
        screen.wait_for_selector('body[data-connected="true"][data-embodiment="screen"][data-companion=""]', timeout=WAIT_MS)
        assert screen.is_visible("#empty") and not screen.is_visible("#face")
        screenshot(screen, "screen-empty")

        wait_for(lambda: {d.get("name"): d.get("inhabitant") for d in client.describe_all(timeout=1.0)}
                 == {"robot": "spirit", "screen": None, "phone": None}, WAIT, "the three embodiments, spirit on the robot")
        client.set_property("robot", keys.BLACKBOARD, "sim", "command", "greet Guest")

        # The companion migrates in: its face appears.
        screen.wait_for_selector('body[data-companion="spirit"]', timeout=WAIT_MS)
        assert screen.is_visible("#face") and not screen.is_visible("#empty")
        screenshot(screen, "screen-arrived")

        # The visitor says they are here: the web UserDetection writes what the simulated one writes.
        screen.click("#visitor")
        wait_for(lambda: wm(client, "screen", "Guest", "present") is True, WAIT, "Guest.present on the screen")

        # The question is spoken (text and sound), then the yes/no buttons wait for the answer.
        screen.wait_for_selector("#question:not([hidden])", timeout=WAIT_MS)
        assert "are you the guest I am expecting" in (screen.text_content("#speech") or "")
        assert screen.get_attribute("body", "data-face") == "listening"
        audio = screen.evaluate("document.getElementById('voice').src")
        assert audio.startswith(screen_url + "/speech/")
        wav = wide.request.get(audio).body()
        seconds = speech.duration(wav)
        assert wav[:4] == b"RIFF" and wav[8:12] == b"WAVE" and len(wav) > 10_000
        spoken = screen.text_content("#speech") or ""
        words = len(spoken.split())
        assert words / 6.0 < seconds < words / 1.0, f"{seconds:.2f} s of sound for {words} words"
        screenshot(screen, "screen-asking")

        screen.click("#yes")
        # The gesture competency took the answer, and the mind's plan goes on: the greeting.
        wait_for(lambda: wm(client, "screen", "Guest", "answer") == "yes", WAIT, "Guest.answer = yes on the screen")
        screen.wait_for_function("document.getElementById('speech').textContent.includes('welcome to the building')",
                                 timeout=WAIT_MS)
        assert screen.is_hidden("#question")
        screenshot(screen, "screen-greeting")

        # Then on to the phone (the narrow page), and the screen is empty again.
        phone.wait_for_selector('body[data-companion="spirit"]', timeout=WAIT_MS)
        phone.wait_for_function("document.getElementById('speech').textContent.includes('on your phone')", timeout=WAIT_MS)
        screenshot(phone, "phone-accompanying")
        screen.wait_for_selector('body[data-companion=""]', timeout=WAIT_MS)
        assert "went to phone" in (screen.text_content("#transition") or "")
        screenshot(screen, "screen-left")
    finally:
        wide.close()
        narrow.close()


#: Installed before the page's script: every text the arrival caption ever shows, in order.
CAPTIONS = """
window.captions = [];
document.addEventListener("DOMContentLoaded", () => {
  const caption = document.getElementById("transition");
  new MutationObserver(() => { if (caption.textContent) window.captions.push(caption.textContent); })
    .observe(caption, { childList: true, characterData: true, subtree: true });
});
"""


def test_the_arrival_is_shown_once_when_it_happens_and_a_page_opened_later_shows_the_companion_at_rest(
        chromium_browser: Any, bodies: Scenario, client: MeshClient) -> None:
    screen_url = web_address(bodies.daemons["screen"])
    context = chromium_browser.new_context(viewport={"width": 1280, "height": 800})
    try:
        context.add_init_script(CAPTIONS)
        watching = context.new_page()
        watching.goto(screen_url)
        watching.wait_for_selector('body[data-connected="true"][data-companion=""]', timeout=WAIT_MS)
        migrate_once_seen(client, "spirit", "screen")
        watching.wait_for_selector('body[data-companion="spirit"]', timeout=WAIT_MS)
        watching.wait_for_function("document.getElementById('transition').textContent === 'spirit arrives from robot'",
                                   timeout=WAIT_MS)
        screenshot(watching, "screen-arriving")
        # The state changes while the arrival is news (the mind wakes, says something...); then the
        # caption goes, and it does not come back with the states that follow.
        client.set_property("screen", keys.BLACKBOARD, "", "probe", 1)
        watching.wait_for_function("document.getElementById('transition').textContent === '' "
                                   "&& document.body.dataset.transition === ''", timeout=int((ARRIVAL_SHOWN + 10) * 1000))
        state = json.loads(context.request.get(screen_url + "/state").text())
        assert state["companion"] == "spirit" and state["transition"] is None, state["transition"]

        # A line said stays readable once spoken, until the next.
        report = client.act("screen", "Greet", ["Guest"], timeout=30)
        assert report.status == "succeeded", report
        watching.wait_for_function("document.getElementById('speech').textContent.includes('welcome to the building') "
                                   "&& document.getElementById('speech').dataset.speaking === 'false'", timeout=WAIT_MS)

        later = context.new_page()
        later.goto(screen_url)
        later.wait_for_selector('body[data-connected="true"][data-companion="spirit"]', timeout=WAIT_MS)
        assert "welcome to the building" in (later.text_content("#speech") or "")
        # A gesture reads as what it is: the hand, and the words for those who do not see it.
        with client.start_action("screen", "Express", ["wave"]) as waving:
            later.wait_for_function("document.getElementById('gesture').textContent === 'spirit waves' "
                                    "&& document.body.dataset.expression === 'wave'", timeout=WAIT_MS)
            assert later.is_visible("#face") and later.is_visible("#hand")
            screenshot(later, "screen-opened-later-waving")
            later.wait_for_function("document.getElementById('gesture').textContent === ''", timeout=WAIT_MS)
            assert waving.action_id
        assert later.evaluate("window.captions") == [] and later.get_attribute("body", "data-transition") == ""
        assert watching.evaluate("window.captions") == ["spirit arrives from robot"], watching.evaluate("window.captions")
        screenshot(later, "screen-opened-later")
    finally:
        context.close()


def test_a_page_input_the_body_does_not_sense_is_refused_with_a_reason(chromium_browser: Any, mesh: str, tmp_path: Path) -> None:
    """The phone has no gesture, visitor or command competency: what a page sends anyway is refused, saying why."""
    phone = Daemon(cli_argv("up", "phone", "--mesh", mesh, "--no-multicast", "--listen", f"tcp/127.0.0.1:{free_port()}",
                            "--state-dir", str(tmp_path / "phone"), "--web", ":0"), name="phone")
    context = chromium_browser.new_context()
    try:
        url = web_address(phone)
        assert url.startswith("http://127.0.0.1:")  # loopback when the address names no host
        page = context.new_page()
        page.goto(url)
        page.wait_for_selector('body[data-connected="true"][data-embodiment="phone"]', timeout=WAIT_MS)
        assert page.is_hidden("#command-form") and page.is_hidden("#visitor-form")
        page.evaluate("socket.send(JSON.stringify({type: 'command', text: 'greet Guest'}))")
        page.wait_for_function("document.getElementById('notice').textContent.includes('does not sense commands')",
                               timeout=WAIT_MS)
        page.evaluate("socket.send('not json')")
        page.wait_for_function("document.getElementById('notice').textContent.includes('expected a JSON object')",
                               timeout=WAIT_MS)
        state = json.loads(context.request.get(url + "/state").text())
        assert state["embodiment"] == "phone" and state["companion"] is None and state["senses"] == []
    finally:
        context.close()
        phone.stop()


def test_only_the_bodys_own_pages_may_open_its_socket_or_read_its_state(mesh: str, tmp_path: Path) -> None:
    """Another site open in the same browser (its ``Origin``), or one whose name was made to resolve
    to 127.0.0.1 (DNS rebinding: its ``Host``), may neither drive the body's senses nor hear it."""
    screen = Daemon(cli_argv("up", "screen", "--mesh", mesh, "--no-multicast", "--listen", f"tcp/127.0.0.1:{free_port()}",
                             "--state-dir", str(tmp_path / "screen"), "--web", "127.0.0.1:0"), name="screen")
    try:
        url = web_address(screen)
        screen.wait_line("up in mesh", WAIT)
        port = int(url.rsplit(":", 1)[1].split("/")[0])
        ws_url = f"ws://127.0.0.1:{port}/ws"
        mallory = json.dumps({"type": "visitor", "name": "Mallory", "present": True})

        with pytest.raises(InvalidStatus) as refused, connect(ws_url, origin=Origin("http://evil.example"),
                                                              open_timeout=WAIT) as ws:
            ws.send(mallory)  # what a foreign page would do with a socket it was given
        assert refused.value.response.status_code == 403
        # DNS rebinding: evil.example made to resolve to 127.0.0.1, its page "same origin" with itself.
        with socket.create_connection(("127.0.0.1", port)) as rebound, pytest.raises(InvalidStatus) as refused, \
                connect(f"ws://evil.example:{port}/ws", sock=rebound, origin=Origin(f"http://evil.example:{port}"),
                        open_timeout=WAIT) as ws:
            ws.send(mallory)
        assert refused.value.response.status_code == 403
        for host in (f"evil.example:{port}", "evil.example"):
            asked = http.client.HTTPConnection("127.0.0.1", port, timeout=WAIT)
            try:
                asked.request("GET", "/state", headers={"Host": host})
                assert asked.getresponse().status == 403, f"/state answered to Host {host}"
            finally:
                asked.close()

        for name in ("127.0.0.1", "localhost"):  # the body's own page, by either loopback name
            with socket.create_connection(("127.0.0.1", port)) as own, \
                    connect(f"ws://{name}:{port}/ws", sock=own, origin=Origin(f"http://{name}:{port}"), open_timeout=WAIT) as ws:
                messages = [json.loads(ws.recv(timeout=WAIT)) for _ in range(2)]
                assert messages[0] == {"type": "access", "act": True}
                assert messages[1]["type"] == "state" and "Mallory" not in messages[1]["visitors"]
                ws.send(json.dumps({"type": "visitor", "name": "Guest", "present": True}))
                for _ in range(20):  # bounded: a state or two may come before the reply
                    reply = json.loads(ws.recv(timeout=WAIT))
                    if reply["type"] != "state":
                        break
                assert reply == {"type": "ok", "input": "visitor"}
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/state", timeout=WAIT) as answer:
            assert json.loads(answer.read())["visitors"] == ["Guest"]
    finally:
        screen.stop()


def test_up_refuses_a_web_address_in_use_naming_it(mesh: str, tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        done = subprocess.run(cli_argv("up", "phone", "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "p"),
                                       "--web", f"127.0.0.1:{port}"), capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2, "an address in use is a configuration error (docs/deploy.md): restarting would not help"
    assert f"cannot listen on http://127.0.0.1:{port}" in done.stderr and not (tmp_path / "p").exists()


def test_up_refuses_a_bad_web_address_as_a_usage_error(mesh: str, tmp_path: Path) -> None:
    done = subprocess.run(cli_argv("up", "phone", "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "p"),
                                   "--web", "screen:80"), capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert "bad web address 'screen:80'" in done.stderr


def test_demo_web_prints_the_pages_and_a_yes_on_the_screen_moves_the_companion_on(chromium_browser: Any) -> None:
    demo = Daemon(cli_argv("demo", "--web"), name="demo")
    context = chromium_browser.new_context()
    try:
        screen_url = demo.wait_line("] screen: http://", WAIT).split("screen: ", 1)[1].strip()
        phone_url = demo.wait_line("] phone: http://", WAIT).split("phone: ", 1)[1].strip()
        view_url = demo.wait_line("] view: http://", WAIT).split("view: ", 1)[1].strip()
        assert all(url.startswith("http://127.0.0.1:") for url in (screen_url, phone_url, view_url))
        view = context.new_page()
        view.goto(view_url)
        for body in ("robot", "screen", "phone"):
            view.wait_for_selector(f'.card[data-embodiment="{body}"][data-alive="true"]', timeout=WAIT_MS)
        page = context.new_page()
        page.goto(screen_url)
        page.wait_for_selector("#question:not([hidden])", timeout=WAIT_MS)
        demo.wait_line("answer yes or no on the screen's page", WAIT)
        page.keyboard.press("y")
        demo.wait_line("Guest answered yes", WAIT)
        demo.wait_line("journey: robot -> screen -> phone -> robot", WAIT)
        demo.wait_line("the pages stay open until Ctrl-C", WAIT)
        assert demo.proc.poll() is None
        stopped = demo.stop(signal.SIGINT, grace=60)
        assert stopped == 0, "\n".join(demo.lines[-12:])  # it stops its three daemons first
        assert demo.lines[-1].endswith("done")
    finally:
        context.close()
        demo.stop()
