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
