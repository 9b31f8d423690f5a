"""Durable migration records: one per companion on each embodiment, written atomically.

A record (``<companion>.record.json``) says where this embodiment stands with a companion: its
state in the handshake, the attempt it is in, and the chain of custody it knows. The identity
document it holds is stored under its own hash (``<companion>.<sha256>.identity.xml``), so writing
a new document never overwrites the one the current record names: a crash between the two writes
leaves the old pair intact, and start-up removes whatever no record names. The custody private key
of the epoch held here is ``<companion>.key``.

A SchemaVersion 2 document is a manifest; the bytes of its sections are in ``sections/``, each
named by its SHA-256 (``SectionStore``), written before any document names them. Sections no
record names any more stay there, a cache for the companion's next visit (only what is missing
crosses the network then), up to ``MAX_CACHE`` bytes: beyond it, the least recently used of
those nobody names go first.

Every write is: temp file, fsync, rename, fsync the folder. The folder is 0700 and every file 0600
(the documents are the companion's memory). A document is checked against the hash its record
names and the record's seal (signed by the custody key) when it is read: a file edited at rest is
refused with an error naming it, never run.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import time
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Literal

import msgspec

from cmion_mesh import custody, keys, signing
from cmion_mesh.custody import Link
from cmion_mesh.errors import ConfigError, InvalidName
from cmion_mesh.identity import MAX_DOCUMENT, Identity, Manifest, SectionMemo, SectionRef, read_manifest
from cmion_mesh.statedir import left_by_a_crash, write_atomic

log = logging.getLogger(__name__)

State = Literal["active", "prepared", "handed", "released", "incoming", "dropped"]
#: States in which this embodiment holds the companion (running it, or in a handshake about it).
HOSTING: frozenset[str] = frozenset({"active", "prepared", "handed", "incoming"})
#: Largest record file read: a record carries its chain of custody (about 300 bytes a link in JSON).
MAX_RECORD = 4 * 1024 * 1024
#: Records of companions only refused or dropped here, kept to refuse replays; the oldest go beyond this.
MAX_STRANGERS = 64
_DOCUMENT = re.compile(r"^(?P<companion>.+)\.(?P<digest>[0-9a-f]{64})\.identity\.xml$")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
#: Most bytes of sections kept that no record names (the cache for return visits).
MAX_CACHE = 1024 * 1024 * 1024
SECTIONS = "sections"
#: Sections at least this large are read and checked on threads of their own (hashing frees the GIL).
_PARALLEL_READ = 1024 * 1024
Bytes = bytes | bytearray | memoryview


def _fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class SectionStore:
    """Section bytes named by their SHA-256: ``<folder>/<sha256>``, checked against the name on every read.

    Each write is a temporary file, fsync, rename; a batch ends with one fsync of the folder, so
    what ``write`` returns from is on disk. ``pin`` keeps sections of a handshake in flight from
    eviction before a record names them."""

    def __init__(self, folder: Path, max_cache: int | None = None) -> None:
        self.dir = folder
        self.max_cache = MAX_CACHE if max_cache is None else max_cache
        self._lock = threading.Lock()
        self._pins: dict[str, frozenset[str]] = {}
        self._bytes = 0
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
        """Bytes of all sections kept here."""
        return self._bytes

    def holds(self, ref: SectionRef) -> bool:
        """Whether a file of the section's name and size is here (its bytes are checked when read)."""
        try:
            return self.path(ref.sha256).stat().st_size == ref.size
        except OSError:
            return False

    def read(self, ref: SectionRef) -> bytes:
        """The section's bytes, checked against its hash; ``ConfigError`` naming the file and the
        component if it is missing, unreadable or altered."""
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
        if hashlib.sha256(data).hexdigest() != ref.sha256:
            raise ConfigError(f"section {ref.component!r} was altered at rest (its bytes do not hash to its name)",
                              path=str(path))
        try:
            os.utime(path)  # recently used: evicted last
        except OSError:
            pass
        return data

    def read_many(self, refs: Iterable[SectionRef]) -> tuple[dict[str, bytes], dict[str, str]]:
        """The sections of ``refs`` that are here and intact (sha256 -> bytes), and why each other one is not."""
        wanted = list({ref.sha256: ref for ref in refs}.values())
        found: dict[str, bytes] = {}
        errors: dict[str, str] = {}

        def one(ref: SectionRef) -> None:
            try:
                found[ref.sha256] = self.read(ref)
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
        """Store each section (sha256 -> bytes, hashed by the caller) not here yet, or with ``replace``
        every one (bytes that came because the file here is damaged); return those written."""
        written: list[str] = []
        if sections and not self._made:
            self.dir.mkdir(exist_ok=True, mode=0o700)
            _fsync_folder(self.dir.parent)
            self._made = True
        for digest, data in sections.items():
            path = self.path(digest)
            try:
                size = path.stat().st_size
                if size == len(data) and not replace:
                    os.utime(path)
                    continue
                with self._lock:
                    self._bytes -= size
            except FileNotFoundError:
                pass
            tmp = path.with_name(f".{digest}.{os.getpid()}.{threading.get_ident()}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, path)
            written.append(digest)
            with self._lock:
                self._bytes += len(data)
        if written:
            _fsync_folder(self.dir)
        return written

    def pin(self, owner: str, digests: Iterable[str]) -> None:
        with self._lock:
            self._pins[owner] = frozenset(digests)

    def unpin(self, owner: str) -> None:
        with self._lock:
            self._pins.pop(owner, None)

    def evict(self, keep: Iterable[str]) -> list[str]:
        """Beyond ``max_cache``, remove the least recently used sections not in ``keep`` nor pinned."""
        if self._bytes <= self.max_cache:
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
            if total <= self.max_cache:
                break
            (self.dir / name).unlink(missing_ok=True)
            total -= size
            removed.append(name)
        with self._lock:
            self._bytes = total
        if removed:
            log.info("section cache over %d bytes: removed %d unused sections", self.max_cache, len(removed))
        return removed


class Record(msgspec.Struct, frozen=True):
    """The durable state of one companion on one embodiment.

    Attempts are ordered by ``(epoch, seq)``: the holder at an epoch numbers its attempts 1, 2, ...
    """

    companion: str
    state: State
    epoch: int
    attempt: str = ""
    peer: str = ""  # the target (source side) or the source (target side) of ``attempt``
    updated: float = 0.0
    public_key: str = ""  # the companion's identity key (base64): pinned at birth, by admission or at a commit
    seq: int = 0
    chain: list[Link] = []  # the chain of custody known here
    custody_key: str = ""  # incoming: the public custody key made here for ``attempt`` (base64)
    link: Link | None = None  # handed/released: the link this source signed for ``attempt``
    document: str = ""  # sha256 (hex) of the identity document held with this record
    seal: bytes = b""  # the custody key's signature over (companion, document hash)

    @property
    def order(self) -> tuple[int, int]:
        return (self.epoch, self.seq)


class Records:
    """Durable records, identity documents and custody keys in one directory."""

    def __init__(self, directory: str | os.PathLike[str], *, max_cache: int | None = None) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(self.dir, 0o700)
        self._lock = threading.RLock()
        self._cache: dict[str, Record] = {}
        self._manifests: dict[str, frozenset[str]] = {}  # document sha256 -> the sections it names
        self.sections = SectionStore(self.dir / SECTIONS, max_cache)
        for path in sorted(self.dir.glob("*.record.json")):
            companion, record = self._load(path)
            self._cache[companion] = record
        self._sweep()

    @staticmethod
    def _load(path: Path) -> tuple[str, Record]:
        try:
            with open(path, "rb") as f:
                raw = f.read(MAX_RECORD + 1)
        except OSError as exc:
            raise ConfigError(f"unreadable migration record: {exc.strerror or exc}", path=str(path)) from None
        if len(raw) > MAX_RECORD:
            raise ConfigError(f"migration record larger than {MAX_RECORD} bytes", path=str(path))
        try:
            record = msgspec.json.decode(raw, type=Record)
        except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise ConfigError(f"unreadable migration record: {exc}", path=str(path)) from None
        try:
            keys.check_name(record.companion, "companion")
        except InvalidName as exc:
            raise ConfigError(f"unusable migration record: {exc}", path=str(path)) from None
        if path.name != f"{record.companion}.record.json":
            raise ConfigError(f"the record is of companion {record.companion!r}, not of the one its file is named after",
                              path=str(path))
        if record.epoch < 0:
            raise ConfigError(f"unusable migration record: negative epoch {record.epoch}", path=str(path))
        return record.companion, record

    def _sweep(self) -> None:
        """Remove what a crash left: temporary files, and documents and keys no record names."""
        for path in self.dir.iterdir():
            name = path.name
            match = _DOCUMENT.match(name)
            orphan = left_by_a_crash(name)
            if match:
                record = self._cache.get(match["companion"])
                orphan = record is None or record.document != match["digest"]
            elif name.endswith(".key"):
                record = self._cache.get(name[:-4])
                orphan = record is None or record.state not in HOSTING
            if orphan and path.is_file():
                log.info("removing %s, left by an interrupted write", path)
                path.unlink(missing_ok=True)

    def _write(self, name: str, data: bytes) -> None:
        write_atomic(self.dir / name, data)

    def get(self, companion: str) -> Record | None:
        with self._lock:
            return self._cache.get(companion)

    def put(self, record: Record, document: bytes | None = None, sections: Mapping[str, Bytes] | None = None) -> Record:
        """Write ``record`` (and first the ``sections`` it names, then ``document``, named by its hash,
        sealed with this embodiment's custody key); then remove the document and key the previous
        record held and this one does not."""
        companion = keys.check_name(record.companion, "companion")
        if sections:
            self.sections.write(sections)
        with self._lock:
            if document is not None:
                digest = custody.digest(document).hex()
                self._write(f"{companion}.{digest}.identity.xml", document)
                private = self.key(companion)
                seal = custody.sign_seal(private, companion, document) if private else b""
                record = msgspec.structs.replace(record, document=digest, seal=seal)
            if record.state not in HOSTING:
                record = msgspec.structs.replace(record, document="", seal=b"")  # nothing to keep once it is gone
            record = msgspec.structs.replace(record, updated=time.time())
            previous = self._cache.get(companion)
            self._write(f"{companion}.record.json", msgspec.json.encode(record))
            self._cache[companion] = record
            if previous is not None and previous.document and previous.document != record.document:
                (self.dir / f"{companion}.{previous.document}.identity.xml").unlink(missing_ok=True)
            if record.state not in HOSTING:
                (self.dir / f"{companion}.key").unlink(missing_ok=True)
            if record.state == "dropped" and not record.chain:
                self._forget_strangers()
        if self.sections.size > self.sections.max_cache:
            self.sections.evict(self.referenced())
        return record

    def referenced(self) -> set[str]:
        """The sections that the documents of the records here name."""
        names: set[str] = set()
        with self._lock:
            records = list(self._cache.values())
        for record in records:
            if not record.document:
                continue
            digests = self._manifests.get(record.document)
            if digests is None:
                try:
                    manifest = self._manifest(record)
                except ConfigError:
                    continue  # reported by damaged(); nothing of it to keep
                digests = frozenset(ref.sha256 for ref in manifest.refs) if manifest is not None else frozenset()
                self._manifests[record.document] = digests
            names |= digests
        return names

    def _forget_strangers(self) -> None:
        strangers = sorted((r for r in self._cache.values() if r.state == "dropped" and not r.chain and not r.public_key),
                           key=lambda r: r.updated)
        for record in strangers[:max(0, len(strangers) - MAX_STRANGERS)]:
            del self._cache[record.companion]
            (self.dir / f"{record.companion}.record.json").unlink(missing_ok=True)

    def all(self) -> list[Record]:
        with self._lock:
            return list(self._cache.values())

    def hosting(self) -> Record | None:
        """The companion this embodiment holds (active, or in a handshake), if any."""
        with self._lock:
            held = [r for r in self._cache.values() if r.state in HOSTING]
        return held[0] if held else None

    def document(self, companion: str) -> bytes | None:
        """The identity document the companion's record names, checked against its hash and seal."""
        record = self.get(companion)
        if record is None or not record.document:
            return None
        path = self.dir / f"{companion}.{record.document}.identity.xml"
        try:
            with open(path, "rb") as f:
                data = f.read(MAX_DOCUMENT + 1)  # one more than unpack takes, so excess is noticed
        except FileNotFoundError:
            raise ConfigError(f"the identity document of {companion!r} is missing", path=str(path)) from None
        except OSError as exc:
            raise ConfigError(f"unreadable identity document: {exc.strerror or exc}", path=str(path)) from None
        if custody.digest(data).hex() != record.document:
            raise ConfigError(f"the identity document of {companion!r} was altered at rest (its hash is not the one "
                              "its record names)", path=str(path))
        head = record.chain[-1].public_key if record.chain and record.state != "incoming" else None
        if record.state == "incoming" and record.custody_key:
            head = signing.decode_public(record.custody_key)
        if head is not None and not custody.check_seal(head, record.seal, companion, data):
            raise ConfigError(f"the identity document of {companion!r} is not sealed by its custody key "
                              "(altered at rest)", path=str(path))
        return data

    def _manifest(self, record: Record) -> Manifest | None:
        data = self.document(record.companion)
        if data is None:
            return None
        return read_manifest(data, name=str(self.dir / f"{record.companion}.{record.document}.identity.xml"))

    def identity(self, companion: str, memo: SectionMemo | None = None) -> Identity | None:
        """The identity the companion's record names, every byte checked (document: hash and seal;
        sections: hash); ``ConfigError`` naming the file at fault. ``memo`` learns the sections' bytes."""
        record = self.get(companion)
        if record is None:
            return None
        manifest = self._manifest(record)
        if manifest is None:
            return None
        found, errors = self.sections.read_many(manifest.refs)
        if errors:
            raise ConfigError(f"the identity of {companion!r} cannot be read: " + "; ".join(errors.values()))
        if memo is not None:
            for ref in manifest.refs:
                memo.remember(ref.component, found[ref.sha256], ref.sha256)
        return manifest.identity(found)

    def damaged(self) -> dict[str, str]:
        """The companions held here whose stored identity is unusable (document or section altered at
        rest, missing, invalid), each with the error naming the file: they are reported, never run."""
        found: dict[str, str] = {}
        for record in self.all():
            if record.state in HOSTING:
                try:
                    self.identity(record.companion)
                except ConfigError as exc:
                    found[record.companion] = str(exc)
        return found

    def put_key(self, companion: str, private: bytes) -> None:
        with self._lock:
            self._write(f"{keys.check_name(companion, 'companion')}.key", private)

    def key(self, companion: str) -> bytes | None:
        path = self.dir / f"{companion}.key"
        try:
            return path.read_bytes()
        except FileNotFoundError:
            return None
