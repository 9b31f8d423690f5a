"""Every message that crosses the wire: frozen, tagged msgspec Structs, encoded as MessagePack.

Each payload is one MessagePack map whose ``"type"`` field names the message (the tag);
fields are named, so a client in any language decodes them with a plain MessagePack library.
``docs/wire.md`` lists them with the keys they travel on.

Values carried by properties, events and requests are "plain data": str, int, float, bool,
None, lists and maps with string keys, nested to at most ``MAX_DEPTH``.

Every request kind has a Struct of its own, so a component dispatches by ``match`` on the decoded
type and a payload without its ``type`` (or with another request's) is refused before any
component sees it. A component outside this package declares its own request Structs (subclasses
of ``Message`` with a tag of their own) the same way.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable
from enum import StrEnum
from typing import Annotated, Any, Literal, TypeVar

import msgspec

from cmion_mesh.errors import ProtocolError

#: Largest payload decoded from the network; bigger ones are refused unread.
MAX_PAYLOAD = 16 * 1024 * 1024
MAX_DEPTH = 32
#: Largest identity manifest (SchemaVersion 2): the XML naming the sections, never their bytes.
MAX_MANIFEST = 1024 * 1024
#: Most section bytes in one chunk of ``migrate_sections`` (a request is under ``MAX_PAYLOAD`` as a whole).
MAX_SECTION_BYTES = 8 * 1024 * 1024
#: Most chunks in one ``migrate_sections`` request, and most sections one manifest names.
MAX_CHUNKS = 1000

Value = Any  # plain data, checked by ``check_value``


class Message(msgspec.Struct, frozen=True, tag_field="type", forbid_unknown_fields=False, gc=False):
    """Base of all wire messages; the subclass name (snake case) is the tag.

    Untracked by the garbage collector (``gc=False``): a message holds names and plain data, which
    cannot refer back to it, and a read of 100k properties otherwise spends about half its time in
    collections of objects that can never form a cycle."""


def tag(kind: type[Message]) -> str:
    """The ``type`` a message kind carries on the wire (also each storage write's request name)."""
    value = kind.__struct_config__.tag
    assert isinstance(value, str), f"{kind.__name__} has no tag"
    return value


# --- storage -----------------------------------------------------------------------------------


class Property(Message, frozen=True, tag="property"):
    """The value of one property, as answered by ``get`` and published on every change."""

    value: Value
    persistent: bool = False


class Container(Message, frozen=True, tag="container"):
    """A (sub-)container, as answered by ``get`` and published when it is added."""

    kind: str = ""


#: Kind of the containers a ``SetProperty`` with ``create`` adds on its way.
CONTAINER_KIND = "container"


class SetProperty(Message, frozen=True, tag="set_property"):
    container: str  # slash-separated path below the store's root, "" for the root
    name: str
    value: Value
    persistent: bool = False
    #: Add the containers of ``container`` that are missing first (kind ``container``), in the same
    #: write; never a world-model entity, which has a kind of its own (``AddEntity``). A daemon
    #: that does not know the field refuses the write for its missing container: nothing is lost.
    create: bool = False


class RemoveProperty(Message, frozen=True, tag="remove_property"):
    container: str
    name: str


class AddContainer(Message, frozen=True, tag="add_container"):
    container: str  # the parent
    name: str
    kind: str = ""


class RemoveContainer(Message, frozen=True, tag="remove_container"):
    container: str  # the parent
    name: str


class AddEntity(Message, frozen=True, tag="add_entity"):
    """A world-model entity and its properties, added in one write (``.../rq/wm/add_entity``): a
    mind hears the entity added, then each property set, in one update (CMION's AgentSimulator)."""

    name: str
    kind: str = "agent"  # or "object"
    properties: dict[str, Value] = {}
    persistent: bool = False  # of every property given


StorageWrite = SetProperty | RemoveProperty | AddContainer | RemoveContainer | AddEntity
#: The writes a store serves, each on the request named by its tag (``.../rq/<store>/set_property``...).
STORAGE_WRITES: tuple[type[StorageWrite], ...] = (SetProperty, RemoveProperty, AddContainer, RemoveContainer)


class StorageChange(Message, frozen=True, tag="storage_change"):
    """Event data raised by a store after each applied write."""

    op: Literal["set_property", "remove_property", "add_container", "remove_container"]
    container: str
    name: str
    value: Value = None
    persistent: bool = False
    kind: str = ""


# --- ION: events and requests --------------------------------------------------------------------


class Event(Message, frozen=True, tag="event"):
    """An event raised by a component; published on ``.../ev/<component>/<name>``."""

    embodiment: str
    component: str
    name: str
    data: Value = None
    seq: int = 0
    time: float = 0.0


Status = Literal["accepted", "rejected", "conflict"]


class Code(StrEnum):
    """Why a request was not accepted, for programs (``Outcome.code``); the reason is for people.

    The field is a plain string on the wire, so a peer that knows more codes is still understood.
    """

    NONE = ""
    #: The payload does not decode to the request's Struct (no ``type``, another type, bad fields).
    MALFORMED = "malformed"
    #: The component has no request of that name, or there is no such component.
    UNKNOWN_REQUEST = "unknown_request"
    #: The request came on the wrong form of its key (per-sender or not).
    WRONG_KEY = "wrong_key"
    SHUTTING_DOWN = "shutting_down"
    #: The component's handler raised; the reason holds the error.
    HANDLER_FAILED = "handler_failed"
    #: The component's handler left the request unanswered.
    UNANSWERED = "unanswered"
    #: Nobody answered, or the link failed: the request may or may not have been applied.
    OUTCOME_UNKNOWN = "outcome_unknown"
    #: The request names a thing (container, property, action, run...) that is not there.
    NOT_FOUND = "not_found"
    #: The request would create a thing whose name is taken.
    EXISTS = "exists"
    #: A value or name the request carries is not acceptable (a property where a container is...).
    INVALID = "invalid"
    #: Another request to the same thing in the same update won.
    CONFLICT = "conflict"
    #: The component cannot take the request now (a competency running, a mind asleep...).
    BUSY = "busy"
    #: A migration's target lacks sections its manifest names (value ``{"missing": [sha256 hex]}``):
    #: send them (``migrate_sections``) and prepare again.
    MISSING_SECTIONS = "missing_sections"


class Outcome(Message, frozen=True, tag="outcome"):
    """The definite answer to every request: accepted, rejected with a reason, or lost a conflict."""

    status: Status
    reason: str = ""
    value: Value = None
    code: str = ""  # a ``Code`` when not accepted (see ``Code``)


class RequestAnswered(Message, frozen=True, tag="request_answered"):
    """How an embodiment answered one request that reached it over the mesh, published on
    ``.../@outcome/<component>/<request>`` only while some session subscribes there (a recorder):
    requests are queries, which nobody else sees. ``sender`` is the per-sender key's last chunk
    (``""`` for the plain form); ``value`` is not carried (it may be large): ``status``, ``code``
    and ``reason`` are."""

    embodiment: str
    component: str
    request: str
    status: Status
    code: str = ""
    reason: str = ""
    sender: str = ""
    time: float = 0.0


# --- requests that only ask -------------------------------------------------------------------------


class Describe(Message, frozen=True, tag="describe"):
    """What an embodiment is and hosts (``.../rq/embodiment/describe``)."""


class ExecutionStatus(Message, frozen=True, tag="execution_status"):
    """The execution system's running plans and competencies (``.../rq/execution/status``)."""


# --- minds ---------------------------------------------------------------------------------------------


class Sleep(Message, frozen=True, tag="sleep"):
    """Put a mind to sleep (``.../rq/<mind>/sleep``): it perceives nothing and sends no action."""


class Wake(Message, frozen=True, tag="wake"):
    """Wake a mind (``.../rq/<mind>/wake``)."""


class MindState(Message, frozen=True, tag="mind_state"):
    """Ask for a mind's plain-data state, the one migration carries (``.../rq/<mind>/state``)."""


class MindMessage(Message, frozen=True, tag="mind_message"):
    """Raw data for a mind to interpret (``.../rq/<mind>/message``), e.g. a goal for the planner."""

    data: dict[str, Value]


class RemoteAction(Message, frozen=True, tag="remote_action"):
    """Another agent's action, as an embodiment perceives it (CMION's ``EventRemoteAction``): sent
    to ``.../rq/embodiment/remote_action``, raised there as the event ``.../ev/embodiment/RemoteAction``
    with this as its ``data``, which every mind of the embodiment perceives (``Mind.on_remote_action``).
    Any component may raise a ``RemoteAction`` event with the same data."""

    name: str
    parameters: list[str] = []
    subject: str = ""  # who acted ("" : nobody said; FAtiMA hears ``World``)


# --- competency manager --------------------------------------------------------------------------


class Act(Message, frozen=True, tag="act"):
    """A mind action to perform; sent to ``.../rq/manager/act``. An empty id is assigned by the manager."""

    name: str
    parameters: list[str] = []
    subject: str = ""
    action_id: str = ""
    deadline: float = 0.0  # seconds for each plan tried; 0 = the embodiment's default


class CancelAction(Message, frozen=True, tag="cancel_action"):
    action_id: str


class ActionStatus(Message, frozen=True, tag="action_status"):
    """``.../rq/manager/status``: how one action stands (running, or its final report), or with
    no id the ids of the running actions."""

    action_id: str = ""


#: An action's report: ``started``, a plan ``attempt``, ``running`` (a status answer), or how it ended.
ActionState = Literal["started", "attempt", "running", "succeeded", "failed", "cancelled"]


class ActionReport(Message, frozen=True, tag="action_report"):
    """Data of the manager's ``ActionStarted/Succeeded/Failed/Cancelled`` events."""

    action_id: str
    name: str
    parameters: list[str] = []
    subject: str = ""
    status: ActionState = "started"
    reason: str = ""
    rule: str = ""
    attempt: int = 0  # plans tried so far (1 for the first)


# --- remote competencies ---------------------------------------------------------------------------


class StartRun(Message, frozen=True, tag="start_run"):
    """Start one execution of a remote competency; sent to ``.../rq/<competency>/start``."""

    run_id: str
    parameters: dict[str, Value] = {}


class CancelRun(Message, frozen=True, tag="cancel_run"):
    run_id: str


RunStatus = Literal["succeeded", "failed", "cancelled"]


class RunEnded(Message, frozen=True, tag="run_ended"):
    """Data of a remote competency's ``RunSucceeded`` / ``RunFailed`` / ``RunCancelled`` events."""

    run_id: str
    status: RunStatus
    reason: str = ""


# --- migration ---------------------------------------------------------------------------------------


class Migrate(Message, frozen=True, tag="migrate"):
    """Ask the embodiment hosting ``companion`` to move it to ``target`` (``.../rq/migration/migrate``)."""

    companion: str
    target: str


class MigratePrepare(Message, frozen=True, tag="migrate_prepare"):
    """Source -> target: store this identity durably and say prepared (``.../rq/migration/prepare/<source>``).

    ``chain`` is the companion's chain of custody (``custody.encode_chain``), ``proof`` the source's
    signature over the ``custody.Offer`` made of these fields, by the custody key at the chain's head.
    The answer's value is ``{"state": "prepared", "custody_key": <base64>}``: the target's fresh key."""

    companion: str
    epoch: int
    seq: int
    attempt: str
    source: str
    target: str
    document: bytes
    chain: bytes
    proof: bytes
    #: Bytes of small sections the target is not known to hold (each named by its SHA-256 in the
    #: SchemaVersion 2 ``document``), so that a small identity takes no round trip more.
    sections: Annotated[list[bytes], msgspec.Meta(max_length=MAX_CHUNKS)] = []


class MigrateHave(Message, frozen=True, tag="migrate_have"):
    """Source -> target, before the prepare of a large identity (``.../rq/migration/have/<source>``):
    the SchemaVersion 2 manifest it is about to offer, with the chain and the proof of that offer
    (those of the prepare that follows). The target checks custody as for a prepare, records
    nothing, and answers ``{"have": [sha256 hex]}``: the sections it holds already, checked
    against their hash, so that only the others cross the network (``migrate_sections``)."""

    companion: str
    epoch: int
    seq: int
    attempt: str
    source: str
    target: str
    manifest: Annotated[bytes, msgspec.Meta(max_length=MAX_MANIFEST)]
    chain: bytes
    proof: bytes


class SectionChunk(msgspec.Struct, frozen=True):
    """``data`` is the bytes at ``offset`` of the section whose SHA-256 (hex) is ``sha256``.

    A view, not a copy: decoded, it points into the received message (megabytes a chunk, copied
    once where the section is put together rather than once more here); sent, into the section."""

    sha256: Annotated[str, msgspec.Meta(pattern="^[0-9a-f]{64}$")]
    offset: Annotated[int, msgspec.Meta(ge=0)]
    data: Annotated[memoryview, msgspec.Meta(max_length=MAX_SECTION_BYTES)]


class MigrateSections(Message, frozen=True, tag="migrate_sections"):
    """Source -> target, after ``have``: bytes of sections the target lacks, as raw MessagePack
    bytes in chunks (``.../rq/migration/sections/<source>``), each section's chunks in order. The
    target answers once every section completed by these chunks is whole and checked against its
    hash (its write and fsync go on beside; the prepare waits for them): ``{"stored": [sha256 hex]}``."""

    companion: str
    attempt: str
    source: str
    target: str
    chunks: Annotated[list[SectionChunk], msgspec.Meta(max_length=MAX_CHUNKS)]


class MigrateCommit(Message, frozen=True, tag="migrate_commit"):
    """Source -> target, after the source recorded ``handed``: become the companion's home. ``link``
    (a MessagePack ``custody.Link``) hands custody at ``epoch + 1`` to the target's fresh key."""

    companion: str
    epoch: int
    attempt: str
    source: str
    target: str
    link: bytes


class MigrateAbort(Message, frozen=True, tag="migrate_abort"):
    companion: str
    epoch: int
    attempt: str


class SetPolicy(Message, frozen=True, tag="set_policy"):
    """Set the companion's own policy (``.../rq/migration/policy``): the embodiments it accepts, or
    null for any. It is part of its identity, so it travels with it. ``accepts`` is required, so
    that clearing the policy is said, never implied by a map that forgot the field."""

    accepts: list[str] | None


class MigrateStatus(Message, frozen=True, tag="migrate_status"):
    """What became of an attempt? Asked of its source by a target that is ``incoming`` (``of="source"``:
    pending/committed/aborted, with the custody link when committed), and of its target by a source
    whose commit was refused (``of="target"``: incoming/committed/dropped)."""

    companion: str
    attempt: str
    epoch: int = 0
    of: Literal["source", "target"] = "source"


class MigrateChain(Message, frozen=True, tag="migrate_chain"):
    """Asker -> claimant (``.../rq/migration/chain/<asker>`` on the claimant): back your custody token.
    The claimant answers with the chain of custody it holds for ``companion`` and, when it holds
    custody (active, prepared, handed), a signature by the key at the chain's head over
    ``custody.ClaimProof(companion, epoch, claimant, asker, nonce)``: value ``{"state", "epoch",
    "chain", "proof"}`` (chain and proof in base64; proof "" while ``incoming``). Refused when it
    claims nothing of the companion. A token nobody backs so is ignored."""

    companion: str
    epoch: int
    nonce: Annotated[bytes, msgspec.Meta(max_length=64)]


class CustodyStandDown(Message, frozen=True, tag="custody_stand_down"):
    """Operator -> a holder of a branch of a forked chain of custody (``.../rq/migration/stand_down``):
    retire your copy, for the branch of ``keep`` (``chain``: its MessagePack custody links, which the
    holder verifies and records). Answered once that is on disk."""

    companion: str
    keep: str
    chain: bytes


class CustodyResume(Message, frozen=True, tag="custody_resume"):
    """Operator -> the holder kept (``.../rq/migration/resume``), once every other branch holder
    (``retired``) stood down: forget the fork, run the companion again."""

    companion: str
    retired: list[str] = []


# --- invitations -------------------------------------------------------------------------------------


class Invite(Message, frozen=True, tag="invite"):
    """An uninhabited embodiment invites the companion (``.../rq/invitation/invite/<inviter>`` on
    the embodiment asked). Accepted: the companion's mind got ``MigrationInvitation <inviter>``;
    rejected: not inhabited here, inviter unknown to this embodiment's device table, or busy."""

    inviter: str


class SendInvitations(Message, frozen=True, tag="send_invitations"):
    """Ask an embodiment to invite (``.../rq/invitation/send``): it sends ``Invite`` to each of
    ``to`` (empty: its device table's devices, or without a table every live embodiment). The
    answer's value is ``{"round", "targets"}``; the end is the ``InvitationsDone`` event."""

    to: list[str] = []


AnyMessage = (
    Property | Container | SetProperty | RemoveProperty | AddContainer | RemoveContainer | AddEntity | StorageChange | Event
    | Outcome | Describe | ExecutionStatus | Sleep | Wake | MindState | MindMessage | RemoteAction
    | Act | CancelAction | ActionStatus | ActionReport | StartRun | CancelRun | RunEnded
    | Migrate | MigratePrepare | MigrateCommit | MigrateAbort | MigrateStatus | SetPolicy | Invite | SendInvitations
    | MigrateHave | MigrateSections | RequestAnswered | MigrateChain | CustodyStandDown | CustodyResume
)


class _Untagged(Message, frozen=True, tag=""):
    """Never sent: decoding into ``kind | _Untagged`` makes msgspec require the ``type`` field,
    which it leaves optional when decoding into one tagged Struct."""

_encoder = msgspec.msgpack.Encoder()
#: Fields, in any message kind, that hold plain data: checked after decoding.
_PLAIN_NAMES = ("value", "data", "parameters", "properties")
#: Per message kind, its fields holding plain data (checked after decoding); never _Untagged.
_PLAIN_FIELDS: dict[type, tuple[str, ...]] = {}
_FLAT = frozenset({str, int, float, bool, type(None)})
#: Types that are plain data whatever their value (an int's range must be checked).
_SCALARS = frozenset({str, float, bool, type(None)})
_any_decoder = msgspec.msgpack.Decoder(AnyMessage)
_decoders: dict[Any, msgspec.msgpack.Decoder[Any]] = {}

M = TypeVar("M")


#: MessagePack bytes of a message (the encoder's own method: no Python call in between, per event).
encode: Callable[[Message], bytes] = _encoder.encode


def _check_plain(value: Any, where: str) -> None:
    """``check_value`` for a decoded field that is not a scalar, as ``ProtocolError`` naming ``where``."""
    try:
        check_value(value)
    except ValueError as exc:
        raise ProtocolError(f"{where or 'payload'}: {exc}") from None


@typing.overload
def decoder(kind: type[M]) -> Callable[[bytes, str], M]: ...
@typing.overload
def decoder(kind: types.UnionType) -> Callable[[bytes, str], Any]: ...
def decoder(kind: Any) -> Callable[[bytes, str], Any]:
    """``decode`` for one message kind, or a union of kinds (``Property | Container``), as a function
    of (data, where): what a hot path calls per message (events, outcomes, the entries of a read)
    without ``decode``'s lookups. Same checks, same errors."""
    kinds = typing.get_args(kind) if isinstance(kind, types.UnionType) else (kind,)
    if not kinds or not all(isinstance(k, type) and issubclass(k, Message) for k in kinds):
        raise TypeError(f"decoder() takes message kinds, not {kind!r}")
    # A union of tagged Structs needs its tag to decode; one kind alone needs _Untagged to need it.
    strict: msgspec.msgpack.Decoder[Any] = msgspec.msgpack.Decoder(kind if len(kinds) > 1 else kind | _Untagged)
    plain = {k: tuple(f for f in _PLAIN_NAMES if f in k.__struct_fields__) for k in kinds}
    flat = _FLAT

    def run(data: bytes, where: str = "") -> Any:
        if len(data) > MAX_PAYLOAD:
            raise ProtocolError(f"{where or 'payload'}: {len(data)} bytes exceeds the {MAX_PAYLOAD}-byte cap")
        try:
            message = strict.decode(data)
        except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError) as exc:
            raise ProtocolError(f"{where or 'payload'}: malformed message: {exc}") from None
        except RecursionError:
            raise ProtocolError(f"{where or 'payload'}: nested too deeply") from None
        fields = plain.get(type(message))
        if fields is None:
            raise ProtocolError(f"{where or 'payload'}: malformed message: its type is empty")
        for field in fields:
            value = getattr(message, field)
            if type(value) not in flat:
                _check_plain(value, where)
        return message

    return run


def many_decoder(kind: types.UnionType | type[Message]) -> Callable[[list[bytes]], list[Any]]:
    """Decode many payloads, each one message of ``kind`` (a kind or a union of kinds), in one
    msgspec call: a read of 100k properties otherwise spends more in a call per payload than in
    decoding. Same checks as ``decoder``. Raises ``ProtocolError`` when any payload is not one
    such message, without saying which: the caller decodes them one by one to find out.

    The payloads are decoded as the items of one MessagePack array, so a payload holding two
    messages and another holding none would shift the ones between: call it only on payloads
    from one sender (one embodiment's keys), whose misaligned payloads can only hurt its own."""
    kinds = typing.get_args(kind) if isinstance(kind, types.UnionType) else (kind,)
    if not kinds or not all(isinstance(k, type) and issubclass(k, Message) for k in kinds):
        raise TypeError(f"many_decoder() takes message kinds, not {kind!r}")
    items: Any = kind if len(kinds) > 1 else kind | _Untagged
    batch: msgspec.msgpack.Decoder[Any] = msgspec.msgpack.Decoder(list[items])
    plain = {k: tuple(f for f in _PLAIN_NAMES if f in k.__struct_fields__) for k in kinds}
    flat = _FLAT

    def run(payloads: list[bytes]) -> list[Any]:
        count = len(payloads)
        if count >= 2**32 or (count and (min(map(len, payloads)) == 0 or max(map(len, payloads)) > MAX_PAYLOAD)):
            raise ProtocolError("a payload is empty or over the cap")
        try:
            messages: list[Any] = batch.decode(b"".join((b"\xdd", count.to_bytes(4, "big"), *payloads)))
        except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError, RecursionError):
            raise ProtocolError("a payload is not one message") from None
        if len(messages) != count:
            raise ProtocolError("a payload is not one message")
        for message in messages:
            fields = plain.get(type(message))
            if fields is None:
                raise ProtocolError("a payload's type is empty")
            for field in fields:
                value = getattr(message, field)
                if type(value) not in flat:
                    _check_plain(value, "a payload")
        return messages

    return run


def decode(data: bytes, kind: Any = AnyMessage, *, where: str = "") -> Any:
    """Decode ``data`` as ``kind`` (a Struct type or union), raising ``ProtocolError`` naming ``where``."""
    if len(data) > MAX_PAYLOAD:
        raise ProtocolError(f"{where or 'payload'}: {len(data)} bytes exceeds the {MAX_PAYLOAD}-byte cap")
    decoder = _any_decoder if kind is AnyMessage else _decoders.get(kind)
    if decoder is None:
        strict = kind | _Untagged if isinstance(kind, type) and issubclass(kind, Message) else kind
        decoder = _decoders.setdefault(kind, msgspec.msgpack.Decoder(strict))
    try:
        message = decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError) as exc:
        raise ProtocolError(f"{where or 'payload'}: malformed message: {exc}") from None
    except RecursionError:
        raise ProtocolError(f"{where or 'payload'}: nested too deeply") from None
    cls = type(message)
    fields = _PLAIN_FIELDS.get(cls)
    if fields is None:
        if cls is _Untagged:
            raise ProtocolError(f"{where or 'payload'}: malformed message: its type is empty")
        fields = _PLAIN_FIELDS.setdefault(cls, tuple(f for f in _PLAIN_NAMES if f in cls.__struct_fields__))
    for field in fields:
        value = getattr(message, field)
        if type(value) in _FLAT:
            continue  # decoded scalars are plain data (MessagePack integers fit in 64 bits)
        try:
            check_value(value)
        except ValueError as exc:
            raise ProtocolError(f"{where or 'payload'}: {exc}") from None
    return message


def check_value(value: Value, _depth: int = 0) -> Value:
    """Return ``value`` if it is plain data (see module doc), else raise ``ValueError`` saying where."""
    if _depth > MAX_DEPTH:
        raise ValueError(f"value nested deeper than {MAX_DEPTH} levels")
    kind = type(value)
    if kind in _SCALARS:
        return value
    if kind is dict or kind is list:  # the common containers: their scalar items checked here, not by a call each
        deeper = _depth + 1
        for k, item in value.items() if kind is dict else enumerate(value):
            if kind is dict and type(k) is not str and not isinstance(k, str):
                raise ValueError(f"map key {k!r} is not a string")
            if type(item) in _SCALARS:
                if deeper > MAX_DEPTH:
                    raise ValueError(f"value nested deeper than {MAX_DEPTH} levels")
            else:
                check_value(item, deeper)
        return value
    if value is None or isinstance(value, (str, bool, float)):
        return value
    if isinstance(value, int):
        if not -(2**63) <= value <= 2**64 - 1:
            raise ValueError("integer does not fit in 64 bits (MessagePack's range)")
        return value
    if isinstance(value, (list, tuple)):
        for item in value:
            check_value(item, _depth + 1)
        return value
    if isinstance(value, dict):
        for k, item in value.items():
            if not isinstance(k, str):
                raise ValueError(f"map key {k!r} is not a string")
            check_value(item, _depth + 1)
        return value
    raise ValueError(f"{type(value).__name__} is not plain data (str, int, float, bool, None, list, map)")
