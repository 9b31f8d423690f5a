"""Three hosts on one LAN (network namespaces on a bridge): daemons find each other by multicast.

No ``--connect`` anywhere: zenoh's multicast scouting (224.0.0.224:7446) on each host's LAN
interface is the only way they learn of each other. Also checks the ``Lan`` harness itself:
multicast, cut/heal, and that nothing is left behind, whatever happens.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.procs import cli_argv
from cmion_mesh.testing import netns
from cmion_mesh.testing.netns import Lan
from cmion_mesh.testing.wait import wait_for

from .test_router import assert_gone, run_probe

pytestmark = pytest.mark.timeout(120)

#: Scouting pinned to the LAN interface (every host names it eth0), rather than zenoh's "auto".
SCOUTING = '{ scouting: { multicast: { enabled: true, interface: "eth0" } } }\n'


def skip_unless_available() -> None:
    reason = netns.unavailable_reason()
    if reason is not None:
        pytest.skip(f"network namespaces unavailable: {reason}")


@pytest.fixture
def lan() -> Iterator[Lan]:
    skip_unless_available()
    topology = Lan(3)
    names = topology.namespaces()
    try:
        yield topology
    finally:
        topology.close()
        assert_gone(names)


def test_daemons_find_each_other_by_multicast(lan: Lan, mesh: str, tmp_path: Path) -> None:
    h1, h2, h3 = lan.hosts
    assert lan.multicast_reaches(h1, [h2, h3]) == {"h2", "h3"}, "the LAN does not carry multicast"
    config = tmp_path / "zenoh.json5"
    config.write_text(SCOUTING)

    a = h1.popen(cli_argv("up", "--name", "a", "--mesh", mesh, "--config", str(config)), name="a")
    b = h2.popen(cli_argv("up", "--name", "b", "--mesh", mesh, "--config", str(config)), name="b")
    a.wait_line("up in mesh", 20)
    b.wait_line("up in mesh", 20)

    # A client on the third host, which was told no address either.
    result = run_probe(h3, {"mesh": mesh, "config": str(config), "multicast": True, "expect": ["a", "b"], "me": "h3",
                            "timeout": 20.0}, 20.0)
    assert result["seen"] == ["a", "b"], result
    for name in ("a", "b"):
        store = result["stores"][name]
        assert store["write"] == "accepted", result
        assert store["bb"][f"cmion/{mesh}/{name}/bb/probe"]["value"] == {"from": "h3"}, result

    # a and b found each other too: a zenoh session runs between them, over the LAN.
    def linked() -> bool:
        # Columns: Recv-Q Send-Q Local Peer; zenoh's sockets are IPv6 ones: [::ffff:10.213.1.2]:36462.
        peers = [line.split()[3] for line in h1.run(["ss", "-tnH", "state", "established"]).stdout.splitlines()]
        return any(peer.rsplit(":", 1)[0].strip("[]").removeprefix("::ffff:") == h2.address for peer in peers)

    wait_for(linked, 10, "a TCP session between a (h1) and b (h2)")
    assert a.stop() == 0 and b.stop() == 0, "\n".join(a.lines + b.lines)
    print(f"client found a and b after {result['found_after']} s (session open after {result['opened_after']} s)")


def test_cut_and_heal(lan: Lan) -> None:
    h1, h2, h3 = lan.hosts
    lan.cut(h2)  # at the switch: h2 keeps its address and routes, its packets go nowhere
    assert lan.multicast_reaches(h1, [h2, h3]) == {"h3"}
    assert not h1.tcp_reaches(h2.address, 9, timeout=0.5)
    lan.heal(h2)
    lan.cut(h3, side="host")  # the host's own interface down: it loses its routes
    assert lan.multicast_reaches(h1, [h2, h3]) == {"h2"}
    lan.heal(h3)  # routes back, the multicast one included
    assert lan.multicast_reaches(h1, [h2, h3]) == {"h2", "h3"}
    assert h1.tcp_reaches(h3.address, 9)  # refused: reachable, nothing listens on port 9


def test_nothing_left_behind_after_errors() -> None:
    skip_unless_available()
    with pytest.raises(RuntimeError, match="boom"), Lan(2) as lan:
        names = lan.namespaces()
        # A process that would keep a namespace (and its devices) alive after `ip netns delete`.
        sleeper = lan.hosts[0].popen([sys.executable, "-c", "import time; print('ready', flush=True); time.sleep(600)"])
        sleeper.wait_line("ready")
        assert set(names) <= netns.list_namespaces()
        raise RuntimeError("boom")
    assert sleeper.proc.poll() is not None
    assert_gone(names)
    lan.close()  # idempotent
    with pytest.raises(netns.NetnsError, match="closed"):
        lan.add_host("late", lan.lan)
