"""Chain of custody: who may hand a companion on, proven by signatures that former hosts cannot forge.

A companion's custody is a chain of **links**. The first (its birth) is self-signed and names the
companion's *identity key*, the one admission lists and pins name. Each later link says "custody of
companion C at epoch e+1 goes to embodiment T, whose custody key is P, with the identity document
of hash D, by attempt A", and is signed by the custody key of epoch e. So:

* Each custody key is fresh: the target makes the key pair when it accepts a prepare, keeps the
  private half on its disk (0600), and only the public half crosses the wire (in its answer). No
  private key ever travels, in plain mode or secure mode, so an eavesdropper learns nothing that
  signs as the companion.
* Only the holder at epoch e can start a migration (its prepare carries an ``Offer`` signed by the
  epoch-e key, checked against the chain's last link) or finish one (the commit carries the new
  link, signed by the same key). A former host kept a key of an older epoch: it can sign nothing
  that extends the chain past the link that took custody away from it, except a *fork*.
* A fork (a second link for an epoch whose link already exists) needs the key of that epoch, so
  only the embodiment that held custody then can make one. Two different links for one epoch,
  both signed by the key the shared link before them names, are therefore a proof (``Fork``)
  that this key's holder **equivocated**: anyone holding the shared prefix can check it, and
  whoever shows it, the evidence names the signer (``Fork.equivocator``).
* A claim is never taken on trust. A custody token in the mesh (``migration``) is a hint to go
  and look: the claimant is asked for its chain and for a signature, by the custody key at the
  chain's head, over the asker's fresh nonce (``ClaimProof``); a claim counts only once its
  chain verifies from the identity key trusted for the companion and ends with the claimant at
  the epoch claimed (``verify_claim``). Two verified chains relate in one way (``compare``): the
  same; one a prefix of the other (its holder is stale: it handed the companion on); or a fork.
* No branch of a fork wins by itself: epochs and names count for nothing, so inflating epochs
  gains an equivocator nothing. Every holder of a branch freezes, durably, until an operator
  keeps one branch and the others stand down (``cmion-mesh custody resolve``, docs/security.md).
  Receivers refuse offers that a verified claim shows stale or forked, and forks they can see in
  their own record; what remains is a receiver that cannot see any live holder (a partition):
  it may accept a fork, which freezes both branches when they meet.
* Nothing is trusted because it was merely offered: a companion's identity key is pinned when a
  chain that starts with it *commits* (or at birth, or by ``--admit NAME=KEY``), never by a
  prepare that was aborted, so a stranger cannot poison the pin.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Literal

import msgspec

from cmion_mesh.migration import signing
from cmion_mesh.migration.signing import SignatureRefused

#: Most links a chain may have (about 200 bytes each): far more migrations than a companion makes
#: in years; the record holding the chain stays small enough to be rewritten at every step.
MAX_LINKS = 10_000

_encoder = msgspec.msgpack.Encoder()


class Link(msgspec.Struct, frozen=True, array_like=True):
    """One step of custody; ``signature`` is over the link encoded with ``signature=b""``."""

    companion: str
    epoch: int
    holder: str
    public_key: bytes
    attempt: str
    document_sha256: bytes
    signature: bytes = b""

    def signed_bytes(self) -> bytes:
        return _encoder.encode(msgspec.structs.replace(self, signature=b""))


class Offer(msgspec.Struct, frozen=True, array_like=True):
    """What the holder signs to start a migration: the prepare's fields that matter."""

    companion: str
    epoch: int
    seq: int
    attempt: str
    source: str
    target: str
    document_sha256: bytes


class Seal(msgspec.Struct, frozen=True, array_like=True):
    """What a holder signs for the document it keeps at rest."""

    companion: str
    document_sha256: bytes


_chain_decoder = msgspec.msgpack.Decoder(list[Link])
_link_decoder = msgspec.msgpack.Decoder(Link)


def digest(document: bytes) -> bytes:
    return signing.sha256(document)


def birth(companion: str, holder: str, private: bytes, document: bytes, epoch: int = 1) -> Link:
    """The first link of a new companion: self-signed, naming its identity key."""
    link = Link(companion, epoch, holder, signing.public_of(private), "", digest(document))
    return msgspec.structs.replace(link, signature=signing.sign(private, link.signed_bytes()))


def hand_on(private: bytes, companion: str, epoch: int, holder: str, public_key: bytes, attempt: str,
            document_sha256: bytes) -> Link:
    """The link giving custody at ``epoch`` to ``holder``, signed by the custody key of ``epoch - 1``."""
    link = Link(companion, epoch, holder, public_key, attempt, document_sha256)
    return msgspec.structs.replace(link, signature=signing.sign(private, link.signed_bytes()))


def sign_offer(private: bytes, offer: Offer) -> bytes:
    return signing.sign(private, _encoder.encode(offer))


def sign_seal(private: bytes, companion: str, document: bytes) -> bytes:
    return signing.sign(private, _encoder.encode(Seal(companion, digest(document))))


def check_seal(public: bytes, signature: bytes, companion: str, document: bytes) -> bool:
    return signing.valid(public, _encoder.encode(Seal(companion, digest(document))), signature)


def encode_chain(chain: Sequence[Link]) -> bytes:
    return _encoder.encode(list(chain))


def decode_chain(data: bytes) -> list[Link]:
    try:
        chain = _chain_decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError, RecursionError) as exc:
        raise SignatureRefused(f"malformed custody chain: {exc}") from None
    return chain


def encode_link(link: Link) -> bytes:
    return _encoder.encode(link)


def decode_link(data: bytes) -> Link:
    try:
        link: Link = _link_decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError, RecursionError) as exc:
        raise SignatureRefused(f"malformed custody link: {exc}") from None
    return link


def identity_key(chain: Sequence[Link]) -> bytes:
    return chain[0].public_key if chain else b""


def verify_chain(chain: Sequence[Link], companion: str, *, identity: bytes | None = None) -> None:
    """Check that ``chain`` is an unbroken chain of custody of ``companion``; ``identity``, when
    given, is the identity key trusted for it. ``SignatureRefused`` says which link fails.

    The links a chain shares with one verified here before (``_Verified``: the same links, from the
    first on) are not checked again: a companion's chain grows by one link a migration and is
    checked at every prepare and every claim check, so checking it whole made each migration cost
    more the older the companion (past ``signing.valid``'s cache, half a second a prepare at 5000
    links)."""
    if not chain:
        raise SignatureRefused(f"no chain of custody for {companion!r}")
    if len(chain) > MAX_LINKS:
        raise SignatureRefused(f"chain of custody of {companion!r} longer than {MAX_LINKS} links")
    first = chain[0]
    if identity is not None and first.public_key != identity:
        raise SignatureRefused(f"{companion!r} is signed by a key other than the one trusted for it")
    known = VERIFIED.known(companion, chain)
    signer = chain[known - 1].public_key if known else first.public_key
    for index in range(known, len(chain)):
        link = chain[index]
        if link.companion != companion:
            raise SignatureRefused(f"custody link {index} is of {link.companion!r}, not {companion!r}")
        if index and link.epoch != chain[index - 1].epoch + 1:
            raise SignatureRefused(f"custody link {index} jumps from epoch {chain[index - 1].epoch} to {link.epoch}")
        if len(link.public_key) != signing.KEY_BYTES:
            raise SignatureRefused(f"custody link {index} (epoch {link.epoch}) names no Ed25519 key")
        if not signing.valid(signer, link.signed_bytes(), link.signature):
            who = "self-signature of the birth link" if index == 0 else f"signature on custody link {index} (epoch {link.epoch})"
            raise SignatureRefused(f"bad {who} of {companion!r}")
        signer = link.public_key
    if known < len(chain):
        VERIFIED.add(companion, chain)


class _Verified:
    """The chain of custody last verified here for each companion (at most ``COMPANIONS`` of them,
    the least recently verified forgotten first). Thread-safe: the loop and the claim checker verify.

    Only the links themselves count: a chain is known up to where it is link for link the same as
    the one kept (compared whole, never by its last link alone: a branch that forked earlier may
    copy a later link of this one). Which key is trusted for a companion is checked apart, at every
    call, as are epochs and names of the links not known."""

    COMPANIONS = 64

    def __init__(self) -> None:
        self._chains: dict[str, tuple[Link, ...]] = {}
        self._lock = threading.Lock()

    def known(self, companion: str, chain: Sequence[Link]) -> int:
        """How many links at the start of ``chain`` were verified here already."""
        with self._lock:
            kept = self._chains.get(companion)
        if kept is None:
            return 0
        n = min(len(kept), len(chain))
        return n if tuple(chain[:n]) == kept[:n] else 0

    def add(self, companion: str, chain: Sequence[Link]) -> None:
        with self._lock:
            self._chains.pop(companion, None)
            self._chains[companion] = tuple(chain)
            while len(self._chains) > self.COMPANIONS:
                del self._chains[next(iter(self._chains))]

    def clear(self) -> None:
        with self._lock:
            self._chains.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._chains)

    def __contains__(self, companion: object) -> bool:
        with self._lock:
            return companion in self._chains


#: The chains verified in this process (``_Verified``).
VERIFIED = _Verified()


def verify_offer(chain: Sequence[Link], offer: Offer, proof: bytes) -> None:
    """The offer must be signed by the custody key at the chain's head, for the head's epoch."""
    head = chain[-1]
    if offer.epoch != head.epoch:
        raise SignatureRefused(f"the offer is for epoch {offer.epoch}, the chain of custody ends at epoch {head.epoch}")
    if head.holder != offer.source:
        raise SignatureRefused(f"{offer.source!r} is not the holder of {offer.companion!r} at epoch {head.epoch} "
                               f"(the chain says {head.holder!r})")
    if not signing.valid(head.public_key, _encoder.encode(offer), proof):
        raise SignatureRefused(f"bad signature on the offer of {offer.companion!r}: not by its holder's custody key")


def check_link(head: Link, link: Link, *, companion: str, attempt: str, holder: str, public_key: bytes,
               document_sha256: bytes) -> None:
    """The commit's link must extend ``head`` by one, to this holder, key, attempt and document."""
    expected = Link(companion, head.epoch + 1, holder, public_key, attempt, document_sha256, link.signature)
    if link != expected:
        for field in ("companion", "epoch", "holder", "public_key", "attempt", "document_sha256"):
            if getattr(link, field) != getattr(expected, field):
                raise SignatureRefused(f"the custody link's {field} is not this handshake's")
    if not signing.valid(head.public_key, link.signed_bytes(), link.signature):
        raise SignatureRefused(f"bad signature on the custody link of {companion!r}: not by its holder's custody key")


class ClaimProof(msgspec.Struct, frozen=True, array_like=True):
    """What a claimant signs, with the custody key at its chain's head, to back its claim to one asker."""

    companion: str
    epoch: int
    claimant: str
    asker: str
    nonce: bytes


def sign_claim(private: bytes, proof: ClaimProof) -> bytes:
    return signing.sign(private, _encoder.encode(proof))


def verify_claim(chain: Sequence[Link], proof: ClaimProof, signature: bytes, *, identity: bytes | None = None) -> None:
    """A claim counts only if ``chain`` verifies (from ``identity``, when given), ends with the
    claimant at the epoch it claims, and the claimant signed the asker's nonce with that link's key:
    a chain alone is public (every prepare carries one), the key at its head is not."""
    verify_chain(chain, proof.companion, identity=identity)
    head = chain[-1]
    if head.holder != proof.claimant:
        raise SignatureRefused(f"{proof.claimant!r} claims {proof.companion!r}, but its chain of custody ends with "
                               f"{head.holder!r}")
    if head.epoch != proof.epoch:
        raise SignatureRefused(f"{proof.claimant!r} claims {proof.companion!r} at epoch {proof.epoch}, but its chain of "
                               f"custody ends at epoch {head.epoch}")
    if not signing.valid(head.public_key, _encoder.encode(proof), signature):
        raise SignatureRefused(f"{proof.claimant!r} did not sign its claim on {proof.companion!r} with the custody key "
                               f"of epoch {head.epoch}")


class Fork(msgspec.Struct, frozen=True):
    """Proof of equivocation: ``first`` and ``second``, two different links for one epoch, both
    signed by the custody key that the last link of ``prefix`` (the chain both branches share)
    names. Its holder, ``equivocator``, signed both. Checked by ``verify_fork``."""

    companion: str
    prefix: list[Link]
    first: Link
    second: Link

    @property
    def epoch(self) -> int:
        return self.first.epoch

    @property
    def equivocator(self) -> str:
        """The embodiment that held the key which signed both links ("" for two births, which the
        identity key itself signed: whoever held it)."""
        return self.prefix[-1].holder if self.prefix else ""

    def describe(self) -> str:
        """One line for people: who signed what."""
        who = repr(self.equivocator) if self.equivocator else "the holder of its identity key"
        return (f"{who} signed two links for epoch {self.epoch} of {self.companion!r}: to {self.first.holder!r} "
                f"(attempt {self.first.attempt[:12] or '-'}) and to {self.second.holder!r} "
                f"(attempt {self.second.attempt[:12] or '-'})")


Relation = Literal["same", "stale", "behind", "fork", "foreign"]


def compare(mine: Sequence[Link], theirs: Sequence[Link]) -> tuple[Relation, Fork | None]:
    """How two verified chains of one companion relate: ``same``; ``stale`` (theirs is a strict
    prefix of mine: its holder handed the companion on); ``behind`` (mine is a strict prefix of
    theirs: I did); ``fork`` (with the proof); ``foreign`` (another identity key: another
    companion of the same name, nothing to compare)."""
    if not mine or not theirs or mine[0].public_key != theirs[0].public_key:
        return "foreign", None
    shared = min(len(mine), len(theirs))
    if list(mine[:shared]) != list(theirs[:shared]):  # compared link by link in C; the loop only finds where
        for index, (a, b) in enumerate(zip(mine, theirs, strict=False)):
            if a != b:
                return "fork", Fork(a.companion, list(mine[:index]), a, b)
    if len(mine) == len(theirs):
        return "same", None
    return ("stale", None) if len(theirs) < len(mine) else ("behind", None)


def verify_fork(fork: Fork, *, identity: bytes | None = None) -> None:
    """Check that ``fork`` proves an equivocation: its prefix verifies, and its two different links
    for the next epoch are both signed by the key the prefix ends with. ``SignatureRefused`` if not."""
    first, second = fork.first, fork.second
    if first == second:
        raise SignatureRefused("the two links of the fork are the same link")
    if fork.prefix:
        verify_chain(fork.prefix, fork.companion, identity=identity)
        signer = fork.prefix[-1].public_key
        epoch = fork.prefix[-1].epoch + 1
    else:
        signer = first.public_key
        epoch = first.epoch
        if identity is not None and signer != identity:
            raise SignatureRefused(f"the births of {fork.companion!r} are not signed by the key trusted for it")
    for link in (first, second):
        if link.companion != fork.companion or link.epoch != epoch:
            raise SignatureRefused(f"a link of the fork is not of {fork.companion!r} at epoch {epoch}")
        if not signing.valid(signer, link.signed_bytes(), link.signature):
            raise SignatureRefused(f"a link of the fork of {fork.companion!r} at epoch {epoch} is not signed by the key "
                                   "of the epoch before")


class Freeze(msgspec.Struct, frozen=True):
    """What a holder keeps of a proven fork, so that it stays frozen across restarts and after the
    other side has gone: the verified chain of each branch's holder (its own among them), from
    which ``compare`` gives each proof again."""

    companion: str
    branches: dict[str, list[Link]]
    found: float = 0.0

    def forks(self, me: str) -> list[tuple[str, Fork]]:
        """The proofs that the other branches fork from ``me``'s (holder, proof)."""
        mine = self.branches.get(me, [])
        found = []
        for holder, chain in sorted(self.branches.items()):
            if holder != me:
                _, fork = compare(mine, chain)
                if fork is not None:
                    found.append((holder, fork))
        return found


def after_fork(chain: Sequence[Link], fork: Fork) -> list[str]:
    """The holders of ``chain`` from the fork's epoch on (its branch), in order; [] if ``chain`` is on
    neither branch of ``fork``."""
    at = len(fork.prefix)
    if len(chain) <= at or chain[at] not in (fork.first, fork.second) or (at and chain[at - 1] != fork.prefix[-1]):
        return []
    return [link.holder for link in chain[at:]]
