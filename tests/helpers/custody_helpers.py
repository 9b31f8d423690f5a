"""A companion's holder played by a test: its chain of custody and key, making real prepares and commits."""

from __future__ import annotations

from typing import Any

from cmion_mesh.messages import MigrateCommit, MigratePrepare, Outcome
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.custody import Link
from cmion_mesh.migration.ledger import Record


class Holder:
    """Holds ``companion`` at ``epoch`` as embodiment ``name`` (born there unless a chain is given)."""

    def __init__(self, companion: str, name: str, epoch: int = 1, *, private: bytes | None = None,
                 chain: list[Link] | None = None, document: bytes = b"") -> None:
        self.companion, self.name, self.epoch = companion, name, epoch
        self.private = private or signing.new_key()
        self.chain = chain or [custody.birth(companion, name, self.private, document, epoch)]
        self.seq = 0

    @property
    def identity_key(self) -> bytes:
        return self.chain[0].public_key

    def prepare(self, target: str, document: bytes, attempt: str, *, seq: int | None = None) -> MigratePrepare:
        self.seq = self.seq + 1 if seq is None else seq
        record = Record(self.companion, "active", self.epoch, seq=self.seq - 1, chain=self.chain)
        _, message = handshake.offer(record, attempt=attempt, me=self.name, target=target, document=document, private=self.private)
        return message

    def link(self, prepare: MigratePrepare, answer: Outcome | Any) -> Link:
        value = answer.value if isinstance(answer, Outcome) else answer
        public = signing.decode_public(value["custody_key"])
        return custody.hand_on(self.private, self.companion, self.epoch + 1, prepare.target, public, prepare.attempt,
                               custody.digest(prepare.document))

    def commit(self, prepare: MigratePrepare, answer: Outcome | Any) -> MigrateCommit:
        return MigrateCommit(self.companion, self.epoch, prepare.attempt, self.name, prepare.target,
                             custody.encode_link(self.link(prepare, answer)))
