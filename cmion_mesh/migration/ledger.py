"""Durable migration records: one per companion on each embodiment, each step one append to the ledger.

A record says where this embodiment stands with a companion: its state in the handshake, the
attempt it is in, and the chain of custody it knows. Records live in the ledger of the state
folder (``journal.Journal``, ``ledger.log``): every ``put`` is one entry appended and one
``fdatasync``, carrying the record and, when they change, the identity document it names (by
its hash) and the custody private key of the epoch held here. Of the record's chain of custody
an entry carries only the links that the companion's entry before it lacks (``Entry.chain_kept``):
so an entry's size, and a step's cost, do not grow with the companion's age. Reading the log at start replays
its entries in order (one pass); a torn last entry is ignored. The log is compacted (the current
entry of every companion rewritten once, atomically) when it grows past its bound, and at once
when a custody key leaves the state (a companion released or dropped here): a former host's key
is then gone from the disk, not only from the latest entry.

Records written before the ledger (``<companion>.record.json``, with the document in
``<companion>.<sha256>.identity.xml`` and the key in ``<companion>.key``) are read at the first
start and written into a new ledger at once (atomically), then removed: migrated once.

A holder frozen by a proven fork of the chain of custody keeps the evidence in
``<companion>.fork.json`` (``custody.Freeze``) until an operator resolves it: a restart does not
unfreeze it. A SchemaVersion 2 document is a manifest; the bytes of its sections are in
``sections/``, each named by its SHA-256 (``sections.SectionStore``: the cache of sections and its
bound are there), written and synced before the entry that names them is appended.

The folder is 0700 and every file 0600 (the documents are the companion's memory). A document is
checked against the hash its record names and the record's seal (signed by the custody key) when
it is read: one altered at rest is refused with an error naming the file, never run.

Threads: ``Records`` is shared by the loop and the handshake threads; its records and the ledger
are under a lock, and the sections an entry names are on disk before it is appended.
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
from cmion_mesh.migration.journal import LOG, Journal, scan
from cmion_mesh.migration.sections import FSYNCS, SECTIONS, SectionStore, fsync_folder, write_files
from cmion_mesh.statedir import left_by_a_crash, write_atomic

log = logging.getLogger(__name__)

State = Literal["active", "prepared", "handed", "released", "incoming", "dropped"]
#: States in which this embodiment holds the companion (running it, or in a handshake about it).
HOSTING: frozenset[str] = frozenset({"active", "prepared", "handed", "incoming"})
#: Largest record file read: a record carries its chain of custody (about 300 bytes a link in JSON).
MAX_RECORD = 4 * 1024 * 1024
#: Records of companions only refused or dropped here, kept to refuse replays; the oldest go beyond this.
MAX_STRANGERS = 64
#: Sections of one step together at most this many bytes travel inside its ledger entry (one
#: append makes them durable) rather than each in a synced file of its own.
INLINE_SECTIONS = 256 * 1024
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


class Entry(msgspec.Struct, frozen=True, omit_defaults=True):
    """One entry of the ledger: ``record`` (None: the companion forgotten here), and the identity
    document and custody key when this step brings new ones."""

    companion: str
    record: Record | None = None
    document: bytes | None = None
    key: bytes | None = None
    #: small sections the document names (sha256 -> bytes), durable in this entry: their files are
    #: written without fsync, synced before a compaction drops them, rewritten at start if lost
    sections: dict[str, bytes] | None = None
    #: the record's chain of custody is the first ``chain_kept`` links of the one in the companion's
    #: entry before this one, then ``record.chain``. A chain gains a link a migration and is the
    #: same at most steps: written whole at every step, each entry grew with the companion's age.
    #: Compaction writes chains whole (0).
    chain_kept: int = 0


def whole(entry: Entry, before: Record | None, where: str) -> Entry:
    """``entry`` as read from a log, its record's chain whole: the links it keeps of ``before``'s
    (the companion's record as the entries before it left it), then its own. ``where`` names the
    entry in the ``ConfigError`` of one that keeps more links than ``before`` has."""
    if not entry.chain_kept or entry.record is None:
        return entry
    if before is None or len(before.chain) < entry.chain_kept:
        raise ConfigError(f"the entry of {entry.companion!r} keeps {entry.chain_kept} links of a chain of custody the "
                          f"entries before it do not hold ({len(before.chain) if before else 0} links)", path=where)
    chain = [*before.chain[:entry.chain_kept], *entry.record.chain]
    return msgspec.structs.replace(entry, record=msgspec.structs.replace(entry.record, chain=chain), chain_kept=0)


def _kept(before: Record | None, chain: list[Link]) -> int:
    """How many links at the start of ``chain`` an entry may keep of ``before``'s chain (written
    before it): all of that chain when ``chain`` begins with it, link for link, else none."""
    if before is None or not before.chain or len(before.chain) > len(chain):
        return 0
    if before.chain is chain:
        return len(chain)
    n = len(before.chain)
    return n if chain[:n] == before.chain else 0


class Records:
    """Durable records, identity documents and custody keys in one directory (its ledger)."""

    def __init__(self, directory: str | os.PathLike[str], *, max_cache: int | None = None,
                 bound: int | None = None) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(self.dir, 0o700)
        self._lock = threading.RLock()
        self._cache: dict[str, Record] = {}
        self._documents: dict[str, bytes] = {}  # companion -> the document its record names
        self._keys: dict[str, bytes] = {}  # companion -> this embodiment's custody private key
        #: companion -> the file its document was migrated from: kept, and named by errors, until replaced
        self._origin: dict[str, Path] = {}
        #: companion -> sections durable only in the ledger so far (their files are not synced)
        self._unsynced: dict[str, dict[str, bytes]] = {}
        self._manifests: dict[str, frozenset[str]] = {}  # document sha256 -> the sections it names
        self.sections = SectionStore(self.dir / SECTIONS, max_cache)
        self.journal = Journal(self.dir, bound)
        self.path = self.journal.path
        for offset, payload in self.journal.entries:
            entry = self._decode(payload, offset)
            self._replay(whole(entry, self._cache.get(entry.companion), f"{self.path} (entry at byte {offset})"))
        self.journal.entries = []
        self._restore_sections()
        legacy = sorted(self.dir.glob("*.record.json"))
        if legacy and self.journal.empty:
            self._migrate(legacy)
        elif legacy:
            log.info("removing %d record files of %s: the ledger holds them", len(legacy), self.dir)
            for path in legacy:
                path.unlink(missing_ok=True)
        self._sweep()

    def _decode(self, payload: bytes, offset: int) -> Entry:
        where = f"{self.path} (entry at byte {offset})"
        try:
            entry = msgspec.msgpack.decode(payload, type=Entry)
        except (msgspec.DecodeError, RecursionError) as exc:
            raise ConfigError(f"unreadable migration ledger entry: {exc}", path=where) from None
        try:
            keys.check_name(entry.companion, "companion")
        except InvalidName as exc:
            raise ConfigError(f"unusable migration ledger entry: {exc}", path=where) from None
        if entry.record is not None and entry.record.companion != entry.companion:
            raise ConfigError(f"the entry of {entry.companion!r} holds a record of {entry.record.companion!r}", path=where)
        if entry.record is not None and entry.record.epoch < 0:
            raise ConfigError(f"unusable migration record: negative epoch {entry.record.epoch}", path=where)
        if entry.chain_kept < 0 or (entry.chain_kept and entry.record is None):
            raise ConfigError(f"unusable migration ledger entry: it keeps {entry.chain_kept} links of a chain", path=where)
        return entry

    def _replay(self, entry: Entry) -> None:
        """``entry`` into the records here (its chain whole: ``whole``)."""
        companion, record = entry.companion, entry.record
        if record is None:
            for held in (self._cache, self._documents, self._keys, self._unsynced):
                held.pop(companion, None)
            return
        self._cache[companion] = record
        if entry.sections:
            self._unsynced.setdefault(companion, {}).update(entry.sections)
        if entry.document is not None:
            self._documents[companion] = entry.document
        if entry.key is not None:
            self._keys[companion] = entry.key
        if record.state not in HOSTING or not record.document:
            self._documents.pop(companion, None)
        if record.state not in HOSTING:
            self._keys.pop(companion, None)
            self._unsynced.pop(companion, None)  # a cache from now on: nothing to keep durable

    def _restore_sections(self) -> None:
        """At start: the sections held only by the ledger, written again where their file is missing or
        of another size (what a power cut leaves of an unsynced write), durably this time. A file of
        the right size whose bytes are not its own is left as it is: altered at rest, it is reported
        (``damaged``), never quietly repaired."""
        lost: dict[str, bytes] = {}
        for sections in self._unsynced.values():
            for digest, data in sections.items():
                try:
                    intact = self.sections.path(digest).stat().st_size == len(data)
                except OSError:
                    intact = False
                if not intact:
                    lost[digest] = data
        if lost:
            log.warning("rewriting %d section(s) of %s from its ledger (their files were lost)", len(lost), self.dir)
            self.sections.write(lost, replace=True)
        self.sections.sync_files(d for sections in self._unsynced.values() for d in sections)
        self._unsynced.clear()

    def _current(self) -> list[bytes]:
        """The state now, one entry a companion: what compaction writes."""
        return [msgspec.msgpack.encode(Entry(c, r, self._documents.get(c), self._keys.get(c), self._unsynced.get(c)))
                for c, r in self._cache.items()]

    def _migrate(self, paths: list[Path]) -> None:
        """Records of the files written before the ledger: read, written into the ledger at once, removed."""
        for path in paths:
            companion, record = self._load(path)
            self._cache[companion] = record
            key = self.dir / f"{companion}.key"
            if record.state in HOSTING and key.is_file():
                self._keys[companion] = key.read_bytes()
            document = self.dir / f"{companion}.{record.document}.identity.xml"
            if record.state in HOSTING and record.document:
                self._origin[companion] = document
                if document.is_file():
                    with open(document, "rb") as f:
                        self._documents[companion] = f.read(MAX_DOCUMENT + 1)
        self.journal.rewrite(self._current())
        log.info("migrated %d record files of %s into its ledger", len(paths), self.dir)
        for path in paths:
            path.unlink(missing_ok=True)  # the sweep takes the documents and keys, held in the ledger now

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
        """Remove what a crash or an older version left: temporary files, documents and keys in
        files of their own (the ledger holds the current ones)."""
        for path in self.dir.iterdir():
            name = path.name
            orphan = left_by_a_crash(name) or bool(_DOCUMENT.match(name)) or name.endswith(".key")
            if orphan and path not in self._origin.values() and path.is_file():
                log.info("removing %s, left by an interrupted write", path)
                path.unlink(missing_ok=True)

    def _compact(self, state: str) -> None:
        """Rewrite the ledger as it stands (a former host's key leaves the disk with it). The step
        before is durable already: a compaction that fails is said, and tried again at the next one."""
        try:
            if self._unsynced:
                self.sections.sync_files(d for sections in self._unsynced.values() for d in sections)
                self._unsynced.clear()
            self.journal.rewrite(self._current(), state)
        except OSError as exc:
            log.warning("the migration ledger %s could not be compacted (tried again at the next step): %s", self.path,
                        exc.strerror or exc)

    def close(self) -> None:
        with self._lock:
            self.journal.close()

    def stats(self) -> dict[str, object]:
        """The ledger's counters: entries appended, compactions, its size, and this process's fsyncs by kind."""
        with self._lock:
            return {"appends": self.journal.appends, "compactions": self.journal.compactions, "bytes": self.journal.size,
                    "fsyncs": FSYNCS.snapshot()}

    def get(self, companion: str) -> Record | None:
        # Without the lock: a handshake thread holds it through its append's fdatasync, and the loop
        # reads records at every step (one dict read is atomic; a record is in the cache only once
        # its entry is durable).
        return self._cache.get(companion)

    def put(self, record: Record, document: bytes | None = None, sections: Mapping[str, Bytes] | None = None,
            key: bytes | None = None, *, replace: bool = False) -> Record:
        """Write ``record``: one entry with the record, this embodiment's custody ``key`` and
        ``document`` (named by its hash, sealed with the custody key), and the ``sections`` it names
        that are not here yet (with ``replace``, even those of a name already here): inside the
        entry when they are small (``INLINE_SECTIONS``; their files then written unsynced), else
        each in a synced file before the entry."""
        companion = keys.check_name(record.companion, "companion")
        files = self.sections.files(sections, replace=replace) if sections else []
        inline = record.state in HOSTING and sum(len(data) for _, data in files) <= INLINE_SECTIONS
        if files and not inline:
            write_files(files)  # large: synced files of their own, written before the lock (the loop reads records)
        with self._lock:
            if document is not None:
                digest = custody.digest(document).hex()
                private = key if key is not None else self._keys.get(companion)
                seal = custody.sign_seal(private, companion, document) if private else b""
                record = msgspec.structs.replace(record, document=digest, seal=seal)
            if record.state not in HOSTING:
                record = msgspec.structs.replace(record, document="", seal=b"")  # nothing to keep once it is gone
                document = key = None
            record = msgspec.structs.replace(record, updated=time.time())
            secret_gone = record.state not in HOSTING and companion in self._keys
            carried = {path.name: bytes(data) for path, data in files} if files and inline else None
            entry = Entry(companion, record, document, key, carried)
            kept = _kept(self._cache.get(companion), record.chain)
            written = msgspec.structs.replace(entry, record=msgspec.structs.replace(record, chain=record.chain[kept:]),
                                              chain_kept=kept) if kept else entry
            self.journal.append(msgspec.msgpack.encode(written), record.state)
            if carried:
                write_files(files, durable=False)  # durable in the entry; synced before a compaction drops it
            self._replay(entry)
            origin = self._origin.pop(companion, None) if document is not None or record.state not in HOSTING else None
            if origin is not None:
                origin.unlink(missing_ok=True)  # its bytes are in the ledger, or gone with the companion
            if record.state not in HOSTING:
                (self.dir / f"{companion}.fork.json").unlink(missing_ok=True)  # no copy here to freeze any more
            if record.state == "dropped" and not record.chain:
                self._forget_strangers()
            if secret_gone or self.journal.due():
                self._compact(record.state)
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
            # Not synced: a forgotten stranger coming back after a crash is harmless (it was dropped).
            entry = Entry(record.companion)
            self.journal.append(msgspec.msgpack.encode(entry), sync=False)
            self._replay(entry)

    def all(self) -> list[Record]:
        return list(self._cache.copy().values())  # a copy is one atomic step: no lock (as ``get``)

    def hosting(self) -> Record | None:
        """The companion this embodiment holds (active, or in a handshake), if any."""
        held = [r for r in self._cache.copy().values() if r.state in HOSTING]
        return held[0] if held else None

    def document(self, companion: str) -> bytes | None:
        """The identity document the companion's record names, checked against its hash and seal."""
        record = self.get(companion)
        if record is None or not record.document:
            return None
        with self._lock:
            data = self._documents.get(companion)
            path = self._origin.get(companion, self.path)
        if data is None:
            raise ConfigError(f"the identity document of {companion!r} is missing", path=str(path))
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
        origin = self._origin.get(record.companion)
        return read_manifest(data, name=str(origin) if origin else f"{self.path} ({record.companion}'s identity document)")

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
            write_atomic(self.dir / f"{keys.check_name(freeze.companion, 'companion')}.fork.json", msgspec.json.encode(freeze))
            FSYNCS.count("file")
            FSYNCS.count("folder")

    def thaw(self, companion: str) -> None:
        """Forget the evidence of a fork (an operator resolved it), durably."""
        with self._lock:
            path = self.dir / f"{keys.check_name(companion, 'companion')}.fork.json"
            if path.exists():
                path.unlink()
                fsync_folder(self.dir)

    def key(self, companion: str) -> bytes | None:
        """This embodiment's custody private key for ``companion`` (held while it hosts it)."""
        return self._keys.get(companion)  # no lock, as ``get``


class Contents(msgspec.Struct, frozen=True):
    """What a ledger holds now, by companion: records, identity documents and custody keys."""

    records: dict[str, Record]
    documents: dict[str, bytes]
    keys: dict[str, bytes]


def read_ledger(directory: str | os.PathLike[str]) -> Contents:
    """The ledger in ``directory`` as its log says, read without writing anything (a live daemon's
    folder is its own): for tools and tests. A torn tail is ignored, as at start."""
    path = Path(directory) / LOG
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        data = b""
    contents = Contents({}, {}, {})
    for offset, payload in scan(data, path)[0]:
        entry = msgspec.msgpack.decode(payload, type=Entry)
        entry = whole(entry, contents.records.get(entry.companion), f"{path} (entry at byte {offset})")
        held = (contents.records, contents.documents, contents.keys)
        if entry.record is None or entry.record.state not in HOSTING:
            for kept in held[1:]:
                kept.pop(entry.companion, None)
        if entry.record is None:
            contents.records.pop(entry.companion, None)
            continue
        contents.records[entry.companion] = entry.record
        for kept, value in zip(held[1:], (entry.document, entry.key), strict=True):
            if value is not None and entry.record.state in HOSTING:
                kept[entry.companion] = value
    return contents
