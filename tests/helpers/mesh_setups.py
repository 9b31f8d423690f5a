"""Meshes, bodies and recordings that several test files start (and read) the same way."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import Daemon, cli_argv, unique_mesh
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport
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


@contextmanager
def body_and_client(name: str, config: str) -> Iterator[tuple[Daemon, str, MeshClient]]:
    """``cmion-mesh up`` of ``config`` as ``name`` in a mesh of its own, and a client connected to it
    alone that has joined it; yields (daemon, its endpoint, client) and stops the daemon at the end."""
    mesh = unique_mesh()
    daemon, endpoint = start_daemon(mesh, name, config)
    try:
        with ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False)) as transport, MeshClient(transport, mesh) as client:
            client.join(name, timeout=20)
            yield daemon, endpoint, client
    finally:
        daemon.stop()


def blackboard(client: MeshClient, body: str, path: str) -> Any:
    """The value at ``path`` (``container/name``) on ``body``'s blackboard; None while there is none."""
    container, _, name = path.rpartition("/")
    try:
        return client.get_property(body, keys.BLACKBOARD, container, name).value
    except MeshError:
        return None
