"""Every request key of a real daemon answers every malformed shape: a refusal with a reason, never silence.

The daemon (the shipped robot: planner mind, stores, manager, execution, migration) and a remote
competency run in processes of their own; this process finds their request keys by asking
``.../rq/**`` (every component answers with its catalogue) and sends each key every shape of
malformed payload. Each must come back as exactly one ``outcome``: rejected, code ``malformed``
(or ``unknown_request`` for a request the component does not have), a reason naming the key.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh import keys, messages
from cmion_mesh.messages import Code, Describe, Message, Outcome, SetProperty, decode, encode, tag
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import start_daemon

pytestmark = pytest.mark.timeout(120)

SENDER = "tester"
#: A MessagePack value no field of any request accepts (not plain data, not a typed value).
NEVER_VALID = msgspec.msgpack.Ext(1, b"x")
BY_TAG: dict[str, type[Message]] = {
    tag(kind): kind for kind in vars(messages).values()
    if isinstance(kind, type) and issubclass(kind, Message) and kind is not Message and not kind.__name__.startswith("_")
}


def malformed_shapes(message_type: str) -> dict[str, bytes]:
    """Every way the payload for a request taking ``message_type`` can be malformed, by name."""
    mp = msgspec.msgpack.encode
    shapes = {
        "empty payload": b"",
        "garbage": b"\xc1\xc1garbage",
        "not a map": mp([1, 2, 3]),
        "a bare value": mp("set_property"),
        "empty map": mp({}),
        "no type": mp({"name": "x", "action_id": "x", "run_id": "x"}),
        "unknown type": mp({"type": "drop_table"}),
        "type of a reply": mp({"type": "outcome", "status": "accepted"}),
        "type of another request": mp({"type": "describe" if message_type != "describe" else "sleep"}),
    }
    kind = BY_TAG[message_type]
    fields = kind.__struct_fields__
    if fields:
        shapes["every field of the wrong type"] = mp({"type": message_type, **{f: NEVER_VALID for f in fields}})
    if len(kind.__struct_defaults__) < len(fields):
        shapes["required fields missing"] = mp({"type": message_type})
    return shapes


@pytest.fixture
def robot(mesh: str, tmp_path: Path) -> Iterator[tuple[str, Daemon]]:
    daemon, endpoint = start_daemon(mesh, "robot", "robot", "--state-dir", str(tmp_path / "robot"))
    with daemon:
        yield endpoint, daemon
    assert daemon.proc.returncode == 0, "\n".join(daemon.lines)


def test_every_malformed_request_to_every_key_is_answered(robot: tuple[str, Daemon], mesh: str) -> None:
    endpoint, daemon = robot
    arm = Daemon(cli_argv("serve-competency", "tests.helpers.remote_helpers:Arm", "--embodiment", "robot", "--mesh", mesh,
                          "--connect", endpoint, "--no-multicast"), name="arm")
    with arm, ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False)) as transport:
        arm.wait_line("serving embodiment", 20)
        every = f"{keys.embodiment_prefix(mesh, 'robot')}/{keys.REQUESTS}/**"

        def catalogues() -> dict[str, dict[str, Any]]:
            found = {}
            for reply in transport.get(every, b"", timeout=5.0):
                outcome = decode(reply.payload, Outcome, where=reply.key)
                assert outcome.code == Code.UNKNOWN_REQUEST, outcome
                found[outcome.value["component"]] = outcome.value
            return found

        expected = {"bb", "wm", "manager", "execution", "embodiment", "migration", "mind", "Arm"}
        components = wait_for(lambda: (found := catalogues()) and expected <= set(found) and found, 20,
                              "every component of the daemon and the remote competency answer .../rq/**")

        def answer(key: str, payload: bytes) -> Outcome:
            replies = transport.get(key, payload, timeout=5.0)
            assert len(replies) == 1 and replies[0].ok, f"{key}: {replies} (none: the request went unanswered)"
            outcome: Outcome = decode(replies[0].payload, Outcome, where=key)
            return outcome

        sent = 0
        for component, catalogue in sorted(components.items()):
            for name, message_type in catalogue["requests"].items():
                key = keys.request_key(mesh, "robot", component, name, SENDER if name in catalogue["per_sender"] else None)
                for shape, payload in malformed_shapes(message_type).items():
                    outcome = answer(key, payload)
                    sent += 1
                    assert (outcome.status, outcome.code) == ("rejected", Code.MALFORMED), f"{key}, {shape}: {outcome}"
                    assert outcome.reason.startswith(key), f"{key}, {shape}: {outcome}"
            unknown = answer(keys.request_key(mesh, "robot", component, "no_such_request"), encode(Describe()))
            assert (unknown.status, unknown.code) == ("rejected", Code.UNKNOWN_REQUEST) and "no_such_request" in unknown.reason
        assert sent > 100

        # Still answering, its loop still turning, nothing left to the log as a traceback.
        written = answer(keys.request_key(mesh, "robot", "bb", "set_property"), encode(SetProperty("", "after", 1)))
        assert written.status == "accepted", written
        assert answer(keys.request_key(mesh, "robot", "embodiment", "describe"), encode(Describe())).status == "accepted"
    assert not any("Traceback" in line for line in daemon.lines), "\n".join(daemon.lines)
