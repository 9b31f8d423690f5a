"""A Foxglove WebSocket client written from the protocol's specification, in a process of its own.

The specification: foxglove/ws-protocol, ``docs/spec.md`` ("Foxglove WebSocket protocol v1", as
it was before commit 8e2a044 moved it out). What this client does of it:

* the WebSocket handshake offers the subprotocols ``foxglove.sdk.v1`` and
  ``foxglove.websocket.v1``, as Foxglove's own app does (``new WebSocket(url, ["foxglove.sdk.v1",
  FoxgloveClient.SUPPORTED_SUBPROTOCOL])``): Foxglove's SDK, which the server is built on, names
  the protocol ``foxglove.sdk.v1`` and refuses a handshake without it (HTTP 400; its
  ``rust/foxglove/src/websocket/handshake.rs``); the messages are those of the v1 specification;
* text frames are JSON objects with an ``op``; the first is ``serverInfo``;
* ``advertise``: ``channels`` of ``id``, ``topic``, ``encoding``, ``schemaName``, ``schema``,
  ``schemaEncoding``; the client answers with ``subscribe``: ``subscriptions`` of ``id`` (its
  own, never reused while active) and ``channelId``; ``unadvertise``: ``channelIds``;
* binary frames start with a one-byte opcode; ``0x01`` Message Data: subscription id (uint32),
  log time in nanoseconds (uint64), both little-endian, then the payload, encoded as the
  channel's ``encoding`` says (here ``json``).

Run as ``python -m tests.helpers.foxglove_client URL TOPIC_PART...``: subscribes to every channel whose
topic contains one of the parts; prints, one JSON line each, ``READY {...}`` (the subprotocol
chosen and the server's info), ``A {...}`` per channel advertised, ``M {...}`` per message
(``topic``, ``schemaName``, ``schema`` only the first time a channel is seen, ``log_time``,
``message`` decoded). Ends when the server closes the connection, or on SIGTERM.
"""

from __future__ import annotations

import json
import signal
import struct
import sys
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.typing import Subprotocol

SUBPROTOCOLS = [Subprotocol("foxglove.sdk.v1"), Subprotocol("foxglove.websocket.v1")]
MESSAGE_DATA = 0x01
#: opcode (1 byte), subscription id (uint32), log time (uint64): little-endian.
MESSAGE_HEADER = struct.Struct("<BIQ")


def emit(tag: str, data: dict[str, Any]) -> None:
    print(f"{tag} {json.dumps(data)}", flush=True)


def run(url: str, parts: list[str]) -> None:
    channels: dict[int, dict[str, Any]] = {}  # subscription id -> the channel advertised
    subscribed: dict[int, int] = {}  # channel id -> subscription id
    shown: set[int] = set()
    with connect(url, subprotocols=SUBPROTOCOLS, open_timeout=10, max_size=None) as ws:
        first = json.loads(ws.recv(timeout=10))
        if first.get("op") != "serverInfo":
            raise SystemExit(f"the first message is not serverInfo: {first}")
        emit("READY", {"subprotocol": ws.subprotocol, "server": first})
        for frame in ws:
            if isinstance(frame, str):
                message = json.loads(frame)
                if message.get("op") == "advertise":
                    wanted = []
                    for channel in message["channels"]:
                        emit("A", {k: channel.get(k) for k in ("id", "topic", "encoding", "schemaName", "schemaEncoding")})
                        if channel["id"] not in subscribed and any(part in channel["topic"] for part in parts):
                            subscription = len(channels)
                            channels[subscription] = channel
                            subscribed[channel["id"]] = subscription
                            wanted.append({"id": subscription, "channelId": channel["id"]})
                    if wanted:
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": wanted}))
                elif message.get("op") == "unadvertise":
                    for channel_id in message["channelIds"]:
                        subscribed.pop(channel_id, None)
                continue
            if frame[0] != MESSAGE_DATA:
                continue
            _, subscription, log_time = MESSAGE_HEADER.unpack_from(frame)
            channel = channels[subscription]
            if channel["encoding"] != "json":
                raise SystemExit(f"{channel['topic']}: encoding {channel['encoding']!r}, not json")
            line = {"topic": channel["topic"], "schemaName": channel["schemaName"], "log_time": log_time,
                    "message": json.loads(frame[MESSAGE_HEADER.size:])}
            if subscription not in shown:
                shown.add(subscription)
                line["schema"] = channel["schema"]
            emit("M", line)


def main() -> None:
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        run(sys.argv[1], sys.argv[2:])
    except ConnectionClosed:
        pass


if __name__ == "__main__":
    main()
