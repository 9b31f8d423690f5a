"""Durable migration records: one per companion on each embodiment, written atomically.

A record (``<companion>.record.json``) says where this embodiment stands with a companion: its
state in the handshake, the attempt it is in, and the chain of custody it knows. The identity
document it holds is stored under its own hash (``<companion>.<sha256>.identity.xml``), so writing
a new document never overwrites the one the current record names: a crash between the two writes
leaves the old pair intact, and start-up removes whatever no record names. The custody private key
of the epoch held here is ``<companion>.key``. A holder frozen by a proven fork of the chain of
custody keeps the evidence in ``<companion>.fork.json`` (``custody.Freeze``) until an operator
resolves it: a restart does not unfreeze it.

A SchemaVersion 2 document is a manifest; the bytes of its sections are in ``sections/``, each
named by its SHA-256 (``sections.SectionStore``: the cache of sections and its bound are there),
written before any document names them.

Every write is: temp file, fsync, rename, fsync the folder. The folder is 0700 and every file 0600
(the documents are the companion's memory). A document is checked against the hash its record
names and the record's seal (signed by the custody key) when it is read: a file edited at rest is
refused with an error naming it, never run.

Threads: ``Records`` is shared by the loop and the handshake threads; its records are under a lock,
and each write is whole before the record that names it is renamed into place.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, InvalidName
from cmion_mesh.migration import custody, signing
from cmion_mesh.migration.custody import Link
from cmion_mesh.migration.identity import MAX_DOCUMENT, Bytes, Identity, Manifest, SectionMemo, read_manifest
from cmion_mesh.migration.sections import SECTIONS, SectionStore, fsync_folder, write_files
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
    #: incoming: when the prepare of ``attempt`` was recorded here (seconds since the epoch); the
    #: bound after which this target drops an undecided attempt counts from it, across restarts.
    since: float = 0.0

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

    def _write_all(self, files: list[tuple[Path, Bytes]], name: str, data: bytes) -> None:
        """``files``, then the record ``name`` (``write_files``)."""
        if files:
            write_files(files, (self.dir / name, data))
        else:
            self._write(name, data)

    def get(self, companion: str) -> Record | None:
        with self._lock:
            return self._cache.get(companion)

    def put(self, record: Record, document: bytes | None = None, sections: Mapping[str, Bytes] | None = None,
            key: bytes | None = None, *, replace: bool = False) -> Record:
        """Write ``record``, and first, together, the ``sections`` it names (with ``replace``, even
        those of a name already here), this embodiment's custody ``key`` and ``document`` (named by
        its hash, sealed with the custody key); then remove the document and key the previous
        record held and this one does not."""
        companion = keys.check_name(record.companion, "companion")
        with self._lock:
            files = self.sections.files(sections, replace=replace) if sections else []
            if key is not None:
                files.append((self.dir / f"{companion}.key", key))
            if document is not None:
                digest = custody.digest(document).hex()
                files.append((self.dir / f"{companion}.{digest}.identity.xml", document))
                private = key if key is not None else self.key(companion)
                seal = custody.sign_seal(private, companion, document) if private else b""
                record = msgspec.structs.replace(record, document=digest, seal=seal)
            if record.state not in HOSTING:
                record = msgspec.structs.replace(record, document="", seal=b"")  # nothing to keep once it is gone
            record = msgspec.structs.replace(record, updated=time.time())
            previous = self._cache.get(companion)
            self._write_all(files, f"{companion}.record.json", msgspec.json.encode(record))
            self._cache[companion] = record
            if previous is not None and previous.document and previous.document != record.document:
                (self.dir / f"{companion}.{previous.document}.identity.xml").unlink(missing_ok=True)
            if record.state not in HOSTING:
                (self.dir / f"{companion}.key").unlink(missing_ok=True)
                (self.dir / f"{companion}.fork.json").unlink(missing_ok=True)  # no copy here to freeze any more
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
        identity = manifest.identity(found)
        if memo is not None:
            for ref in manifest.refs:
                memo.remember(ref.component, found[ref.sha256], ref.sha256, identity.sections.get(ref.component))
        return identity

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

    def freeze(self, companion: str) -> custody.Freeze | None:
        """The evidence of a fork that froze the companion here, if any; ``ConfigError`` naming the
        file if it cannot be read (the companion is then reported damaged, never run)."""
        path = self.dir / f"{keys.check_name(companion, 'companion')}.fork.json"
        try:
            with open(path, "rb") as f:
                raw = f.read(MAX_RECORD * 8 + 1)
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise ConfigError(f"unreadable evidence of a custody fork: {exc.strerror or exc}", path=str(path)) from None
        try:
            freeze = msgspec.json.decode(raw, type=custody.Freeze)
        except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise ConfigError(f"unreadable evidence of a custody fork: {exc}", path=str(path)) from None
        if freeze.companion != companion:
            raise ConfigError(f"the evidence is of companion {freeze.companion!r}, not {companion!r}", path=str(path))
        return freeze

    def put_freeze(self, freeze: custody.Freeze) -> None:
        """Keep the evidence of a fork, durably, before the companion is frozen on it."""
        with self._lock:
            self._write(f"{keys.check_name(freeze.companion, 'companion')}.fork.json", msgspec.json.encode(freeze))

    def thaw(self, companion: str) -> None:
        """Forget the evidence of a fork (an operator resolved it), durably."""
        with self._lock:
            path = self.dir / f"{keys.check_name(companion, 'companion')}.fork.json"
            if path.exists():
                path.unlink()
                fsync_folder(self.dir)

    def put_key(self, companion: str, private: bytes) -> None:
        with self._lock:
            self._write(f"{keys.check_name(companion, 'companion')}.key", private)

    def key(self, companion: str) -> bytes | None:
        path = self.dir / f"{companion}.key"
        try:
            return path.read_bytes()
        except FileNotFoundError:
            return None
