"""Large files written once and synced, around the page cache: ``BulkFile``.

A section of a companion's identity (megabytes) is written once, synced at once, and read again
only after a restart or on the companion's next visit. Written through the page cache, each of its
pages is first allocated and filled there, then written out by the fsync: on a machine whose free
memory is slow to take back (a virtual machine that has lent it to its host) that allocation costs
more CPU than all the rest of a migration, and it pushes out pages the daemon will read again.

``BulkFile`` writes the block-aligned middle of every large piece with ``O_DIRECT`` (straight from a
small aligned buffer that is reused, to the device) and the unaligned ends, small pieces and
everything on a file system that refuses ``O_DIRECT`` (tmpfs, some network file systems) through
the page cache as before. Nothing changes about durability: the caller still fsyncs the file (which
then has little or nothing left to write) and its folder.

Threads: a ``BulkFile`` is written from one thread at a time (a section's writer, or the thread
writing a record's files); the pool of aligned buffers is shared, under a lock.
"""

from __future__ import annotations

import errno
import mmap
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from cmion_mesh.migration.identity import Bytes

#: Alignment of ``O_DIRECT`` offsets, lengths and buffers: the page size, a multiple of every
#: logical block size in use.
BLOCK = mmap.PAGESIZE
#: Pieces smaller than this go through the page cache: for them, a direct write's wait for the
#: device costs more than the pages.
DIRECT_MIN = 256 * 1024
#: Bytes of one aligned buffer; a larger piece goes through it in turns.
BOUNCE = 1024 * 1024
#: Aligned buffers kept for reuse (a fresh one costs its pages, the thing avoided); more may be
#: lent at once, and are then let go.
KEEP = 4
_O_DIRECT = getattr(os, "O_DIRECT", 0)

_lock = threading.Lock()
_free: list[mmap.mmap] = []


@contextmanager
def _bounce() -> Iterator[memoryview]:
    with _lock:
        buffer = _free.pop() if _free else None
    if buffer is None:
        buffer = mmap.mmap(-1, BOUNCE)  # anonymous: page-aligned
    view = memoryview(buffer)
    try:
        yield view
    finally:
        view.release()
        with _lock:
            if len(_free) < KEEP:
                _free.append(buffer)
                buffer = None
        if buffer is not None:
            buffer.close()


def kept() -> int:
    """Aligned buffers kept for reuse now (at most ``KEEP``)."""
    with _lock:
        return len(_free)


def _align_up(n: int) -> int:
    return -(-n // BLOCK) * BLOCK


class BulkFile:
    """A new file at ``path`` (created, or emptied), written in pieces at any offsets (``write``),
    then synced by the caller (``fd``) and closed (``close``, idempotent). ``direct``: whether to try
    ``O_DIRECT`` at all. ``direct_bytes`` counts the bytes that went around the page cache."""

    def __init__(self, path: os.PathLike[str] | str, *, mode: int = 0o600, direct: bool = True) -> None:
        self.fd: int | None = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        self._direct: int | None = None
        self.direct_bytes = 0
        if direct and _O_DIRECT:
            try:
                self._direct = os.open(path, os.O_WRONLY | _O_DIRECT)
            except OSError:
                self._direct = None  # this file system does not take O_DIRECT: the page cache it is

    def __enter__(self) -> BulkFile:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def write(self, offset: int, data: Bytes) -> None:
        """All of ``data`` at ``offset``."""
        view = memoryview(data).cast("B")
        if self._direct is not None and len(view) >= DIRECT_MIN:
            start, end = _align_up(offset), (offset + len(view)) // BLOCK * BLOCK
            if end - start >= DIRECT_MIN:
                self._buffered(offset, view[:start - offset])
                done = self._write_direct(start, view[start - offset:end - offset])
                self._buffered(start + done, view[start - offset + done:])
                return
        self._buffered(offset, view)

    def _buffered(self, offset: int, view: memoryview) -> None:
        assert self.fd is not None
        while view:
            n = os.pwrite(self.fd, view, offset)
            view, offset = view[n:], offset + n

    def _write_direct(self, offset: int, view: memoryview) -> int:
        """Write the aligned ``view`` at the aligned ``offset`` with ``O_DIRECT``; return how many bytes
        went (all, or fewer if the file system refused: the caller writes the rest buffered)."""
        assert self._direct is not None
        done = 0
        with _bounce() as bounce:
            while done < len(view):
                n = min(BOUNCE, len(view) - done)
                bounce[:n] = view[done:done + n]
                try:
                    written = os.pwrite(self._direct, bounce[:n], offset + done)
                except OSError as exc:
                    if exc.errno != errno.EINVAL:
                        raise
                    self._stop_direct()  # refused after all (alignment this device wants): buffered from here
                    break
                if written <= 0 or written % BLOCK:
                    self._stop_direct()  # a short, unaligned write: let the page cache take the rest
                    done += max(0, written)
                    break
                done += written
        self.direct_bytes += done
        return done

    def _stop_direct(self) -> None:
        fd, self._direct = self._direct, None
        if fd is not None:
            os.close(fd)

    def close(self) -> None:
        self._stop_direct()
        fd, self.fd = self.fd, None
        if fd is not None:
            os.close(fd)
