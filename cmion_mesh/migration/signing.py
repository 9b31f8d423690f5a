"""Ed25519 keys and signatures over canonical bytes: the primitives custody is built on.

Signed things are array-like msgspec Structs encoded as MessagePack (field order fixed, no names),
so the signed bytes are canonical. Private keys are raw 32 bytes; ``records`` writes them readable by
this user only, and they never leave the embodiment that made them (see ``custody``).

SHA-256 (documents, sections) is computed here too, by the same library: every process that hashes
a companion also signs or verifies its chain, and ``hashlib`` would load a second OpenSSL beside
cryptography's own (the system's libcrypto: 3.3 MiB resident) for the same function at the same speed.
"""

from __future__ import annotations

import base64
import functools

from cmion_mesh.errors import MeshError

# cryptography is imported by the functions that sign or verify, not here: every daemon imports
# this module (custody, records, migration), and its import costs start time that a daemon with
# no companion to hand on never needs. Keys go to and from raw bytes with the key's own methods,
# not through ``serialization`` (which brings the PEM, SSH and PKCS modules: 1.6 MiB and 8 ms at
# a companion's birth).

KEY_BYTES = 32
SIGNATURE_BYTES = 64


class SignatureRefused(MeshError):
    """A signature, key or signed structure that does not prove what it claims; the message says which check failed."""


def new_key() -> bytes:
    """A fresh private key, raw 32 bytes."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.generate().private_bytes_raw()


@functools.lru_cache(maxsize=256)
def public_of(private: bytes) -> bytes:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.from_private_bytes(private).public_key().public_bytes_raw()


def sign(private: bytes, data: bytes) -> bytes:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.from_private_bytes(private).sign(data)


@functools.lru_cache(maxsize=4096)
def valid(public: bytes, data: bytes, signature: bytes) -> bool:
    """Whether ``signature`` is ``public``'s over ``data``. Cached: a custody chain is checked again at
    every migration, and the same links recur."""
    if len(public) != KEY_BYTES or len(signature) != SIGNATURE_BYTES:
        return False
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    try:
        Ed25519PublicKey.from_public_bytes(public).verify(signature, data)
    except (InvalidSignature, ValueError):
        return False
    return True


class Sha256:
    """A SHA-256 being computed: ``update`` with each part, then ``hexdigest`` (once)."""

    __slots__ = ("_hash",)

    def __init__(self, data: bytes | bytearray | memoryview = b"") -> None:
        from cryptography.hazmat.primitives import hashes

        self._hash = hashes.Hash(hashes.SHA256())
        if data:
            self._hash.update(data)

    def update(self, data: bytes | bytearray | memoryview) -> None:
        self._hash.update(data)

    def digest(self) -> bytes:
        return self._hash.finalize()

    def hexdigest(self) -> str:
        return self.digest().hex()


def sha256(data: bytes | bytearray | memoryview) -> bytes:
    return Sha256(data).digest()


def encode_public(public: bytes) -> str:
    return base64.b64encode(public).decode()


def decode_public(text: str) -> bytes:
    try:
        raw = base64.b64decode(text, validate=True)
    except ValueError as exc:
        raise MeshError(f"public key {text[:16]!r}... is not base64: {exc}") from None
    if len(raw) != KEY_BYTES:
        raise MeshError(f"public key {text[:16]!r}... is not a 32-byte Ed25519 key")
    return raw
