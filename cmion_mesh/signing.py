"""Signed identities: a companion's key signs every handshake envelope.

A companion owns an Ed25519 key pair, made when it is born; the private key lives with the
companion (in its host's state folder, 0600) and travels with it in the prepare message. Each
``migrate_prepare`` carries an **envelope** (companion, epoch, attempt, source, target, the
SHA-256 of the identity document, the companion's public key), encoded as canonical MessagePack,
and the Ed25519 signature over those exact bytes. The target checks, *before it parses any XML*:
the signature; that the public key is the one its admission policy lists for the companion, or the
one it pinned when it first saw the companion; that every field of the envelope matches the
message and names this embodiment as the target; and that the document's hash matches. A
replayed (stale epoch), redirected (other target), truncated or altered (hash) or wrongly signed
envelope is refused.
"""

from __future__ import annotations

import base64
import hashlib
import os
from pathlib import Path

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from cmion_mesh.errors import MeshError


class SignatureRefused(MeshError):
    """An envelope or signature that does not prove what it claims; the message says which check failed."""


class Envelope(msgspec.Struct, frozen=True, array_like=True):
    """Signed bytes: array-like so the encoding is canonical (field order fixed, no names)."""

    companion: str
    epoch: int
    attempt: str
    source: str
    target: str
    document_sha256: bytes
    public_key: bytes


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(Envelope)


def new_key() -> bytes:
    """A fresh private key, raw 32 bytes."""
    return Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.Raw, serialization.PrivateFormat.Raw, serialization.NoEncryption())


def public_of(private: bytes) -> bytes:
    return Ed25519PrivateKey.from_private_bytes(private).public_key().public_bytes(
        serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def encode_public(public: bytes) -> str:
    return base64.b64encode(public).decode()


def decode_public(text: str) -> bytes:
    try:
        raw = base64.b64decode(text, validate=True)
    except ValueError as exc:
        raise MeshError(f"public key {text[:16]!r}... is not base64: {exc}") from None
    if len(raw) != 32:
        raise MeshError(f"public key {text[:16]!r}... is not a 32-byte Ed25519 key")
    return raw


def seal(private: bytes, companion: str, epoch: int, attempt: str, source: str, target: str, document: bytes) -> tuple[bytes, bytes]:
    """``(envelope bytes, signature)`` for one prepare."""
    envelope = Envelope(companion, epoch, attempt, source, target, hashlib.sha256(document).digest(), public_of(private))
    data = _encoder.encode(envelope)
    return data, Ed25519PrivateKey.from_private_bytes(private).sign(data)


def verify(envelope_bytes: bytes, signature: bytes, *, expected: Envelope, document: bytes, trusted_key: bytes | None) -> Envelope:
    """Check an envelope as described in the module doc; ``SignatureRefused`` says which check failed."""
    if len(envelope_bytes) > 4096:
        raise SignatureRefused("envelope larger than 4 KiB")
    try:
        envelope = _decoder.decode(envelope_bytes)
    except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError) as exc:
        raise SignatureRefused(f"malformed envelope: {exc}") from None
    if len(envelope.public_key) != 32:
        raise SignatureRefused("envelope public key is not an Ed25519 key")
    try:
        Ed25519PublicKey.from_public_bytes(envelope.public_key).verify(signature, envelope_bytes)
    except (InvalidSignature, ValueError):
        raise SignatureRefused(f"bad signature on the envelope of {envelope.companion!r}") from None
    if trusted_key is not None and envelope.public_key != trusted_key:
        raise SignatureRefused(f"{envelope.companion!r} is signed by a key other than the one trusted for it")
    for field in ("companion", "epoch", "attempt", "source", "target"):
        got, want = getattr(envelope, field), getattr(expected, field)
        if got != want:
            raise SignatureRefused(f"envelope {field} is {got!r}, the message says {want!r} (replayed or redirected)")
    if hashlib.sha256(document).digest() != envelope.document_sha256:
        raise SignatureRefused("the document does not match the signed hash (truncated or altered)")
    return envelope


def save_private(path: Path, private: bytes) -> None:
    """Write a companion's private key, readable by this user only, atomically."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(private)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
