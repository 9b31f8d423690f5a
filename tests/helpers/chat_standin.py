"""A chat-completions endpoint stand-in, written from OpenAI's public API specification
(``POST /v1/chat/completions``: the request's ``model``, ``messages``, ``tools``, ``stream`` and
``stream_options``; the ``chat.completion`` object, or ``chat.completion.chunk`` server-sent
events ending with ``data: [DONE]``; errors as ``{"error": {"message", "type", "param", "code"}}``).

It runs in a process of its own (``python -m tests.helpers.chat_standin --port P``) on 127.0.0.1 and
answers from a script that the test sends it over HTTP:

* ``POST /_standin/script`` ``{"steps": [...], "default": step | null}``: steps are used one per
  request, in order; when none is left, ``default`` (else a plain "ok" answer). A step is
  ``{"content": "...", "tool_calls": [{"name": ..., "arguments": {...} | "text"}], "delay": s}``
  or ``{"status": 503, "message": "...", "retry_after": s, "delay": s}``;
* ``GET /_standin/requests``: every request received (``body``: its exact text, ``auth``: whether
  its key was right, ``received``/``answered``: perf_counter times in this process, ``calls``: the
  ids of the tool calls answered, ``answers``: the tool call ids its tool messages answer);
  ``GET /_standin/timings?since=N``: the same without the bodies, and how many steps are left.

A request that offers no tools is answered in words even where the step has tool calls (a model
cannot call what it was not offered), unless the step says ``"force": true``.

Like the real API it refuses (400) a body that is not a chat-completions request: no model, no
messages, an unknown role, a tool message answering no call of the assistant message before it,
or an assistant message whose tool calls are not all answered before the next message of another
kind: a mind that sends a broken conversation learns it here as it would from a real endpoint.
With ``--key K`` a request without ``Authorization: Bearer K`` gets 401.
"""

from __future__ import annotations

import argparse
import itertools
import json
import socket
import threading
import time
import urllib.request
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from cmion_mesh.procs import Daemon, free_port

ROLES = {"system", "developer", "user", "assistant", "tool"}


class Script:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.steps: list[dict[str, Any]] = []
        self.default: dict[str, Any] | None = None
        self.requests: list[dict[str, Any]] = []
        self.ids = itertools.count(1)

    def next_step(self) -> dict[str, Any]:
        with self.lock:
            if self.steps:
                return self.steps.pop(0)
            return dict(self.default) if self.default is not None else {"content": "ok"}


def conversation_problem(body: Any) -> str:
    """Why ``body`` is not a valid chat-completions request ("" when it is)."""
    if not isinstance(body, dict):
        return "the body must be a JSON object"
    if not isinstance(body.get("model"), str) or not body["model"]:
        return "you must provide a model parameter"
    messages = body.get("messages")
    if not isinstance(messages, list) or not messages:
        return "'messages' must be a non-empty array"
    open_ids: set[str] = set()
    for i, m in enumerate(messages):
        if not isinstance(m, dict) or m.get("role") not in ROLES:
            return f"messages[{i}]: unknown role {m.get('role') if isinstance(m, dict) else m!r}"
        role = m["role"]
        if role == "tool":
            if m.get("tool_call_id") not in open_ids:
                return (f"messages[{i}]: messages with role 'tool' must be a response to a preceeding message with "
                        "'tool_calls'")
            open_ids.discard(m["tool_call_id"])
            if not isinstance(m.get("content"), str):
                return f"messages[{i}].content: a tool message's content is a string"
            continue
        if open_ids:
            return (f"messages[{i}]: an assistant message with 'tool_calls' must be followed by tool messages responding "
                    f"to each 'tool_call_id'; missing: {sorted(open_ids)}")
        if role == "assistant":
            for call in m.get("tool_calls") or ():
                if not isinstance(call, dict) or call.get("type") != "function" or not isinstance(call.get("id"), str):
                    return f"messages[{i}].tool_calls: each is {{id, type: function, function}}"
                function = call.get("function") or {}
                if not isinstance(function.get("name"), str) or not isinstance(function.get("arguments"), str):
                    return f"messages[{i}].tool_calls: function name and arguments are strings"
                open_ids.add(call["id"])
            if m.get("content") is None and not m.get("tool_calls"):
                return f"messages[{i}]: an assistant message has content or tool_calls"
        elif not isinstance(m.get("content"), str):
            return f"messages[{i}].content: must be a string"
    if open_ids:
        return f"the tool calls {sorted(open_ids)} have no tool message"
    for t in body.get("tools") or ():
        if not isinstance(t, dict) or t.get("type") != "function" or not isinstance((t.get("function") or {}).get("name"), str):
            return "tools: each is {type: function, function: {name, description, parameters}}"
    return ""


class Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server: Server

    def setup(self) -> None:
        super().setup()
        # Headers and body are two writes: without this, Nagle's algorithm holds the body back
        # until the client acknowledges the headers (a delayed ACK, 40 ms on Linux).
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def log_message(self, format: str, *args: Any) -> None:  # quiet
        pass

    def _send_json(self, status: int, data: Any, headers: dict[str, str] | None = None) -> None:
        raw = json.dumps(data).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(raw)))
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(raw)
        self.wfile.flush()

    def _error(self, status: int, message: str, kind: str = "invalid_request_error", code: str | None = None,
               headers: dict[str, str] | None = None) -> None:
        self._send_json(status, {"error": {"message": message, "type": kind, "param": None, "code": code}}, headers)

    def do_GET(self) -> None:
        path, _, query = self.path.partition("?")
        since = int(query.removeprefix("since=") or 0) if query.startswith("since=") else 0
        if path == "/_standin/requests":
            with self.server.script.lock:
                self._send_json(200, self.server.script.requests[since:])
        elif path == "/_standin/timings":
            with self.server.script.lock:
                records = self.server.script.requests[since:]
                self._send_json(200, {"steps_left": len(self.server.script.steps), "requests": len(self.server.script.requests),
                                      "timings": [{k: r[k] for k in ("received", "answered", "calls", "answers")} for r in records]})
        elif self.path == "/v1/models":
            self._send_json(200, {"object": "list", "data": [{"id": "standin", "object": "model", "created": 0, "owned_by": "test"}]})
        else:
            self._error(404, f"no route {self.path}", code="not_found")

    def do_POST(self) -> None:
        raw = self.rfile.read(int(self.headers.get("Content-Length") or 0))
        received = time.perf_counter()
        script = self.server.script
        if self.path == "/_standin/script":
            data = json.loads(raw)
            with script.lock:
                script.steps.extend(data.get("steps") or [])
                if "default" in data:
                    script.default = data["default"]
            self._send_json(200, {"ok": True})
            return
        if self.path != "/v1/chat/completions":
            self._error(404, f"no route {self.path}", code="not_found")
            return
        auth = self.server.key is None or self.headers.get("Authorization") == f"Bearer {self.server.key}"
        record: dict[str, Any] = {"body": raw.decode("utf-8", "replace"), "auth": auth, "received": received, "answered": None,
                                  "calls": [], "answers": []}
        with script.lock:
            script.requests.append(record)
        if not auth:
            self._error(401, "Incorrect API key provided.", code="invalid_api_key")
            return
        try:
            body = json.loads(raw)
        except ValueError:
            self._error(400, "We could not parse the JSON body of your request.")
            return
        problem = conversation_problem(body)
        if problem:
            self._error(400, problem)
            return
        record["answers"] = [m.get("tool_call_id") for m in body["messages"] if m.get("role") == "tool"]
        step = script.next_step()
        if not body.get("tools") and not step.get("force"):
            # A model offered no tools answers in words (``force``: one that calls them anyway).
            step = {k: v for k, v in step.items() if k != "tool_calls"}
            step.setdefault("content", "(words)")
        delay = float(step.get("delay") or 0)
        if delay:
            time.sleep(delay)  # a slow model (this process only serves the test)
        if "status" in step:
            headers = {"Retry-After": str(step["retry_after"])} if "retry_after" in step else None
            self._error(int(step["status"]), str(step.get("message") or "stand-in error"), "server_error", headers=headers)
        elif body.get("stream"):
            self._stream(body, step, record)
        else:
            self._send_json(200, self._completion(body, step, record))
        record["answered"] = time.perf_counter()

    def _calls(self, step: dict[str, Any], record: dict[str, Any]) -> list[dict[str, Any]]:
        out = []
        for call in step.get("tool_calls") or ():
            arguments = call.get("arguments", {})
            text = arguments if isinstance(arguments, str) else json.dumps(arguments)
            out.append({"id": f"call_{next(self.server.script.ids)}", "type": "function",
                        "function": {"name": call["name"], "arguments": text}})
        record["calls"] = [c["id"] for c in out]
        return out

    def _completion(self, body: dict[str, Any], step: dict[str, Any], record: dict[str, Any]) -> dict[str, Any]:
        calls = self._calls(step, record)
        message: dict[str, Any] = {"role": "assistant", "content": step.get("content"), "refusal": None}
        if calls:
            message["tool_calls"] = calls
        prompt = len(json.dumps(body["messages"])) // 4
        completion = len(json.dumps(message)) // 4
        return {"id": f"chatcmpl-{next(self.server.script.ids)}", "object": "chat.completion", "created": int(time.time()),
                "model": body["model"], "system_fingerprint": None,
                "choices": [{"index": 0, "message": message, "logprobs": None, "finish_reason": "tool_calls" if calls else "stop"}],
                "usage": {"prompt_tokens": prompt, "completion_tokens": completion, "total_tokens": prompt + completion}}

    def _stream(self, body: dict[str, Any], step: dict[str, Any], record: dict[str, Any]) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-cache")
        self.send_header("Connection", "close")  # the stream ends with the connection (no chunked framing here)
        self.end_headers()
        base = {"id": f"chatcmpl-{next(self.server.script.ids)}", "object": "chat.completion.chunk",
                "created": int(time.time()), "model": body["model"], "system_fingerprint": None}

        def chunk(delta: dict[str, Any], finish: str | None = None) -> None:
            data = {**base, "choices": [{"index": 0, "delta": delta, "logprobs": None, "finish_reason": finish}]}
            self.wfile.write(f"data: {json.dumps(data)}\n\n".encode())
            self.wfile.flush()

        chunk({"role": "assistant", "content": ""})
        content = step.get("content") or ""
        for piece in _pieces(content, 5):
            chunk({"content": piece})
        calls = self._calls(step, record)
        for index, call in enumerate(calls):
            chunk({"tool_calls": [{"index": index, "id": call["id"], "type": "function",
                                   "function": {"name": call["function"]["name"], "arguments": ""}}]})
            for piece in _pieces(call["function"]["arguments"], 7):
                chunk({"tool_calls": [{"index": index, "function": {"arguments": piece}}]})
        chunk({}, "tool_calls" if calls else "stop")
        if (body.get("stream_options") or {}).get("include_usage"):
            usage = {"prompt_tokens": 10, "completion_tokens": 5, "total_tokens": 15}
            self.wfile.write(f"data: {json.dumps({**base, 'choices': [], 'usage': usage})}\n\n".encode())
        self.wfile.write(b"data: [DONE]\n\n")
        self.wfile.flush()
        self.close_connection = True


def _pieces(text: str, size: int) -> Iterator[str]:
    for i in range(0, len(text), size):
        yield text[i : i + size]


class Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, port: int, key: str | None) -> None:
        super().__init__(("127.0.0.1", port), Handler)
        self.script = Script()
        self.key = key


# --- the test's side -----------------------------------------------------------------------------


class StandIn:
    """The stand-in in its own process; a context manager that stops it."""

    def __init__(self, port: int | None = None, key: str | None = None) -> None:
        self.port = port or free_port()
        args = ["--port", str(self.port)] + (["--key", key] if key else [])
        import sys

        self.process = Daemon([sys.executable, "-m", "tests.helpers.chat_standin", *args], name="chat-standin")
        try:
            self.process.wait_line("stand-in ready", 20)
        except BaseException:
            self.process.kill()
            raise

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/v1"

    def _call(self, path: str, data: Any = None) -> Any:
        request = urllib.request.Request(f"http://127.0.0.1:{self.port}{path}", method="POST" if data is not None else "GET",
                                         data=json.dumps(data).encode() if data is not None else None,
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as answer:
            return json.loads(answer.read())

    def script(self, *steps: dict[str, Any], default: dict[str, Any] | bool | None = False) -> None:
        payload: dict[str, Any] = {"steps": list(steps)}
        if default is not False:
            payload["default"] = default
        self._call("/_standin/script", payload)

    def requests(self) -> list[dict[str, Any]]:
        return list(self._call("/_standin/requests"))

    def timings(self, since: int = 0) -> dict[str, Any]:
        """``steps_left``, ``requests`` (how many in all) and each request's times from ``since`` on."""
        answer: dict[str, Any] = self._call(f"/_standin/timings?since={since}")
        return answer

    def bodies(self) -> list[dict[str, Any]]:
        return [json.loads(r["body"]) for r in self.requests()]

    def kill(self) -> None:
        self.process.kill()

    def close(self) -> None:
        self.process.stop()

    def __enter__(self) -> StandIn:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def main() -> None:
    parser = argparse.ArgumentParser(description="A chat-completions stand-in on 127.0.0.1 (tests only).")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--key", default=None)
    args = parser.parse_args()
    server = Server(args.port, args.key)
    print(f"stand-in ready on http://127.0.0.1:{args.port}/v1", flush=True)
    try:
        server.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()


if __name__ == "__main__":
    main()
