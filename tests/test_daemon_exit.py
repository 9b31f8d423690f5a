"""A daemon says it stopped cleanly only when it is about to exit, and leaves nothing behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cmion_mesh.migration.ledger import Records
from cmion_mesh.procs import Daemon, cli_argv, free_port

pytestmark = pytest.mark.timeout(60)


def test_stopped_cleanly_means_the_process_is_gone(tmp_path: Path, mesh: str) -> None:
    daemon = Daemon(cli_argv("up", "robot", "--mesh", mesh, "--no-multicast", "--listen", f"tcp/127.0.0.1:{free_port()}",
                             "--state-dir", str(tmp_path / "robot"), "--companion", "spirit"), name="robot")
    with daemon:
        daemon.wait_line("up in mesh", 30)
        daemon.proc.send_signal(signal.SIGTERM)
        daemon.wait_line("stopped cleanly", 30)
        assert daemon.proc.wait(5) == 0, "it said it stopped cleanly, and then it exited"


def test_start_up_removes_what_an_interrupted_write_left(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a writer that has died
    leftovers = [state / f".spirit.record.json.{gone.pid}.456.tmp", state / f"spirit.{'0' * 64}.identity.xml", state / "spirit.key"]
    for path in leftovers:
        path.write_bytes(b"x")
    (state / "notes.txt").write_bytes(b"not ours")
    # A live writer's temporary file is its own (a tool reading the folder of a running daemon sweeps too).
    (state / f".spirit.record.json.{os.getpid()}.789.tmp").write_bytes(b"x")
    Records(state)
    assert sorted(p.name for p in state.iterdir()) == [f".spirit.record.json.{os.getpid()}.789.tmp", "notes.txt"]
    assert oct(state.stat().st_mode & 0o777) == "0o700"


#: Runs ``cmion-mesh`` as its own process (``main()`` reading ``sys.argv``), saying how the cyclic
#: collector stands when the daemon, up, settles into its wait for a signal.
_COLLECTOR_PROBE = """
import gc, sys
from cmion_mesh import signals
wait = signals.Stopper.wait
def reporting(self, *args, **kwargs):
    print(f"collector enabled={gc.isenabled()} frozen={gc.get_freeze_count()}", flush=True)
    return wait(self, *args, **kwargs)
signals.Stopper.wait = reporting
from cmion_mesh.cli.main import main
sys.exit(main())
"""


def test_a_daemon_runs_with_the_collector_on_and_its_start_up_frozen(tmp_path: Path, mesh: str) -> None:
    """Start-up runs with the cyclic collector paused; once up, the daemon collects again, and what
    start-up loaded is out of the collector's way (frozen): a daemon never runs without it."""
    argv = [sys.executable, "-c", _COLLECTOR_PROBE, "up", "robot", "--mesh", mesh, "--no-multicast",
            "--listen", f"tcp/127.0.0.1:{free_port()}", "--state-dir", str(tmp_path / "robot")]
    with Daemon(argv, name="robot") as daemon:
        line = daemon.wait_line("collector enabled=", 30)
        daemon.wait_line("up in mesh", 30)
    enabled, frozen = (part.partition("=")[2] for part in line.split()[1:])
    assert enabled == "True"
    assert int(frozen) > 10_000, "start-up's objects are frozen"
