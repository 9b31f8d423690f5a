"""The ledger's file: one append-only log of checksummed entries per state folder (``Journal``).

Each durable step of the handshake is one entry appended to ``ledger.log`` and one ``fdatasync``:
no temporary file, no rename, no fsync of the folder (the folder is synced once, when the log is
made). An entry is framed as ``magic (4) | length (4, little-endian) | CRC-32 of length and payload
(4) | payload``. The bytes of one append reach the disk in any order, and the next append starts
only once ``fdatasync`` has returned, so a crash can leave at most the *last* entry incomplete: a
frame that is short, or whose checksum fails, with no intact frame after it, is a torn tail. It is
ignored (the state before it is the durable one: nothing acted on the torn step, which answers and
signs only once its entry is synced) and cut off when the log is opened for writing. A frame that
fails its check with an intact one after it is damage at rest, not a crash: ``ConfigError``
naming the file and the byte offset, never a silent step back.

When the log grows past its bound (``CMION_MESH_LEDGER_BOUND`` bytes, ``COMPACT_AT``), or when the
caller asks (a custody key left the state), it is compacted: the caller's current entries written
once to a temporary file, fsynced, renamed over the log, the folder fsynced. A crash during it
leaves the old log or the new one, each whole. Reading at start is one pass over the file.

Threads: a ``Journal`` is its owner's (``ledger.Records``, which holds its lock around every call).
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import threading
import zlib
from collections.abc import Iterable
from pathlib import Path

from cmion_mesh.errors import ConfigError
from cmion_mesh.migration import crash
from cmion_mesh.migration.bounds import env_limit
from cmion_mesh.migration.sections import FSYNCS, fsync_file, fsync_folder

log = logging.getLogger(__name__)

LOG = "ledger.log"
MAGIC = b"CMLJ"
HEADER = struct.Struct("<4sII")
#: Largest entry read: a record, its chain, a custody key and an identity document (``identity.MAX_DOCUMENT``).
MAX_ENTRY = 64 * 1024 * 1024
#: Bytes past which the log is compacted (``CMION_MESH_LEDGER_BOUND`` changes it).
COMPACT_AT = 1024 * 1024
BOUND_ENV = "CMION_MESH_LEDGER_BOUND"


def compact_bound() -> int:
    return int(env_limit(BOUND_ENV, COMPACT_AT, low=1, high=2**40, unit="bytes"))


def frame(payload: bytes) -> bytes:
    size = len(payload).to_bytes(4, "little")
    return HEADER.pack(MAGIC, len(payload), zlib.crc32(payload, zlib.crc32(size))) + payload


def _intact_at(data: bytes | memoryview, offset: int) -> int:
    """The end of the intact frame at ``offset``, or -1."""
    if len(data) - offset < HEADER.size:
        return -1
    magic, length, crc = HEADER.unpack_from(data, offset)
    end = offset + HEADER.size + length
    if magic != MAGIC or length > MAX_ENTRY or end > len(data):
        return -1
    payload = data[offset + HEADER.size:end]
    return end if zlib.crc32(payload, zlib.crc32(length.to_bytes(4, "little"))) == crc else -1


def scan(data: bytes, path: Path) -> tuple[list[tuple[int, bytes]], int]:
    """The payloads of the intact entries of ``data`` (each with its offset) and where they end:
    a torn tail after them is left out; damage with intact entries after it is ``ConfigError``."""
    view = memoryview(data)
    entries: list[tuple[int, bytes]] = []
    offset = 0
    while offset < len(data):
        end = _intact_at(view, offset)
        if end < 0:
            following = data.find(MAGIC, offset + 1)
            while following >= 0:
                if _intact_at(view, following) >= 0:
                    raise ConfigError(f"the migration ledger is damaged at byte {offset} (intact entries follow: "
                                      "not a write cut short by a crash)", path=str(path))
                following = data.find(MAGIC, following + 1)
            break
        entries.append((offset, bytes(view[offset + HEADER.size:end])))
        offset = end
    return entries, offset


class Journal:
    """``ledger.log`` in ``folder``: read once when opened (``entries``), then appended to."""

    def __init__(self, folder: Path, bound: int | None = None) -> None:
        self.path = folder / LOG
        self.bound = compact_bound() if bound is None else bound
        self.appends = 0
        self.compactions = 0
        try:
            with open(self.path, "rb") as f:
                data = f.read()
        except FileNotFoundError:
            data = b""
        except OSError as exc:
            raise ConfigError(f"unreadable migration ledger: {exc.strerror or exc}", path=str(self.path)) from None
        #: The payloads of the entries read when opened, oldest first, each with its byte offset.
        self.entries, self.size = scan(data, self.path)
        self._fd = -1
        if self.size < len(data):
            log.warning("the migration ledger %s ends in an entry cut short by a crash (%d bytes): ignored, the state "
                        "before it is read", self.path, len(data) - self.size)
            self._open()
            os.ftruncate(self._fd, self.size)
            fsync_file(self._fd, "append")

    def _open(self) -> None:
        """Open the log for appending, made at the first write (a daemon that stored nothing leaves no file)."""
        if self._fd >= 0:
            return
        made = not self.path.exists()
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        except OSError as exc:
            raise ConfigError(f"migration ledger cannot be written: {exc.strerror or exc}", path=str(self.path)) from None
        if made:
            fsync_folder(self.path.parent)  # the log's name is durable before anything counts on it

    @property
    def empty(self) -> bool:
        return self.size == 0

    def append(self, payload: bytes, state: str = "", *, sync: bool = True) -> None:
        """One entry, durable when this returns (``sync``: else with the next synced one). ``state``
        names the crash points of this entry (``crash``)."""
        self._open()
        data = frame(payload)
        if state and crash.wanted(f"ledger:torn:{state}"):
            os.write(self._fd, data[:max(1, len(data) // 2)])
            os.fdatasync(self._fd)
            crash.die(f"ledger:torn:{state}")
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view):]
            if sync:
                os.fdatasync(self._fd)
                FSYNCS.count("append")
        except OSError:
            # A full disk, say: the step failed (the caller is told), and what was written of it
            # goes, so that the next entry does not follow a broken one (read as damage at start).
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self.size)
            raise
        self.size += len(data)
        self.appends += 1

    def due(self) -> bool:
        """Whether the log has grown past its bound."""
        return self.size > self.bound

    def rewrite(self, payloads: Iterable[bytes], state: str = "") -> None:
        """Replace the log by ``payloads`` (the current state), atomically."""
        data = b"".join(frame(p) for p in payloads)
        tmp = self.path.with_name(f".{LOG}.{os.getpid()}.{threading.get_ident()}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            fsync_file(fd, "compact")
        finally:
            os.close(fd)
        if state:
            crash.crash_point(f"ledger:compacting:{state}")
        os.replace(tmp, self.path)
        if state:
            crash.crash_point(f"ledger:compacted:{state}")
        fsync_folder(self.path.parent)
        old, self._fd = self._fd, os.open(self.path, os.O_WRONLY | os.O_APPEND, 0o600)
        if old >= 0:
            os.close(old)
        self.size = len(data)
        self.compactions += 1

    def close(self) -> None:
        fd, self._fd = self._fd, -1
        if fd >= 0:
            os.close(fd)
