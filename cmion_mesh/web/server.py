"""A web server in a thread: uvicorn serving one ASGI app on an address we bind ourselves.

The socket is bound here, before uvicorn starts, so a taken or unusable address is an error
raised by ``__enter__`` naming it (uvicorn would log it and exit the thread), and the real port
is known at once when port 0 was asked. uvicorn's main loop wakes ten times a second to poll for
shutdown; ours waits on an event instead, so an idle server costs no CPU.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any
from urllib.parse import urlsplit

import uvicorn

from cmion_mesh.errors import ConfigError, WebServerError

_START_TIMEOUT = 10.0
_STOP_TIMEOUT = 5.0
# Open WebSockets are told to close at shutdown; a page that does not answer is not waited for longer.
_GRACEFUL_SHUTDOWN = 1
#: The names a page of a server bound to loopback may have been opened by.
LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})


def parse_bind(text: str) -> tuple[str, int]:
    """``"127.0.0.1:8080"``, ``"[::1]:8080"``, ``":8080"`` or ``"8080"`` -> (host, port).

    The host defaults to loopback: a page that drives a body is not offered to the network unless
    an address says so.
    """
    raw = text.strip()
    host, sep, port_text = raw.rpartition(":")
    if not sep:
        host, port_text = "", raw
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ConfigError(f"bad web address {text!r}: write an IPv6 host in brackets, as [::1]:8080")
    host = host or "127.0.0.1"
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ConfigError(f"bad web address {text!r}: expected HOST:PORT, :PORT or PORT with a port 0..65535")
    if host != "localhost":
        try:
            ipaddress.ip_address(host)
        except ValueError:
            raise ConfigError(f"bad web address {text!r}: {host!r} is not an IP address (or localhost)") from None
    return host, int(port_text)


def host_allowed(headers: Mapping[str, str], *, loopback: bool) -> bool:
    """Whether a request to a server bound to loopback (``loopback``) asked for it by a loopback
    name. A site whose name is made to resolve to 127.0.0.1 (DNS rebinding) is, to the browser,
    the origin of whatever this server answers: its requests name it in ``Host``, and are refused.
    A server bound to another address is reached by names it cannot know; it checks nothing here."""
    if not loopback:
        return True
    return urlsplit(f"//{headers.get('host', '').lower()}").hostname in LOOPBACK_NAMES


def same_origin(headers: Mapping[str, str], *, loopback: bool) -> bool:
    """Whether a WebSocket was opened by a page this server served: a browser lets any site open
    a WebSocket to 127.0.0.1 (and says which in ``Origin``), so a foreign page must neither read
    what the socket carries nor send on it; and on loopback the ``Host`` must be a loopback name
    (``host_allowed``), or a rebound site would count as this server's own. The one check of both
    the live view and the web body."""
    if not host_allowed(headers, loopback=loopback):
        return False
    origin = headers.get("origin")
    if origin is None:
        return True  # not a browser (a script, a test client): nothing to guard against here
    return urlsplit(origin).netloc.lower() == headers.get("host", "").lower()


class _Server(uvicorn.Server):
    """uvicorn's server, reporting when it serves and waiting for shutdown without polling."""

    def __init__(self, config: uvicorn.Config, on_started: Callable[[asyncio.AbstractEventLoop], None]) -> None:
        super().__init__(config)
        self._on_started = on_started
        self._stop: asyncio.Event | None = None

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        self._stop = asyncio.Event()
        await super().startup(sockets=sockets)
        self._on_started(asyncio.get_running_loop())

    async def main_loop(self) -> None:
        await self.on_tick(0)  # sets the default headers once
        assert self._stop is not None
        if not self.should_exit:
            await self._stop.wait()

    def stop(self) -> None:
        """Called on the server's loop."""
        self.should_exit = True
        if self._stop is not None:
            self._stop.set()


class WebServer:
    """Serves ``app`` on ``host:port`` from a thread of its own until ``close()``.

    ``call_soon(fn, *args)`` runs ``fn`` on the server's event loop: the way for other threads
    (zenoh callbacks, workers) to hand something to the pages without blocking.
    """

    def __init__(self, app: Any, host: str = "127.0.0.1", port: int = 0, name: str = "web") -> None:
        self.app = app
        self.host = host
        self.port = port
        self.name = name
        self._cond = threading.Condition()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._failure: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._server: _Server | None = None
        self._sock: socket.socket | None = None
        self._closed = False

    @property
    def _label(self) -> str:
        return "web server" if self.name == "web" else f"{self.name} web server"

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise WebServerError(f"{self._label} at {self.url} is not running")
        return self._loop

    def _bind(self) -> socket.socket:
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(128)
        except OSError as exc:
            sock.close()
            raise WebServerError(f"{self._label} cannot listen on {self.url}: {exc.strerror or exc}") from None
        sock.setblocking(False)
        return sock

    def __enter__(self) -> WebServer:
        if self._closed:
            raise WebServerError(f"{self._label} was closed")
        self._sock = self._bind()
        self.port = self._sock.getsockname()[1]
        config = uvicorn.Config(
            self.app,
            host=self.host,
            port=self.port,
            log_level="warning",
            lifespan="off",
            # The date would only be refreshed by the polling loop this server does not run.
            date_header=False,
            timeout_graceful_shutdown=_GRACEFUL_SHUTDOWN,
        )
        self._server = _Server(config, self._started)
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-web", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + _START_TIMEOUT
        with self._cond:
            while self._loop is None and self._failure is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
        if self._loop is None:
            failure = self._failure
            self.close()
            why = f": {failure!r}" if failure is not None else f" within {_START_TIMEOUT:.0f} s"
            raise WebServerError(f"{self._label} at {self.url} did not start{why}")
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _started(self, loop: asyncio.AbstractEventLoop) -> None:
        with self._cond:
            self._loop = loop
            self._cond.notify_all()

    def _run(self) -> None:
        assert self._server is not None and self._sock is not None
        try:
            self._server.run(sockets=[self._sock])
        except BaseException as exc:  # SystemExit from uvicorn's startup included: reported by __enter__
            with self._cond:
                self._failure = exc
                self._cond.notify_all()

    def call_soon(self, fn: Callable[..., object], *args: Any) -> None:
        """Run ``fn(*args)`` on the server's loop; never blocks; dropped once the server is closed."""
        loop = self._loop
        if loop is None or self._closed:
            return
        with contextlib.suppress(RuntimeError):  # the loop closed between the check and the call
            loop.call_soon_threadsafe(fn, *args)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        server, loop, thread = self._server, self._loop, self._thread
        if server is not None and loop is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(server.stop)
        elif server is not None:
            server.should_exit = True
        if thread is not None:
            thread.join(_STOP_TIMEOUT)
            if thread.is_alive() and server is not None:
                server.force_exit = True
                thread.join(_STOP_TIMEOUT)
        if self._sock is not None:
            self._sock.close()
