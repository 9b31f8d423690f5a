"""The custody rules as pure functions: how two chains relate, what proves an equivocation, what
backs a claim, a holder's verdict, a target's objection, and a record checked at rest."""

from __future__ import annotations

import threading
from pathlib import Path

import msgspec
import pytest

from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import MigratePrepare
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.claims import ClaimChecker, ClaimKey
from cmion_mesh.migration.custody import ClaimProof
from cmion_mesh.migration.handshake import Claim
from cmion_mesh.migration.ledger import Record
from cmion_mesh.migration.signing import SignatureRefused
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport import certs, security

DOC = custody.digest(b"<Identity/>")


class Chain:
    """A chain of custody grown link by link, with every custody key it used (as each holder kept it)."""

    def __init__(self, first: str = "a", companion: str = "spirit") -> None:
        self.companion = companion
        self.keys = [signing.new_key()]
        self.links = [custody.birth(companion, first, self.keys[0], b"<Identity/>")]

    def copy(self) -> Chain:
        other = Chain.__new__(Chain)
        other.companion, other.keys, other.links = self.companion, list(self.keys), list(self.links)
        return other

    def to(self, holder: str, attempt: str = "", *, signer: bytes | None = None) -> Chain:
        """Hand on to ``holder`` (signed by the current key, or ``signer``: a forger's)."""
        key = signing.new_key()
        link = custody.hand_on(signer or self.keys[-1], self.companion, self.links[-1].epoch + 1, holder,
                               signing.public_of(key), attempt or f"{holder}{len(self.links)}", DOC)
        self.keys.append(key)
        self.links.append(link)
        return self

    def at(self, epoch: int) -> Chain:
        """This chain cut back to ``epoch`` (what a former host kept)."""
        cut = self.copy()
        n = next(i for i, link in enumerate(self.links) if link.epoch == epoch) + 1
        cut.links, cut.keys = cut.links[:n], cut.keys[:n]
        return cut

    @property
    def identity(self) -> bytes:
        return self.links[0].public_key

    def claim(self) -> Claim:
        return Claim(self.links[-1].holder, list(self.links))

    def record(self, state: str = "active", **fields: object) -> Record:
        head = self.links[-1]
        return Record(self.companion, state, head.epoch, chain=list(self.links), public_key=signing.encode_public(self.identity),
                      **fields)  # type: ignore[arg-type]


def true_and_forged() -> tuple[Chain, Chain]:
    """spirit goes a -> b -> a -> c; b, a former host that kept its key of epoch 2, forks from there to
    itself and inflates the epochs to 503."""
    true = Chain("a").to("b").to("a").to("c")
    forged = true.at(2)
    forged.to("b", "forged")
    for _ in range(500):
        forged.to("b")
    return true, forged


# --- compare and the proof of a fork -----------------------------------------------------------------


def test_two_chains_relate_as_same_stale_behind_fork_or_foreign() -> None:
    true, forged = true_and_forged()
    assert custody.compare(true.links, list(true.links)) == ("same", None)
    assert custody.compare(true.links, true.at(2).links) == ("stale", None)
    assert custody.compare(true.at(2).links, true.links) == ("behind", None)
    assert custody.compare(true.links, Chain("a").links) == ("foreign", None)
    relation, fork = custody.compare(true.links, forged.links)
    assert relation == "fork" and fork is not None
    assert fork.epoch == 3 and fork.equivocator == "b"
    assert (fork.first.holder, fork.second.holder) == ("a", "b") and fork.prefix == true.links[:2]
    custody.verify_fork(fork, identity=true.identity)
    assert "'b' signed two links for epoch 3 of 'spirit': to 'a'" in fork.describe()
    # seen from the other side, the same equivocator: inflating epochs changes nothing
    relation, back = custody.compare(forged.links, true.links)
    assert relation == "fork" and back is not None and back.equivocator == "b" and back.epoch == 3


def test_a_fork_is_proven_only_by_two_links_the_same_key_signed() -> None:
    true, forged = true_and_forged()
    _, fork = custody.compare(true.links, forged.links)
    assert fork is not None
    with pytest.raises(SignatureRefused, match="same link"):
        custody.verify_fork(msgspec.structs.replace(fork, second=fork.first))
    stranger = custody.hand_on(signing.new_key(), "spirit", 3, "x", signing.public_of(signing.new_key()), "x", DOC)
    with pytest.raises(SignatureRefused, match="not signed by the key of the epoch before"):
        custody.verify_fork(msgspec.structs.replace(fork, second=stranger))
    with pytest.raises(SignatureRefused, match="signed by a key other than the one trusted"):
        custody.verify_fork(fork, identity=Chain("z").identity)
    late = forged.links[5]
    with pytest.raises(SignatureRefused, match="at epoch 3"):
        custody.verify_fork(msgspec.structs.replace(fork, second=late))


def test_after_fork_names_the_holders_of_a_branch() -> None:
    true, forged = true_and_forged()
    _, fork = custody.compare(true.links, forged.links)
    assert fork is not None
    assert custody.after_fork(true.links, fork) == ["a", "c"]
    assert set(custody.after_fork(forged.links, fork)) == {"b"}
    assert custody.after_fork(true.at(2).links, fork) == []  # on neither branch
    assert custody.after_fork(Chain("z").to("y").to("x").links, fork) == []


def test_a_freeze_gives_the_proofs_again() -> None:
    true, forged = true_and_forged()
    forged.to("f")
    freeze = custody.Freeze("spirit", {"c": list(true.links), "f": list(forged.links)})
    decoded = msgspec.json.decode(msgspec.json.encode(freeze), type=custody.Freeze)
    [(holder, fork)] = decoded.forks("c")
    assert holder == "f" and fork.equivocator == "b" and fork.epoch == 3
    [(holder, fork)] = decoded.forks("f")
    assert holder == "c" and fork.equivocator == "b"


# --- what backs a claim --------------------------------------------------------------------------------


def test_a_claim_is_backed_by_its_chain_and_the_key_at_its_head() -> None:
    true = Chain("a").to("b")
    proof = ClaimProof("spirit", 2, "b", "c", b"n" * 16)
    custody.verify_claim(true.links, proof, custody.sign_claim(true.keys[-1], proof), identity=true.identity)
    with pytest.raises(SignatureRefused, match="did not sign its claim"):  # the chain alone is public
        custody.verify_claim(true.links, proof, custody.sign_claim(true.keys[0], proof))
    with pytest.raises(SignatureRefused, match="did not sign its claim"):  # another asker's, or another nonce
        custody.verify_claim(true.links, proof, custody.sign_claim(true.keys[-1], msgspec.structs.replace(proof, nonce=b"x")))
    inflated = msgspec.structs.replace(proof, epoch=1002)
    with pytest.raises(SignatureRefused, match="at epoch 1002, but its chain of custody ends at epoch 2"):
        custody.verify_claim(true.links, inflated, custody.sign_claim(true.keys[-1], inflated))
    mallory = msgspec.structs.replace(proof, claimant="mallory")
    with pytest.raises(SignatureRefused, match="ends with 'b'"):
        custody.verify_claim(true.links, mallory, custody.sign_claim(true.keys[-1], mallory))
    impostor = Chain("b")
    own = ClaimProof("spirit", 1, "b", "c", b"n" * 16)
    with pytest.raises(SignatureRefused, match="signed by a key other than the one trusted"):
        custody.verify_claim(impostor.links, own, custody.sign_claim(impostor.keys[-1], own), identity=true.identity)


# --- a target's objection, a holder's verdict ----------------------------------------------------------


def test_a_target_refuses_an_offer_a_backed_claim_shows_stale_or_forked() -> None:
    true, forged = true_and_forged()
    assert handshake.check_claims(true.links, [true.claim()], source="c") == ("", None)
    assert handshake.check_claims(true.links, [true.at(2).claim()], source="c") == ("", None)  # a former holder's token
    why, fork = handshake.check_claims(true.at(2).links, [true.claim()], source="b")
    assert "'c' holds 'spirit' at epoch 4, newer than the offer's epoch 2: 'b' handed it on" in why and fork is None
    why, fork = handshake.check_claims(forged.links, [true.claim()], source="b")
    assert fork is not None and fork.equivocator == "b" and "(equivocation)" in why and "'b' signed two links" in why
    why, fork = handshake.check_claims(Chain("x").links, [true.claim()], source="x")
    assert "another companion named 'spirit'" in why and fork is None
    assert handshake.check_claims(forged.links, [], source="b") == ("", None), "no backed claim: nothing to object"


def test_epochs_and_names_count_for_nothing_in_a_holders_verdict() -> None:
    true, forged = true_and_forged()
    forged.to("f")
    record = true.record()
    stale = handshake.judge(record, [true.at(2).claim(), true.at(3).claim()])
    assert stale == handshake.Verdict()
    verdict = handshake.judge(record, [forged.claim()])
    assert verdict.superseded_by is None and [(c.holder, f.equivocator) for c, f in verdict.forks] == [("f", "b")]
    # the branch with 500 epochs more is no better: the verdict on the other side is a fork as well
    other = handshake.judge(forged.record(), [true.claim()])
    assert [(c.holder, f.equivocator) for c, f in other.forks] == [("c", "b")]
    # a rolled-back holder: its own key signed the link past its head
    rolled_back = true.at(3).record()
    verdict = handshake.judge(rolled_back, [true.claim()])
    assert verdict.superseded_by is not None and verdict.superseded_by.holder == "c" and not verdict.forks
    released = handshake.superseded(rolled_back, verdict.superseded_by)
    assert (released.state, released.epoch, released.peer, released.link) == ("released", 3, "c", true.links[3])
    assert handshake.at_rest(released, me="a", key=None) == ""


def test_a_retired_branch_refuses_its_own_offers_and_takes_the_kept_ones() -> None:
    true, forged = true_and_forged()
    forged.to("f")
    retired = handshake.retired(forged.record(), true.links)
    assert (retired.state, retired.epoch, retired.seq, retired.chain) == ("dropped", 4, 0, true.links)
    assert handshake.at_rest(retired, me="f", key=None) == ""
    # the kept holder's next offer is newer; the retired branch's is a fork of what is known now
    assert handshake.precheck(_prepare(true, "f", seq=1), retired, me="f", held=None, admit=None) is None
    refused = handshake.on_prepare(_prepare(forged, "x", seq=1, target="f"), retired, me="f", held=None, admit=None, claims=[])
    assert refused.outcome.status == "rejected" and "forks from the one known here" in refused.outcome.reason
    assert refused.fork is not None and refused.fork.equivocator == "b"


def _prepare(chain: Chain, source_target: str, *, seq: int, target: str | None = None) -> MigratePrepare:
    record = chain.record(seq=seq - 1)
    _, message = handshake.offer(record, attempt=f"t{seq}", me=chain.links[-1].holder, target=target or source_target,
                                 document=b"<Identity/>", private=chain.keys[-1])
    return message


# --- verifying a chain that grows ---------------------------------------------------------------------


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[bytes]:
    """The signatures ``signing.valid`` is asked to check from now on (its cache emptied)."""
    checked: list[bytes] = []
    valid = signing.valid

    def counted(public: bytes, data: bytes, signature: bytes) -> bool:
        checked.append(signature)
        return valid(public, data, signature)

    valid.cache_clear()
    monkeypatch.setattr(signing, "valid", counted)
    return checked


def test_a_chain_that_grows_is_checked_only_where_it_grew(monkeypatch: pytest.MonkeyPatch) -> None:
    """A companion's chain gains a link a migration and is checked at every prepare: the links
    checked before are not checked again, so a migration does not cost more as the companion ages."""
    custody.VERIFIED.clear()
    chain = Chain("a")
    for i in range(300):
        chain.to("b" if i % 2 else "c")
    checked = _counting(monkeypatch)
    custody.verify_chain(chain.links, "spirit", identity=chain.identity)
    assert len(checked) == 301
    checked.clear()
    custody.verify_chain(chain.links, "spirit", identity=chain.identity)
    custody.verify_chain(chain.links[:120], "spirit")  # a former host's, shorter: known too
    assert checked == []
    chain.to("a")
    custody.verify_chain(chain.links, "spirit", identity=chain.identity)
    assert checked == [chain.links[-1].signature]
    with pytest.raises(SignatureRefused, match="other than the one trusted"):  # trust is checked at every call
        custody.verify_chain(chain.links, "spirit", identity=Chain("x").identity)


def test_a_chain_that_differs_anywhere_from_the_one_known_is_checked_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only link-for-link sameness counts: a chain that shares the known chain's last link but not
    an earlier one (a bad signature in the middle) is checked from its first link and refused."""
    custody.VERIFIED.clear()
    chain = Chain("a").to("b").to("c").to("d")
    custody.verify_chain(chain.links, "spirit")
    tampered = list(chain.links)
    tampered[2] = msgspec.structs.replace(tampered[2], signature=bytes(64))
    checked = _counting(monkeypatch)
    with pytest.raises(SignatureRefused, match="custody link 2"):
        custody.verify_chain(tampered, "spirit")
    assert len(checked) == 3  # from the birth link to the bad one
    true, forged = true_and_forged()  # a fork verified after the true chain is checked whole, and is valid
    custody.verify_chain(true.links, "spirit")
    checked.clear()
    custody.verify_chain(forged.links, "spirit")
    assert len(checked) == len(forged.links)


def test_the_chains_kept_are_bounded() -> None:
    custody.VERIFIED.clear()
    for i in range(custody.VERIFIED.COMPANIONS + 10):
        chain = Chain("a", companion=f"c{i}")
        custody.verify_chain(chain.links, f"c{i}")
    assert len(custody.VERIFIED) == custody.VERIFIED.COMPANIONS
    assert "c0" not in custody.VERIFIED and f"c{custody.VERIFIED.COMPANIONS + 9}" in custody.VERIFIED


# --- a record at rest --------------------------------------------------------------------------------


def test_a_record_whose_epoch_or_holder_its_chain_does_not_back_is_refused() -> None:
    true = Chain("a").to("b")
    key = true.keys[-1]
    active = true.record()
    assert handshake.at_rest(active, me="b", key=key) == ""
    assert "says epoch 3, its chain of custody ends at epoch 2" in handshake.at_rest(
        msgspec.structs.replace(active, epoch=3), me="b", key=key)
    assert "says 'b' held it at epoch 2, not 'robot2'" in handshake.at_rest(active, me="robot2", key=key)
    assert "custody key is not the one" in handshake.at_rest(active, me="b", key=true.keys[0])
    assert "custody key is missing" in handshake.at_rest(active, me="b", key=None)
    assert "no chain of custody" in handshake.at_rest(msgspec.structs.replace(active, chain=[]), me="b", key=key)
    tampered = [*true.links[:-1], msgspec.structs.replace(true.links[-1], holder="mallory")]
    assert "does not verify" in handshake.at_rest(msgspec.structs.replace(active, chain=tampered), me="mallory", key=key)
    # handed and released: the link it signed extends the chain, to its peer
    target_key = signing.new_key()
    link = custody.hand_on(key, "spirit", 3, "c", signing.public_of(target_key), "t1", DOC)
    handed = msgspec.structs.replace(active, state="handed", attempt="t1", peer="c", link=link)
    assert handshake.at_rest(handed, me="b", key=key) == ""
    released = msgspec.structs.replace(handed, state="released")
    assert handshake.at_rest(released, me="b", key=None) == ""
    assert "does not extend" in handshake.at_rest(msgspec.structs.replace(released, peer="d"), me="b", key=None)
    assert "without the link" in handshake.at_rest(msgspec.structs.replace(released, link=None), me="b", key=None)
    # incoming: the chain ends with the source, the key is the one made for the attempt
    incoming = msgspec.structs.replace(active, state="incoming", attempt="t1", peer="b",
                                       custody_key=signing.encode_public(signing.public_of(target_key)))
    assert handshake.at_rest(incoming, me="c", key=target_key) == ""
    assert "not with the source" in handshake.at_rest(msgspec.structs.replace(incoming, peer="x"), me="c", key=target_key)
    assert "not the one it gave" in handshake.at_rest(incoming, me="c", key=key)
    dropped = msgspec.structs.replace(incoming, state="dropped", custody_key="")
    assert handshake.at_rest(dropped, me="c", key=None) == ""
    assert "epoch" in handshake.at_rest(msgspec.structs.replace(dropped, epoch=9), me="c", key=None)


# --- revocation ----------------------------------------------------------------------------------------


def test_a_revoked_name_is_never_admitted_nor_trusted_again_silently(tmp_path: Path) -> None:
    folder = tmp_path / "pki"
    certs.init(folder)
    for name in ("robot", "screen"):
        certs.issue(folder, name)
    certs.revoke_name(folder, "screen", "equivocated custody of spirit")
    trust = certs.Trust.load(folder)
    assert "screen" not in trust.names and trust.role("screen") is None
    assert trust.revoked["screen"]["reason"] == "equivocated custody of spirit"
    subjects = {n for s in security.access_control("m", trust)["subjects"] for n in s["cert_common_names"]}
    assert subjects == {"robot"}
    with pytest.raises(ConfigError, match=r"'screen' was revoked on .* trust it again only on purpose"):
        certs.trust_name(folder, "screen")
    with pytest.raises(ConfigError, match="was revoked"):
        certs.issue(folder, "screen", force=True)
    # a copy of the list that still names it never admits it either
    trust.names["screen"] = "embodiment"
    assert {n for s in security.access_control("m", trust)["subjects"] for n in s["cert_common_names"]} == {"robot"}
    assert {n for s in security.access_control("m", trust, mode="client")["subjects"] for n in s["cert_common_names"]} == {"robot"}
    certs.trust_name(folder, "screen", unrevoke=True)
    again = certs.Trust.load(folder)
    assert again.role("screen") == "embodiment" and "screen" not in again.revoked


def test_a_claim_whose_token_went_is_no_longer_pending_even_while_a_retry_waits() -> None:
    # A target that moved on to the next epoch refuses to back its token of the one before; the
    # retry of that refusal must not keep the claim pending (offers on the companion wait for it).
    done: list[ClaimKey] = []
    asked = threading.Event()

    def check(key: ClaimKey, tries: int) -> float | None:
        asked.set()
        return 60.0  # not backed this time: asked again in a minute

    stale, live = ("b", "spirit", 3), ("b", "spirit", 4)
    with ClaimChecker(check, done.append) as checker:
        assert checker.submit(stale)
        assert asked.wait(5.0)
        assert checker.pending("spirit")
        checker.withdraw(live)  # never submitted: nothing happens
        assert checker.pending("spirit") and done == []
        checker.withdraw(stale)
        wait_for(lambda: done == [stale], 5.0, "the withdrawn claim done")
        assert not checker.pending("spirit")
