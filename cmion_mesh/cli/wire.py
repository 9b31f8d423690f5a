"""The mesh's keys and messages by hand, as ``ros2 topic list``, ``ros2 topic pub`` and ``ros2
service call`` do a ROS graph's: ``keys [PATTERN]`` (the keys that exist, with their kind), ``pub
KEY VALUE`` (one publication) and ``call KEY PAYLOAD`` (one request, its answer decoded). Messages
are those of the wire's table (``messages.AnyMessage``, docs/wire.md): what is sent is checked as
a daemon checks it, before it leaves."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import typing
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.cli.common import Spinner, join_timeout_option, mesh_options, table, timeout_option
from cmion_mesh.cli.session import session
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, ExitCode, MeshError, ProtocolError
from cmion_mesh.messages import CONTAINER_KIND, AnyMessage, Code, Event, Message, Outcome, Property, decode, encode, tag
from cmion_mesh.requests import send_request
from cmion_mesh.tools import hz_echo as tap

#: Every message kind of the wire, by its tag (``set_property`` -> ``SetProperty``).
KINDS: dict[str, type[Message]] = {tag(kind): kind for kind in typing.get_args(AnyMessage)}
#: The liveliness tokens of a mesh, by the kind ``keys`` gives them.
TOKENS = {keys.ALIVE: "liveliness: a daemon alive", keys.CLAIM: "liveliness: a claim on a name",
          keys.COMPETENCY: "liveliness: a remote competency", keys.CUSTODY: "liveliness: custody of a companion"}


def keys_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("List the keys that exist in the mesh, with their kind, as ros2 topic list does a graph's "
                     "topics: the blackboard's and world model's properties and containers (read), the requests "
                     "each component answers with their message type (asked), the liveliness tokens (daemons, "
                     "claims, remote competencies, custody), and the event keys published while it looks "
                     "(--watch: events have no register to read). Keys are shown relative to cmion/<mesh>/.")
    p.add_argument("pattern", nargs="?", default="", metavar="PATTERN",
                   help="only keys matching this key expression, relative to the mesh (robot/**, */rq/**, */wm/Visitor/*) "
                        "or absolute (default: every key)")
    p.add_argument("--watch", type=float, default=1.0, metavar="SECONDS",
                   help="how long to listen for events being published (default: %(default)s s; 0: none)")
    timeout_option(p, 3.0, "longest wait for the embodiments' answers")
    mesh_options(p)


def cmd_keys(args: argparse.Namespace) -> int:
    if args.watch < 0:
        raise ConfigError("--watch must be at least 0")
    pattern = tap.resolve(args.mesh, args.pattern) if args.pattern else ""
    prefix = keys.mesh_prefix(args.mesh) + "/"
    found: dict[str, tuple[str, str]] = {}  # key -> (kind, message type)
    lock = threading.Lock()

    def on_event(sample: Any) -> None:
        with lock:
            found.setdefault(sample.key, ("event", "event"))

    with session(args) as client, Spinner(f"listing the keys of mesh {args.mesh!r}", enabled=not args.json):
        started = time.monotonic()
        watching = client.transport.subscribe(f"{prefix}*/ev/**", on_event) if args.watch else None
        try:
            names = sorted(str(d.get("name")) for d in client.describe_all(timeout=args.timeout) if d.get("name"))
            listed = _stored(client, names, args.timeout) | _requests(client, names, args.timeout) | _tokens(client, args.timeout)
            if watching is not None:
                time.sleep(max(0.0, started + args.watch - time.monotonic()))  # the events published meanwhile
        finally:
            if watching is not None:
                watching.close()
    with lock:
        listed |= found
    rows = sorted((k, kind, kind_type) for k, (kind, kind_type) in listed.items()
                  if not pattern or keys.matches(pattern, k))
    if args.json:
        print(json.dumps([{"key": k, "kind": kind, "type": kind_type} for k, kind, kind_type in rows]))
        return ExitCode.OK
    if not rows:
        # `doctor` only where nothing of the mesh was reached: a pattern matching nothing in a live mesh is no fault of it.
        hint = "" if names else ": try `cmion-mesh doctor`"
        print(f"(no key{' matching ' + pattern if pattern else ''} in mesh {args.mesh!r}{hint})")
        return ExitCode.OK
    table([("KEY", "KIND", "TYPE"), *((k.removeprefix(prefix), kind, kind_type) for k, kind, kind_type in rows)])
    return ExitCode.OK


def _stored(client: MeshClient, names: list[str], timeout: float) -> dict[str, tuple[str, str]]:
    """Every property and container of every embodiment's stores (each answers for its own keys)."""
    out: dict[str, tuple[str, str]] = {}
    for name in names:
        for store in (keys.BLACKBOARD, keys.WORLD_MODEL):
            for key, entry in client.read(f"{keys.embodiment_prefix(client.mesh, name)}/{store}/**", timeout=timeout).items():
                if isinstance(entry, Property):
                    out[key] = (f"{store} property" + (" (persistent)" if entry.persistent else ""), "property")
                else:
                    special = entry.kind not in ("", CONTAINER_KIND, "blackboard", "world_model")
                    out[key] = (f"{store} container" + (f" ({entry.kind})" if special else ""), "container")
    return out


def _requests(client: MeshClient, names: list[str], timeout: float) -> dict[str, tuple[str, str]]:
    """The requests each component of each embodiment answers: a query on ``.../rq/**`` is answered
    by every component with its catalogue (docs/wire.md)."""
    out: dict[str, tuple[str, str]] = {}
    for name in names:
        selector = f"{keys.embodiment_prefix(client.mesh, name)}/{keys.REQUESTS}/**"
        for reply in client.transport.get(selector, timeout=timeout):
            try:
                outcome = decode(reply.payload, Outcome, where=selector) if reply.ok else None
            except ProtocolError:
                continue
            catalogue = outcome.value if outcome is not None and outcome.code == Code.UNKNOWN_REQUEST else None
            if not isinstance(catalogue, dict) or not isinstance(catalogue.get("requests"), dict):
                continue
            component = str(catalogue.get("component"))
            per_sender = set(catalogue.get("per_sender") or ())
            for request, kind in catalogue["requests"].items():
                key = keys.request_key(client.mesh, name, component, request)
                if request in per_sender:
                    out[key + "/<sender>"] = ("request (per sender)", str(kind))
                else:
                    out[key] = ("request", str(kind))
    return out


def _tokens(client: MeshClient, timeout: float) -> dict[str, tuple[str, str]]:
    out: dict[str, tuple[str, str]] = {}
    for chunk, kind in TOKENS.items():
        for key in client.transport.alive(f"{keys.mesh_prefix(client.mesh)}/{chunk}/**", timeout=timeout):
            out[key] = (kind, "token")
    return out


def pub_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Publish VALUE on KEY, as ros2 topic pub does on a topic. On an event key "
                     "(EMBODIMENT/ev/COMPONENT/NAME) VALUE is the event's data (JSON, or plain text) and an "
                     "`event` message is sent, as that component would raise it; elsewhere VALUE is a message of "
                     "the wire's table as JSON with its \"type\" (docs/wire.md), checked before it leaves, or with "
                     "--raw any bytes (UTF-8). It waits (--join) for a subscriber of KEY first: a publication "
                     "nobody hears is lost.")
    p.add_argument("key", metavar="KEY", help="where: relative to the mesh (robot/ev/sensor/Touched) or absolute (cmion/MESH/...)")
    p.add_argument("value", metavar="VALUE", nargs="?", default="null",
                   help="the event's data, or a message as JSON ({\"type\": \"event\", ...}) (default: null)")
    p.add_argument("--raw", action="store_true", help="publish VALUE's UTF-8 bytes as they are, no message")
    p.add_argument("--count", type=int, default=1, help="publish it this many times (default: %(default)s)")
    p.add_argument("--rate", type=float, default=1.0, help="publications per second when --count is more than 1 (default: %(default)s)")
    join_timeout_option(p, 3.0)
    mesh_options(p)


def cmd_pub(args: argparse.Namespace) -> int:
    if args.count < 1 or args.rate <= 0:
        raise ConfigError("--count must be at least 1 and --rate more than 0")
    key = tap.resolve(args.mesh, args.key)
    if "*" in key:
        raise ConfigError(f"pub: {key!r} is a pattern: publish on one key")
    payload, what = _publication(key, args.value, args.raw)
    with session(args) as client:
        heard = client.transport.wait_subscribers(key, args.join_timeout)
        if not heard:
            print(f"warning: nobody subscribes to {key} (waited {args.join_timeout:g} s): published to nobody",
                  file=sys.stderr, flush=True)
        for n in range(args.count):
            if n:
                time.sleep(1.0 / args.rate)  # the rate asked for, between publications
            client.transport.publish(key, payload(n))
    if args.json:
        print(json.dumps({"key": key, "message": what, "count": args.count, "subscribed": heard}))
    else:
        print(f"published {what} on {key}" + (f" {args.count} times" if args.count > 1 else ""))
    return ExitCode.OK


def _publication(key: str, value: str, raw: bool) -> tuple[typing.Callable[[int], bytes], str]:
    """What ``pub`` sends (a payload per publication, numbered) and what it is, for people."""
    if raw:
        data = value.encode()
        return (lambda _n: data), f"{len(data)} raw bytes"
    chunks = key.split("/")
    if len(chunks) == 6 and chunks[0] == keys.ROOT and chunks[3] == keys.EVENTS:
        data = parse_json(value)
        embodiment, component, name = chunks[2], chunks[4], chunks[5]
        check(encode(Event(embodiment, component, name, data, 0, 0.0)), key)
        return (lambda n: encode(Event(embodiment, component, name, data, n, time.time()))), f"event {name}"
    message = message_of(value, None, key)
    payload = encode(message)
    return (lambda _n: payload), f"a {tag(type(message))} message"


def call_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Send PAYLOAD as a request to KEY (EMBODIMENT/rq/COMPONENT/REQUEST[/SENDER]) and print its "
                     "one answer decoded, as ros2 service call does. PAYLOAD is the request's fields as JSON; their "
                     "message type is the one the component takes on that key (asked of it, as `keys` shows: "
                     "docs/wire.md), or PAYLOAD's own \"type\". Exit code: 0 accepted, 1 rejected or conflict, "
                     "4 no answer (outcome unknown).")
    p.add_argument("key", metavar="KEY", help="a request key, relative to the mesh (robot/rq/bb/set_property) or absolute")
    p.add_argument("payload", metavar="PAYLOAD", nargs="?", default="{}",
                   help="the request's fields as JSON, e.g. '{\"container\": \"\", \"name\": \"battery\", \"value\": 0.8}' (default: {})")
    timeout_option(p, 10.0, "seconds to wait for the answer")
    join_timeout_option(p)
    mesh_options(p)


def cmd_call(args: argparse.Namespace) -> int:
    key = tap.resolve(args.mesh, args.key)
    try:
        parsed = keys.parse(key)
    except MeshError:
        parsed = None
    if parsed is None or parsed.kind != keys.REQUESTS or parsed.mesh != args.mesh:
        raise ConfigError(f"call: {key!r} is no request key of mesh {args.mesh!r} (EMBODIMENT/rq/COMPONENT/REQUEST; "
                          "`cmion-mesh keys '*/rq/**'` lists them)")
    fields = parse_json(args.payload)
    if not isinstance(fields, dict):
        raise ConfigError(f"call: PAYLOAD must be a JSON object of the request's fields, not {args.payload!r}")
    with session(args) as client, Spinner(f"calling {key}", enabled=not args.json):
        client.join(parsed.embodiment, timeout=args.join_timeout)
        kind = fields.get("type") or _request_type(client, key, parsed.embodiment, parsed.rest, args.timeout)
        message = message_of(json.dumps(fields), str(kind), key)
        outcome = send_request(client.transport, key, message, timeout=args.timeout)
    answer = msgspec.to_builtins(outcome)
    if args.json:
        print(json.dumps(answer))
    else:
        print(f"{outcome.status}" + (f" ({outcome.code})" if outcome.code else "") + (f": {outcome.reason}" if outcome.reason else ""))
        if outcome.value is not None:
            print(json.dumps(outcome.value, indent=2))
    return ExitCode.OK if outcome.status == "accepted" else ExitCode.FAILED


def _request_type(client: MeshClient, key: str, embodiment: str, rest: tuple[str, ...], timeout: float) -> str:
    """The message type the component takes on ``key``: its catalogue says (docs/wire.md)."""
    component, request = rest[0], rest[1]
    selector = f"{keys.embodiment_prefix(client.mesh, embodiment)}/{keys.REQUESTS}/{component}/**"
    for reply in client.transport.get(selector, timeout=timeout):
        try:
            outcome = decode(reply.payload, Outcome, where=selector) if reply.ok else None
        except ProtocolError:
            continue
        catalogue = outcome.value if outcome is not None else None
        if isinstance(catalogue, dict) and catalogue.get("component") == component and isinstance(catalogue.get("requests"), dict):
            requests: dict[str, Any] = catalogue["requests"]
            if request not in requests:
                from cmion_mesh.presence import did_you_mean

                raise ConfigError(f"call: component {component!r} of {embodiment} has no request {request!r} "
                                  f"(known: {', '.join(sorted(requests)) or 'none'}){did_you_mean(request, requests)}")
            return str(requests[request])
    raise ConfigError(f"call: no component {component!r} answers on {embodiment} (`cmion-mesh keys '{embodiment}/rq/**'` "
                      "lists them); give PAYLOAD's \"type\" to send it anyway")


def message_of(text: str, kind: str | None, where: str) -> Message:
    """The wire's message that JSON ``text`` writes (with its ``type``, or of ``kind``), checked as a
    daemon checks what it receives; ``ConfigError`` naming what is wrong."""
    fields = parse_json(text)
    if not isinstance(fields, dict):
        raise ConfigError(f"{where}: a message is a JSON object with its \"type\" (docs/wire.md), not {text!r}")
    kind = str(fields.get("type") or kind or "")
    if kind not in KINDS:
        from cmion_mesh.presence import did_you_mean

        raise ConfigError(f"{where}: {kind!r} is no message type of the wire (docs/wire.md){did_you_mean(kind, KINDS)}"
                          if kind else f"{where}: say the message's \"type\" (docs/wire.md), e.g. {{\"type\": \"event\", ...}}")
    message = check(msgspec.msgpack.encode({**fields, "type": kind}), where)
    if not isinstance(message, KINDS[kind]):
        raise ConfigError(f"{where}: not a {kind} message")
    return message


def check(payload: bytes, where: str) -> Message:
    try:
        message: Message = decode(payload, where=where)
    except ProtocolError as exc:
        raise ConfigError(str(exc)) from None
    return message


def parse_json(text: str) -> Any:
    """JSON when ``text`` parses as JSON, else the text itself (as ``bb set`` takes values)."""
    try:
        return msgspec.json.decode(text)
    except msgspec.DecodeError:
        return text
