"""The web server thread: binds where asked, reports a taken address, stops and joins."""

from __future__ import annotations

import threading
import urllib.request

import pytest
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import PlainTextResponse
from starlette.routing import Route

from cmion_mesh.errors import ConfigError, WebServerError
from cmion_mesh.web.server import WebServer, parse_bind


def _app() -> Starlette:
    def hello(request: Request) -> PlainTextResponse:
        return PlainTextResponse("hello")

    return Starlette(routes=[Route("/", hello)])


def test_serves_on_the_real_port_and_stops() -> None:
    server = WebServer(_app(), port=0, name="screen")
    with server:
        assert server.port != 0 and server.url == f"http://127.0.0.1:{server.port}"
        with urllib.request.urlopen(server.url, timeout=10) as reply:
            assert reply.read() == b"hello"
        done = threading.Event()
        server.call_soon(done.set)
        assert done.wait(10)
    server.close()  # idempotent
    assert not any(t.name == "screen-web" for t in threading.enumerate())


def test_a_taken_address_is_an_error_naming_it() -> None:
    with WebServer(_app()) as first, pytest.raises(WebServerError, match=f"cannot listen on http://127.0.0.1:{first.port}"):
        WebServer(_app(), port=first.port).__enter__()


@pytest.mark.parametrize(
    ("text", "expected"),
    [("127.0.0.1:8080", ("127.0.0.1", 8080)), (":8080", ("127.0.0.1", 8080)), ("8080", ("127.0.0.1", 8080)), ("[::1]:9", ("::1", 9))],
)
def test_parse_bind(text: str, expected: tuple[str, int]) -> None:
    assert parse_bind(text) == expected


@pytest.mark.parametrize("text", ["", "web", "127.0.0.1:http", "1:70000", "example.org:80", "::1:80"])
def test_parse_bind_names_the_bad_text(text: str) -> None:
    with pytest.raises(ConfigError, match=f"bad web address {text!r}"):
        parse_bind(text)
