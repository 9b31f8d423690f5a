from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.memory_transport import MemoryNetwork, MemoryTransport
from cmion_mesh.procs import unique_mesh

DATA = Path(__file__).parent / "data"
CMION_2011 = DATA / "cmion2011"


@pytest.fixture(scope="session", autouse=True)
def private_state_home(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Daemons keep durable records under $XDG_STATE_HOME: never the user's own, in tests."""
    import os

    old = os.environ.get("XDG_STATE_HOME")
    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("state-home"))
    yield
    if old is None:
        os.environ.pop("XDG_STATE_HOME", None)
    else:
        os.environ["XDG_STATE_HOME"] = old


@pytest.fixture
def mesh() -> str:
    """A mesh name no other test or parallel run uses."""
    return unique_mesh()


@pytest.fixture
def network() -> MemoryNetwork:
    return MemoryNetwork()


@pytest.fixture
def transport(network: MemoryNetwork) -> Iterator[MemoryTransport]:
    with MemoryTransport(network, "local") as t:
        yield t


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    """Every thread a test starts must be stopped by the end of the test."""
    before = {t.ident for t in threading.enumerate()}
    yield
    def leaked() -> list[str]:
        return [t.name for t in threading.enumerate() if t.ident not in before and t.is_alive() and not t.name.startswith("zenoh-")]
    # Threads that are finishing get a bounded moment to exit.
    for t in [t for t in threading.enumerate() if t.ident not in before]:
        t.join(2.0)
    assert not leaked(), f"threads left running: {leaked()}"


def start_daemon(mesh: str, name: str, *extra: str, port: int | None = None) -> tuple[Daemon, str]:
    """``cmion-mesh up`` in its own process, listening on loopback only; returns it and its endpoint."""
    from cmion_mesh.procs import Daemon, cli_argv, free_port

    endpoint = f"tcp/127.0.0.1:{port or free_port()}"
    daemon = Daemon(cli_argv("up", "--name", name, "--mesh", mesh, "--listen", endpoint, "--no-multicast", *extra), name=name)
    try:
        daemon.wait_line("up in mesh", 20)
    except BaseException:
        daemon.kill()
        raise
    return daemon, endpoint


from cmion_mesh.procs import Daemon  # noqa: E402  (for the annotation above)
from tests.browser import chromium_browser  # noqa: E402, F401  (the real-browser fixture, for the web page tests)
