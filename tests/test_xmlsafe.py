"""The XML door: CMION 2011 files load as they are; hostile, oversize or broken input is refused.

Every refusal must be an ``XmlError`` whose text starts ``file:line:``, so an operator can find the
fault without a debugger.
"""

from __future__ import annotations

import re
import shutil
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from lxml import etree

from cmion_mesh import xmlsafe
from cmion_mesh.errors import ConfigError, XmlError

CMION = Path(__file__).parent / "data" / "cmion2011"

SCHEMA_OF: dict[str, str | None] = {
    "ArchitectureConfiguration.xml": "ArchitectureConfiguration.xsd",
    "CompManagerRulesExample.xml": "CompetencyManagerRules.xsd",
    "CompManagerRulesTest.xml": "CompetencyManagerRules.xsd",
    "CompetencyLibraryTest.xml": "CompetencyLibrary.xsd",
    "worldModelInit.xml": "WorldModel.xsd",
    "MigrationConfigReceive.xml": None,
    "MigrationConfigSend.xml": None,
}

SECRET = "TOP-SECRET-7f3a9c"


def located(exc: XmlError, name: str) -> int:
    """Assert the error names ``name`` and a line; return that line."""
    assert exc.path == name
    assert isinstance(exc.line, int) and exc.line >= 1, str(exc)
    assert str(exc).startswith(f"{name}:{exc.line}: "), str(exc)
    return exc.line


def refuse(data: bytes, name: str = "doc.xml", schema: str | None = None, **limits: int) -> XmlError:
    with pytest.raises(XmlError) as info:
        xmlsafe.loads(data, schema, name=name, **limits)
    located(info.value, name)
    return info.value


@pytest.fixture
def resolver_calls(monkeypatch: pytest.MonkeyPatch) -> list[str | None]:
    """Record every attempt libxml2 makes to fetch an external resource (there must be none)."""
    calls: list[str | None] = []
    original = xmlsafe.DenyAllResolver.resolve

    def spy(self: xmlsafe.DenyAllResolver, url: str | None, public_id: str | None, context: object) -> Any:
        calls.append(url)
        return original(self, url, public_id, context)

    monkeypatch.setattr(xmlsafe.DenyAllResolver, "resolve", spy)
    return calls


# --- CMION 2011 files --------------------------------------------------------------------------------


def test_every_cmion_file_is_covered() -> None:
    assert sorted(p.name for p in CMION.glob("*.xml")) == sorted(SCHEMA_OF)


@pytest.mark.parametrize("file_name", sorted(SCHEMA_OF))
def test_cmion_file_loads_and_validates(file_name: str, resolver_calls: list[str | None]) -> None:
    tree = xmlsafe.load(CMION / file_name, SCHEMA_OF[file_name])
    assert tree.getroot() is not None
    assert resolver_calls == []  # the DTD named by the DOCTYPE was never asked for


def test_cmion_content_is_read_as_written() -> None:
    root = xmlsafe.load(CMION / "worldModelInit.xml", "WorldModel.xsd").getroot()
    assert root.tag == "WorldModel"
    agents = root.findall("Agent")
    assert [a.get("Name") for a in agents] == ["UserA", "UserB"]
    first = agents[0].find("Property")
    assert first is not None
    assert (first.get("Name"), first.get("Value"), first.get("Persistent")) == (
        "speaksEnglish",
        "True",
        "True",
    )
    config = xmlsafe.load(CMION / "ArchitectureConfiguration.xml", "ArchitectureConfiguration.xsd").getroot()
    assert config.get("WorldModelInitFile") == "worldModelInit.xml"
    assert len(config.findall("ArchitectureComponent")) == 4


def test_dtd_beside_the_file_is_never_read(tmp_path: Path, resolver_calls: list[str | None]) -> None:
    shutil.copy(CMION / "worldModelInit.xml", tmp_path / "worldModelInit.xml")
    # Were this DTD read, it would fail to parse, inject a secret, or blow up memory.
    (tmp_path / "WorldModelInit.dtd").write_text(
        f'<!ENTITY secret "{SECRET}">\n'
        '<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">'
        '<!ENTITY c "&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;"><!ENTITY d "&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;">\n'
        "<!ELEMENT WorldModel (Nothing)> this is not a DTD at all <<<\n",
        encoding="utf-8",
    )
    tree = xmlsafe.load(tmp_path / "worldModelInit.xml", "WorldModel.xsd")
    assert resolver_calls == []
    assert SECRET not in etree.tostring(tree, encoding="unicode")
    assert len(tree.getroot()) == 4


def test_schema_extensions_validate(tmp_path: Path) -> None:
    xmlsafe.loads(
        b'<WorldModel><Object Name="o"><Property Name="n" Value="3" Type="int"/></Object></WorldModel>',
        "WorldModel.xsd",
    )
    xmlsafe.loads(
        b'<ArchitectureConfiguration CompetencyManagerRulesFile="r.xml"'
        b' CompetencyLibraryConfigurationFile="l.xml" Embodiment="robot-1" Companion="spirit"/>',
        "ArchitectureConfiguration.xsd",
    )
    xmlsafe.loads(
        b"<CompetencyManagerRules><Rule>"
        b'<MindAction Name="Talk" Subject="SELF"><Parameter No="1" Value="*"/></MindAction>'
        b'<CompetencyExecutionPlan><Competency ID="1" Type="Speak"/></CompetencyExecutionPlan>'
        b'<CompetencyExecutionPlan><Competency ID="1" Type="Write"/></CompetencyExecutionPlan>'
        b"</Rule></CompetencyManagerRules>",
        "CompetencyManagerRules.xsd",
    )


@pytest.mark.parametrize(
    ("schema", "data", "bad_line", "words"),
    [
        (
            "WorldModel.xsd",
            b'<WorldModel>\n<Agent Name="a">\n<Property Name="p" Value="1" Type="long"/>\n</Agent>\n'
            b"</WorldModel>",
            3,
            "Type",
        ),
        (
            "WorldModel.xsd",
            b"<WorldModel>\n<Agent Name='a'>\n<Agent Name='b'/>\n</Agent>\n</WorldModel>",
            3,
            "Agent",
        ),
        (
            "CompetencyLibrary.xsd",
            b"<CompetencyLibrary>\n<SamgarCompetency ClassName='x'/>\n</CompetencyLibrary>",
            2,
            "Port",
        ),
        (  # any order (as CMION's loader read them), but only these two elements
            "CompetencyLibrary.xsd",
            b"<CompetencyLibrary>\n<SamgarCompetency ClassName='x' Port='p'/>\n<Competency ClassName='y'/>\n"
            b"<Competence ClassName='z'/>\n</CompetencyLibrary>",
            4,
            "Competence",
        ),
        (
            "CompetencyManagerRules.xsd",
            b"<CompetencyManagerRules>\n<Rule>\n<MindAction Name='a'>\n<Parameter No='0' Value='v'/>\n"
            b"</MindAction>\n<CompetencyExecutionPlan/>\n</Rule>\n</CompetencyManagerRules>",
            4,
            "No",
        ),
        (
            "CompetencyManagerRules.xsd",
            b"<CompetencyManagerRules>\n<Rule>\n<MindAction Name='a'/>\n<ExecutionPlan/>\n</Rule>\n</CompetencyManagerRules>",
            4,
            "ExecutionPlan",
        ),
        # libxml2 puts an element on the line where its start tag ends
        (
            "ArchitectureConfiguration.xsd",
            b"<ArchitectureConfiguration\n CompetencyManagerRulesFile='r'/>",
            2,
            "CompetencyLibraryConfigurationFile",
        ),
        (
            "ArchitectureConfiguration.xsd",
            b"<ArchitectureConfiguration CompetencyManagerRulesFile='r'\n"
            b" CompetencyLibraryConfigurationFile='l' Embodiment='a/b'/>",
            2,
            "Embodiment",
        ),
        ("WorldModel.xsd", b"<Agent Name='a'/>", 1, "Agent"),  # only the documented root is a root
    ],
)
def test_schema_violation_names_file_and_line(schema: str, data: bytes, bad_line: int, words: str) -> None:
    exc = refuse(data, name="bad.xml", schema=schema)
    assert exc.line == bad_line
    assert schema in str(exc) and words in str(exc)


def test_schema_violation_in_file(tmp_path: Path) -> None:
    text = (CMION / "worldModelInit.xml").read_text(encoding="utf-8")
    bad = tmp_path / "wm.xml"
    bad.write_text(text.replace('<Object Name="Cake">', "<Object>"), encoding="utf-8")
    with pytest.raises(XmlError) as info:
        xmlsafe.load(bad, "WorldModel.xsd")
    assert located(info.value, str(bad)) == 19
    assert "Name" in str(info.value)


# --- hostile input -----------------------------------------------------------------------------------


def test_external_entity_reading_a_secret_is_refused(
    tmp_path: Path, resolver_calls: list[str | None]
) -> None:
    secret = tmp_path / "secret.txt"
    secret.write_text(SECRET, encoding="utf-8")
    doc = tmp_path / "xxe.xml"
    doc.write_text(
        f'<?xml version="1.0"?>\n<!DOCTYPE r [\n<!ENTITY xxe SYSTEM "{secret.as_uri()}">\n]>\n<r>&xxe;</r>\n',
        encoding="utf-8",
    )
    with pytest.raises(XmlError) as info:
        xmlsafe.load(doc, None)
    assert located(info.value, str(doc)) == 2
    assert "DTD" in str(info.value)
    assert SECRET not in repr(info.value) and SECRET not in str(info.value.__cause__ or "")
    assert resolver_calls == []


def test_entity_reference_to_external_dtd_entity_is_refused() -> None:
    # A DOCTYPE naming an external DTD makes an undeclared entity legal to libxml2 (it would become ""
    # in an attribute): refuse it instead of silently dropping text.
    exc = refuse(b'<!DOCTYPE a SYSTEM "a.dtd">\n<a x="&foo;"/>')
    assert exc.line == 2 and "&foo;" in str(exc)
    exc = refuse(b'<!DOCTYPE a SYSTEM "a.dtd">\n<a>\n&foo;</a>')
    assert exc.line == 3


def test_billion_laughs_is_refused() -> None:
    lines = ['<?xml version="1.0"?>', "<!DOCTYPE lolz [", ' <!ENTITY lol "lol">']
    lines += [f' <!ENTITY lol{i} "{f"&lol{i - 1};" * 10 if i > 1 else "&lol;" * 10}">' for i in range(1, 10)]
    lines += ["]>", "<lolz>&lol9;</lolz>"]
    exc = refuse("\n".join(lines).encode(), name="laughs.xml")
    assert exc.line == 2


def test_external_parameter_entity_is_refused(tmp_path: Path, resolver_calls: list[str | None]) -> None:
    evil = tmp_path / "evil.dtd"
    evil.write_text(f'<!ENTITY leak "{SECRET}">', encoding="utf-8")
    data = f'<!DOCTYPE r [\n<!ENTITY % x SYSTEM "{evil.as_uri()}">\n%x;\n]>\n<r>&leak;</r>'.encode()
    exc = refuse(data, name="pe.xml")
    assert exc.line == 1 and SECRET not in str(exc)
    assert resolver_calls == []


def test_internal_subset_entity_is_refused() -> None:
    exc = refuse(b'<?xml version="1.0"?>\n<!DOCTYPE r [ <!ENTITY greeting "hello"> ]>\n<r>&greeting;</r>')
    assert exc.line == 2
    exc = refuse(b"<r>\n<!-- a stray declaration -->\n<!ENTITY x 'y'>\n</r>")
    assert exc.line == 3 and "ENTITY" in str(exc)


@pytest.mark.parametrize(
    "data",
    [
        b'<!DOCTYPE r [\n<!ENTITY e "x">\n]>\n<r>&e;</r>',
        b"<!DOCTYPE r [\n<!ELEMENT r ANY>\n]>\n<r/>",
        b'<!DOCTYPE r SYSTEM "r.dtd" [\n<!ATTLIST r a CDATA "default">\n]>\n<r/>',
    ],
)
def test_parsed_tree_is_checked_even_if_prescan_missed(
    data: bytes, monkeypatch: pytest.MonkeyPatch, resolver_calls: list[str | None]
) -> None:
    """The post-parse check stands on its own: disable the pre-scan and the DTD is still refused."""
    monkeypatch.setattr(xmlsafe, "_prescan", lambda text, name: None)
    exc = refuse(data)
    assert "DTD" in str(exc) or "entity" in str(exc)
    assert resolver_calls == []


def test_entity_node_is_refused_even_if_prescan_missed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(xmlsafe, "_prescan", lambda text, name: None)
    exc = refuse(b'<!DOCTYPE a SYSTEM "a.dtd">\n<a>\n<b>&foo;</b></a>')
    assert exc.line == 3 and "&foo;" in str(exc)


def test_resolver_stops_a_parser_that_would_read_files(tmp_path: Path) -> None:
    """The resolver is the backstop should parser options ever let libxml2 fetch something."""
    (tmp_path / "x.dtd").write_text(f'<!ENTITY s "{SECRET}">', encoding="utf-8")
    doc = tmp_path / "x.xml"
    doc.write_text('<!DOCTYPE a SYSTEM "x.dtd"><a>&s;</a>', encoding="utf-8")
    parser = etree.XMLParser(load_dtd=True, resolve_entities=True, no_network=True)
    parser.resolvers.add(xmlsafe.DenyAllResolver())
    with pytest.raises(xmlsafe.ExternalResourceRefused):
        etree.parse(str(doc), parser)


def test_oversize_file_is_refused_unparsed(tmp_path: Path) -> None:
    big = tmp_path / "big.xml"
    big.write_bytes(b"<r>\n" + b"<a/>\n" * 400 + b"</r>\n")
    with pytest.raises(XmlError) as info:
        xmlsafe.load(big, None, max_bytes=1000)
    located(info.value, str(big))
    assert "1000 bytes" in str(info.value)
    exc = refuse(b"<r>" + b" " * 100 + b"</r>", max_bytes=50)
    assert "50 bytes" in str(exc)


def test_exactly_max_bytes_is_accepted() -> None:
    data = b"<r>" + b" " * 93 + b"</r>"
    assert len(data) == 100
    xmlsafe.loads(data, None, max_bytes=100)


def test_deep_nesting_is_refused_at_the_crossing_line() -> None:
    exc = refuse(b"<a>" * 10_000 + b"</a>" * 10_000, name="deep.xml")
    assert exc.line == 1 and "64" in str(exc)
    exc = refuse(b"\n".join([b"<a>"] * 20 + [b"</a>"] * 20), max_depth=10)
    assert exc.line == 11 and "10 levels" in str(exc)
    xmlsafe.loads(b"<a>" * 10 + b"</a>" * 10, None, max_depth=10)


def test_too_many_elements_is_refused_at_the_crossing_line() -> None:
    # libxml2 reports lines from 65535 on one too high, so the default limit is only checked loosely.
    exc = refuse(b"<r>\n" + b"<a/>\n" * 200_000 + b"</r>")
    assert (
        exc.line is not None and xmlsafe.DEFAULT_MAX_ELEMENTS <= exc.line <= xmlsafe.DEFAULT_MAX_ELEMENTS + 2
    )
    assert f"more than {xmlsafe.DEFAULT_MAX_ELEMENTS} elements" in str(exc)
    exc = refuse(b"<r>\n" + b"<a/>\n" * 30 + b"</r>", max_elements=10)
    assert exc.line == 11 and "10 elements" in str(exc)  # the 11th element is on line 11


@pytest.mark.parametrize(
    ("data", "line"),
    [
        (b"<a>\n<b>\n</a>", 3),
        (b'<?xml version="1.0"?>\n<r>\n  <x y="1" y="2"/>\n</r>', 3),
        (b"<r>\n<x>\n</x>\n", 4),
        (b"<r/>\n<r/>", 2),
        (b"<r>\n & </r>", 2),
        (b"", 1),
    ],
)
def test_malformed_syntax_names_the_line(data: bytes, line: int) -> None:
    exc = refuse(data, name="broken.xml")
    assert exc.line == line
    assert "malformed XML" in str(exc)


def test_malformed_file_names_the_path(tmp_path: Path) -> None:
    doc = tmp_path / "broken.xml"
    doc.write_bytes(b"<r>\n\n\n<open>\n</r>\n")
    with pytest.raises(XmlError) as info:
        xmlsafe.load(doc, None)
    assert located(info.value, str(doc)) == 5


@pytest.mark.parametrize(
    ("data", "line"),
    [
        (b"<r>\n\xff\xfe\x80garbage</r>", 2),
        (b"\x80\x81\x82\x83", 1),
        (b'<?xml version="1.0" encoding="UTF-8"?>\n<r>\n\xc3\x28</r>', 3),
        # UTF-7 could spell "<!DOCTYPE r [<!ENTITY e 'x'>]>" without a single "<"
        (
            b'<?xml version="1.0" encoding="UTF-7"?>'
            b'+ADw-!DOCTYPE r +AFs-+ADw-!ENTITY e "x"+AD4-+AF0-+AD4-<r/>',
            1,
        ),
        # a declaration padded past the pre-scan's window
        (b'<?xml version="1.0"' + b" " * 2000 + b'encoding="UTF-7"?><r/>', 1),
        (b'<?xml version="1.0" encoding="no-such-codec"?><r/>', 1),
        (b"\x4c\x6f\xa7\x94\x93\x40", 1),  # EBCDIC
        ('<?xml version="1.0" encoding="UTF-16"?><r/>'.encode("utf-32"), 1),
    ],
)
def test_undecodable_or_unsupported_bytes_are_refused(data: bytes, line: int) -> None:
    assert refuse(data, name="garbage.xml").line == line


def test_other_encodings_load() -> None:
    for codec, declared in [("utf-16", "UTF-16"), ("iso-8859-1", "ISO-8859-1"), ("utf-8-sig", "UTF-8")]:
        data = f'<?xml version="1.0" encoding="{declared}"?>\n<r v="é">ü</r>'.encode(codec)
        root = xmlsafe.loads(data, None).getroot()
        assert (root.get("v"), root.text) == ("é", "ü")
    exc = refuse(
        '<?xml version="1.0" encoding="UTF-16"?>\n<!DOCTYPE r [<!ENTITY e "x">]><r/>'.encode("utf-16")
    )
    assert exc.line == 2


def test_character_and_predefined_references_are_fine() -> None:
    root = xmlsafe.loads(
        b'<r a="&lt;&amp;&#65;&#x42;">&gt;&quot;&apos;<!-- Tom & Jerry --></r>', None
    ).getroot()
    assert root.get("a") == "<&AB"
    assert root.text == ">\"'"


def test_public_doctype_without_subset_is_fine(resolver_calls: list[str | None]) -> None:
    xmlsafe.loads(b'<!DOCTYPE r PUBLIC "-//CMION//Test//EN" "http://example.invalid/r.dtd">\n<r/>', None)
    assert resolver_calls == []


def test_unreadable_file_is_an_xml_error(tmp_path: Path) -> None:
    with pytest.raises(XmlError) as info:
        xmlsafe.load(tmp_path / "missing.xml", None)
    assert str(info.value).startswith(str(tmp_path / "missing.xml"))
    assert isinstance(info.value, ConfigError)


# --- schemas -----------------------------------------------------------------------------------------


def test_schema_path_finds_repository_schemas() -> None:
    for name in (
        "WorldModel.xsd",
        "CompetencyLibrary.xsd",
        "CompetencyManagerRules.xsd",
        "ArchitectureConfiguration.xsd",
    ):
        path = xmlsafe.schema_path(name)
        assert path.is_file() and path.name == name
        xmlsafe.load(path, None)  # the schemas pass through the same door


def test_schema_path_prefers_the_packaged_copy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    packaged = tmp_path / "cmion_mesh" / "schemas"
    packaged.mkdir(parents=True)
    shutil.copy(xmlsafe.schema_path("WorldModel.xsd"), packaged / "WorldModel.xsd")
    repo = xmlsafe.SCHEMA_DIRS[-1]
    monkeypatch.setattr(xmlsafe, "SCHEMA_DIRS", (packaged, repo))
    assert xmlsafe.schema_path("WorldModel.xsd") == packaged / "WorldModel.xsd"
    assert xmlsafe.schema_path("CompetencyLibrary.xsd") == repo / "CompetencyLibrary.xsd"


@pytest.mark.parametrize("name", ["../pyproject.toml", "/etc/passwd", "", "..", "sub/x.xsd"])
def test_schema_path_refuses_paths(name: str) -> None:
    with pytest.raises(ValueError):
        xmlsafe.schema_path(name)


def test_unknown_schema() -> None:
    with pytest.raises(FileNotFoundError):
        xmlsafe.schema_path("Nope.xsd")


def test_concurrent_validation_keeps_each_error() -> None:
    good = b'<WorldModel><Agent Name="a"/></WorldModel>'
    bad = b"<WorldModel>\n<Agent/></WorldModel>"
    failures: list[str] = []

    def work(i: int) -> None:
        for _ in range(30):
            try:
                xmlsafe.loads(bad if i % 2 else good, "WorldModel.xsd", name=f"doc{i}")
                if i % 2:
                    failures.append(f"doc{i} accepted")
            except XmlError as exc:
                if not (i % 2 and exc.line == 2 and "Name" in str(exc)):
                    failures.append(str(exc))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert failures == []


# --- fuzz --------------------------------------------------------------------------------------------

VALID = [((CMION / name).read_bytes(), SCHEMA_OF[name]) for name in sorted(SCHEMA_OF)]
_fuzz = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def only_xml_errors(call: Callable[[], object]) -> None:
    try:
        call()
    except XmlError as exc:
        assert re.match(r"^<fuzz>(:\d+)?: ", str(exc)), str(exc)


@_fuzz
@given(st.binary(max_size=4096))
def test_fuzz_random_bytes(data: bytes) -> None:
    only_xml_errors(lambda: xmlsafe.loads(data, "WorldModel.xsd", name="<fuzz>"))


_INTERESTING = [
    b"<",
    b">",
    b"&",
    b"&amp;",
    b"&x;",
    b"<!ENTITY x 'y'>",
    b"[",
    b"]",
    b'"',
    b"'",
    b"\x00",
    b"\xff",
    b"<!--",
    b"-->",
    b"<![CDATA[",
    b"]]>",
    b"<?",
    b"?>",
    b"<a>",
    b"</a>",
    b"=",
    b"%x;",
    b"\n",
    b"\xc3",
]


@_fuzz
@given(
    st.sampled_from(VALID),
    st.lists(
        st.tuples(
            st.floats(0, 1),
            st.integers(0, 8),
            st.one_of(st.sampled_from(_INTERESTING), st.binary(max_size=8)),
        ),
        min_size=1,
        max_size=6,
    ),
)
def test_fuzz_mutated_cmion_files(
    original: tuple[bytes, str | None], edits: list[tuple[float, int, bytes]]
) -> None:
    content, schema = original
    data = bytearray(content)
    for where, cut, insert in edits:
        at = int(where * len(data))
        data[at : at + cut] = insert
    only_xml_errors(lambda: xmlsafe.loads(bytes(data), schema, name="<fuzz>"))
