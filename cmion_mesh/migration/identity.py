"""The identity document: a companion's packed identity, the thing that migrates.

SchemaVersion 2, what this version writes, is a small manifest that names each section's bytes
by their SHA-256; the bytes are stored apart, content-addressed (``records``: ``<state>/sections/
<sha256>``), and travel apart, as raw bytes (``migration``)::

    <Identity SchemaVersion="2" Companion="spirit" Epoch="3">
      <Section Component="mind" Encoding="msgpack" Sha256="9f86d08...0f00a08" Size="18211"/>
      <Section Component="voice" Encoding="msgpack" Sha256="60303ae...1e5c2b1" Size="12"/>
    </Identity>

So no section goes through the XML parser (libxml2 refuses text nodes over 10 MB), a section of
any size up to ``max_section()`` works, and a section an embodiment already holds from an earlier
visit never crosses the network again. The custody signatures (``custody``) are over the
manifest's hash, and the manifest names every section by its hash: they cover every byte.

One section per contributing component, its content plain data (``messages.check_value``),
encoded as MessagePack (``Encoding="json"``, JSON text, is read too). The manifest is validated by
``schemas/identity.xsd`` through ``xmlsafe`` (a document from the network is hostile until proven
otherwise). Sections nobody here understands are kept as they are and carried on.

SchemaVersion 1 documents (each section inline, as JSON text) still load: documents stored before
this format, and peers that send them. ``Identity.pack`` still writes that self-contained form
(tools, tests, small identities); ``Identity.pack_sections`` writes version 2.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import msgspec
from lxml import etree

from cmion_mesh import keys, xmlsafe
from cmion_mesh.errors import ConfigError, InvalidName
from cmion_mesh.messages import MAX_MANIFEST, check_value
from cmion_mesh.migration import signing

SCHEMA = "identity.xsd"
SCHEMA_VERSION = 2
#: Largest SchemaVersion 1 document accepted (sections inline); a version 2 manifest is at most ``MAX_MANIFEST``.
MAX_DOCUMENT = 48 * 1024 * 1024
#: Largest inline (SchemaVersion 1) section: libxml2 refuses longer text nodes unless "huge tree" mode, which stays off.
MAX_INLINE_SECTION = 9_000_000
#: Largest section by default (bytes); ``CMION_MESH_MAX_SECTION`` changes it (see ``max_section``).
MAX_SECTION = 256 * 1024 * 1024
MAX_SECTION_ENV = "CMION_MESH_MAX_SECTION"
#: MessagePack carries bytes up to 4 GiB - 1 in one value.
_SECTION_CEILING = 2**32 - 1
ENCODINGS = ("msgpack", "json")
Bytes = bytes | bytearray | memoryview

_msgpack = msgspec.msgpack.Encoder()
_json = msgspec.json.Encoder()


def max_section() -> int:
    """The largest section this process packs or accepts: ``CMION_MESH_MAX_SECTION`` (bytes), else ``MAX_SECTION``."""
    raw = os.environ.get(MAX_SECTION_ENV, "").strip()
    if not raw:
        return MAX_SECTION
    try:
        value = int(raw)
    except ValueError:
        value = 0
    if not 1 <= value <= _SECTION_CEILING:
        raise ConfigError(f"{MAX_SECTION_ENV}={raw[:40]!r}: not a number of bytes between 1 and {_SECTION_CEILING}")
    return value


def sha256_hex(data: Bytes) -> str:
    return signing.sha256(data).hex()


class MissingSections(ConfigError):
    """A version 2 document whose section bytes are not all at hand; ``missing`` names them."""

    def __init__(self, message: str, missing: list[SectionRef], *, path: str | None = None) -> None:
        super().__init__(message, path=path)
        self.missing = missing


class SectionRef(msgspec.Struct, frozen=True):
    """One ``<Section>`` of a version 2 manifest: whose section, and the bytes that hold it."""

    component: str
    sha256: str
    size: int
    encoding: str = "msgpack"


class Packed(msgspec.Struct, frozen=True):
    """An identity as version 2: the manifest and every section's bytes (by SHA-256, hex)."""

    manifest: bytes
    refs: tuple[SectionRef, ...]
    data: dict[str, Bytes]

    @property
    def size(self) -> int:
        """The document's bytes: the manifest and each distinct section."""
        return len(self.manifest) + sum(len(b) for b in self.data.values())


_NOTHING = object()
#: Values that cannot change once made: the same object is the same section.
_IMMUTABLE = (str, int, float, bool, type(None))


class SectionMemo:
    """The last bytes packed or received for each component, with their hash: a section that did
    not change since keeps its hash (compared byte for byte, far cheaper than hashing it again),
    and when its value is the very same immutable object (a mind's large string, kept as it
    arrived), its bytes too, without encoding it again."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[object, Bytes, str]] = {}

    def known(self, component: str, value: object) -> tuple[Bytes, str] | None:
        last = self._last.get(component)
        if last is not None and last[0] is value and isinstance(value, _IMMUTABLE):
            return last[1], last[2]
        return None

    def digest(self, component: str, data: Bytes, value: object = _NOTHING) -> str:
        last = self._last.get(component)
        same = last is not None and len(last[1]) == len(data) and last[1] == data
        digest = last[2] if last is not None and same else sha256_hex(data)
        self._last[component] = (value, data, digest)
        return digest

    def values(self) -> dict[str, Any]:
        """The immutable values held here with their bytes, by the bytes' SHA-256 (hex)."""
        return {digest: value for value, _data, digest in self._last.values() if isinstance(value, _IMMUTABLE)}

    def held(self) -> dict[str, Bytes]:
        """The bytes held here, by their SHA-256 (hex)."""
        return {digest: data for _value, data, digest in self._last.values()}

    def remember(self, component: str, data: Bytes, digest: str, value: object = _NOTHING) -> None:
        self._last[component] = (value, data, digest)

    def keep_only(self, components: set[str]) -> None:
        self._last = {c: v for c, v in self._last.items() if c in components}


@dataclass
class Identity:
    companion: str
    epoch: int
    sections: dict[str, Any] = field(default_factory=dict)
    schema_version: int = 1

    def pack(self) -> bytes:
        """The self-contained SchemaVersion 1 document (sections inline, JSON): tools, tests and small
        identities. What migrates is ``pack_sections``."""
        keys.check_name(self.companion, "companion")
        root = etree.Element("Identity", SchemaVersion="1", Companion=self.companion, Epoch=str(self.epoch))
        for name in sorted(self.sections):
            section = etree.SubElement(root, "Section", Component=keys.check_name(name, "section"))
            text = _json.encode(check_value(self.sections[name]))
            if len(text) > MAX_INLINE_SECTION:
                raise ValueError(f"section {name!r} of {self.companion!r} is {len(text)} bytes of JSON; the most an "
                                 f"inline section may hold is {MAX_INLINE_SECTION} (pack_sections has no such limit)")
            section.text = text.decode()
        data: bytes = etree.tostring(root, xml_declaration=True, encoding="UTF-8")
        return data

    def pack_sections(self, memo: SectionMemo | None = None) -> Packed:
        """SchemaVersion 2: the manifest and each section's MessagePack bytes. ``ValueError`` names a
        section that is not plain data or is larger than ``max_section()``, with its size."""
        keys.check_name(self.companion, "companion")
        limit = max_section()
        root = etree.Element("Identity", SchemaVersion=str(SCHEMA_VERSION), Companion=self.companion, Epoch=str(self.epoch))
        refs: list[SectionRef] = []
        data: dict[str, Bytes] = {}
        for name in sorted(self.sections):
            keys.check_name(name, "section")
            value = self.sections[name]
            known = memo.known(name, value) if memo is not None else None
            if known is not None:
                encoded, digest = known
            else:
                try:
                    encoded = _msgpack.encode(check_value(value))
                except (ValueError, TypeError, OverflowError) as exc:
                    raise ValueError(f"section {name!r} of {self.companion!r}: not plain data: {exc}") from None
            if len(encoded) > limit:
                raise ValueError(f"section {name!r} of {self.companion!r} is {len(encoded)} bytes; the most a section "
                                 f"may hold is {limit} ({MAX_SECTION_ENV})")
            if known is None:
                digest = memo.digest(name, encoded, value) if memo is not None else sha256_hex(encoded)
            refs.append(SectionRef(name, digest, len(encoded)))
            data[digest] = encoded
            etree.SubElement(root, "Section", Component=name, Encoding="msgpack", Sha256=digest, Size=str(len(encoded)))
        if memo is not None:
            memo.keep_only(set(self.sections))
        manifest: bytes = etree.tostring(root, xml_declaration=True, encoding="UTF-8")
        return Packed(manifest, tuple(refs), data)


class Manifest(msgspec.Struct, frozen=True):
    """A parsed document: version 2 names its sections (``refs``); version 1 holds them (``inline``)."""

    companion: str
    epoch: int
    schema_version: int
    refs: tuple[SectionRef, ...] = ()
    inline: dict[str, Any] = msgspec.field(default_factory=dict)
    name: str = "<identity>"

    def missing(self, have: Mapping[str, Any]) -> list[SectionRef]:
        return [ref for ref in self.refs if ref.sha256 not in have]

    def identity(self, sections: Mapping[str, Bytes] | None = None, values: Mapping[str, Any] | None = None) -> Identity:
        """The identity, each version 2 section decoded from ``sections`` (SHA-256 hex -> bytes, already
        checked against their hash by whoever holds them), or taken from ``values`` (SHA-256 hex ->
        the immutable value those bytes decode to, ``SectionMemo.values``). ``MissingSections`` lists
        those not given; ``ConfigError`` names a section whose bytes are not plain data or not its size."""
        if self.schema_version < 2:
            return Identity(self.companion, self.epoch, dict(self.inline), self.schema_version)
        given = sections or {}
        missing = self.missing(given)
        if missing:
            listed = ", ".join(f"{r.component!r} ({r.sha256[:12]}, {r.size} bytes)" for r in missing)
            raise MissingSections(f"sections not at hand: {listed}", missing, path=self.name)
        decoded: dict[str, Any] = {}
        for ref in self.refs:
            if values and ref.sha256 in values and len(given[ref.sha256]) == ref.size:
                decoded[ref.component] = values[ref.sha256]
            else:
                decoded[ref.component] = decode_section(ref, given[ref.sha256], name=self.name)
        return Identity(self.companion, self.epoch, decoded, self.schema_version)


def decode_section(ref: SectionRef, data: Bytes, *, name: str = "<identity>") -> Any:
    if len(data) != ref.size:
        raise ConfigError(f"section {ref.component!r} ({ref.sha256}) is {len(data)} bytes, the manifest says {ref.size}",
                          path=name)
    try:
        value = msgspec.msgpack.decode(data) if ref.encoding == "msgpack" else msgspec.json.decode(data)
        return check_value(value)
    except (msgspec.DecodeError, ValueError, TypeError, RecursionError) as exc:
        raise ConfigError(f"section {ref.component!r}: not plain {ref.encoding} data: {exc}", path=name) from None


def read_manifest(data: bytes, *, name: str = "<identity>") -> Manifest:
    """Parse and validate a document (version 1 or 2): ``XmlError``/``ConfigError`` naming ``name``
    and the line of any fault, and a version 2 section larger than ``max_section()`` with its size."""
    tree = xmlsafe.loads(data, SCHEMA, name=name, max_bytes=MAX_DOCUMENT, max_depth=8, max_elements=2000)
    root = tree.getroot()
    root_line = root.sourceline if isinstance(root.sourceline, int) else None
    companion = root.get("Companion", "")
    try:
        keys.check_name(companion, "companion")
    except InvalidName as exc:
        raise ConfigError(str(exc), path=name, line=root_line) from None
    numbers = []
    for attribute, default in (("Epoch", "0"), ("SchemaVersion", "1")):
        numbers.append(_number(root.get(attribute, default), attribute, name, root_line))
    epoch, version = numbers
    if version >= 2 and len(data) > MAX_MANIFEST:
        raise ConfigError(f"a SchemaVersion {version} manifest is {len(data)} bytes, over {MAX_MANIFEST}",
                          path=name, line=root_line)
    inline: dict[str, Any] = {}
    refs: list[SectionRef] = []
    limit = max_section() if version >= 2 else 0
    for element in root:
        line = element.sourceline if isinstance(element.sourceline, int) else None
        component = element.get("Component", "")
        try:
            keys.check_name(component, "section")
        except InvalidName as exc:
            raise ConfigError(str(exc), path=name, line=line) from None
        digest, size = element.get("Sha256"), element.get("Size")
        if version < 2:
            if digest is not None or size is not None:
                raise ConfigError(f"section {component!r}: Sha256 and Size belong to SchemaVersion 2, this is {version}",
                                  path=name, line=line)
            try:
                inline[component] = check_value(msgspec.json.decode((element.text or "null").encode()))
            except (msgspec.DecodeError, ValueError, RecursionError) as exc:
                raise ConfigError(f"section {component!r}: not plain JSON data: {exc}", path=name, line=line) from None
            continue
        if digest is None or size is None or (element.text or "").strip():
            raise ConfigError(f"section {component!r}: a SchemaVersion {version} section names its bytes by Sha256 and "
                              "Size and holds no text", path=name, line=line)
        count = _number(size, "Size", name, line)
        if count > limit:
            raise ConfigError(f"section {component!r} of {companion!r} is {count} bytes; the most a section may hold "
                              f"here is {limit} ({MAX_SECTION_ENV})", path=name, line=line)
        refs.append(SectionRef(component, digest, count, element.get("Encoding", "json")))
    return Manifest(companion, epoch, version, tuple(refs), inline, name)


def _number(raw: str, attribute: str, name: str, line: int | None) -> int:
    digits = raw.strip().lstrip("+").lstrip("0") or "0"  # the schema made it a non-negative integer
    if len(digits) > 19 or int(digits) >= 2**63:
        raise ConfigError(f"{attribute} {raw[:24]!r}... does not fit in 63 bits", path=name, line=line)
    return int(digits)


def unpack(data: bytes, *, name: str = "<identity>",
           sections: Mapping[str, Bytes] | None = None) -> Identity:
    """Parse and validate a document; version 2 sections are decoded from ``sections`` (SHA-256 hex
    -> bytes). ``XmlError``/``ConfigError`` naming ``name`` and line on any fault; ``MissingSections``."""
    return read_manifest(data, name=name).identity(sections)
