"""``cmion-mesh hz`` and ``echo`` against a publisher at a known rate in another process."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from cmion_mesh.errors import InvalidName
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.tools.hz_echo import is_liveliness, resolve, yamlish
from tests.helpers.rate_publisher import BINARY, RAW_KEY, TEXT, TICK_KEY

pytestmark = pytest.mark.timeout(120)
RATE = 50.0


def test_keys_are_relative_to_the_mesh_unless_absolute() -> None:
    assert resolve("m", "robot/ev/**") == "cmion/m/robot/ev/**"
    assert resolve("m", "**") == "cmion/m/**"
    assert resolve("m", "cmion/other/robot/bb/**") == "cmion/other/robot/bb/**"
    assert resolve("m", "/demo/raw/*") == "demo/raw/*"
    assert is_liveliness(resolve("m", "@alive/*")) and not is_liveliness(resolve("m", "robot/**"))
    # Requests' answers are published under @outcome (a verbatim chunk), not liveliness tokens.
    assert not is_liveliness(resolve("m", "*/@outcome/**")) and is_liveliness(resolve("m", "@custody/**"))
    for bad in ("robot//ev", "", "robot/ev?x", "a b"):
        with pytest.raises(InvalidName):
            resolve("m", bad)
    assert yamlish({"name": "Tick", "data": {"i": 3, "tags": ["a", "b c"]}, "text": "x: y"}) == [
        "name: Tick", "data:", "  i: 3", "  tags: [a, b c]", 'text: "x: y"']


def test_hz_reports_the_publishers_rate_and_echo_decodes_mesh_messages_and_shows_raw_payloads(mesh: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Daemon([sys.executable, "-m", "tests.helpers.rate_publisher", mesh, endpoint, str(RATE)], name="publisher") as publisher:
        publisher.wait_line("READY", 30)
        net = ["--mesh", mesh, "--connect", endpoint, "--no-multicast"]
        # The first messages after the link comes up are left out of the window (a start-up burst).
        hz = subprocess.Popen(cli_argv("hz", TICK_KEY, "--count", "260", "--window", "200", "--json", *net),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        echoed = subprocess.run(cli_argv("echo", "**", "--count", "6", "--json", *net), capture_output=True, text=True, timeout=60)
        once = subprocess.run(cli_argv("echo", TICK_KEY, "--once", *net), capture_output=True, text=True, timeout=60)
        out, err = hz.communicate(timeout=60)
    assert hz.returncode == 0, err
    final = json.loads(out.splitlines()[-1])
    assert final["final"] is True and final["key"] == f"cmion/{mesh}/{TICK_KEY}" and final["window"] == 200
    assert abs(final["rate"] - RATE) <= 0.1 * RATE, final

    assert echoed.returncode == 0, echoed.stderr
    shown = [json.loads(line) for line in echoed.stdout.splitlines()]
    assert len(shown) == 6
    ticks = [s for s in shown if s["key"] == f"cmion/{mesh}/{TICK_KEY}"]
    raws = [s["raw"] for s in shown if s["key"] == f"cmion/{mesh}/{RAW_KEY}"]
    assert ticks and all(t["type"] == "event" and t["message"]["name"] == "Tick" for t in ticks)
    assert {"size": len(TEXT), "text": TEXT.decode()} in raws
    assert {"size": len(BINARY), "hex": BINARY.hex(" ")} in raws

    assert once.returncode == 0, once.stderr
    lines = once.stdout.splitlines()
    assert lines[0].startswith(f"--- cmion/{mesh}/{TICK_KEY}  (") and lines[0].endswith(", event)")
    assert "name: Tick" in lines and "component: test" in lines and len([ln for ln in lines if ln.startswith("---")]) == 1
