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
  only the embodiment that held custody then can make one. Receivers refuse forks they can see:
  a prepare whose chain disagrees with the one they hold for the companion, one for a companion
  they are running or hold at a newer epoch, and one whose source is not the live custody holder
  that the mesh advertises (``migration`` declares a liveliness token per held companion and
  every embodiment watches them). What remains, written down in docs/security.md: a receiver that
  has never seen the companion and cannot see its live holder (a partition) can be shown a fork
  by a hostile former host; when the partition heals, both holders advertise and the conflict is
  reported loudly, and the documented rule decides who keeps running it.
* Nothing is trusted because it was merely offered: a companion's identity key is pinned when a
  chain that starts with it *commits* (or at birth, or by ``--admit NAME=KEY``), never by a
  prepare that was aborted, so a stranger cannot poison the pin.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence

import msgspec

from cmion_mesh import signing
from cmion_mesh.signing import SignatureRefused

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
    return hashlib.sha256(document).digest()


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
    given, is the identity key trusted for it. ``SignatureRefused`` says which link fails."""
    if not chain:
        raise SignatureRefused(f"no chain of custody for {companion!r}")
    if len(chain) > MAX_LINKS:
        raise SignatureRefused(f"chain of custody of {companion!r} longer than {MAX_LINKS} links")
    first = chain[0]
    if identity is not None and first.public_key != identity:
        raise SignatureRefused(f"{companion!r} is signed by a key other than the one trusted for it")
    signer = first.public_key
    for index, link in enumerate(chain):
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


def rivals(chain: Sequence[Link], claims: Mapping[str, int], holder: str) -> list[str]:
    """The embodiments that claim the companion (``claims``: name -> epoch) although ``chain``, held
    or offered by ``holder``, shows them handing it on at the epoch they claim."""
    handed_on = {(link.holder, link.epoch) for link in chain[:-1]}
    return sorted(h for h, epoch in claims.items() if h != holder and (h, epoch) not in handed_on)


def forks(known: Sequence[Link], offered: Sequence[Link]) -> str:
    """Why ``offered`` conflicts with the chain ``known`` here ("" if one extends the other)."""
    for mine, theirs in zip(known, offered, strict=False):
        if mine != theirs:
            return (f"the chain of custody forks at epoch {mine.epoch}: the link offered (to {theirs.holder!r}) is not "
                    f"the one known here (to {mine.holder!r})")
    if len(known) > len(offered):
        return f"stale: the chain of custody here reaches epoch {known[-1].epoch}, the offer only {offered[-1].epoch}"
    return ""
