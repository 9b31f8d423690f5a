"""Two subnets that share no multicast and no IP route, joined only by ``cmion-mesh router``.

    l1 (daemon a) --- lan1 --- [router namespace] --- lan2 --- r1 (client)

The router namespace has an address on both subnets but forwards nothing, so the zenoh router
process is the only way across. The test process lives in the caller's namespace, so the client
is a small script (``PROBE``) run inside r1 that prints one JSON line of results.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest

from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.testing import netns
from cmion_mesh.testing.netns import Host, RoutedSubnets

from .conftest import CMION_2011

pytestmark = pytest.mark.timeout(120)

ROUTER_PORT = 7447

#: A mesh client in a process of its own: waits (bounded) until the expected embodiments'
#: liveliness tokens are visible, then writes a property to each one's blackboard and reads
#: both stores back. argv[1] is a JSON spec; the result is one JSON line on stdout.
PROBE = """
import json, sys, threading, time
import msgspec
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import SetProperty
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

spec = json.loads(sys.argv[1])
start = time.monotonic()
out = {"seen": [], "found_after": None, "stores": {}}
config = TransportConfig(mode=spec.get("mode", "peer"), connect=tuple(spec.get("connect", ())), config_file=spec.get("config"),
                         multicast=spec.get("multicast", False))
with ZenohTransport(config) as transport:
    out["opened_after"] = round(time.monotonic() - start, 3)
    client = MeshClient(transport, spec["mesh"])
    want = set(spec["expect"])
    deadline = start + spec["timeout"]
    while True:
        out["seen"] = client.embodiments(timeout=0.5)
        if want <= set(out["seen"]):
            out["found_after"] = round(time.monotonic() - start, 3)
            break
        if time.monotonic() >= deadline:
            break
        threading.Event().wait(0.05)
    if out["found_after"] is not None:
        for name in sorted(want):
            outcome = client.write(name, "bb", SetProperty("", "probe", {"from": spec["me"]}))
            out["stores"][name] = {
                "write": outcome.status,
                "bb": {k: msgspec.to_builtins(v) for k, v in client.read_store(name, "bb").items()},
                "wm": sorted(client.read_store(name, "wm")),
            }
    else:  # nobody seen: do the stores answer anyway? (they must not: the control of the control)
        out["stores"] = {name: {"bb": sorted(client.read_store(name, "bb", timeout=1.0))} for name in sorted(want)}
    out["elapsed"] = round(time.monotonic() - start, 3)
print(json.dumps(out), flush=True)
"""


def run_probe(host: Host, spec: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Run ``PROBE`` in ``host``; its JSON result (the process must end on its own in time)."""
    result = host.run([sys.executable, "-c", PROBE, json.dumps(spec)], timeout=timeout + 20, check=False)
    assert result.returncode == 0, f"probe in {host.name} failed:\n{result.stdout}\n{result.stderr}"
    out: dict[str, Any] = json.loads(result.stdout.strip().splitlines()[-1])
    return out


def assert_gone(namespaces: list[str]) -> None:
    left = set(namespaces) & netns.list_namespaces()
    assert not left, f"namespaces left behind: {sorted(left)}"


@pytest.fixture
def net() -> Iterator[RoutedSubnets]:
    reason = netns.unavailable_reason()
    if reason is not None:
        pytest.skip(f"network namespaces unavailable: {reason}")
    topology = RoutedSubnets()
    names = topology.namespaces()
    try:
        yield topology
    finally:
        topology.close()  # idempotent: the test may have closed it already to check
        assert_gone(names)


def test_router_joins_two_subnets(net: RoutedSubnets, mesh: str) -> None:
    l1, r1 = net.left[0], net.right[0]
    router_lan1, router_lan2 = net.router.on(net.lan1).address, net.router.on(net.lan2).address
    timings: dict[str, float] = {}

    # The ground: multicast works on each LAN but does not cross, and there is no IP path across.
    assert net.multicast_reaches(l1, [net.router, r1]) == {"router"}
    assert not l1.tcp_reaches(r1.address, ROUTER_PORT)
    assert not r1.tcp_reaches(l1.address, ROUTER_PORT)
    assert not l1.tcp_reaches(router_lan2, ROUTER_PORT)  # the router's far side is not routed to
    assert net.router.run(["sysctl", "-n", "net.ipv4.ip_forward"]).stdout.strip() == "0"

    # Daemon a: points at the router (not running yet: zenoh retries in the background) and also
    # scouts by multicast, which must not find anything beyond lan1.
    start = time.monotonic()
    a = l1.popen(cli_argv("up", "--name", "a", "--mesh", mesh, "--connect", f"tcp/{router_lan1}:{ROUTER_PORT}",
                          "--world-model", str(CMION_2011 / "worldModelInit.xml")), name="a")
    a.wait_line("up in mesh", 20)
    timings["daemon up"] = time.monotonic() - start

    # Negative control: no router process, the same client (multicast on too) sees nothing.
    spec = {"mesh": mesh, "connect": [f"tcp/{router_lan2}:{ROUTER_PORT}"], "multicast": True, "expect": ["a"],
            "me": "r1", "timeout": 3.0}
    alone = run_probe(r1, spec, 3.0)
    assert alone["seen"] == [] and alone["found_after"] is None, alone
    assert alone["stores"] == {"a": {"bb": []}}, alone
    timings["negative control"] = alone["elapsed"]

    # With the router process, the same client reaches a: liveliness, blackboard read and write.
    start = time.monotonic()
    router = net.router.popen([sys.executable, "-m", "cmion_mesh.cli.main", "router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}",
                               "--no-multicast"], name="router")
    ready = router.wait_line("router up, listening on tcp/0.0.0.0:7447", 20)
    assert "LANs: eth0, eth1" in ready, ready  # the namespace's two interfaces, one LAN each
    timings["router up"] = time.monotonic() - start
    through = run_probe(r1, {**spec, "timeout": 20.0}, 20.0)
    timings["client found a"] = through["found_after"]
    assert through["seen"] == ["a"], through
    store = through["stores"]["a"]
    assert store["write"] == "accepted", through
    assert store["bb"][f"cmion/{mesh}/a/bb/probe"] == {"type": "property", "value": {"from": "r1"}, "persistent": False}
    assert f"cmion/{mesh}/a/wm/UserA/speaksEnglish" in store["wm"], through

    # The router is the only path: stopping it cuts r1 off again, and it stops cleanly.
    assert router.stop() == 0, "\n".join(router.lines)
    assert "router stopped" in router.lines
    after = run_probe(r1, {**spec, "timeout": 2.0}, 2.0)
    assert after["seen"] == [], after

    assert a.proc.poll() is None, "daemon a died:\n" + "\n".join(a.lines)
    assert a.stop() == 0, "\n".join(a.lines)
    names = net.namespaces()
    net.close()
    assert_gone(names)
    print("timings (s):", {k: round(v, 2) for k, v in timings.items()})


def test_router_cli_errors_are_one_line(tmp_path: Any) -> None:
    """A bad config file: one clear line on stderr and exit 2, a configuration error (no namespaces needed)."""
    missing = tmp_path / "nope.json5"
    daemon = Daemon([sys.executable, "-m", "cmion_mesh.cli.main", "router", "--config", str(missing), "--listen", "tcp/127.0.0.1:0",
                     "--no-multicast"], name="router")
    with daemon:
        assert daemon.proc.wait(30) == 2
    daemon.stop()
    assert any("error:" in line and "nope.json5" in line for line in daemon.lines), daemon.lines
    assert not any("Traceback" in line for line in daemon.lines), daemon.lines


def test_chained_routers(net: RoutedSubnets, mesh: str) -> None:
    """One router per subnet, the second ``--connect``-ing to the first: peers still meet."""
    l1, r1 = net.left[0], net.right[0]
    router_lan1, router_lan2 = net.router.on(net.lan1).address, net.router.on(net.lan2).address
    # Both routers run in the router namespace, each listening on one side only and each with
    # that side as its one LAN; the link between them is a router-to-router one.
    first = net.router.popen([sys.executable, "-m", "cmion_mesh.cli.main", "router", "--listen", f"tcp/{router_lan1}:{ROUTER_PORT}",
                              "--lan", "eth0", "--no-multicast"], name="router1")
    second = net.router.popen([sys.executable, "-m", "cmion_mesh.cli.main", "router", "--listen", f"tcp/{router_lan2}:{ROUTER_PORT}",
                               "--lan", "eth1", "--connect", f"tcp/{router_lan1}:{ROUTER_PORT}", "--no-multicast"], name="router2")
    first.wait_line("router up", 20)
    assert f"connecting to tcp/{router_lan1}:{ROUTER_PORT}" in second.wait_line("router up", 20)
    a = l1.popen(cli_argv("up", "--name", "a", "--mesh", mesh, "--connect", f"tcp/{router_lan1}:{ROUTER_PORT}"), name="a")
    a.wait_line("up in mesh", 20)
    result = run_probe(r1, {"mesh": mesh, "connect": [f"tcp/{router_lan2}:{ROUTER_PORT}"], "expect": ["a"], "me": "r1",
                            "timeout": 20.0}, 20.0)
    assert result["seen"] == ["a"] and result["stores"]["a"]["write"] == "accepted", result
    assert second.stop() == 0 and first.stop() == 0 and a.stop() == 0
