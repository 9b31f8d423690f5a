"""What systemd does with ``$NOTIFY_SOCKET``, for the tests: a unix datagram socket, read with a deadline."""

from __future__ import annotations

import socket
import uuid


class NotifySocket:
    """Bound at ``address`` (a file), or at a fresh abstract name (``@...``) when none is given."""

    def __init__(self, address: str | None = None) -> None:
        self.address = address or f"@cmion-test-{uuid.uuid4().hex}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + self.address[1:] if self.address.startswith("@") else self.address)
        self.got: list[list[str]] = []

    def env(self, watchdog_usec: int = 1_000_000) -> dict[str, str]:
        return {"NOTIFY_SOCKET": self.address, "WATCHDOG_USEC": str(watchdog_usec)}

    def next(self, timeout: float = 5.0) -> list[str]:
        self.sock.settimeout(timeout)
        fields = self.sock.recv(4096).decode().split("\n")
        self.got.append(fields)
        return fields

    def until(self, field: str, timeout: float = 5.0) -> list[list[str]]:
        """The datagrams up to and including the first holding ``field`` (bounded by their count and the timeout)."""
        seen = []
        for _ in range(1000):
            fields = self.next(timeout)
            seen.append(fields)
            if field in fields:
                return seen
        raise AssertionError(f"no {field} in {seen[-5:]}")

    def pending(self) -> list[list[str]]:
        """Whatever has arrived and not been read (without waiting)."""
        out = []
        self.sock.setblocking(False)
        try:
            for _ in range(1000):
                out.append(self.sock.recv(4096).decode().split("\n"))
        except BlockingIOError:
            pass
        return out

    def close(self) -> None:
        self.sock.close()
