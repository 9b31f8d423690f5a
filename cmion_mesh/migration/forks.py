"""What the companion living here makes of the others' backed claims (``Forks``): it stands down
for good when one extends its chain, freezes on a proven fork, and runs again once an operator
resolves the fork.

Backed claims (``claims``) decide two things for a holder (``handshake.judge``):

* it stands down for good when a backed claim extends its chain (its own key signed the link past
  its head: a rolled-back state folder): ``CustodySuperseded``;
* on a proven fork (two links for one epoch signed by one key: the proof names who equivocated)
  it freezes: no branch wins by itself, epochs and names count for nothing. The evidence is kept
  in the state folder (a restart does not unfreeze it), the fork is reported (``CustodyFork``
  event, the log, the description) with the command that resolves it:
  ``cmion-mesh custody resolve COMPANION --keep EMBODIMENT`` makes every other branch holder stand
  down (``stand_down``: the kept chain recorded, on disk before the answer), then tells the keeper
  to run it again (``resume``).

A target that refuses an offer because of a fork reports it too (``seen_fork``). A record whose
state, epoch or holder its chain of custody does not back (``handshake.at_rest``) is reported
damaged at start and never run (``unbacked``).

Threads: all of it runs on the loop (``check_conflict`` is posted there when a claim is found
backed); ``frozen`` and ``superseded_by`` are the loop's.

Each conflict is one log line (``custody of <companion>: ...``; fields ``companion``, ``epoch``
(this copy's), ``peer`` (the other holder), and ``peer_epoch``, ``equivocator`` where known): a
copy superseded or frozen by a fork at error, a fork refused from an offer at error (once a minute
per equivocator), standing down and resuming as an operator resolves it at warning.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

from cmion_mesh import logs
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import Code, CustodyResume, CustodyStandDown
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.claims import Claims
from cmion_mesh.migration.handshake import Claim
from cmion_mesh.migration.host import Host
from cmion_mesh.migration.ledger import HOSTING, Record
from cmion_mesh.migration.signing import SignatureRefused
from cmion_mesh.requests import IncomingRequest

log = logging.getLogger(__name__)

#: The command that resolves a fork, in logs and descriptions.
RESOLVE = "cmion-mesh custody resolve {companion} --keep EMBODIMENT"


def fork_summary(fork: custody.Fork) -> dict[str, Any]:
    """A proof of equivocation as plain data, for people and tools (its links are checked where it was found)."""

    def link(item: custody.Link) -> dict[str, Any]:
        return {"holder": item.holder, "epoch": item.epoch, "attempt": item.attempt,
                "key": signing.encode_public(item.public_key)}

    return {"epoch": fork.epoch, "equivocator": fork.equivocator, "description": fork.describe(),
            "links": [link(fork.first), link(fork.second)], "after": link(fork.prefix[-1]) if fork.prefix else None}


def fork_report(freeze: custody.Freeze, me: str) -> dict[str, Any]:
    """What a frozen holder says of its fork (``describe``, ``CustodyFork``): the proofs, each branch's
    holder with its epoch and the equivocators it includes (a branch an equivocator holds is kept
    only when forced), and the command that resolves it."""
    forks = freeze.forks(me)
    equivocators = sorted({fork.equivocator for _, fork in forks if fork.equivocator})
    branches: dict[str, Any] = {}
    for holder, chain in sorted(freeze.branches.items()):
        tainted = sorted({fork.equivocator for _, fork in forks if fork.equivocator in custody.after_fork(chain, fork)})
        branches[holder] = {"epoch": chain[-1].epoch if chain else 0, "equivocators": tainted}
    return {"frozen": True, "forks": [{"with": holder, **fork_summary(fork)} for holder, fork in forks],
            "equivocators": equivocators, "branches": branches, "since": freeze.found,
            "resolve": RESOLVE.format(companion=freeze.companion)}


class Forks:
    """The inhabitant's custody verdicts: ``frozen`` by a fork, or ``superseded_by`` a claim."""

    def __init__(self, host: Host, claims: Claims) -> None:
        self.host = host
        self.claims = claims
        #: The evidence of a fork of the inhabitant's chain of custody that freezes it here, until an
        #: operator resolves it (loop; kept in the state folder too).
        self.frozen: custody.Freeze | None = None
        #: A backed claim extends the chain of the inhabitant, caught in its own handshake: it runs no
        #: more, and stands down for good once the handshake ends here (loop).
        self.superseded_by: Claim | None = None

    @property
    def halted(self) -> bool:
        """Whether a verdict keeps the inhabitant from running (frozen, or superseded)."""
        return self.frozen is not None or self.superseded_by is not None

    def clear(self) -> None:
        """Forget the verdicts: the copy they were about has left, or a new one arrived (a frozen
        holder accepts no prepare: any evidence here was of a copy long gone)."""
        self.frozen = None
        self.superseded_by = None

    def report(self) -> dict[str, Any]:
        """What ``describe`` says of custody here: for the companion held here, its state, epoch,
        whether a fork freezes it and the evidence (plain data)."""
        host = self.host
        report: dict[str, Any] = {}
        for record in host.records.all():
            if record.state not in HOSTING:
                continue
            entry: dict[str, Any] = {"state": record.state, "epoch": record.epoch, "frozen": False}
            freeze, superseded = self.frozen, self.superseded_by
            if freeze is not None and freeze.companion == record.companion:
                entry.update(fork_report(freeze, host.sim.embodiment))
            if superseded is not None:
                entry["superseded_by"] = {"holder": superseded.holder, "epoch": superseded.epoch}
            if record.companion in host.damaged:
                entry["damaged"] = True
            report[record.companion] = entry
        return report

    # --- verdicts ------------------------------------------------------------------------------

    def check_conflict(self) -> None:
        """The inhabitant's verdict on the others' backed claims: stand down for good when one extends
        its chain, freeze on a proven fork (no branch wins by itself)."""
        identity = self.host.identity
        if identity is None:
            return
        record = self.host.records.get(identity.companion)
        if record is None or record.state not in ("active", "prepared"):
            return
        verdict = handshake.judge(record, self.claims.backed(identity.companion))
        superseded = verdict.superseded_by
        if superseded is None and self.superseded_by is not None \
                and custody.compare(record.chain, self.superseded_by.chain)[0] == "behind":
            superseded = self.superseded_by  # seen while in a handshake: the proof stands if its token went since
        self.superseded_by = superseded
        if superseded is not None and record.state == "active":
            self._superseded(record, superseded)
        elif verdict.forks:
            self._freeze(record, verdict.forks)

    def _superseded(self, record: Record, claim: Claim) -> None:
        host = self.host
        released = host.records.put(handshake.superseded(record, claim))
        assert released.link is not None
        host.identity = None
        self.clear()
        host.sleep_minds()
        host.withdraw_claim()
        logs.event(log, f"custody of {record.companion} moved on without this copy: {claim.holder!r} holds it at epoch "
                        f"{claim.epoch}, by a link that this embodiment's custody key of epoch {record.epoch} signed to "
                        f"{released.link.holder!r} (a state folder rolled back?): this copy stands down for good",
                   level=logging.ERROR, conflict="superseded", companion=record.companion, epoch=record.epoch,
                   peer=claim.holder, peer_epoch=claim.epoch)
        host.raise_event("CustodySuperseded", {"companion": record.companion, "holder": claim.holder, "epoch": claim.epoch,
                                               "handed_to": released.link.holder, "handed_at": record.epoch + 1})

    def _freeze(self, record: Record, forks: Sequence[tuple[Claim, custody.Fork]]) -> None:
        host = self.host
        me = host.sim.embodiment
        held = self.frozen if self.frozen is not None and self.frozen.companion == record.companion else None
        branches = dict(held.branches) if held is not None else {}
        new = [(claim, fork) for claim, fork in forks if branches.get(claim.holder) != list(claim.chain)]
        if not new:
            return
        branches[me] = list(record.chain)
        for claim, _ in new:
            branches[claim.holder] = list(claim.chain)
        freeze = custody.Freeze(record.companion, branches, time.time())
        host.records.put_freeze(freeze)  # on disk before anything acts on it: a restart stays frozen
        self.frozen = freeze
        host.sleep_minds()
        for claim, fork in new:
            logs.event(log, f"CUSTODY FORK of {record.companion}: {fork.describe()}. This embodiment holds one branch (epoch "
                            f"{record.epoch}), {claim.holder!r} the other (epoch {claim.epoch}). No branch wins by itself: "
                            f"{record.companion} is frozen here until an operator resolves it (`cmion-mesh custody show "
                            f"{record.companion}`, then `{RESOLVE.format(companion=record.companion)}`)"
                            + (f"; revoke the equivocator: `cmion-mesh certs revoke PKI {fork.equivocator}`" if fork.equivocator else ""),
                       level=logging.ERROR, conflict="fork", companion=record.companion, epoch=record.epoch,
                       peer=claim.holder, peer_epoch=claim.epoch, equivocator=fork.equivocator or None)
        host.raise_event("CustodyFork", {"companion": record.companion, "frozen": True, **fork_report(freeze, me)})

    def seen_fork(self, fork: custody.Fork, source: str) -> None:
        """A target refused an offer because of a proven fork: logged (per equivocator, quietly) and raised."""
        muted = self.host.quiet.allow(f"fork:{fork.companion}:{fork.equivocator}:{fork.epoch}")
        if muted is not None:
            logs.event(log, f"CUSTODY FORK of {fork.companion}: {fork.describe()} (the offer of {source!r} refused here). "
                            f"Equivocation: revoke it (`cmion-mesh certs revoke PKI {fork.equivocator}`)",
                       level=logging.ERROR, conflict="fork_offered", companion=fork.companion, epoch=fork.epoch, peer=source,
                       equivocator=fork.equivocator or None, muted=muted)
        self.host.raise_event("CustodyFork", {"companion": fork.companion, "frozen": False, "refused_from": source,
                                              "forks": [fork_summary(fork)], "equivocators": [fork.equivocator]})

    def unbacked(self, record: Record) -> str:
        """Why ``record``, as stored here, must not run ("" if it may); loads a fork's evidence that
        still freezes it."""
        records, me = self.host.records, self.host.sim.embodiment
        key = records.key(record.companion) if record.state in HOSTING else None
        problem = handshake.at_rest(record, me=me, key=key)
        if problem:
            return f"its migration record is not backed by its chain of custody: {problem} " \
                   f"({records.path}, the record of {record.companion})"
        if record.state in ("active", "prepared"):
            try:
                freeze = records.freeze(record.companion)
            except ConfigError as exc:
                return str(exc)
            if freeze is not None and freeze.branches.get(me) == list(record.chain) and freeze.forks(me):
                self.frozen = freeze
                logs.event(log, f"custody of {record.companion} is frozen here by a fork of its chain "
                                f"({'; '.join(f.describe() for _, f in freeze.forks(me))}), until an operator resolves it: "
                                f"`{RESOLVE.format(companion=record.companion)}`",
                           level=logging.ERROR, conflict="frozen", companion=record.companion, epoch=record.epoch,
                           peer=sorted(h for h in freeze.branches if h != me))
            elif freeze is not None:
                records.thaw(record.companion)  # evidence about a chain this record no longer holds
        return ""

    # --- an operator resolves a fork ---------------------------------------------------------------

    def on_stand_down(self, request: IncomingRequest, msg: CustodyStandDown) -> None:
        """Retire this copy, for the branch of ``msg.keep``: only a copy whose chain forks from the kept
        one, or that the kept one extends; answered once the retired record is on disk."""
        host = self.host
        me = host.sim.embodiment
        record = host.records.get(msg.companion)
        if record is None or record.state not in HOSTING:
            request.accept({"state": record.state if record is not None else "none"})  # nothing here to retire
            return
        if record.state != "active":
            request.reject(f"{me!r} is in a migration of {msg.companion!r} ({record.state}); try again when it ends", Code.BUSY)
            return
        if msg.keep == me:
            request.reject(f"{me!r} is the embodiment to keep", Code.INVALID)
            return
        try:
            kept = custody.decode_chain(msg.chain)
            custody.verify_chain(kept, msg.companion, identity=self.claims.trusted(msg.companion))
        except SignatureRefused as exc:
            request.reject(f"the chain of {msg.keep!r} does not verify here: {exc}", Code.INVALID)
            return
        if kept[-1].holder != msg.keep:
            request.reject(f"the chain given ends with {kept[-1].holder!r}, not {msg.keep!r}", Code.INVALID)
            return
        relation, fork = custody.compare(record.chain, kept)
        if relation not in ("fork", "behind"):
            request.reject(f"keeping {msg.keep!r} would make two: the chain here ({me!r}, epoch {record.epoch}) is "
                           f"{'the same as' if relation == 'same' else 'newer than' if relation == 'stale' else 'foreign to'} "
                           f"the one kept", Code.CONFLICT)
            return
        retired = host.records.put(handshake.retired(record, kept))  # on disk before the answer
        host.identity = None
        self.clear()
        host.sleep_minds()
        host.withdraw_claim()
        logs.event(log, f"custody of {msg.companion}: this copy (epoch {record.epoch}) stood down for the branch of "
                        f"{msg.keep!r} (epoch {retired.epoch}), as an operator resolved the fork"
                        + (f" ({fork.describe()})" if fork is not None else ""),
                   level=logging.WARNING, conflict="stood_down", companion=msg.companion, epoch=record.epoch,
                   peer=msg.keep, peer_epoch=retired.epoch)
        host.raise_event("CustodyStoodDown", {"companion": msg.companion, "keep": msg.keep, "epoch": record.epoch,
                                              "kept_epoch": retired.epoch})
        request.accept({"state": retired.state, "epoch": retired.epoch})

    def on_resume(self, request: IncomingRequest, msg: CustodyResume) -> None:
        """The keeper of a resolved fork runs the companion again, once the others stood down."""
        host = self.host
        identity = host.identity
        record = host.records.get(msg.companion)
        if identity is None or identity.companion != msg.companion or record is None or record.state != "active":
            request.reject(f"{host.sim.embodiment!r} does not hold {msg.companion!r}", Code.NOT_FOUND)
            return
        freeze = self.frozen
        if freeze is None:
            request.accept({"state": "running"})
            return
        self.claims.retire(msg.companion, msg.retired)
        left = sorted(h for h in freeze.branches if h != host.sim.embodiment and h not in msg.retired)
        if left:
            request.reject(f"the branches of {', '.join(map(repr, left))} have not stood down: resuming would make two",
                           Code.CONFLICT)
            return
        host.records.thaw(msg.companion)
        self.frozen = None
        logs.event(log, f"custody of {msg.companion}: the fork is resolved "
                        f"({', '.join(map(repr, msg.retired)) or 'nobody else'} stood down); it runs here again",
                   level=logging.WARNING, conflict="resolved", companion=msg.companion, epoch=record.epoch,
                   peer=list(msg.retired))
        host.raise_event("CustodyResolved", {"companion": msg.companion, "retired": list(msg.retired)})
        self.check_conflict()
        if self.frozen is not None:
            request.reject(f"another branch of {msg.companion!r} is claimed still: frozen again", Code.CONFLICT)
            return
        host.wake_minds()
        request.accept({"state": "running"})
