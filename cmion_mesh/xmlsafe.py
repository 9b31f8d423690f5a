"""The one door through which cmion-mesh reads XML: bounded, entity-free, optionally schema-checked.

Configuration files come from disk and identity documents from the network, so every XML byte is
treated as hostile.  ``load`` / ``loads`` therefore:

* read at most ``max_bytes`` (plus one, to notice excess) before any parsing happens;
* accept only encodings the pre-scan can decode exactly as libxml2 will (UTF-8, US-ASCII,
  ISO-8859-x, windows-125x, UTF-16), so no construct can hide from the pre-scan in an exotic
  encoding;
* refuse any DTD content: an internal subset (``<!DOCTYPE x [ ... ]>``), any ``<!ENTITY``
  declaration, and any entity reference other than the five predefined ones and character
  references.  A bare external ``<!DOCTYPE X SYSTEM "X.dtd">`` (CMION 2011 style) is accepted,
  but the DTD it names is never fetched or opened;
* parse with libxml2's entity substitution, DTD loading, network access and "huge tree" mode
  switched off, and with a resolver that refuses every external resource, so even a pre-scan
  bug cannot make the parser read a file or URL;
* bound nesting depth and element count *while* parsing, so a hostile document cannot make the
  tree large before it is refused;
* re-check the parsed tree (internal DTD declarations, entity-reference nodes), a second line of
  defence independent of the pre-scan.

Every refusal is an ``XmlError`` whose text starts ``path:line:``.
"""

from __future__ import annotations

import codecs
import os
import re
import threading
from pathlib import Path
from typing import Any

from lxml import etree

from cmion_mesh.errors import XmlError

__all__ = [
    "DEFAULT_MAX_BYTES",
    "DEFAULT_MAX_DEPTH",
    "DEFAULT_MAX_ELEMENTS",
    "DenyAllResolver",
    "ExternalResourceRefused",
    "load",
    "loads",
    "schema_path",
    "schema_problems",
    "sourceline",
    "validate",
]

#: Largest document accepted.  Configuration and identity documents are a few kilobytes.
DEFAULT_MAX_BYTES = 4 * 1024 * 1024
#: Deepest element nesting accepted (CMION's deepest file nests 5 levels).
DEFAULT_MAX_DEPTH = 64
#: Most elements accepted in one document.
DEFAULT_MAX_ELEMENTS = 100_000

# Fed to libxml2 in slices so the depth/element limits are checked before the tree grows large.
_CHUNK = 64 * 1024

# Python codec names (as ``codecs.lookup(...).name`` spells them) the pre-scan may use.  All are
# either ASCII-compatible single/multi-byte encodings or UTF-16, which libxml2 decodes identically.
_ASCII_COMPATIBLE = frozenset(
    {"utf-8", "ascii"}
    | {f"iso8859-{n}" for n in (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 13, 14, 15, 16)}
    | {f"cp125{n}" for n in range(9)}
)
_UTF16 = frozenset({"utf-16", "utf-16-le", "utf-16-be"})

# How far into the document the XML declaration must have ended.
_DECL_WINDOW = 1024
_XML_DECL_START = re.compile(r"<\?xml[ \t\r\n]")
_DECL_ENCODING = re.compile(r"""\sencoding\s*=\s*(?:"([^"]*)"|'([^']*)')""")
_LITERAL = r"""(?:"[^"]*"|'[^']*')"""
# The only DOCTYPE form accepted: a name and an optional external id, no internal subset.
_SAFE_DOCTYPE = re.compile(
    rf"<!DOCTYPE\s+[^\s\[\]<>'\"]+(?:\s+SYSTEM\s+{_LITERAL}|\s+PUBLIC\s+{_LITERAL}\s+{_LITERAL})?\s*>"
)
_DOCTYPE = re.compile(r"<!DOCTYPE")
_ENTITY_DECL = re.compile(r"<!ENTITY")
_ENTITY_REF = re.compile(r"&([^\s&;<>\"']*);")
_PREDEFINED = frozenset({"amp", "lt", "gt", "apos", "quot"})
_CHAR_REF = re.compile(r"#(?:[0-9]+|x[0-9A-Fa-f]+)")
# lxml appends the location to its messages; the location is reported separately.
_LOCATION_SUFFIX = re.compile(r"(?:, line \d+, column \d+)+\s*$")


class ExternalResourceRefused(Exception):
    """Raised from libxml2's loader callback so the parse aborts instead of reading the resource.

    lxml stores it and re-raises it once the parse stops; ``load``/``loads`` turn it into an
    ``XmlError``.  It is a separate type so a parser built elsewhere with ``DenyAllResolver``
    shows plainly why it failed.
    """

    def __init__(self, url: str | None) -> None:
        self.url = url
        super().__init__(f"external resource refused: {url!r}")


class DenyAllResolver(etree.Resolver):
    """Refuses every external entity, DTD or include, so a parser holding it can read no file or URL.

    Returning ``None`` would let libxml2 fall back to its default loader, which opens local files;
    raising aborts the parse instead.
    """

    # The stubs omit ``context``, which lxml always passes.
    def resolve(  # type: ignore[override]
        self, system_url: str | None, public_id: str | None, context: object
    ) -> Any:
        raise ExternalResourceRefused(system_url)


def _make_parser(comments: bool = False) -> etree.XMLPullParser:
    """A fresh pull parser per document: lxml parsers are not safe to share between threads.

    Do not add ``collect_ids=False``: lxml passes it to libxml2 as ``XML_SKIP_IDS``, which libxml2
    (2.14) treats as "load the external subset", so the DTD named by a DOCTYPE would be fetched
    even with ``load_dtd=False`` (the resolver below would then refuse every CMION file).
    """
    parser = etree.XMLPullParser(
        events=("start", "end"),
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        dtd_validation=False,
        attribute_defaults=False,
        huge_tree=False,
        # Comments are harmless text; kept only for readers that use them (a rules file's comments
        # describe its actions), so every other reader's trees stay free of comment nodes.
        remove_comments=not comments,
        remove_pis=True,
    )
    parser.resolvers.add(DenyAllResolver())
    return parser


def _line_at(data: bytes, offset: int) -> int:
    """1-based line of a byte offset, counted before decoding (the data may not decode at all)."""
    return data.count(b"\n", 0, max(offset, 0)) + 1


def sourceline(node: object) -> int | None:
    """``sourceline`` of an lxml node (the stubs type it loosely); ``None`` when libxml2 has none."""
    line = getattr(node, "sourceline", None)
    return line if isinstance(line, int) and line > 0 else None


def _text_line(text: str, offset: int) -> int:
    return text.count("\n", 0, max(offset, 0)) + 1


def _decode(data: bytes, name: str) -> str:
    """Decode the whole document as libxml2 will, so the pre-scan sees exactly what the parser sees.

    Encodings outside a small, well-understood set are refused rather than guessed: an encoding
    the pre-scan misreads (UTF-7, EBCDIC...) could smuggle ``<!ENTITY`` past it.
    """
    head = data[:4]
    if data.startswith((codecs.BOM_UTF32_LE, codecs.BOM_UTF32_BE)) or head in (
        b"\x00\x00\x00<",
        b"<\x00\x00\x00",
    ):
        raise XmlError("UTF-32 documents are not accepted; use UTF-8", path=name, line=1)
    if head == b"\x4c\x6f\xa7\x94":
        raise XmlError("EBCDIC documents are not accepted; use UTF-8", path=name, line=1)
    if data.startswith(codecs.BOM_UTF8):
        family, codec = "utf-8", "utf-8-sig"
    elif data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        family, codec = "utf-16", "utf-16"
    elif head == b"<\x00?\x00":
        family, codec = "utf-16", "utf-16-le"
    elif head == b"\x00<\x00?":
        family, codec = "utf-16", "utf-16-be"
    else:
        family, codec = "ascii-compatible", "utf-8"

    declared = _declared_encoding(data, family, codec, name)

    if declared is not None:
        try:
            declared_codec = codecs.lookup(declared).name
        except (LookupError, ValueError):  # ValueError: a NUL in the name
            raise XmlError(f"unsupported encoding {declared!r}; use UTF-8", path=name, line=1) from None
        if family == "utf-16":
            if declared_codec not in _UTF16:
                raise XmlError(f"document is UTF-16 but declares encoding {declared!r}", path=name, line=1)
        elif declared_codec in _UTF16:
            raise XmlError(f"document declares {declared!r} but is not UTF-16", path=name, line=1)
        elif declared_codec not in _ASCII_COMPATIBLE:
            raise XmlError(f"unsupported encoding {declared!r}; use UTF-8", path=name, line=1)
        elif family == "utf-8" and declared_codec != "utf-8":
            raise XmlError(
                f"document has a UTF-8 byte-order mark but declares {declared!r}", path=name, line=1
            )
        elif family == "ascii-compatible":
            codec = declared_codec

    try:
        return data.decode(codec)
    except UnicodeDecodeError as exc:
        prefix = data[: exc.start].decode(codec, errors="replace")
        label = declared or ("UTF-16" if family == "utf-16" else "UTF-8")
        raise XmlError(
            f"bytes are not valid {label} (byte offset {exc.start}: {exc.reason})",
            path=name,
            line=prefix.count("\n") + 1,
        ) from None


def _declared_encoding(data: bytes, family: str, codec: str, name: str) -> str | None:
    """The ``encoding`` named by the XML declaration, or ``None`` when there is none.

    A declaration we cannot read is refused: guessing UTF-8 while libxml2 honours a declaration we
    missed is exactly the disagreement the pre-scan must not have.
    """
    if family == "utf-16":
        sample = data[: 2 * _DECL_WINDOW].decode(codec, errors="ignore").lstrip("\ufeff")
    else:
        sample = data[:_DECL_WINDOW].decode("latin-1").removeprefix("\xef\xbb\xbf")
    if not _XML_DECL_START.match(sample):
        return None
    end = sample.find("?>")
    if end < 0:
        raise XmlError(f"XML declaration does not end within {_DECL_WINDOW} bytes", path=name, line=1)
    declaration = sample[:end]
    match = _DECL_ENCODING.search(declaration)
    if match is None:
        if "encoding" in declaration:
            raise XmlError("unreadable encoding in the XML declaration", path=name, line=1)
        return None
    return match.group(1) if match.group(1) is not None else match.group(2)


def _prescan(text: str, name: str) -> None:
    """Refuse DTD declarations and entity references before libxml2 sees them.

    Deliberately blunt: it also trips on ``<!ENTITY`` or ``&foo;`` inside comments and CDATA,
    because a precise lexer could disagree with libxml2 and be bypassed; a blunt scan cannot.
    """
    for found in _DOCTYPE.finditer(text):
        if not _SAFE_DOCTYPE.match(text, found.start()):
            raise XmlError(
                "DOCTYPE with an internal DTD subset (or malformed DOCTYPE) is not allowed; "
                'only <!DOCTYPE Name SYSTEM "file.dtd"> is accepted, and the DTD is never read',
                path=name,
                line=_text_line(text, found.start()),
            )
    entity = _ENTITY_DECL.search(text)
    if entity is not None:
        raise XmlError(
            "<!ENTITY declarations are not allowed", path=name, line=_text_line(text, entity.start())
        )
    for ref in _ENTITY_REF.finditer(text):
        ident = ref.group(1)
        if ident in _PREDEFINED or _CHAR_REF.fullmatch(ident):
            continue
        raise XmlError(
            f"entity reference &{ident[:40]}; is not allowed (only &amp; &lt; &gt; &apos; &quot; "
            "and character references are)",
            path=name,
            line=_text_line(text, ref.start()),
        )


def _syntax_error(exc: etree.XMLSyntaxError, name: str, text: str) -> XmlError:
    """Turn lxml's error into ours, taking the line from the exception, not the shared error log.

    ``exc.error_log`` can hold stale entries from earlier parses in the same thread.
    """
    message = _LOCATION_SUFFIX.sub("", str(exc.msg or exc)).strip() or "malformed XML"
    line = exc.lineno if exc.lineno else None
    if line is None:  # errors raised at close() carry no position: they are about the end of input
        line = text.count("\n") + 1
    column = ""
    if exc.position and exc.position[1]:
        column = f" (column {exc.position[1]})"
    return XmlError(f"malformed XML: {message}{column}", path=name, line=line)


def _parse(data: bytes, text: str, name: str, max_depth: int, max_elements: int, comments: bool = False) -> etree._ElementTree:
    """Parse in slices, checking depth and element count after each, so excess is caught early."""
    parser = _make_parser(comments)
    depth = 0
    elements = 0

    def drain() -> None:
        nonlocal depth, elements
        for event, element in parser.read_events():
            if event == "start":
                depth += 1
                elements += 1
                if depth > max_depth:
                    raise XmlError(
                        f"elements nested deeper than {max_depth} levels",
                        path=name,
                        line=sourceline(element),
                    )
                if elements > max_elements:
                    raise XmlError(f"more than {max_elements} elements", path=name, line=sourceline(element))
            else:
                depth -= 1

    failure: etree.XMLSyntaxError | None = None
    try:
        for start in range(0, len(data), _CHUNK):
            parser.feed(data[start : start + _CHUNK])
            drain()
        root = parser.close()
    except etree.XMLSyntaxError as exc:
        failure = exc
    except ExternalResourceRefused as exc:
        url = exc.url or ""
        pos = text.find(url) if url else -1
        raise XmlError(
            f"refused to load external resource {url!r}",
            path=name,
            line=_text_line(text, pos) if pos >= 0 else None,
        ) from None
    except etree.LxmlError as exc:
        raise XmlError(f"malformed XML: {exc}", path=name, line=_text_line(text, len(text))) from None
    # libxml2's own limits (depth 256...) may fire inside a slice; ours, if crossed before that
    # point, gives the more useful message.  close() also queues the last "end" events.
    drain()
    if failure is not None:
        raise _syntax_error(failure, name, text)
    return root.getroottree()


def _has_internal_subset(tree: etree._ElementTree, dtd: Any) -> bool:
    """Whether the DOCTYPE carries declarations (``dtd`` is ``Any``: the stubs lack the DTD API)."""
    if any(True for _ in dtd.iterentities()) or any(True for _ in dtd.iterelements()):
        return True
    header: str = tree.docinfo.doctype  # type: ignore[attr-defined]
    serialised = etree.tostring(tree, encoding="unicode")
    return not serialised.startswith(header) or serialised[len(header) :].lstrip().startswith("[")


def _postcheck(tree: etree._ElementTree, name: str) -> None:
    """Second line of defence, independent of the pre-scan: look at what libxml2 actually built."""
    dtd = tree.docinfo.internalDTD
    # A bare ``<!DOCTYPE X SYSTEM "X.dtd">`` yields an empty internal DTD node; declarations do not.
    # lxml lists element and entity declarations but not e.g. an ATTLIST for an undeclared element,
    # so the serialised DOCTYPE is checked too: any internal subset shows there as " [...]".
    if dtd is not None and _has_internal_subset(tree, dtd):
        raise XmlError("internal DTD declarations are not allowed", path=name, line=1)
    for node in tree.getroot().iter(etree.Entity):
        parent = node.getparent()
        line = sourceline(node) or sourceline(parent)
        raise XmlError(f"entity reference {node.text} is not allowed", path=name, line=line)


def _check_limits(max_bytes: int, max_depth: int, max_elements: int) -> None:
    if max_bytes < 1 or max_depth < 1 or max_elements < 1:
        raise ValueError(f"limits must be positive: {max_bytes=} {max_depth=} {max_elements=}")


def _loads(
    data: bytes, schema: str | None, name: str, max_bytes: int, max_depth: int, max_elements: int, comments: bool = False
) -> etree._ElementTree:
    if len(data) > max_bytes:
        raise XmlError(
            f"document is larger than the limit of {max_bytes} bytes; refused unparsed",
            path=name,
            line=_line_at(data, max_bytes),
        )
    text = _decode(data, name)
    _prescan(text, name)
    tree = _parse(data, text, name, max_depth, max_elements, comments)
    _postcheck(tree, name)
    if schema is not None:
        validate(tree, schema, name)
    return tree


def loads(
    data: bytes,
    schema: str | None,
    *,
    name: str = "<bytes>",
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_depth: int = DEFAULT_MAX_DEPTH,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
    comments: bool = False,
) -> etree._ElementTree:
    """Parse an in-memory document (e.g. one received from the network) under the same rules as files.

    ``name`` is only used in error messages.  Raises ``XmlError`` for every fault in ``data``.
    ``comments`` keeps the document's comments.
    """
    _check_limits(max_bytes, max_depth, max_elements)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"loads() wants bytes, got {type(data).__name__}")
    return _loads(bytes(data), schema, name, max_bytes, max_depth, max_elements, comments)


def load(
    source: str | os.PathLike[str],
    schema: str | None,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_depth: int = DEFAULT_MAX_DEPTH,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
    comments: bool = False,
) -> etree._ElementTree:
    """Read and parse an XML file, validating it against ``schema`` (a file name such as
    ``"WorldModel.xsd"``) unless that is ``None``.

    The file is read by us, capped at ``max_bytes + 1`` bytes, so an oversize (or endless, e.g. a
    FIFO) file is refused without being parsed.  Unreadable files are ``XmlError`` too, so callers
    loading configuration need to catch one family only. ``comments`` keeps the document's comments.
    """
    _check_limits(max_bytes, max_depth, max_elements)
    name = os.fspath(source)
    try:
        with open(name, "rb") as handle:
            data = handle.read(max_bytes + 1)
    except OSError as exc:
        raise XmlError(f"cannot read file: {exc.strerror or exc}", path=name) from None
    return _loads(data, schema, name, max_bytes, max_depth, max_elements, comments)


# --- schemas -------------------------------------------------------------------------------------

_PACKAGE_DIR = Path(__file__).resolve().parent
#: Where ``schema_path`` looks, in order: the copy packaged in a wheel, then the repository's.
SCHEMA_DIRS = (_PACKAGE_DIR / "schemas", _PACKAGE_DIR.parent / "schemas")


def schema_path(name: str) -> Path:
    """Where schema ``name`` lives: inside the package (wheel install) or in the repository root.

    Names are bare file names, never paths, so a caller cannot point validation elsewhere.
    """
    if not name or Path(name).name != name or name in (".", ".."):
        raise ValueError(f"schema must be a bare file name such as 'WorldModel.xsd', got {name!r}")
    for directory in SCHEMA_DIRS:
        candidate = directory / name
        if candidate.is_file():
            return candidate
    searched = ", ".join(str(d) for d in SCHEMA_DIRS)
    raise FileNotFoundError(f"schema {name!r} not found in {searched}")


class _CompiledSchema:
    """A compiled schema with its own lock: an lxml validator keeps its error log on the object,
    so concurrent validations would overwrite each other's diagnostics."""

    def __init__(self, schema: etree.XMLSchema) -> None:
        self.schema = schema
        self.lock = threading.Lock()


_schemas: dict[str, _CompiledSchema] = {}
_schemas_lock = threading.Lock()


def _compiled(name: str) -> _CompiledSchema:
    with _schemas_lock:
        cached = _schemas.get(name)
        if cached is not None:
            return cached
        path = schema_path(name)
        # The schema itself is XML, so it comes through the same door.
        document = load(path, None)
        try:
            compiled = _CompiledSchema(etree.XMLSchema(document))
        except etree.XMLSchemaParseError as exc:
            raise XmlError(f"invalid schema: {exc}", path=str(path), line=None) from None
        _schemas[name] = compiled
        return compiled


def validate(tree: etree._ElementTree, schema: str, name: str) -> None:
    """Raise ``XmlError`` at the first element of ``tree`` that ``schema`` rejects.

    ``name`` is the document's file name (or label) for the message.
    """
    problems = schema_problems(tree, schema, name)
    if problems:
        raise problems[0]


def schema_problems(tree: etree._ElementTree, schema: str, name: str) -> list[XmlError]:
    """Every violation of ``schema`` that libxml2 reports for ``tree``, in document order (empty
    when it matches); each an ``XmlError`` naming ``name`` and the line."""
    compiled = _compiled(schema)
    with compiled.lock:
        if compiled.schema.validate(tree):
            return []
        errors: list[Any] = list(compiled.schema.error_log)  # type: ignore[call-overload]
    if not errors:  # pragma: no cover - libxml2 always logs why
        return [XmlError(f"does not match schema {schema}", path=name)]
    return [XmlError(f"does not match schema {schema}: {error.message}", path=name, line=error.line if error.line else None)
            for error in errors]
