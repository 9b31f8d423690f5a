"""Property tests over every decoder of bytes from the network or a file.

(a) ``messages.decode`` for every message type and the unions: random bytes, MessagePack maps with
    random tags and fields, and mutated valid encodings; only ``ProtocolError`` escapes, and every
    decoded message holds plain data only.
(b) The request path: random payloads sent as queries to every component of an embodiment on the
    memory transport; every query gets exactly one reply, an ``Outcome``, and the embodiment
    keeps answering.
(c) Identity documents (``identity.unpack``) and the semantic loaders of CMION configuration
    files (``tests/test_xmlsafe.py`` already fuzzes ``xmlsafe.loads`` itself): only ``ConfigError``.
(d) custody chains and offers (``custody.verify_chain``, ``verify_offer``): only ``SignatureRefused``.
(e) The planner spec (``spec_from_data``, ``load_spec``): only ``ConfigError``.

Hangs: every call is timed against ``BOUND`` (pytest-timeout stops a call that never returns).
Tests with an ``@example`` pin a bug they found when they were written (fixed since).
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import threading
import time
import typing
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from cmion_mesh import keys, messages
from cmion_mesh.body.architecture import load_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.library import read_library
from cmion_mesh.body.remote import CompetencyHost
from cmion_mesh.body.rules import load_rules
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, ProtocolError
from cmion_mesh.messages import (
    Act,
    ActionReport,
    ActionStatus,
    AddContainer,
    AddEntity,
    AnyMessage,
    CancelAction,
    CancelRun,
    Container,
    CustodyResume,
    CustodyStandDown,
    Describe,
    Event,
    ExecutionStatus,
    Invite,
    Message,
    Migrate,
    MigrateAbort,
    MigrateChain,
    MigrateCommit,
    MigrateHave,
    MigratePrepare,
    MigrateSections,
    MigrateStatus,
    MindMessage,
    MindState,
    Outcome,
    Property,
    RemoteAction,
    RemoveContainer,
    RemoveProperty,
    RequestAnswered,
    RunEnded,
    SectionChunk,
    SendInvitations,
    SetPolicy,
    SetProperty,
    Sleep,
    StartRun,
    StorageChange,
    StorageWrite,
    Wake,
    check_value,
    decode,
    encode,
)
from cmion_mesh.migration import custody, identity, signing
from cmion_mesh.migration.identity import Identity
from cmion_mesh.minds.planner.spec import load_spec, spec_from_data
from cmion_mesh.storage import load_world_model_init
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .conftest import CMION_2011
from .helpers.custody_helpers import Holder
from .helpers.remote_helpers import Diary

pytestmark = pytest.mark.timeout(120)

#: Seconds any one call may take before it counts as a hang (they normally take microseconds).
BOUND = 2.0

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ_SLOW = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@contextmanager
def within(seconds: float = BOUND) -> Iterator[None]:
    """Fail if the block takes longer than ``seconds``: a hang, or work out of proportion to the input."""
    started = time.perf_counter()
    yield
    elapsed = time.perf_counter() - started
    assert elapsed < seconds, f"took {elapsed:.2f} s (bound {seconds} s)"


# --- strategies ----------------------------------------------------------------------------------------

PLAIN_LEAVES = st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=12)
#: What MessagePack can carry, plain or not: bytes, extensions, non-string map keys.
WIRE_LEAVES = PLAIN_LEAVES | st.binary(max_size=8) | st.builds(msgspec.msgpack.Ext, st.integers(-128, 127), st.binary(max_size=4))
WIRE = st.recursive(
    WIRE_LEAVES,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6) | st.integers(-5, 5), inner, max_size=4),
    max_leaves=20,
)
JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=25,
)
#: Python data, as ``spec_from_data`` may also be given: NaN and infinities included.
PY_DATA = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=25,
)
NAME = st.text(alphabet="abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.", min_size=1, max_size=12)


def _edit(data: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
    """Apply (position, bytes to cut, bytes to insert) edits; flips are a cut of one and an insert of one."""
    out = bytearray(data)
    for position, cut, insert in edits:
        at = position % (len(out) + 1)
        out[at : at + cut] = insert
    return bytes(out)


#: Bytes that mean something to MessagePack or to XML and JSON.
INTERESTING = [
    b"\xc1", b"\xff", b"\xc0", b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff", b"\xdb\xff\xff\xff\xff", b"\xd9\xff", b"\xc7\x01\xff",
    b"\xcf\xff\xff\xff\xff\xff\xff\xff\xff", b"\xcb\x7f\xf0\x00\x00\x00\x00\x00\x00", b"\x91" * 40, b"\xa4type", b"\xa0",
    b"<", b">", b"&", b"&x;", b"<!ENTITY x 'y'>", b"[", b"]" * 3, b"{", b"}", b'"', b"\\u0000", b"\x00", b"\xc3", b"<!--", b"]]>",
    b"\n", b"1e400", b"-", b"9" * 30,
]
EDITS = st.lists(
    st.tuples(st.integers(0, 1 << 16), st.integers(0, 6), st.sampled_from(INTERESTING) | st.binary(max_size=6)),
    min_size=1,
    max_size=5,
)

# --- (a) messages.decode ---------------------------------------------------------------------------------

SAMPLES: list[Message] = [
    Property({"x": [1, 2.5, None, "é"]}, True),
    Container("agent"),
    SetProperty("a/b", "p", {"x": [1, -2, 3.5, True]}, True),
    RemoveProperty("a", "p"),
    AddContainer("", "Vase", "object"),
    RemoveContainer("", "Vase"),
    SetProperty("blink", "count", 3, create=True),
    AddEntity("Visitor", "agent", {"present": True, "seen": [1, "x"]}, True),
    RemoteAction("Greet", ["Spirit"], "Visitor"),
    StorageChange("set_property", "Vase", "broken", True, True, ""),
    Event("robot", "bb", "PropertyChanged", {"op": "set_property", "value": [1, 2]}, 7, 1.5),
    Outcome("rejected", "no rule matches", {"action_id": "a-1"}, "not_found"),
    Describe(),
    ExecutionStatus(),
    Sleep(),
    Wake(),
    MindState(),
    MindMessage({"goal": {"name": "greet", "facts": [["Guest", "greeted", True]]}}),
    Act("Wave", ["left", "high"], "robot", "a-1", 2.5),
    CancelAction("a-1"),
    ActionStatus("a-1"),
    ActionReport("a-1", "Wave", ["left"], "robot", "failed", "jammed", "rules.xml:3", 2),
    StartRun("r-1", {"speed": 3, "where": ["a", "b"]}),
    CancelRun("r-1"),
    RunEnded("r-1", "succeeded", ""),
    RequestAnswered("robot", "manager", "act", "rejected", "not_found", "no rule matches", "", 1.5),
    Migrate("spirit", "screen"),
    MigratePrepare("spirit", 3, 1, "a1b2", "robot", "screen", b"<Identity/>", b"\x91\x97\xa1s", b"\x00" * 64),
    MigratePrepare("spirit", 3, 1, "a1b2", "robot", "screen", b"<Identity/>", b"\x91\x97\xa1s", b"\x00" * 64, [b"\xa1x"]),
    MigrateHave("spirit", 3, 1, "a1b2", "robot", "screen", b"<Identity/>", b"\x91\x97\xa1s", b"\x00" * 64),
    MigrateSections("spirit", "a1b2", "robot", "screen", [SectionChunk("0" * 64, 0, b"\x92\x01\x02")]),
    MigrateCommit("spirit", 3, "a1b2", "robot", "screen", b"\x97\xa1s"),
    MigrateAbort("spirit", 3, "a1b2"),
    MigrateStatus("spirit", "a1b2", 3, "target"),
    MigrateChain("spirit", 3, b"\x01" * 16),
    CustodyStandDown("spirit", "robot", b"\x91\x97\xa1s"),
    CustodyResume("spirit", ["screen"]),
    SetPolicy(["robot", "screen"]),
    Invite("screen"),
    SendInvitations(["robot"]),
]
MESSAGE_TYPES = sorted(
    (c for c in vars(messages).values()
     if isinstance(c, type) and issubclass(c, Message) and c is not Message and not c.__name__.startswith("_")),
    key=lambda c: c.__name__,
)
KINDS: list[Any] = [*MESSAGE_TYPES, AnyMessage, StorageWrite, Property | Container]
ENCODED = [encode(m) for m in SAMPLES]
TAGS = sorted({str(type(m).__struct_config__.tag) for m in SAMPLES})
FIELDS = sorted({f for m in SAMPLES for f in type(m).__struct_fields__})

#: A str field that is not UTF-8 (the tag of a Migrate, then its target).
NON_UTF8_TAG = b"\x83\xa4type\xa7migr\xffte\xa9companion\xa1s\xa6target\xa1t"
NON_UTF8_FIELD = encode(Migrate("s", "screen")).replace(b"screen", b"scr\xffen")


def test_every_message_type_has_a_sample() -> None:
    assert sorted({type(m).__name__ for m in SAMPLES}) == [c.__name__ for c in MESSAGE_TYPES]
    for message in SAMPLES:
        assert decode(encode(message), type(message)) == message
        assert decode(encode(message)) == message


def decodes_cleanly(data: bytes, *, tolerate: tuple[type[BaseException], ...] = ()) -> None:
    """Every kind refuses ``data`` with a ``ProtocolError`` naming where, or yields plain-data fields.

    ``tolerate``: exception types of a known bug, skipped by the variants kept running until it is fixed.
    """
    for kind in KINDS:
        try:
            with within():
                message = decode(data, kind, where="<fuzz>")
        except ProtocolError as exc:
            assert str(exc).startswith("<fuzz>: "), exc
            continue
        except tolerate:
            continue
        assert isinstance(message, Message)
        _check_fields(message)


def _check_fields(struct: msgspec.Struct) -> None:
    """Each field is what its type says: bytes where bytes are declared (also inside lists and nested
    Structs, as the section chunks carry them), plain data everywhere else."""
    for field in msgspec.structs.fields(struct):
        _check_typed(field.type, getattr(struct, field.name))


def _check_typed(kind: Any, value: Any) -> None:
    if typing.get_origin(kind) is typing.Annotated:
        kind = typing.get_args(kind)[0]
    if kind is bytes:
        assert isinstance(value, bytes)
    elif typing.get_origin(kind) is list and typing.get_args(kind)[0] is not Any and value is not None:
        item = typing.get_args(kind)[0]
        if item is bytes or (isinstance(item, type) and issubclass(item, msgspec.Struct)):
            for element in value:
                _check_typed(item, element)
        else:
            check_value(value)
    elif isinstance(kind, type) and issubclass(kind, msgspec.Struct):
        assert isinstance(value, kind)
        _check_fields(value)
    else:
        check_value(value)


@FUZZ
@given(st.binary(max_size=300))
@example(NON_UTF8_TAG)
@example(NON_UTF8_FIELD)
def test_decode_random_bytes(data: bytes) -> None:
    decodes_cleanly(data)


@given(st.binary(max_size=300))
@FUZZ
def test_decode_random_bytes_tolerating_the_unicode_bug(data: bytes) -> None:
    """The same as above, tolerating the known UnicodeDecodeError bug (kept running meanwhile)."""
    decodes_cleanly(data, tolerate=(UnicodeDecodeError,))


RANDOM_MAPS = st.builds(
    lambda tag, fields, keep_tag: {**fields, "type": tag} if keep_tag else fields,
    st.sampled_from([*TAGS, "", "Property", "nope"]) | st.text(max_size=6) | WIRE,
    st.dictionaries(st.sampled_from(FIELDS) | st.text(max_size=6), WIRE, max_size=8),
    st.booleans(),
)


@FUZZ
@given(RANDOM_MAPS)
@example({"type": "start_run", "run_id": "r", "parameters": {"blob": b"\x00"}})
def test_decode_random_maps(fields: dict[Any, Any]) -> None:
    decodes_cleanly(msgspec.msgpack.encode(fields))


@FUZZ
@given(RANDOM_MAPS)
def test_decode_random_maps_except_start_run_parameters(fields: dict[Any, Any]) -> None:
    """The same as above without ``parameters`` values that are not plain (the known bug), kept running meanwhile."""
    try:
        check_value(fields.get("parameters"))
    except ValueError:
        return
    decodes_cleanly(msgspec.msgpack.encode(fields))


@FUZZ
@given(st.sampled_from(ENCODED), EDITS)
@example(encode(Migrate("s", "screen")), [(encode(Migrate("s", "screen")).index(b"screen"), 1, b"\xff")])
def test_decode_mutated_encodings(original: bytes, edits: list[tuple[int, int, bytes]]) -> None:
    decodes_cleanly(_edit(original, edits))


@FUZZ
@given(st.sampled_from(ENCODED), EDITS)
def test_decode_mutated_encodings_tolerating_the_unicode_bug(original: bytes, edits: list[tuple[int, int, bytes]]) -> None:
    """The same as above, tolerating the known UnicodeDecodeError bug (kept running meanwhile)."""
    decodes_cleanly(_edit(original, edits), tolerate=(UnicodeDecodeError,))


# --- (b) the request path -------------------------------------------------------------------------------


class Wave(Competency):
    type = "Wave"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return True


RULES = (b'<CompetencyManagerRules><Rule><MindAction Name="Wave"/><CompetencyExecutionPlan><Competency ID="1" Type="Wave"/>'
         b"</CompetencyExecutionPlan></Rule></CompetencyManagerRules>")
VOCABULARY = ["Wave", "Migrate", "s", "spirit", "robot", "screen", "", "a/b", "*", "a-1", "r-1", "mind", "waver"]


@st.composite
def payload_for(draw: st.DrawFn, kind: Any) -> bytes:
    """Random bytes, a random map (with the kind's tag and fields, values from a vocabulary or random), or a
    mutated valid message of that kind."""
    choice = draw(st.integers(0, 2))
    if choice == 0:
        return draw(st.binary(max_size=200))
    samples = [m for m in SAMPLES if isinstance(m, kind)] or SAMPLES
    if choice == 1:
        sample = draw(st.sampled_from(samples))
        names = type(sample).__struct_fields__
        fields = draw(st.dictionaries(st.sampled_from(names), st.sampled_from(VOCABULARY) | WIRE, max_size=len(names))) \
            if names else {}
        tag = draw(st.sampled_from([type(sample).__struct_config__.tag, "act", "nope"]))
        return msgspec.msgpack.encode({**msgspec.structs.asdict(sample), **fields, "type": tag})
    return _edit(encode(draw(st.sampled_from(samples))), draw(EDITS))


def request_targets(embodiment: Embodiment) -> list[tuple[str, Any]]:
    """(key, payload kind) of every request of every component, in the per-sender form where one is wanted
    (sent as ``robot``, the source of the samples), plus two unknown requests."""
    mesh, name = embodiment.mesh, embodiment.name
    targets = []
    for component in embodiment.sim.components:
        senders: frozenset[str] = getattr(component, "sender_requests", frozenset())
        for request, kind in sorted(component.requests.items()):
            if request in senders:
                targets.append((keys.request_key(mesh, name, component.name, request, "robot"), kind))
            else:
                targets.append((keys.request_key(mesh, name, component.name, request), kind))
    return [*targets, (keys.request_key(mesh, name, "bb", "nope"), Describe), (keys.request_key(mesh, name, "manager", "x"), Describe)]


@st.composite
def hostile_request(draw: st.DrawFn, targets: list[tuple[str, Any]]) -> tuple[str, bytes]:
    key, kind = draw(st.sampled_from(targets))
    return key, draw(payload_for(kind))


def test_every_request_gets_one_outcome(network: MemoryNetwork, mesh: str, tmp_path: Path) -> None:
    (tmp_path / "rules.xml").write_bytes(RULES)
    with MemoryTransport(network, "robot") as transport, MemoryTransport(network, "intruder") as intruder, \
            Embodiment("robot", mesh=mesh, transport=transport, rules=tmp_path / "rules.xml", competencies=[Wave()],
                       components=[Diary(), CompetencyHost(Wave(name="waver"))], state_dir=tmp_path / "state") as robot:
        settled(robot)
        targets = request_targets(robot)
        covered = {key.split("/rq/")[1].split("/")[0] for key, _ in targets}
        assert {"bb", "wm", "manager", "migration", "mind", "waver", "embodiment", "execution"} <= covered

        def outcome_of(key: str, payload: bytes) -> Outcome:
            with within(BOUND + 1):
                replies = intruder.get(key, payload, timeout=BOUND)
            assert len(replies) == 1, f"{key}: {len(replies)} replies (none = outcome unknown)"
            assert replies[0].ok
            outcome: Outcome = decode(replies[0].payload, Outcome)
            return outcome

        def key_of(component: str, request: str) -> str:
            return keys.request_key(mesh, "robot", component, request)

        @FUZZ_SLOW
        @given(hostile_request(targets))
        @example((key_of("bb", "set_property"), NON_UTF8_FIELD))
        @example((key_of("manager", "act"), encode(Act("Wave", deadline=math.inf))))
        def one(request: tuple[str, bytes]) -> None:
            outcome_of(*request)

        one()
        # Still answering, and its loop still turning.
        assert outcome_of(key_of("bb", "set_property"), encode(SetProperty("", "after", 1))).status == "accepted"
        assert outcome_of(key_of("embodiment", "describe"), encode(Describe())).status == "accepted"
        settled(robot)


def settled(embodiment: Embodiment) -> None:
    done = threading.Event()
    embodiment.sim.call(done.set)
    assert done.wait(BOUND), "the update loop is stuck"


def test_every_storage_request_gets_one_outcome(network: MemoryNetwork, mesh: str) -> None:
    """The part of the request path free of known bugs (stores and the describer), kept running meanwhile."""
    with MemoryTransport(network, "robot") as transport, MemoryTransport(network, "intruder") as intruder, \
            Embodiment("robot", mesh=mesh, transport=transport, world_model_init=CMION_2011 / "worldModelInit.xml") as robot:
        settled(robot)
        targets = [t for t in request_targets(robot) if t[0].split("/rq/")[1].split("/")[0] in ("bb", "wm", "embodiment", "execution")]
        kinds = dict(targets)

        @FUZZ_SLOW
        @given(hostile_request(targets))
        def one(request: tuple[str, bytes]) -> None:
            key, payload = request
            try:
                decode(payload, kinds[key])
            except UnicodeDecodeError:
                return  # the known bug: see test_every_request_gets_one_outcome
            except ProtocolError:
                pass
            with within(BOUND + 1):
                replies = intruder.get(key, payload, timeout=BOUND)
            assert len(replies) == 1 and replies[0].ok, f"{key}: {replies}"
            decode(replies[0].payload, Outcome)

        one()
        settled(robot)


# --- (c) identity documents and configuration loaders -------------------------------------------------

#: Text an XML document can hold (JSON escapes control characters; U+FFFE and U+FFFF cannot appear at all),
#: and integers that MessagePack can carry on.
XML_TEXT = st.text(alphabet=st.characters(codec="utf-8", exclude_characters="\ufffe\uffff"), max_size=12)
XML_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**63 - 1) | st.floats(allow_nan=False, allow_infinity=False) | XML_TEXT,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(XML_TEXT, inner, max_size=4),
    max_leaves=25,
)
IDENTITIES = st.builds(Identity, NAME, st.integers(0, 2**63 - 1), st.dictionaries(NAME, XML_JSON, max_size=4))


def only_config_errors(call: Callable[[], object], where: str) -> object:
    try:
        with within():
            return call()
    except ConfigError as exc:
        assert str(exc).startswith(where), exc
        return None


def _checked_identity(data: bytes, *, names: bool = True, sections: dict[str, bytes] | None = None) -> None:
    """Only ``ConfigError`` escapes ``unpack``; what it returns is usable (with ``names``: companion and
    sections are names that can be key chunks, as everything downstream assumes)."""
    result = only_config_errors(lambda: identity.unpack(data, name="<fuzz>", sections=sections), "<fuzz>")
    if result is not None:
        assert isinstance(result, Identity)
        assert result.epoch >= 0
        check_value(result.sections)
        if names:
            keys.check_name(result.companion, "companion")
            for section in result.sections:
                keys.check_name(section, "section")


@FUZZ
@given(IDENTITIES)
def test_identity_round_trips(original: Identity) -> None:
    assert identity.unpack(original.pack()) == original


@FUZZ
@given(IDENTITIES)
def test_identity_round_trips_as_manifest_and_sections(original: Identity) -> None:
    packed = original.pack_sections()
    assert identity.unpack(packed.manifest, sections=packed.data) == Identity(original.companion, original.epoch,
                                                                              original.sections, 2)


@FUZZ
@given(IDENTITIES, EDITS)
def test_unpack_mutated_manifests(original: Identity, edits: list[tuple[int, int, bytes]]) -> None:
    packed = original.pack_sections()
    _checked_identity(_edit(packed.manifest, edits), sections=packed.data)


@FUZZ
@given(IDENTITIES, EDITS)
def test_unpack_mutated_section_bytes(original: Identity, edits: list[tuple[int, int, bytes]]) -> None:
    """Section bytes edited in place (as if their hash had been checked by a careless holder): still only ConfigError."""
    packed = original.pack_sections()
    _checked_identity(packed.manifest, sections={k: _edit(v, edits)[:len(v)].ljust(len(v), b"\xc1") for k, v in packed.data.items()})


@FUZZ
@given(st.binary(max_size=2048))
def test_unpack_random_bytes(data: bytes) -> None:
    _checked_identity(data)


_DECLARATION = b"<?xml version='1.0' encoding='UTF-8'?>\n"
_COMPANION_AT = len(_DECLARATION + b'<Identity SchemaVersion="1" Companion="s')


@FUZZ
@given(IDENTITIES, EDITS)
@example(Identity("s", 1, {}), [(_COMPANION_AT, 0, b"\n")])
@example(Identity("s", 1, {}), [(_DECLARATION.index(b"UTF"), 0, b"\x00")])
def test_unpack_mutated_documents(original: Identity, edits: list[tuple[int, int, bytes]]) -> None:
    assert original.pack().startswith(_DECLARATION)
    _checked_identity(_edit(original.pack(), edits))


@FUZZ
@given(IDENTITIES, EDITS)
def test_unpack_mutated_documents_without_declaration_or_name_check(original: Identity, edits: list[tuple[int, int, bytes]]) -> None:
    """The same as above on documents without an XML declaration, names unchecked: clear of both known bugs,
    kept running meanwhile."""
    _checked_identity(_edit(original.pack().removeprefix(_DECLARATION), edits), names=False)


@FUZZ
@given(
    st.sampled_from([b"", b"{", b"[" * 60, b"1e400", b'"\\ud800"', b"-0", b"9" * 5000, b'{"a":', b"\\", b"NaN", b"]]>"]),
    st.integers(1, 3),
)
def test_unpack_hostile_section_text(text: bytes, copies: int) -> None:
    body = b"".join(b'<Section Component="c%d">' % i + text + b"</Section>" for i in range(copies))
    _checked_identity(b'<Identity SchemaVersion="1" Companion="s" Epoch="1">' + body + b"</Identity>")


CONFIG_FILES = {
    "worldModelInit.xml": load_world_model_init,
    "CompManagerRulesTest.xml": load_rules,
    "CompManagerRulesExample.xml": load_rules,
    "CompetencyLibraryTest.xml": read_library,
    "ArchitectureConfiguration.xml": load_architecture,
}


@pytest.fixture(scope="module")
def config_dir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as folder:
        for name in CONFIG_FILES:
            shutil.copy(CMION_2011 / name, Path(folder) / name)
        yield Path(folder)


def test_config_loaders_on_mutated_files(config_dir: Path) -> None:
    """Every loader of a CMION file, on mutated copies: a ``ConfigError`` naming the file, or a result."""
    counter = iter(range(1 << 30))

    @FUZZ_SLOW
    @given(st.sampled_from(sorted(CONFIG_FILES)), EDITS)
    def one(name: str, edits: list[tuple[int, int, bytes]]) -> None:
        path = config_dir / f"mutated-{next(counter)}-{name}"
        path.write_bytes(_edit((CMION_2011 / name).read_bytes(), edits))
        try:
            only_config_errors(lambda: CONFIG_FILES[name](path), str(path.resolve() if "Architecture" in name else path))
        finally:
            path.unlink()

    one()


# --- (d) custody: chains and offers ------------------------------------------------------------------------

_PRIVATE = signing.new_key()
_DOCUMENT = Identity("s", 1, {"mind": {"x": 1}}).pack()
_PREPARE = Holder("s", "robot", private=_PRIVATE).prepare("screen", _DOCUMENT, "a1")
_CHAIN, _PROOF = _PREPARE.chain, _PREPARE.proof
_OFFER = custody.Offer("s", 1, 1, "a1", "robot", "screen", custody.digest(_DOCUMENT))
CHAINS = (
    st.binary(max_size=200)
    | st.just(_CHAIN)
    | EDITS.map(lambda edits: _edit(_CHAIN, edits))
    | st.lists(WIRE, max_size=9).map(msgspec.msgpack.encode)
)
OFFERS = st.just(_OFFER) | st.builds(custody.Offer, st.sampled_from(["s", "t", ""]), st.integers(-1, 3), st.integers(0, 2),
                                     st.sampled_from(["a1", "a2"]), st.sampled_from(["robot", "phone"]),
                                     st.sampled_from(["screen", "robot"]), st.just(custody.digest(_DOCUMENT)) | st.binary(max_size=33))
NON_UTF8_CHAIN = _CHAIN.replace(b"\xa5robot", b"\xa5rob\xfft", 1)


def _verify_checked(chain: bytes, proof: bytes, offer: custody.Offer, trusted: bytes | None) -> None:
    try:
        with within():
            links = custody.decode_chain(chain)
            custody.verify_chain(links, "s", identity=trusted)
            custody.verify_offer(links, offer, proof)
    except signing.SignatureRefused as exc:
        assert str(exc), "a refusal says which check failed"
        return
    # Accepted: only the genuine chain, proof and offer get here.
    assert (chain, proof, offer) == (_CHAIN, _PROOF, _OFFER)


@FUZZ
@given(CHAINS, st.just(_PROOF) | st.binary(max_size=80), OFFERS,
       st.none() | st.just(signing.public_of(_PRIVATE)) | st.binary(min_size=32, max_size=32))
@example(NON_UTF8_CHAIN, _PROOF, _OFFER, None)
def test_custody_checks_only_refuse(chain: bytes, proof: bytes, offer: custody.Offer, trusted: bytes | None) -> None:
    _verify_checked(chain, proof, offer, trusted)


def test_custody_accepts_the_genuine_offer() -> None:
    links = custody.decode_chain(_CHAIN)
    custody.verify_chain(links, "s", identity=signing.public_of(_PRIVATE))
    custody.verify_offer(links, _OFFER, _PROOF)


# --- (e) the planner spec ------------------------------------------------------------------------------------

FACTS = st.lists(st.lists(PY_DATA, min_size=0, max_size=4) | st.tuples(NAME, NAME, PY_DATA) | PY_DATA, max_size=3)
SPEC_SHAPED = st.fixed_dictionaries(
    {},
    optional={
        "operators": st.lists(st.fixed_dictionaries({}, optional={
            "name": NAME | PY_DATA, "action": NAME | PY_DATA, "parameters": st.lists(NAME) | PY_DATA,
            "preconditions": FACTS, "effects": FACTS, "cost": st.floats() | st.integers() | PY_DATA,
            "remember": st.booleans() | PY_DATA, "subject": NAME | PY_DATA}), max_size=3),
        "goals": st.lists(st.fixed_dictionaries({}, optional={"name": NAME | PY_DATA, "facts": FACTS,
                                                              "priority": st.floats() | PY_DATA, "persistent": PY_DATA}), max_size=3),
        "triggers": st.lists(st.fixed_dictionaries({}, optional={"when": FACTS | st.tuples(NAME, NAME, PY_DATA),
                                                                 "goal": PY_DATA, "believe": FACTS}), max_size=2),
        "emotion": st.fixed_dictionaries({}, optional={"decay": st.floats() | PY_DATA,
                                                       "appraisals": st.dictionaries(NAME, PY_DATA, max_size=2)}) | PY_DATA,
        "limits": st.dictionaries(st.sampled_from(["max_depth", "max_expanded", "memory", "retry_delay", "other"]),
                                  st.integers() | st.floats() | PY_DATA, max_size=3) | PY_DATA,
        "description": PY_DATA,
    },
)


def _spec_checked(data: Any) -> None:
    only_config_errors(lambda: spec_from_data(data), "")


@FUZZ
@given(st.dictionaries(st.text(max_size=8), PY_DATA, max_size=5) | st.lists(PY_DATA, max_size=4) | st.text(max_size=5))
def test_spec_from_random_data(data: Any) -> None:
    _spec_checked(data)


@FUZZ
@given(SPEC_SHAPED | st.lists(st.fixed_dictionaries({"name": NAME, "action": NAME}, optional={"cost": PY_DATA}), max_size=3))
def test_spec_from_spec_shaped_data(data: Any) -> None:
    _spec_checked(data)


_VALID_SPEC = json.dumps({
    "operators": [{"name": "walk", "action": "GoTo", "parameters": ["?p"], "preconditions": [["Robot", "at", "?f"]],
                   "effects": [["Robot", "at", "?p"]], "cost": 1}],
    "goals": [{"name": "g", "facts": [["Guest", "greeted", True]], "priority": 5}],
    "triggers": [{"when": ["Command", "greet", "?who"], "goal": {"name": "greet ?who", "facts": [["?who", "greeted", True]]}}],
    "emotion": {"decay": 0.9, "appraisals": {"action_failed": {"valence": -0.2, "arousal": 0.2}}},
    "limits": {"max_depth": 8, "retry_delay": 1.0},
}).encode()


@pytest.fixture(scope="module")
def spec_dir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as folder:
        yield Path(folder)


def test_load_spec_only_refuses(spec_dir: Path) -> None:
    path = spec_dir / "spec.json"
    assert load_spec(_write(path, _VALID_SPEC)).operators

    @FUZZ
    @given(st.binary(max_size=300) | EDITS.map(lambda edits: _edit(_VALID_SPEC, edits)) | JSON.map(lambda d: json.dumps(d).encode()))
    @example(_VALID_SPEC.replace(b"GoTo", b"Go\xffTo"))
    @example(b"[" * 5000)
    def one(data: bytes) -> None:
        only_config_errors(lambda: load_spec(_write(path, data)), str(path))

    one()


def test_load_spec_refuses_random_json(spec_dir: Path) -> None:
    """Random JSON documents, and mutations that stay valid UTF-8 and shallow: kept running while the bug above stands."""
    path = spec_dir / "spec.json"

    @FUZZ
    @given(JSON.map(lambda d: json.dumps(d).encode()) | EDITS.map(lambda edits: _edit(_VALID_SPEC, edits)))
    def one(data: bytes) -> None:
        try:
            data.decode()
        except UnicodeDecodeError:
            return
        if data.count(b"[") + data.count(b"{") > 500:
            return
        only_config_errors(lambda: load_spec(_write(path, data)), str(path))

    one()


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path
