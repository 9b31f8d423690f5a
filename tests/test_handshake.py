"""The migration handshake's decisions (``handshake``), record by record, with real chains of custody.

Each test feeds one pure decision a record and a message and checks the next record and the
answer: what the migration manager would write and say. No transport, no disk: the sha256 a
record names for its document is set here as ``Records.put`` sets it."""

from __future__ import annotations

import hashlib
from typing import Any

import msgspec
import pytest

from cmion_mesh.messages import Code, MigrateAbort, MigrateCommit, MigratePrepare, MigrateStatus, Outcome
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.identity import Bytes, Identity
from cmion_mesh.migration.ledger import Record

from .helpers.custody_helpers import Holder

COMPANION = "spirit"


def document(companion: str = COMPANION, epoch: int = 1, **sections: Any) -> bytes:
    return Identity(companion, epoch, {"memory": {"met": ["Ada"]}, **sections}).pack()


def at_target(msg: MigratePrepare, record: Record | None = None, *, me: str = "screen", held: Record | None = None,
              admit: dict[str, bytes | None] | None = None, claims: list[handshake.Claim] | None = None,
              **kwargs: Any) -> handshake.Decision:
    return handshake.on_prepare(msg, record, me=me, held=held, admit=admit, claims=claims or [], **kwargs)


def written(decision: handshake.Decision) -> Record:
    """The record as the target writes it: ``Records.put`` names the document's sha256 in it."""
    assert decision.record is not None and decision.document is not None, decision.outcome
    return msgspec.structs.replace(decision.record, document=hashlib.sha256(decision.document).hexdigest())


def reason(decision: handshake.Decision | None) -> str:
    assert decision is not None and decision.outcome.status == "rejected", decision
    return decision.outcome.reason


def refused_without_a_trace(decision: handshake.Decision) -> str:
    """A refusal writes nothing: no record, no document, no key."""
    assert (decision.record, decision.document, decision.key, decision.identity) == (None, None, None, None)
    return reason(decision)


@pytest.fixture
def robot() -> Holder:
    return Holder(COMPANION, "robot")


@pytest.fixture
def doc() -> bytes:
    return document()


# --- precheck: what costs nothing ---------------------------------------------------------------


def test_precheck_refuses_names_that_cannot_be_keys(robot: Holder, doc: bytes) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    for field, bad in (("companion", "a/b"), ("source", "*"), ("attempt", "")):
        msg = msgspec.structs.replace(prepare, **{field: bad})
        assert field in reason(handshake.precheck(msg, None, me="screen", held=None, admit=None))


def test_precheck_refuses_a_prepare_for_another_target_and_a_companion_not_admitted(robot: Holder, doc: bytes) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    assert reason(handshake.precheck(prepare, None, me="phone", held=None, admit=None)) == "this is 'phone', not 'screen'"
    assert "admission" in reason(handshake.precheck(prepare, None, me="screen", held=None, admit={"other": None}))
    assert handshake.precheck(prepare, None, me="screen", held=None, admit={COMPANION: None}) is None


@pytest.mark.parametrize(("state", "epoch", "seq", "attempt", "expected"), [
    ("active", 1, 0, "", "holds 'spirit' itself"),
    ("prepared", 1, 0, "b1", "holds 'spirit' itself"),
    ("handed", 1, 0, "b1", "holds 'spirit' itself"),
    ("incoming", 1, 1, "other", "busy: 'screen' is in migration other"),
    ("dropped", 1, 1, "a0", "stale: attempt a1 (1.1)"),
    ("released", 2, 0, "a0", "stale: attempt a1 (1.1)"),
    ("dropped", 0, 7, "a0", None),  # an older epoch: the offer is newer
    ("incoming", 1, 1, "a1", None),  # the same attempt again: a repeated prepare, answered again
])
def test_precheck_against_the_record_here(robot: Holder, doc: bytes, state: Any, epoch: int, seq: int, attempt: str,
                                          expected: str | None) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    record = Record(COMPANION, state, epoch, attempt, "robot", seq=seq)
    decision = handshake.precheck(prepare, record, me="screen", held=None, admit=None)
    if expected is None:
        assert decision is None
    else:
        assert expected in reason(decision)


def test_precheck_refuses_an_embodiment_occupied_by_another_companion(robot: Holder, doc: bytes) -> None:
    occupant = Record("other", "active", 3)
    prepare = robot.prepare("screen", doc, "a1")
    assert "occupied by companion 'other'" in reason(handshake.precheck(prepare, None, me="screen", held=occupant, admit=None))


# --- on_prepare: the target's decision ----------------------------------------------------------


def test_an_accepted_prepare_records_incoming_with_a_fresh_custody_key(robot: Holder, doc: bytes) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    decision = at_target(prepare)
    assert decision.outcome.status == "accepted" and decision.outcome.value["state"] == "prepared"
    public = decision.outcome.value["custody_key"]
    assert decision.key is not None and signing.encode_public(signing.public_of(decision.key)) == public
    record = decision.record
    assert record is not None
    assert (record.state, record.epoch, record.seq, record.attempt, record.peer) == ("incoming", 1, 1, "a1", "robot")
    assert record.chain == robot.chain and record.custody_key == public
    assert record.public_key == "", "no identity key is pinned by a prepare: only a commit pins one"
    assert decision.document == doc and decision.identity is not None
    assert decision.identity.sections["memory"] == {"met": ["Ada"]}


def test_a_repeated_prepare_gets_the_same_answer_and_writes_nothing(robot: Holder, doc: bytes) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    first = at_target(prepare)
    again = at_target(prepare, written(first))
    assert again.outcome == first.outcome
    assert again.record is None and again.key is None, "the key made for the attempt stays the one answered"


def test_a_prepare_is_refused_without_a_trace_when_custody_does_not_hold(robot: Holder, doc: bytes) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    by_another_key = Holder(COMPANION, "robot", chain=robot.chain).prepare("screen", doc, "a1")
    assert "bad signature on the offer" in refused_without_a_trace(at_target(by_another_key))
    garbage_chain = msgspec.structs.replace(prepare, chain=b"\x93not a chain")
    assert "malformed custody chain" in refused_without_a_trace(at_target(garbage_chain))
    stranger = Holder(COMPANION, "robot")
    pinned_elsewhere = Record(COMPANION, "dropped", 0, "a0", "robot", public_key=signing.encode_public(stranger.identity_key))
    assert "a key other than the one trusted" in refused_without_a_trace(at_target(prepare, pinned_elsewhere))
    assert "a key other than the one trusted" in refused_without_a_trace(at_target(prepare, admit={COMPANION: stranger.identity_key}))
    assert at_target(prepare, admit={COMPANION: robot.identity_key}).outcome.status == "accepted"


def fork_of(robot: Holder, doc: bytes, holder: str) -> Holder:
    """``holder`` at epoch 2 on a link robot's key signed: two such holders are a proven equivocation."""
    key = signing.new_key()
    link = custody.hand_on(robot.private, COMPANION, 2, holder, signing.public_of(key), f"to-{holder}", custody.digest(doc))
    return Holder(COMPANION, holder, 2, private=key, chain=[*robot.chain, link])


def test_a_prepare_whose_chain_forks_from_the_one_known_here_is_refused(robot: Holder, doc: bytes) -> None:
    phone, tablet = fork_of(robot, doc, "phone"), fork_of(robot, doc, "tablet")
    known = Record(COMPANION, "dropped", 2, "a0", "phone", chain=phone.chain)
    decision = at_target(tablet.prepare("screen", document(epoch=2), "a1"), known)
    assert "forks from the one known here" in refused_without_a_trace(decision)
    assert decision.fork is not None and decision.fork.epoch == 2


def test_a_stranger_of_the_same_name_known_only_from_a_dropped_attempt_pins_nothing(robot: Holder, doc: bytes) -> None:
    stranger = Holder(COMPANION, "robot")  # another birth: another identity key, never committed here
    record = Record(COMPANION, "dropped", 0, "a0", "robot", chain=stranger.chain)
    assert at_target(robot.prepare("screen", doc, "a1"), record).outcome.status == "accepted"


def test_backed_claims_in_the_mesh_decide_who_may_offer(robot: Holder, doc: bytes) -> None:
    prepare = robot.prepare("screen", doc, "a1")
    assert at_target(prepare, claims=[handshake.Claim("robot", robot.chain)]).outcome.status == "accepted", \
        "the source's own claim"
    # robot handed the companion to phone: a claim whose chain extends the offer
    handed = [*robot.chain, custody.hand_on(robot.private, COMPANION, 2, "phone", signing.public_of(signing.new_key()), "a0",
                                            custody.digest(doc))]
    assert "'phone' holds 'spirit' at epoch 2, newer than the offer's epoch 1" in refused_without_a_trace(
        at_target(prepare, claims=[handshake.Claim("phone", handed)]))
    # a branch that forks from the offer's: robot's key signed two links for epoch 2
    phone, tablet = fork_of(robot, doc, "phone"), fork_of(robot, doc, "tablet")
    decision = at_target(tablet.prepare("screen", document(epoch=2), "a2"), claims=[handshake.Claim("phone", phone.chain)])
    assert "(equivocation)" in refused_without_a_trace(decision)
    assert decision.fork is not None and decision.fork.equivocator == "robot"
    assert at_target(prepare, claims=[]).outcome.status == "accepted", "a bare token is no claim at all"


def test_a_prepare_whose_document_is_not_the_offers_is_refused(robot: Holder) -> None:
    for other, expected in ((document("someone"), "document is for 'someone' at epoch 1"),
                            (document(epoch=5), "at epoch 5, not 'spirit' at epoch 1"),
                            (b"<Identity", "")):
        assert expected in refused_without_a_trace(at_target(robot.prepare("screen", other, "a1")))


def test_the_companions_own_policy_refuses_an_embodiment_it_does_not_accept(robot: Holder) -> None:
    picky = document(policy={"accepts": ["phone"]})
    assert "does not accept embodiment 'screen'" in refused_without_a_trace(at_target(robot.prepare("screen", picky, "a1")))
    assert at_target(robot.prepare("phone", picky, "a1"), me="phone").outcome.status == "accepted"


def test_a_version_2_prepare_is_refused_missing_sections_until_they_are_at_hand(robot: Holder) -> None:
    packed = Identity(COMPANION, 1, {"memory": {"met": ["Ada"]}, "blob": "x" * 100}).pack_sections()
    prepare = robot.prepare("screen", packed.manifest, "a1")
    lacking = at_target(prepare, sections=lambda refs: {})
    assert lacking.outcome.code == Code.MISSING_SECTIONS and lacking.record is None
    assert sorted(lacking.outcome.value["missing"]) == sorted(packed.data)
    asked: list[list[str]] = []

    def on_disk(refs: Any) -> dict[str, Bytes]:
        asked.append([ref.sha256 for ref in refs])
        return {ref.sha256: packed.data[ref.sha256] for ref in refs}

    found = at_target(prepare, sections=on_disk)
    assert found.outcome.status == "accepted" and found.identity is not None
    assert found.identity.sections["blob"] == "x" * 100
    assert found.sections == packed.data and sorted(asked[0]) == sorted(packed.data)


def test_have_checks_the_offer_as_a_prepare_does_and_takes_only_a_manifest(robot: Holder, doc: bytes) -> None:
    packed = Identity(COMPANION, 1, {"memory": {"met": ["Ada"]}}).pack_sections()
    have = handshake.have(robot.prepare("screen", packed.manifest, "a1"))
    decision = handshake.on_have(have, None, me="screen", held=None, admit=None, claims=[])
    assert decision.outcome.status == "accepted" and decision.record is None
    assert decision.manifest is not None and decision.manifest.refs == packed.refs
    version_1 = handshake.have(robot.prepare("screen", doc, "a2"))
    assert "takes a SchemaVersion 2 manifest" in reason(handshake.on_have(version_1, None, me="screen", held=None, admit=None,
                                                                          claims=[]))
    phone = fork_of(robot, doc, "phone")  # robot handed it to phone
    claims = [handshake.Claim("phone", phone.chain)]
    assert "'phone' holds" in reason(handshake.on_have(have, None, me="screen", held=None, admit=None, claims=claims))


# --- on_commit: the target becomes the home ----------------------------------------------------


def prepared_at_target(robot: Holder, doc: bytes, attempt: str = "a1") -> tuple[MigratePrepare, handshake.Decision, Record]:
    prepare = robot.prepare("screen", doc, attempt)
    decision = at_target(prepare)
    return prepare, decision, written(decision)


def test_a_commit_with_the_sources_link_makes_the_target_active_at_the_next_epoch(robot: Holder, doc: bytes) -> None:
    prepare, decision, incoming = prepared_at_target(robot, doc)
    commit = robot.commit(prepare, decision.outcome)
    done = handshake.on_commit(commit, incoming, me="screen")
    assert done.outcome.value == {"state": "committed"}
    active = done.record
    assert active is not None
    assert (active.state, active.epoch, active.seq, active.custody_key) == ("active", 2, 0, "")
    assert active.chain == [*robot.chain, custody.decode_link(commit.link)]
    assert active.public_key == signing.encode_public(robot.identity_key), "the commit pins the identity key"
    custody.verify_chain(active.chain, COMPANION, identity=robot.identity_key)
    again = handshake.on_commit(commit, active, me="screen")
    assert again.outcome.value == {"state": "committed"} and again.record is None, "a repeated commit changes nothing"


def test_a_commit_is_refused_unless_it_is_the_sources_for_the_attempt_held_here(robot: Holder, doc: bytes) -> None:
    prepare, decision, incoming = prepared_at_target(robot, doc)
    commit = robot.commit(prepare, decision.outcome)
    assert "'phone' is not the source" in reason(handshake.on_commit(msgspec.structs.replace(commit, source="phone"), incoming,
                                                                     me="screen"))
    assert "no incoming migration a9" in reason(handshake.on_commit(msgspec.structs.replace(commit, attempt="a9"), incoming,
                                                                    me="screen"))
    assert "no incoming migration a1" in reason(handshake.on_commit(commit, None, me="screen"))
    dropped = handshake.dropped(incoming)
    assert "no incoming migration a1" in reason(handshake.on_commit(commit, dropped, me="screen"))


def test_a_commit_whose_link_is_not_the_handshakes_is_refused(robot: Holder, doc: bytes) -> None:
    prepare, decision, incoming = prepared_at_target(robot, doc)
    forged = Holder(COMPANION, "robot", chain=robot.chain).commit(prepare, decision.outcome)
    assert "bad signature on the custody link" in reason(handshake.on_commit(forged, incoming, me="screen"))
    other_key = {"custody_key": signing.encode_public(signing.public_of(signing.new_key()))}
    to_another_key = robot.commit(prepare, other_key)
    assert "link's public_key is not this handshake's" in reason(handshake.on_commit(to_another_key, incoming, me="screen"))
    other_document = msgspec.structs.replace(prepare, document=document(epoch=1, extra=1))
    assert "document_sha256 is not this handshake's" in reason(
        handshake.on_commit(robot.commit(other_document, decision.outcome), incoming, me="screen"))
    garbage = MigrateCommit(COMPANION, 1, "a1", "robot", "screen", b"\xc1")
    assert "malformed custody link" in reason(handshake.on_commit(garbage, incoming, me="screen"))


# --- on_abort and dropped ------------------------------------------------------------------------


def test_only_the_source_aborts_an_incoming_attempt_and_the_order_stays(robot: Holder, doc: bytes) -> None:
    _, _, incoming = prepared_at_target(robot, doc)
    abort = MigrateAbort(COMPANION, 1, "a1")
    assert "only 'robot', the source of attempt a1" in reason(handshake.on_abort(abort, incoming, requester="phone"))
    decision = handshake.on_abort(abort, incoming, requester="robot")
    assert decision.outcome.value == {"state": "dropped"}
    dropped = decision.record
    assert dropped is not None
    assert (dropped.state, dropped.order, dropped.attempt, dropped.custody_key) == ("dropped", (1, 1), "a1", "")
    assert dropped.chain == [], "an aborted offer teaches nothing: its chain is not kept"


def test_an_abort_of_an_attempt_not_held_here_is_answered_dropped_and_writes_nothing(robot: Holder, doc: bytes) -> None:
    _, _, incoming = prepared_at_target(robot, doc)
    for record in (None, incoming):
        decision = handshake.on_abort(MigrateAbort(COMPANION, 1, "other"), record, requester="robot")
        assert decision.outcome.value == {"state": "dropped"} and decision.record is None


def test_a_dropped_record_keeps_a_chain_only_when_custody_was_pinned_here(robot: Holder, doc: bytes) -> None:
    _, _, incoming = prepared_at_target(robot, doc)
    pinned = msgspec.structs.replace(incoming, public_key=signing.encode_public(robot.identity_key))
    assert handshake.dropped(pinned).chain == robot.chain
    assert handshake.dropped(incoming).chain == []


# --- on_status: what became of an attempt --------------------------------------------------------


def source_records(robot: Holder, doc: bytes) -> tuple[Record, Record]:
    """The source's ``prepared`` record of attempt a1 to the screen, and its ``handed`` one."""
    active = Record(COMPANION, "active", 1, chain=robot.chain)
    prepared, prepare = handshake.offer(active, attempt="a1", me="robot", target="screen", document=doc, private=robot.private)
    answer = at_target(prepare).outcome
    handed = handshake.after_prepare(prepared, answer, private=robot.private, document=doc)
    return prepared, handed


def test_status_asked_of_the_source(robot: Holder, doc: bytes) -> None:
    prepared, handed = source_records(robot, doc)
    ask = MigrateStatus(COMPANION, "a1", 1, "source")
    assert handshake.on_status(ask, prepared, requester="screen").outcome.value == {"state": "pending"}
    committed = handshake.on_status(ask, handed, requester="screen").outcome.value
    assert committed["state"] == "committed" and handed.link is not None
    assert handshake.link_of_text(committed["link"]) == handed.link
    released = msgspec.structs.replace(handed, state="released")
    assert handshake.on_status(ask, released, requester="screen").outcome.value["state"] == "committed"
    resumed = handshake.resume(prepared)
    assert handshake.on_status(ask, resumed, requester="screen").outcome.value == {"state": "aborted"}
    assert handshake.on_status(ask, None, requester="screen").outcome.value == {"state": "aborted"}
    assert "not 'phone''s to ask about" in handshake.on_status(ask, prepared, requester="phone").outcome.reason


def test_status_asked_of_the_target(robot: Holder, doc: bytes) -> None:
    prepare, decision, incoming = prepared_at_target(robot, doc)
    ask = MigrateStatus(COMPANION, "a1", 1, "target")
    assert handshake.on_status(ask, incoming, requester="robot").outcome.value == {"state": "incoming"}
    active = handshake.on_commit(robot.commit(prepare, decision.outcome), incoming, me="screen").record
    assert handshake.on_status(ask, active, requester="robot").outcome.value == {"state": "committed"}
    moved_on = Record(COMPANION, "released", 4, "a7", "phone")  # gone further since: the attempt committed
    assert handshake.on_status(ask, moved_on, requester="robot").outcome.value == {"state": "committed"}
    assert handshake.on_status(ask, handshake.dropped(incoming), requester="robot").outcome.value == {"state": "dropped"}
    assert handshake.on_status(ask, None, requester="robot").outcome.value == {"state": "dropped"}


# --- settle_incoming: the target told by the source ----------------------------------------------


def test_settle_incoming_acts_only_on_a_definite_answer(robot: Holder, doc: bytes) -> None:
    prepare, decision, incoming = prepared_at_target(robot, doc)
    assert handshake.settle_incoming(incoming, {"state": "aborted"}, me="screen") == handshake.dropped(incoming)
    link = robot.link(prepare, decision.outcome)
    active = handshake.settle_incoming(incoming, {"state": "committed", "link": handshake.link_text(link)}, me="screen")
    assert active is not None and active.state == "active" and active.chain[-1] == link
    forged = Holder(COMPANION, "robot", chain=robot.chain).link(prepare, decision.outcome)
    for unsure in ({"state": "committed", "link": handshake.link_text(forged)}, {"state": "committed", "link": "not base64!"},
                   {"state": "committed"}, {"state": "pending"}, None, "committed", {}):
        assert handshake.settle_incoming(incoming, unsure, me="screen") is None, f"{unsure!r}: ask again, take nothing over"


# --- the source: offer, after_prepare, resume, after_refused_commit -------------------------------


def test_offer_numbers_the_attempt_from_the_record_and_signs_it(robot: Holder, doc: bytes) -> None:
    active = Record(COMPANION, "active", 1, seq=4, chain=robot.chain)
    prepared, prepare = handshake.offer(active, attempt="a5", me="robot", target="screen", document=doc, private=robot.private)
    assert (prepared.state, prepared.seq, prepared.attempt, prepared.peer, prepared.link) == ("prepared", 5, "a5", "screen", None)
    assert (prepare.epoch, prepare.seq, prepare.source, prepare.target) == (1, 5, "robot", "screen")
    assert custody.decode_chain(prepare.chain) == robot.chain
    assert at_target(prepare).outcome.status == "accepted"


def test_after_prepare_hands_the_companion_on_only_to_the_key_the_target_made(robot: Holder, doc: bytes) -> None:
    prepared, handed = source_records(robot, doc)
    assert handed.state == "handed" and handed.link is not None
    assert (handed.link.epoch, handed.link.holder, handed.link.attempt) == (2, "screen", "a1")
    assert handed.link.document_sha256 == custody.digest(doc)
    assert signing.valid(robot.chain[-1].public_key, handed.link.signed_bytes(), handed.link.signature)
    for answer in (Outcome("rejected", "busy"), Outcome("accepted", "", {"state": "prepared", "custody_key": "garbage"}),
                   Outcome("accepted", "", None)):
        back = handshake.after_prepare(prepared, answer, private=robot.private, document=doc)
        assert (back.state, back.attempt, back.peer, back.link, back.order) == ("active", "", "", None, prepared.order)


def test_a_resumed_source_offers_a_newer_attempt_that_a_target_which_dropped_the_old_one_takes(robot: Holder, doc: bytes) -> None:
    """The replay case of the module's docstring: T dropped (1, 1); S resumed offers (1, 2); a replay
    of (1, 1) is refused, before and after."""
    active = Record(COMPANION, "active", 1, chain=robot.chain)
    prepared, first = handshake.offer(active, attempt="a1", me="robot", target="screen", document=doc, private=robot.private)
    incoming = written(at_target(first))
    dropped = handshake.on_abort(MigrateAbort(COMPANION, 1, "a1"), incoming, requester="robot").record
    assert dropped is not None
    resumed = handshake.resume(prepared)
    _, second = handshake.offer(resumed, attempt="a2", me="robot", target="screen", document=doc, private=robot.private)
    assert second.seq == 2
    assert "stale: attempt a1 (1.1)" in reason(at_target(first, dropped))
    newer = at_target(second, dropped)
    assert newer.outcome.status == "accepted"
    assert "busy: 'screen' is in migration a2" in reason(at_target(first, written(newer)))


@pytest.mark.parametrize(("answer", "step", "state"), [
    ({"state": "committed"}, "released", "released"),
    ({"state": "dropped"}, "resume", "active"),
    ({"state": "incoming"}, "abort", None),
    ({"state": "pending"}, "retry", None),
    (None, "retry", None),
    ("committed", "retry", None),
])
def test_after_refused_commit_follows_what_the_target_says(robot: Holder, doc: bytes, answer: Any, step: str, state: str | None) -> None:
    _, handed = source_records(robot, doc)
    next_step, record = handshake.after_refused_commit(handed, answer)
    assert next_step == step
    assert (record.state if record is not None else None) == state
    if state == "active":
        assert record is not None and record.link is None and record.order == handed.order


# --- a round trip, all decisions in order ---------------------------------------------------------


def test_the_companion_goes_to_the_screen_and_back_on_a_chain_that_grows_by_one_link_each_way(robot: Holder, doc: bytes) -> None:
    source = Record(COMPANION, "active", 1, chain=robot.chain)
    prepared, prepare = handshake.offer(source, attempt="out", me="robot", target="screen", document=doc, private=robot.private)
    answer = at_target(prepare)
    screen_key = answer.key
    handed = handshake.after_prepare(prepared, answer.outcome, private=robot.private, document=doc)
    assert handed.link is not None
    commit = MigrateCommit(COMPANION, 1, "out", "robot", "screen", custody.encode_link(handed.link))
    screen = handshake.on_commit(commit, written(answer), me="screen").record
    assert screen is not None and screen_key is not None
    _, robot_now = handshake.after_refused_commit(handed, {"state": "committed"})
    assert robot_now is not None and robot_now.state == "released"

    back_doc = document(epoch=2)
    away, back = handshake.offer(screen, attempt="back", me="screen", target="robot", document=back_doc, private=screen_key)
    assert (back.epoch, back.seq) == (2, 1)
    at_robot = at_target(back, robot_now, me="robot")
    assert at_robot.outcome.status == "accepted", "released at epoch 1, the robot takes the companion at epoch 2"
    handed_back = handshake.after_prepare(away, at_robot.outcome, private=screen_key, document=back_doc)
    assert handed_back.link is not None
    home = handshake.on_commit(MigrateCommit(COMPANION, 2, "back", "screen", "robot", custody.encode_link(handed_back.link)),
                               written(at_robot), me="robot").record
    assert home is not None and (home.state, home.epoch) == ("active", 3)
    assert [k.holder for k in home.chain] == ["robot", "screen", "robot"]
    custody.verify_chain(home.chain, COMPANION, identity=robot.identity_key)
    _, screen_now = handshake.after_refused_commit(handed_back, {"state": "committed"})
    assert screen_now is not None and screen_now.state == "released"
    assert "stale: attempt out (1.1)" in reason(at_target(prepare, screen_now)), "a replay of the first offer moves nothing back"
    assert "holds 'spirit' itself" in reason(at_target(back, home, me="robot"))
