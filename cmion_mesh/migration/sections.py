"""Section bytes on disk, named by their SHA-256: ``SectionStore`` (``<state>/sections/<sha256>``) and
``IncomingSection`` (one received from a peer in chunks), and ``write_files``, the durable batch write
the records use too.

A SchemaVersion 2 identity document is a manifest; the bytes of its sections are here, each named by
its SHA-256, durable before any document names them (``ledger``: small ones are durable inside the
ledger entry that names them, and their files here written without fsync until a compaction). Sections no record names any more
stay, a cache for the companion's next visit (only what is missing crosses the network then), up to
``MAX_CACHE`` bytes (``CMION_MESH_MAX_CACHE``): beyond it, the least recently used of those nobody
names go first. The bound holds when the folder grows, not only when a record is written: a section
received from a peer is written only if it fits (``SectionStore.make_room``), and its bytes count
from the first chunk on.

Every durable write is: temp file, fsync, rename, fsync the folder (``FSYNCS`` counts them, by
kind, for the benchmark); the bytes of a large one go around the page cache (``bulkio``). The
folder is 0700 and every file 0600.
Every read checks the bytes against the name: a file altered at rest is refused with an error naming
it, never used.

Threads: one store serves the loop (a target checking and receiving sections) and the handshake
threads (a source writing its own copy): its byte counts and pins are under a lock. An
``IncomingSection`` belongs to the thread that receives it (the loop); it writes its chunks on a
thread of its own and hashes them on another: ``finish`` joins the hashing, ``settle`` the
writing, ``abandon`` both.
"""

from __future__ import annotations

import logging
import os
import re
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

from cmion_mesh.errors import ConfigError
from cmion_mesh.migration import signing
from cmion_mesh.migration.bounds import env_limit
from cmion_mesh.migration.bulkio import DIRECT_MIN, BulkFile
from cmion_mesh.migration.identity import Bytes, SectionRef, sha256_hex
from cmion_mesh.statedir import left_by_a_crash

log = logging.getLogger(__name__)

_SHA256 = re.compile(r"^[0-9a-f]{64}$")
#: Most bytes of sections kept that no record names (the cache for return visits, and sections
#: received for a prepare still to come); ``CMION_MESH_MAX_CACHE`` changes it (``cache_bound``).
MAX_CACHE = 1024 * 1024 * 1024
MAX_CACHE_ENV = "CMION_MESH_MAX_CACHE"
#: The folder of sections in a state folder.
SECTIONS = "sections"
#: Sections at least this large are read and checked on threads of their own (hashing frees the GIL).
_PARALLEL_READ = 1024 * 1024
T = TypeVar("T")


def cache_bound() -> int:
    """Most bytes of sections this process keeps that no record names: ``CMION_MESH_MAX_CACHE``, else ``MAX_CACHE``."""
    return int(env_limit(MAX_CACHE_ENV, MAX_CACHE, low=1, high=2**50, unit="bytes"))


class Fsyncs:
    """How many times this process made its migration state durable, by kind: ``append`` (an entry
    of the ledger, ``fdatasync``), ``compact`` (the ledger rewritten), ``file`` (a section or another
    file) and ``folder`` (a folder, so that a name given is durable). Thread-safe; the benchmark
    reads them (``describe``'s ``ledger``) to count the fsyncs of one migration on each side."""

    KINDS = ("append", "compact", "file", "folder")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(self.KINDS, 0)

    def count(self, kind: str, n: int = 1) -> None:
        with self._lock:
            self._counts[kind] += n

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            counts = dict(self._counts)
        counts["total"] = sum(counts.values())
        return counts


#: This process's counts (one daemon per process: its ledger's).
FSYNCS = Fsyncs()


def fsync_file(fd: int, kind: str = "file") -> None:
    os.fsync(fd)
    FSYNCS.count(kind)


def fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        fsync_file(fd, "folder")
    finally:
        os.close(fd)


def _at_once(fn: Callable[[T], object], items: Sequence[T]) -> None:
    """``fn`` on every item, on threads of their own when there are several: fsyncs of several
    files wait for the disk together (the file system commits them as one)."""
    if len(items) <= 1:
        for item in items:
            fn(item)
        return
    with ThreadPoolExecutor(min(4, len(items)), thread_name_prefix="fsync") as pool:
        for _ in pool.map(fn, items):
            pass


def write_files(files: Sequence[tuple[Path, Bytes]], last: tuple[Path, Bytes] | None = None, *,
                durable: bool = True) -> None:
    """Write ``files`` durably, together, and then ``last`` (a record naming them): each through a
    temporary file, fsync, rename; every folder holding one of ``files`` is fsynced before ``last``
    is renamed, so a crash leaves ``last`` old, or new with all it names on disk. The temporary
    names carry the process and thread, as ``statedir.write_atomic``'s do. Not ``durable``: no
    fsync at all (the bytes are durable elsewhere: in the ledger entry that names them)."""
    entries = [*files, *([last] if last is not None else [])]
    tmps = [path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp") for path, _ in entries]

    def write(i: int) -> None:
        data = entries[i][1]
        with BulkFile(tmps[i], direct=len(data) >= DIRECT_MIN) as file:  # a large section around the page cache
            file.write(0, data)
            if durable:
                assert file.fd is not None
                fsync_file(file.fd)

    try:
        if durable:
            _at_once(write, range(len(entries)))
        else:
            for i in range(len(entries)):
                write(i)
        for tmp, (path, _) in zip(tmps, files, strict=False):
            os.replace(tmp, path)
        if durable:
            _at_once(fsync_folder, sorted({path.parent for path, _ in files}))
        if last is not None:
            os.replace(tmps[-1], last[0])
            fsync_folder(last[0].parent)
    except BaseException:
        for tmp in tmps:
            tmp.unlink(missing_ok=True)
        raise


class SectionStore:
    """Section bytes named by their SHA-256: ``<folder>/<sha256>``, checked against the name on every read.

    Each write is a temporary file, fsync, rename; a batch ends with one fsync of the folder, so
    what ``write`` returns from is on disk. ``pin`` keeps sections of a handshake in flight from
    eviction before a record names them. ``size`` counts the bytes of sections being received
    (``IncomingSection``) as they are written, so that ``make_room`` bounds the folder while it grows."""

    def __init__(self, folder: Path, max_cache: int | None = None) -> None:
        self.dir = folder
        self.max_cache = cache_bound() if max_cache is None else max_cache
        self._lock = threading.Lock()
        self._pins: dict[str, frozenset[str]] = {}
        self._bytes = 0  # sections stored under their name
        self._receiving = 0  # bytes written so far of sections being received (temporary files)
        self._made = self.dir.is_dir()  # made at the first write: a state folder that never held a section has none
        for path in self.dir.iterdir() if self._made else ():
            if _SHA256.match(path.name) and path.is_file():
                self._bytes += path.stat().st_size
            elif path.is_file() and (left_by_a_crash(path.name) or not path.name.startswith(".")):
                log.info("removing %s, left by an interrupted write", path)
                path.unlink(missing_ok=True)

    def path(self, digest: str) -> Path:
        if not _SHA256.match(digest):
            raise ConfigError(f"{digest[:80]!r} is not a SHA-256 in hex", path=str(self.dir))
        return self.dir / digest

    @property
    def size(self) -> int:
        """Bytes of all sections kept here, and of those being received."""
        return self._bytes + self._receiving

    def holds(self, ref: SectionRef) -> bool:
        """Whether a file of the section's name and size is here (its bytes are checked when read)."""
        try:
            return self.path(ref.sha256).stat().st_size == ref.size
        except OSError:
            return False

    def read(self, ref: SectionRef, known: Bytes | None = None) -> Bytes:
        """The section's bytes, checked against its hash; ``ConfigError`` naming the file and the
        component if it is missing, unreadable or altered. ``known``: bytes already checked against
        that hash (kept in memory since): the file is compared with them, cheaper than hashing it."""
        path = self.path(ref.sha256)
        try:
            with open(path, "rb") as f:
                data = f.read(ref.size + 1)
        except FileNotFoundError:
            raise ConfigError(f"section {ref.component!r} ({ref.size} bytes) is missing", path=str(path)) from None
        except OSError as exc:
            raise ConfigError(f"section {ref.component!r}: unreadable: {exc.strerror or exc}", path=str(path)) from None
        if len(data) != ref.size:
            raise ConfigError(f"section {ref.component!r} was altered at rest: {len(data)} bytes, its manifest says "
                              f"{ref.size}", path=str(path))
        same = data == known if known is not None and len(known) == ref.size else None
        if not (same if same is not None else sha256_hex(data) == ref.sha256):
            raise ConfigError(f"section {ref.component!r} was altered at rest (its bytes do not hash to its name)",
                              path=str(path))
        try:
            os.utime(path)  # recently used: evicted last
        except OSError:
            pass
        return data

    def read_many(self, refs: Iterable[SectionRef], known: Mapping[str, Bytes] | None = None,
                  ) -> tuple[dict[str, Bytes], dict[str, str]]:
        """The sections of ``refs`` that are here and intact (sha256 -> bytes), and why each other one
        is not; ``known`` as for ``read`` (sha256 -> bytes)."""
        wanted = list({ref.sha256: ref for ref in refs}.values())
        found: dict[str, Bytes] = {}
        errors: dict[str, str] = {}

        def one(ref: SectionRef) -> None:
            try:
                found[ref.sha256] = self.read(ref, known.get(ref.sha256) if known else None)
            except ConfigError as exc:
                errors[ref.sha256] = str(exc)

        large = [ref for ref in wanted if ref.size >= _PARALLEL_READ]
        if len(large) > 1:
            with ThreadPoolExecutor(min(4, len(large)), thread_name_prefix="section-read") as pool:
                list(pool.map(one, large))
        else:
            for ref in large:
                one(ref)
        for ref in wanted:
            if ref.size < _PARALLEL_READ:
                one(ref)
        return found, errors

    def write(self, sections: Mapping[str, Bytes], *, replace: bool = False) -> list[str]:
        """Store each section (sha256 -> bytes, hashed by the caller) not here yet; with ``replace``,
        also those whose file here holds other bytes (it is damaged: they came for that). Return
        those written."""
        files = self.files(sections, replace=replace)
        write_files(files)
        return [path.name for path, _ in files]

    def sync_files(self, digests: Iterable[str]) -> None:
        """Make sections written without fsync (``write_files(durable=False)``) durable: each file,
        then the folder. One no longer here is skipped (evicted or replaced meanwhile)."""
        synced = 0
        for digest in digests:
            try:
                fd = os.open(self.path(digest), os.O_RDONLY)
            except FileNotFoundError:
                continue
            try:
                fsync_file(fd)
            finally:
                os.close(fd)
            synced += 1
        if synced:
            fsync_folder(self.dir)

    def files(self, sections: Mapping[str, Bytes], *, replace: bool = False) -> list[tuple[Path, Bytes]]:
        """The (path, bytes) of the sections to write for ``write`` (those not here yet), counted as
        stored: for a caller that writes them with other files (``write_files``)."""
        if sections:
            self._make()
        files: list[tuple[Path, Bytes]] = []
        for digest, data in sections.items():
            path = self.path(digest)
            try:
                size = path.stat().st_size
                if size == len(data) and (not replace or self._holds_bytes(path, data)):
                    os.utime(path)  # recently used: evicted last
                    continue
            except FileNotFoundError:
                size = 0
            files.append((path, data))
            self._added(len(data) - size)
        return files

    @staticmethod
    def _holds_bytes(path: Path, data: Bytes) -> bool:
        try:
            with open(path, "rb") as f:
                return f.read(len(data) + 1) == data
        except OSError:
            return False

    def receive(self, ref: SectionRef) -> IncomingSection:
        """A section to be received in chunks (``IncomingSection``)."""
        self._make()
        return IncomingSection(self, ref)

    def _make(self) -> None:
        if not self._made:
            self.dir.mkdir(exist_ok=True, mode=0o700)
            fsync_folder(self.dir.parent)
            self._made = True

    def _added(self, size: int, receiving: int = 0) -> None:
        with self._lock:
            self._bytes += size
            self._receiving += receiving

    def sync(self) -> None:
        """Make the names given to sections by ``IncomingSection.finish`` durable."""
        fsync_folder(self.dir)

    def pin(self, owner: str, digests: Iterable[str]) -> None:
        with self._lock:
            self._pins[owner] = frozenset(digests)

    def unpin(self, owner: str) -> None:
        with self._lock:
            self._pins.pop(owner, None)

    def pinned(self) -> frozenset[str]:
        with self._lock:
            return frozenset().union(*self._pins.values())

    def make_room(self, size: int, keep: Callable[[], Iterable[str]]) -> bool:
        """Whether ``size`` more bytes fit within ``max_cache``, after removing as many of the least
        recently used sections as needed that are neither in ``keep()`` (called only then) nor pinned."""
        if self.size + size <= self.max_cache:
            return True
        self.evict(keep(), room=size)
        return self.size + size <= self.max_cache

    def discard(self, digests: Iterable[str], keep: Iterable[str]) -> int:
        """Remove the sections ``digests`` but those in ``keep`` or pinned (received for a prepare that
        never came); the bytes removed."""
        spared = set(keep) | self.pinned()
        removed = 0
        for digest in set(digests) - spared:
            path = self.path(digest)
            try:
                size = path.stat().st_size
                path.unlink()
            except FileNotFoundError:
                continue
            removed += size
        if removed:
            self._added(-removed)
        return removed

    def evict(self, keep: Iterable[str], room: int = 0) -> list[str]:
        """Beyond ``max_cache`` (less ``room`` bytes about to be written), remove the least recently
        used sections not in ``keep`` nor pinned."""
        if self.size + room <= self.max_cache:
            return []
        with self._lock:
            kept = set(keep).union(*self._pins.values())
        entries = []
        total = 0
        for path in self.dir.iterdir() if self._made else ():
            if _SHA256.match(path.name):
                try:
                    st = path.stat()
                except FileNotFoundError:
                    continue
                total += st.st_size
                if path.name not in kept:
                    entries.append((st.st_mtime_ns, path.name, st.st_size))
        removed: list[str] = []
        for _mtime, name, size in sorted(entries):
            if total + self._receiving + room <= self.max_cache:
                break
            (self.dir / name).unlink(missing_ok=True)
            total -= size
            removed.append(name)
        with self._lock:
            self._bytes = total
        if removed:
            log.info("section cache over %d bytes: removed %d unused sections", self.max_cache - room, len(removed))
        return removed


class IncomingSection:
    """A section received in chunks, in any order: each is written at its offset of a temporary
    file (on a thread of its own, while another hashes and puts together the bytes as far as they
    are contiguous: once complete, the section is at hand without one more copy of it), and
    the kernel is asked to start writing it out, so that the fsync at the end has little left to
    do. ``add`` waits for neither: the caller (the loop) takes the next chunk, or other requests,
    meanwhile; a write that failed is said at the next ``add`` or when the section is settled.
    ``finish`` waits for the hashing and checks the hash; ``settle`` waits for the writes, fsyncs
    and gives the file its name; the bytes stay at hand in ``data``. ``finish`` or ``abandon`` ends
    it (its file and threads); a caller that makes it durable later (on a thread of its own)
    finishes with ``settle=False`` and then calls ``settle``, always."""

    def __init__(self, store: SectionStore, ref: SectionRef) -> None:
        self.store = store
        self.ref = ref
        self.data: Bytes = b""  # the whole section, once finished
        self._whole = bytearray()  # the contiguous prefix received, hashed: ``data`` once complete
        self._hasher = signing.Sha256()
        self._received = 0  # bytes received as a contiguous prefix (handed to the hashing thread)
        self._ahead: dict[int, Bytes] = {}  # offset -> chunk received beyond that prefix
        self._hashing: ThreadPoolExecutor | None = None  # hashes and puts together the prefix, in order
        self._hashes: list[Future[None]] = []
        self._path = store.path(ref.sha256)
        self._tmp = self._path.with_name(f".{ref.sha256}.{os.getpid()}.{threading.get_ident()}.tmp")
        self._file: BulkFile | None = BulkFile(self._tmp)
        self._writer: ThreadPoolExecutor | None = None
        self._writes: list[Future[None]] = []  # chunk writes under way, waited for by ``finish``
        self._written = 0  # bytes in the temporary file, counted in the store's size

    @property
    def written(self) -> int:
        return self._written

    @property
    def complete(self) -> bool:
        return self._received == self.ref.size

    def add(self, offset: int, data: Bytes, room: Callable[[int], str] | None = None) -> str:
        """Take a chunk; "" or why it does not fit. A chunk received before (sent again when its
        answer was lost) is ignored: the hash of the whole says whether the bytes are right.
        ``room(n)``: "" if ``n`` new bytes may be written, else why not (asked only for new bytes)."""
        end = offset + len(data)
        if end > self.ref.size:
            return f"chunk of {len(data)} bytes at offset {offset} runs past the section's {self.ref.size} bytes"
        if not data or end <= self._received or (offset in self._ahead and len(self._ahead[offset]) == len(data)):
            return ""
        if offset < self._received or any(offset < o + len(c) and o < end for o, c in self._ahead.items()):
            return f"chunk at offset {offset} ({len(data)} bytes) overlaps bytes received before"
        refused = room(len(data)) if room is not None else ""
        if refused:
            return refused
        file = self._file
        assert file is not None
        self._written += len(data)
        self.store._added(0, receiving=len(data))
        if self._writer is None:
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="section-write")
        failed = next((w for w in self._writes if w.done() and w.exception() is not None), None)
        if failed is not None:
            failed.result()  # a chunk before this one could not be written: say so now
        self._writes.append(self._writer.submit(self._write_out, file, offset, data))
        self._ahead[offset] = data
        while self._received in self._ahead:
            chunk = self._ahead.pop(self._received)
            if self._hashing is None:
                self._hashing = ThreadPoolExecutor(1, thread_name_prefix="section-hash")
            # Megabytes hashed and copied off the caller's thread: the loop answers this chunk (and
            # takes the next) meanwhile; ``finish`` waits for it.
            self._hashes.append(self._hashing.submit(self._take, chunk))
            self._received += len(chunk)
        return ""

    def _take(self, chunk: Bytes) -> None:
        self._hasher.update(chunk)
        self._whole += chunk

    def _write_out(self, file: BulkFile, offset: int, data: Bytes) -> None:
        file.write(offset, data)
        assert file.fd is not None
        try:  # what went through the page cache: start writing it out now
            os.posix_fadvise(file.fd, offset, len(data), os.POSIX_FADV_DONTNEED)
        except (AttributeError, OSError):
            pass

    def finish(self, *, settle: bool = True) -> str:
        """Once complete: "" with the bytes checked and at hand (``data``) and, unless ``settle`` is
        False, the section stored under its name (``settle``: the writes, fsync; the folder is the
        caller's to fsync); or why not (its bytes hash to something else: nothing is kept)."""
        self._stop_hashing()
        hashes, self._hashes = self._hashes, []
        try:
            for taken in hashes:
                taken.result()
        except BaseException:
            self.abandon()  # its file and writer go with it
            raise
        digest = self._hasher.hexdigest()
        if digest != self.ref.sha256:
            self.abandon()
            return f"the {self.ref.size} bytes received hash to {digest}, not {self.ref.sha256}"
        self.data, self._whole = self._whole, bytearray()
        if settle:
            self.settle()
        return ""

    def settle(self) -> None:
        """After ``finish(settle=False)``, on any thread: wait for the writes still going to the
        device (a caller that settles elsewhere answers without waiting for them), fsync the
        section and give it its name (the folder is the caller's to fsync). ``OSError`` if it
        cannot: nothing of it is kept."""
        file, self._file = self._file, None
        assert file is not None and file.fd is not None
        try:
            self._stop_writer()
            writes, self._writes = self._writes, []
            for write in writes:
                write.result()  # every chunk on its way to the disk before the fsync that makes it durable
            fsync_file(file.fd)
            try:
                replaced = self._path.stat().st_size
            except FileNotFoundError:
                replaced = 0
            os.replace(self._tmp, self._path)
        except OSError:
            self._tmp.unlink(missing_ok=True)
            written, self._written = self._written, 0
            self.store._added(0, receiving=-written)
            raise
        finally:
            file.close()
        written, self._written = self._written, 0
        self.store._added(self.ref.size - replaced, receiving=-written)

    def _stop_hashing(self) -> None:
        hashing, self._hashing = self._hashing, None
        if hashing is not None:
            hashing.shutdown(wait=True)

    def _stop_writer(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.shutdown(wait=True)

    def abandon(self) -> None:
        self._stop_hashing()
        self._hashes = []
        self._stop_writer()
        self._writes = []  # nothing of it is kept: a write that failed changes nothing
        self._whole = bytearray()
        self._ahead.clear()
        file, self._file = self._file, None
        if file is not None:
            file.close()
            self._tmp.unlink(missing_ok=True)
        written, self._written = self._written, 0
        self.store._added(0, receiving=-written)
