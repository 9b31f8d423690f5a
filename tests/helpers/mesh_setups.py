"""Meshes and recordings that several test files start the same way."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from cmion_mesh.procs import cli_argv
from tests.conftest import start_daemon


@contextmanager
def three_daemons(mesh: str, folder: Path) -> Iterator[list[str]]:
    """robot (where the companion spirit is born), screen and phone, each a daemon with its state
    folder in ``folder``; yields their endpoints, the robot's first (the others connect to it)."""
    with ExitStack() as stack:
        robot, first = start_daemon(mesh, "robot", "--companion", "spirit", "--state-dir", str(folder / "robot"))
        stack.enter_context(robot)
        endpoints = [first]
        for name in ("screen", "phone"):
            daemon, endpoint = start_daemon(mesh, name, "--connect", first, "--state-dir", str(folder / name))
            stack.enter_context(daemon)
            endpoints.append(endpoint)
        yield endpoints


def record_demo(path: Path) -> Path:
    """``cmion-mesh demo --record path``: the demo's mesh and its three migrations, recorded."""
    result = subprocess.run(cli_argv("demo", "--record", str(path)), capture_output=True, text=True, timeout=150,
                            stdin=subprocess.DEVNULL)
    assert result.returncode == 0, result.stdout + result.stderr
    return path
