"""The identity document: a companion's packed identity, the thing that migrates.

::

    <Identity SchemaVersion="1" Companion="spirit" Epoch="3">
      <Section Component="mind">{"goals": [...], "memory": [...]}</Section>
      <Section Component="voice">{"pitch": 1.2}</Section>
    </Identity>

One section per contributing component, its content plain data as JSON text. Validated by
``schemas/identity.xsd`` through ``xmlsafe`` (a document from the network is hostile until
proven otherwise). Sections nobody here understands are kept as they are and carried on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgspec
from lxml import etree

from cmion_mesh import keys, xmlsafe
from cmion_mesh.errors import ConfigError, InvalidName
from cmion_mesh.messages import check_value

SCHEMA = "identity.xsd"
SCHEMA_VERSION = 1
#: Largest identity document accepted (the 10 MB benchmark documents fit with room).
MAX_DOCUMENT = 48 * 1024 * 1024
#: Largest section: libxml2 refuses longer text nodes unless "huge tree" mode, which stays off.
MAX_SECTION = 9_000_000


@dataclass
class Identity:
    companion: str
    epoch: int
    sections: dict[str, Any] = field(default_factory=dict)
    schema_version: int = SCHEMA_VERSION

    def pack(self) -> bytes:
        keys.check_name(self.companion, "companion")
        root = etree.Element("Identity", SchemaVersion=str(self.schema_version), Companion=self.companion, Epoch=str(self.epoch))
        for name in sorted(self.sections):
            section = etree.SubElement(root, "Section", Component=keys.check_name(name, "section"))
            text = msgspec.json.encode(check_value(self.sections[name]))
            if len(text) > MAX_SECTION:
                raise ValueError(f"section {name!r} of {self.companion!r} is {len(text)} bytes of JSON; "
                                 f"the most a section may hold is {MAX_SECTION} (split it into several sections)")
            section.text = text.decode()
        data: bytes = etree.tostring(root, xml_declaration=True, encoding="UTF-8")
        return data


def unpack(data: bytes, *, name: str = "<identity>") -> Identity:
    """Parse and validate a document; ``XmlError``/``ConfigError`` naming ``name`` and line on any fault."""
    tree = xmlsafe.loads(data, SCHEMA, name=name, max_bytes=MAX_DOCUMENT, max_depth=8, max_elements=2000)
    root = tree.getroot()
    root_line = root.sourceline if isinstance(root.sourceline, int) else None
    sections: dict[str, Any] = {}
    for element in root:
        line = element.sourceline if isinstance(element.sourceline, int) else None
        component = element.get("Component", "")
        try:
            keys.check_name(component, "section")
        except InvalidName as exc:
            raise ConfigError(str(exc), path=name, line=line) from None
        try:
            sections[component] = check_value(msgspec.json.decode((element.text or "null").encode()))
        except (msgspec.DecodeError, ValueError, RecursionError) as exc:
            raise ConfigError(f"section {component!r}: not plain JSON data: {exc}", path=name, line=line) from None
    companion = root.get("Companion", "")
    try:
        keys.check_name(companion, "companion")
    except InvalidName as exc:
        raise ConfigError(str(exc), path=name, line=root_line) from None
    numbers = []
    for attribute, default in (("Epoch", "0"), ("SchemaVersion", "1")):
        raw = root.get(attribute, default)
        digits = raw.strip().lstrip("+").lstrip("0") or "0"  # the schema made it a non-negative integer
        if len(digits) > 19 or int(digits) >= 2**63:
            raise ConfigError(f"{attribute} {raw[:24]!r}... does not fit in 63 bits", path=name, line=root_line)
        numbers.append(int(digits))
    return Identity(companion, numbers[0], sections, numbers[1])
