"""The daemon as a systemd service: sd_notify over a real unix datagram socket, the watchdog fed by
the update loop (and starved by a stuck one), and the unit file (checked by systemd-analyze where
systemd is installed)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.claim import claim_name
from cmion_mesh.errors import ConfigError, InvalidName, Refused
from cmion_mesh.ops import systemd
from cmion_mesh.ops.heartbeat import Heartbeat
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .helpers.competency_helpers import Stall
from .helpers.notify import NotifySocket

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def listener(tmp_path: Path) -> Iterator[tuple[NotifySocket, str]]:
    path = str(tmp_path / "notify")
    got = NotifySocket(path)
    yield got, path
    got.close()




def test_notifier_speaks_to_a_path_socket_and_an_abstract_one(listener: tuple[NotifySocket, str]) -> None:
    got, path = listener
    with systemd.Notifier(path) as notifier:
        assert notifier.ready("up in mesh home\nsecond line")
        assert got.next() == ["READY=1", "STATUS=up in mesh home second line"], "one assignment per line: the status is one line"
        notifier.status("migrating")
        notifier.watchdog()
        notifier.stopping()
        assert [got.next() for _ in range(3)] == [["STATUS=migrating"], ["WATCHDOG=1"], ["STOPPING=1"]]
    name = f"cmion-mesh-test-{uuid.uuid4().hex}"
    abstract = NotifySocket("\0" + name)
    try:
        with systemd.Notifier(environ={"NOTIFY_SOCKET": "@" + name}) as notifier:
            assert notifier.ready()
            assert abstract.next() == ["READY=1"]
    finally:
        abstract.close()


def test_without_notify_socket_nothing_is_sent_and_a_lost_systemd_is_said_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with systemd.Notifier(environ={}) as quiet:
        assert not quiet.enabled and not quiet.ready("x") and quiet.sent == 0
    with systemd.Notifier(str(tmp_path / "nobody-listens")) as lost:
        assert lost.enabled
        assert not lost.ready() and not lost.watchdog(), "a failed send is not raised: the daemon runs on"
    said = [r for r in caplog.records if "cannot notify systemd" in r.getMessage()]
    assert len(said) == 1, said


def test_watchdog_interval_follows_systemd() -> None:
    assert systemd.watchdog_interval({"WATCHDOG_USEC": "30000000"}) == 15.0
    assert systemd.watchdog_interval({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())}) == 15.0
    assert systemd.watchdog_interval({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "1"}) is None, "for another process"
    assert systemd.watchdog_interval({}) is None
    assert systemd.watchdog_interval({"WATCHDOG_USEC": "soon"}) is None
    assert systemd.watchdog_interval({"WATCHDOG_USEC": "0"}) is None


def test_ready_once_the_name_is_held_then_pings_then_stopping(listener: tuple[NotifySocket, str], mesh: str, tmp_path: Path) -> None:
    got, path = listener
    network = MemoryNetwork()
    environ = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"}  # pings every 0.1 s
    with MemoryTransport(network, "robot") as transport, MemoryTransport(network, "newcomer") as other:
        robot = Embodiment("robot", mesh=mesh, transport=transport, join=0.0, state_dir=tmp_path / "robot")
        with robot, systemd.Service(robot, environ=environ) as service:
            first = got.next()
            assert service.ready
            assert first == ["READY=1", f"STATUS=embodiment 'robot' up in mesh {mesh!r}"], "READY=1 comes first, with its status"
            # When systemd hears READY=1 the name is held: another daemon is refused it.
            with pytest.raises(Refused, match="already alive"):
                claim_name(other, mesh, "robot", 0.0)
            assert service.watchdog is not None and service.heartbeat is not None
            assert got.next() == ["WATCHDOG=1"] and got.next() == ["WATCHDOG=1"], "the loop turns: the watchdog is pinged"
        tail = got.until("STOPPING=1")
        assert all(fields == ["WATCHDOG=1"] for fields in tail[:-1]) and tail[-1] == ["STOPPING=1"]
        assert got.pending() == [], "nothing after STOPPING=1: the watchdog stopped with the service"


def test_a_stuck_loop_stops_the_pings_and_they_resume_when_it_turns(
    listener: tuple[NotifySocket, str], mesh: str, caplog: pytest.LogCaptureFixture
) -> None:
    got, path = listener
    stall = Stall()
    with MemoryTransport(MemoryNetwork(), "robot") as transport, \
            Embodiment("robot", mesh=mesh, transport=transport, components=[stall]) as robot:
        heartbeat = Heartbeat(robot.sim, 0.02)
        with heartbeat, systemd.Service(robot, heartbeat=heartbeat, environ={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000"}) as service:
            watchdog = service.watchdog
            assert watchdog is not None and watchdog.interval == 0.05
            assert got.next() == ["READY=1", "STATUS=embodiment 'robot' up in mesh " + repr(mesh)]
            assert watchdog.wait(lambda w: w.pings >= 2, 5.0), "pinged while the loop turns"
            try:
                stall.block()
                assert stall.entered.wait(5.0)
                said = len([r for r in caplog.records if "has not turned" in r.getMessage()])
                # A ping may be on its way from a beat just before the block; from the first round that
                # finds no new beat on, none is sent.
                missed = watchdog.missed
                assert watchdog.wait(lambda w: w.missed >= missed + 1, 5.0)
                pings = watchdog.pings
                assert watchdog.wait(lambda w: w.missed >= missed + 4, 5.0)
                assert watchdog.pings == pings, "no ping while the loop is stuck"
            finally:
                stall.release.set()
            assert watchdog.wait(lambda w: w.pings > pings, 5.0), "pings resume once the loop turns"
        datagrams = got.pending()
        assert datagrams[-1] == ["STOPPING=1"] and all(fields == ["WATCHDOG=1"] for fields in datagrams[:-1])
        assert len(datagrams) - 1 == watchdog.pings, "each ping counted is a datagram sent"
    stuck = [r for r in caplog.records if "has not turned" in r.getMessage()]
    assert len(stuck) - said == 1, "the stall is said once, however long it lasts"


def test_a_loop_stuck_from_the_start_is_never_reported_ready(listener: tuple[NotifySocket, str], mesh: str) -> None:
    got, path = listener
    stall = Stall()
    with MemoryTransport(MemoryNetwork(), "robot") as transport, \
            Embodiment("robot", mesh=mesh, transport=transport, components=[stall]) as robot:
        stall.block()
        try:
            assert stall.entered.wait(5.0)
            with systemd.Service(robot, environ={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000"}, first_beat_wait=0.2) as service:
                assert not service.ready and service.watchdog is None
                assert got.next() == ["STATUS=the update loop of 'robot' did not turn within 0.2 s: not ready"]
        finally:
            stall.release.set()
        assert got.next() == ["STOPPING=1"] and got.pending() == []


def test_the_heartbeat_must_beat_between_two_pings(mesh: str) -> None:
    with MemoryTransport(MemoryNetwork(), "robot") as transport, Embodiment("robot", mesh=mesh, transport=transport) as robot, \
            Heartbeat(robot.sim, 1.0) as slow, systemd.Notifier(environ={}) as notifier:
        with pytest.raises(ValueError, match="more often"):
            systemd.Watchdog(notifier, slow, 0.5)
        # Given a heartbeat too slow for systemd's watchdog, the service beats on one of its own.
        with systemd.Service(robot, heartbeat=slow, notifier=systemd.Notifier("@unused-" + uuid.uuid4().hex),
                             environ={"WATCHDOG_USEC": "1000000"}) as service:
            assert service.heartbeat is not slow and service.heartbeat is not None and service.heartbeat.period == 0.25
        with systemd.Service(robot, environ={}) as quiet:
            assert quiet.watchdog is None, "not run by systemd: no watchdog thread"


# --- the unit file ------------------------------------------------------------------------------


def settings(text: str) -> dict[str, list[str]]:
    """A unit file's assignments (a key may repeat, as SystemCallFilter does)."""
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key, []).append(value)
    return out


def test_the_unit_file_runs_the_daemon_as_a_hardened_notify_service() -> None:
    text = systemd.unit("robot", command=["/opt/cmion-mesh/bin/cmion-mesh"], mesh="home", metrics="127.0.0.1:9464")
    found = settings(text)
    assert found["ExecStart"] == ["/opt/cmion-mesh/bin/cmion-mesh up --name robot --settings /etc/cmion-mesh/robot.toml "
                                  "--state-dir %S/cmion-mesh/robot --mesh home --metrics 127.0.0.1:9464"]
    expected = {
        "Type": "notify", "NotifyAccess": "main", "WatchdogSec": "30", "Restart": "on-failure", "RestartPreventExitStatus": "2",
        "StateDirectory": "cmion-mesh/robot", "DynamicUser": "yes", "User": "cmion-mesh", "NoNewPrivileges": "yes",
        "ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes", "PrivateDevices": "yes",
        "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6 AF_NETLINK", "CapabilityBoundingSet": "",
        "WantedBy": "multi-user.target",
    }
    assert {key: found[key][0] for key in expected} == expected
    assert found["SystemCallFilter"] == ["@system-service", "~@privileged @resources"]
    assert "[Unit]" in text and "[Service]" in text and "[Install]" in text


def test_the_unit_file_escapes_what_systemd_would_expand_and_refuses_what_it_cannot_carry() -> None:
    text = systemd.unit("robot", command=["/opt/my tools/python", "-m", "cmion_mesh.cli.main"], settings="/etc/cmion mesh/100%.toml")
    assert settings(text)["ExecStart"] == ['"/opt/my tools/python" -m cmion_mesh.cli.main up --name robot '
                                           '--settings "/etc/cmion mesh/100%%.toml" --state-dir %S/cmion-mesh/robot']
    home = systemd.unit("robot", command=["/home/ann/venv/bin/cmion-mesh"])
    assert settings(home)["ProtectHome"] == ["read-only"], "a program under a home folder stays readable"
    with pytest.raises(InvalidName):
        systemd.unit("no/slash")
    with pytest.raises(ConfigError, match="absolute path"):
        systemd.unit("robot", command=["cmion-mesh"])
    with pytest.raises(ConfigError, match="absolute path"):
        systemd.unit("robot", settings="robot.toml")
    with pytest.raises(ConfigError, match="control character"):
        systemd.unit("robot", settings="/etc/a\nExecStartPre=/bin/evil")
    with pytest.raises(ConfigError, match="at least 2"):
        systemd.unit("robot", watchdog_sec=0)


def _verify(path: Path) -> str:
    done = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True, text=True, timeout=60, check=False)
    # Only what it says of this unit: a machine's own units may draw warnings of their own.
    said = [line for line in (done.stdout + done.stderr).splitlines() if path.name in line]
    return f"exit {done.returncode}: " + "\n".join(said) if done.returncode or said else ""


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd is not installed: systemd-analyze verify is not available")
def test_the_unit_file_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    path = tmp_path / "cmion-mesh-robot.service"
    path.write_text(systemd.unit("robot", command=[sys.executable, "-m", "cmion_mesh.cli.main"], metrics="127.0.0.1:9464"))
    assert _verify(path) == ""
    # The check is real: a misspelt key and a bad value are reported.
    broken = tmp_path / "cmion-mesh-broken.service"
    broken.write_text(path.read_text().replace("Type=notify", "Tpye=notify").replace("ProtectSystem=strict", "ProtectSystem=bogus"))
    said = _verify(broken)
    assert "Tpye" in said and "bogus" in said, said
