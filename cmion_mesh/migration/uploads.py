"""A target's uploads (``Uploads``): the sections a sender sends ahead of its prepare, and their
bounds.

For a large identity the source first sends ``have`` (its custody checked as for a prepare, by
``incoming``); the target answers which sections of the manifest it holds already (each read and
checked against its hash: a damaged one is missing, and fetched again), and the others arrive as
raw bytes in ``migrate_sections`` chunks. The target answers each chunk once what it completed is
checked against its hash; the fsync that makes a completed section durable runs on a handshake
thread meanwhile (``settled`` waits for it: the prepare records ``incoming`` only after it), so
that syncing a large section overlaps the prepare's way here and its checks rather than coming
before them; its decoding runs on another one (``values``), for the prepare to find done. The
prepare then finds its sections inside it, in its sender's upload or on this disk
(``sections_for``).

A target holds one upload (``have`` and its sections) per sender, at most ``MAX_UPLOADS``. Every
byte received counts, before it is written, against what one sender may upload ahead of its
prepare (``MAX_UPLOAD``) and against the section folder's bound (``sections.MAX_CACHE``, making
room by evicting the cache); a chunk over either is refused naming its sender. An upload that
never becomes a prepare is deleted when its sender's next ``have`` replaces it, when its prepare is
refused or aborted, and once idle for ``UPLOAD_IDLE`` seconds.

Threads: all of it runs on the loop (request handlers and the timer that expires idle uploads);
each section being received writes its chunks on a thread of its own (``sections.IncomingSection``),
and completed sections are synced on a handshake thread and decoded on another (``Host.spawn``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import Code, MigrateHave, MigratePrepare, MigrateSections
from cmion_mesh.migration import handshake
from cmion_mesh.migration.host import Host
from cmion_mesh.migration.identity import Bytes, Manifest, SectionRef, decode_section, sha256_hex
from cmion_mesh.migration.sections import MAX_CACHE_ENV, IncomingSection
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.timers import Timer

log = logging.getLogger(__name__)

#: Most bytes of sections one sender may have uploaded here ahead of its prepare (``have`` then
#: ``migrate_sections``); ``CMION_MESH_MAX_UPLOAD`` changes it. Half the section cache
#: (``sections.MAX_CACHE``, which bounds all uploads together): no one sender takes all of it.
MAX_UPLOAD = 512 * 1024 * 1024
MAX_UPLOAD_ENV = "CMION_MESH_MAX_UPLOAD"
#: Seconds an upload may wait for its next chunk or its prepare before it expires (its bytes
#: deleted); ``CMION_MESH_UPLOAD_IDLE`` changes it.
UPLOAD_IDLE = 60.0
UPLOAD_IDLE_ENV = "CMION_MESH_UPLOAD_IDLE"
#: Bytes of one upload's sections decoded ahead of its prepare, at most: their values are held
#: beside their bytes until it comes, so a sender that never prepares costs twice the memory of
#: what it sent only up to here (the prepare decodes the rest itself).
DECODE_AHEAD = 64 * 1024 * 1024
#: Uploads held at once (one per sender); a ``have`` beyond them is refused busy.
MAX_UPLOADS = 8
#: Pins of the section store held by the uploads staged here (one owner per sender).
_STAGING = "staging"


@dataclass(eq=False)
class Upload:
    """The sections gathered for one attempt between its ``have`` and its prepare: one per sender,
    that ends with the prepare or expires (``Uploads.end``)."""

    attempt: str
    source: str
    refs: dict[str, SectionRef]  # sha256 -> section, as the manifest offered names them
    data: dict[str, Bytes] = field(default_factory=dict)  # checked bytes: held here already, or received
    partial: dict[str, IncomingSection] = field(default_factory=dict)
    stored: set[str] = field(default_factory=set)  # sections this upload wrote: deleted if no prepare names them
    received: int = 0  # bytes of this upload written to disk (partial sections included)
    settling: list[Future[None]] = field(default_factory=list)  # completed sections being synced
    decoding: list[Future[None]] = field(default_factory=list)  # completed sections being decoded
    decoded: dict[str, Any] = field(default_factory=dict)  # sha256 -> value, decoded ahead of the prepare
    ahead: int = 0  # bytes of sections given to be decoded ahead (at most ``DECODE_AHEAD``)
    unsynced: list[str] = field(default_factory=list)  # why some of them could not be (a prepare is refused)
    last: float = field(default_factory=time.monotonic)  # when it last took a chunk (or began)

    def abandon(self) -> None:
        for incoming in self.partial.values():
            incoming.abandon()
        self.partial.clear()


class Uploads:
    """The uploads held here, one per sender, within ``max_upload`` bytes each and ``idle`` seconds
    between chunks (loop)."""

    def __init__(self, host: Host, *, max_upload: int, idle: float) -> None:
        self.host = host
        self.max_upload = max_upload
        self.idle = idle
        self._uploads: dict[str, Upload] = {}  # sender -> sections gathered for its next prepare
        self._timer: Timer | None = None  # expires idle uploads

    def staged(self, attempt: str, source: str) -> Upload | None:
        """``source``'s upload, if it is of ``attempt``."""
        upload = self._uploads.get(source)
        return upload if upload is not None and upload.attempt == attempt else None

    def full(self, source: str) -> str:
        """"" if a ``have`` of ``source`` may begin an upload, else why not (busy)."""
        if source not in self._uploads and len(self._uploads) >= MAX_UPLOADS:
            return (f"busy: {len(self._uploads)} uploads to {self.host.sim.embodiment!r} are in progress, the most it "
                    f"takes at once; {source!r} may try again later")
        return ""

    def begin(self, request: IncomingRequest, msg: MigrateHave, manifest: Manifest) -> None:
        """Answer an accepted ``have``: the sections of ``manifest`` held here already; the upload of
        the others begins, replacing its sender's last (unless they are over a bound: refused)."""
        host = self.host
        upload = Upload(msg.attempt, msg.source, {ref.sha256: ref for ref in manifest.refs})
        store = host.records.sections
        for staged in self._uploads.values():
            _wait(staged)  # what they completed has its name before this one looks for what is here
        found, errors = store.read_many((ref for ref in upload.refs.values() if store.holds(ref)), host.memo.held())
        for error in errors.values():
            log.warning("%s; fetching it again from %s", error, msg.source)
        # What nobody names yet is bounded by the cache, and by what one sender may upload: a larger
        # offer would fill the disk.
        missing = sum(ref.size for ref in upload.refs.values() if ref.sha256 not in found)
        if missing > store.max_cache:
            request.reject(f"the sections of {msg.companion!r} missing at {host.sim.embodiment!r} total {missing} bytes, "
                           f"over its section cache of {store.max_cache} bytes ({MAX_CACHE_ENV})", Code.INVALID)
            return
        if missing > self.max_upload:
            request.reject(f"the sections of {msg.companion!r} that {msg.source!r} would upload to {host.sim.embodiment!r} "
                           f"total {missing} bytes, over the {self.max_upload} one sender may upload ahead of its prepare "
                           f"({MAX_UPLOAD_ENV})", Code.INVALID)
            return
        upload.data = dict(found)
        # One upload per sender: a newer have replaces it (and deletes what it wrote, but what the new one holds).
        replaced = self._uploads.get(msg.source)
        self._uploads[msg.source] = upload
        store.pin(f"{_STAGING}/{msg.source}", upload.refs)
        if replaced is not None:
            self._end(replaced)
        if self._timer is None:
            self._timer = host.sim.call_later(self.idle, self._expire)
        request.accept({"have": sorted(found)})

    def on_sections(self, request: IncomingRequest, msg: MigrateSections) -> None:
        """Chunks of sections; each completed section is checked against its hash and written
        (fsync) before the answer."""
        me = self.host.sim.embodiment
        upload = self.staged(msg.attempt, msg.source)
        if upload is None or msg.target != me:
            request.reject(f"no have of attempt {msg.attempt} from {msg.source!r} at {me!r}: "
                           "sections are sent after it", Code.NOT_FOUND)
            return
        complete: list[str] = []
        settle: list[IncomingSection] = []
        problems: list[str] = []
        refusals: list[str] = []
        store = self.host.records.sections

        def room(size: int) -> str:  # new bytes are counted before they are written
            why = self._room(upload, size)
            if why:
                refusals.append(why)
            return why

        for chunk in msg.chunks:
            ref = upload.refs.get(chunk.sha256)
            if ref is None:
                problems.append(f"section {chunk.sha256} is not in the manifest of attempt {msg.attempt}")
                break
            if chunk.sha256 in upload.data:
                continue
            incoming = upload.partial.get(chunk.sha256)
            if incoming is None:
                incoming = upload.partial[chunk.sha256] = store.receive(ref)
            problem = incoming.add(chunk.offset, chunk.data, room)
            if not problem and incoming.complete:
                del upload.partial[chunk.sha256]
                problem = incoming.finish(settle=False)  # synced below, beside what follows
                if not problem:
                    upload.data[chunk.sha256] = incoming.data
                    upload.stored.add(chunk.sha256)
                    complete.append(chunk.sha256)
                    settle.append(incoming)
            if problem:
                problems.append(problem if refusals else f"section {ref.component!r} of {msg.companion!r}: {problem}")
                break
        if settle:
            upload.settling.append(self._settle(settle))
            ahead = []
            for incoming in settle:
                if upload.ahead + incoming.ref.size <= DECODE_AHEAD:
                    upload.ahead += incoming.ref.size
                    ahead.append(incoming)
            if ahead:
                upload.decoding.append(self._decode(upload, ahead))
        if problems:
            request.reject("; ".join(problems), Code.BUSY if refusals and refusals[-1].startswith("busy") else Code.INVALID)
        else:
            upload.last = time.monotonic()  # only chunks it takes keep an upload alive
            request.accept({"stored": sorted(complete)})
        log.debug("sections of attempt %s: %d stored", msg.attempt, len(complete))

    def _settle(self, sections: list[IncomingSection]) -> Future[None]:
        """Sync ``sections`` (each given its name replaces a damaged file of that name, if any) and
        then the folder, on a handshake thread; the future says when they are durable."""
        done: Future[None] = Future()
        store = self.host.records.sections

        def settle() -> None:
            failed: BaseException | None = None
            for incoming in sections:  # each of them, whatever the others do: settling ends its file and writer
                try:
                    incoming.settle()
                except BaseException as exc:
                    failed = failed or exc
            try:
                if failed is None:
                    store.sync()
            except BaseException as exc:
                failed = exc
            if failed is not None:  # said by ``settled``, to the prepare that needs them
                done.set_exception(failed)
            else:
                done.set_result(None)

        if not self.host.spawn("settle-sections", settle):
            settle()  # stopping: no worker takes jobs any more
        return done

    def _decode(self, upload: Upload, sections: list[IncomingSection]) -> Future[None]:
        """Decode ``sections`` on a handshake thread, beside their fsync and while the prepare is on
        its way: it finds their values (``values``) instead of decoding megabytes on the loop. One
        that is not plain data is left to the prepare, which refuses it saying why."""
        done: Future[None] = Future()

        def decode() -> None:
            try:
                for incoming in sections:
                    try:
                        upload.decoded[incoming.ref.sha256] = decode_section(incoming.ref, incoming.data)
                    except ConfigError:
                        pass
            finally:
                done.set_result(None)

        if not self.host.spawn("decode-sections", decode):
            decode()  # stopping: no worker takes jobs any more
        return done

    def values(self, attempt: str, source: str) -> dict[str, Any]:
        """The values of the sections ``source``'s upload of ``attempt`` completed, by SHA-256 (hex),
        once decoded (waited for)."""
        upload = self.staged(attempt, source)
        if upload is None:
            return {}
        decoding, upload.decoding = upload.decoding, []
        for done in decoding:
            done.result()
        return dict(upload.decoded)

    def settled(self, attempt: str, source: str) -> str:
        """Wait until the sections ``source``'s upload of ``attempt`` completed are durable: "" once
        they are (or there is no such upload), else why not."""
        upload = self.staged(attempt, source)
        if upload is None:
            return ""
        return _wait(upload)

    def sections_for(self, msg: MigratePrepare, carried: dict[str, Bytes]) -> handshake.SectionSource:
        """Where a prepare's sections are: inside it (those used are put in ``carried``), staged since
        its ``have``, or on this disk."""

        def find(refs: Sequence[SectionRef]) -> dict[str, Bytes]:
            inline: dict[str, Bytes] = {sha256_hex(data): data for data in msg.sections}
            upload = self.staged(msg.attempt, msg.source)
            found: dict[str, Bytes] = {}
            for ref in refs:
                data = inline.get(ref.sha256)
                if data is not None:
                    carried[ref.sha256] = data
                elif upload is not None:
                    data = upload.data.get(ref.sha256)
                if data is not None:
                    found[ref.sha256] = data
            store = self.host.records.sections
            read, errors = store.read_many(r for r in refs if r.sha256 not in found and store.holds(r))
            for error in errors.values():
                log.warning("%s; asking %s for it again", error, msg.source)
            found.update(read)
            return found

        return find

    def end(self, source: str, attempt: str | None = None, *, prepared: bool = False) -> None:
        """End ``source``'s upload (of ``attempt``, if given). Unless a record now names them
        (``prepared``), the sections it wrote are deleted: an upload that never became a prepare
        leaves nothing behind, but what another upload holds or a record names."""
        upload = self._uploads.get(source)
        if upload is None or (attempt is not None and upload.attempt != attempt):
            return
        del self._uploads[source]
        self._end(upload, prepared=prepared)

    def close(self) -> None:
        """End every upload (their bytes deleted) and the timer: the component detaches."""
        for source in list(self._uploads):
            self.end(source)
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _end(self, upload: Upload, *, prepared: bool = False) -> None:
        upload.abandon()
        _wait(upload)  # a section still being named would come back after its deletion
        records = self.host.records
        store = records.sections
        if self._uploads.get(upload.source) is None:
            store.unpin(f"{_STAGING}/{upload.source}")
        if upload.stored and not prepared:
            removed = store.discard(upload.stored, records.referenced())
            if removed:
                log.info("upload of attempt %s from %s ended without a prepare: %d bytes of sections deleted",
                         upload.attempt, upload.source, removed)

    def _expire(self) -> None:
        """Loop timer: end the uploads idle for ``idle`` seconds; wake again for the next."""
        self._timer = None
        now = time.monotonic()
        for source, upload in list(self._uploads.items()):
            if now - upload.last >= self.idle:
                log.info("upload of attempt %s from %s idle for %g s: expired", upload.attempt, source, self.idle)
                self.end(source)
        if self._uploads and not self.host.stopping.is_set():
            due = min(u.last for u in self._uploads.values()) + self.idle
            self._timer = self.host.sim.call_later(max(0.0, due - now), self._expire)

    def _room(self, upload: Upload, size: int) -> str:
        """"" if ``size`` more bytes of ``upload`` may be written now, else why not (naming its
        sender): at most ``max_upload`` per sender, and the section folder within its bound."""
        me, records = self.host.sim.embodiment, self.host.records
        store = records.sections
        if upload.received + size > self.max_upload:
            return (f"{upload.source!r} has uploaded {upload.received} bytes of sections to {me!r} for attempt "
                    f"{upload.attempt}; {size} more is over the {self.max_upload} one sender may upload ahead of its "
                    f"prepare ({MAX_UPLOAD_ENV})")
        if not store.make_room(size, records.referenced):
            return (f"busy: the section store of {me!r} is full ({store.size} of {store.max_cache} bytes, "
                    f"{MAX_CACHE_ENV}, held by uploads not yet prepared and by companions here): {size} bytes more "
                    f"from {upload.source!r} are refused; try again later")
        upload.received += size
        return ""


def _wait(upload: Upload) -> str:
    """Wait for the syncs of ``upload``'s completed sections: "" once all are durable, else why not."""
    settling, upload.settling = upload.settling, []
    for done in settling:
        try:
            done.result()
        except OSError as exc:
            upload.unsynced.append(f"a section received could not be stored: {exc.strerror or exc}")
    return "; ".join(upload.unsynced)
