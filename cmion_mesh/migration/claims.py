"""Custody claims in the mesh as this embodiment sees them (``Claims``): who is alive, who claims
custody of which companion, which of those claims their claimants backed; and this embodiment's
answer when another asks it to back its own (``chain``).

A holder says so in the mesh with a liveliness token ``@custody/<holder>/<companion>/<epoch>``
(the manager declares this embodiment's). A token is a hint to go and look, never evidence: a
claim counts only once its claimant backs it (``chain``: its chain of custody, verified from the
identity key trusted here, ending with it at the epoch claimed, and the asker's nonce signed by
that link's key). A claim that cannot be backed is ignored, and logged naming the claimant (at
most once a minute each). What backed claims decide is ``handshake``'s: the target side refuses
offers they show stale or forked (``incoming``), the inhabitant stands down or freezes
(``forks``); both hear of them through the callbacks the manager wires (``on_backed``,
``on_checked``), posted to the loop.

Threads:

* the transport's worker keeps the set of live embodiments and the custody tokens seen
  (``_on_alive``, ``_on_custody``), under ``_lock``; it only records a token and queues its check;
* one thread (``ClaimChecker``) checks custody claims: it asks each claimant for its chain of
  custody and a signature by its head's key over a fresh nonce, verifies them, keeps the claims so
  backed (under ``_lock``) and posts what it found to the loop;
* the loop answers ``chain`` requests (``on_chain``) and reads the claims (``backed``,
  ``pending``, ``is_alive``: any thread may);
* a source's handshake thread tells what it knows without asking (``receiving``, ``vouch``,
  ``forget``): the tokens of the target it hands the companion to, at the epoch it receives it
  (no claim) and the next (backed by the link this side signed), are not checked; asking cost a
  chain request, a signature and its check on both sides in the middle of every migration.
"""

from __future__ import annotations

import base64
import binascii
import heapq
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable

from cmion_mesh import keys, logs
from cmion_mesh.errors import OutcomeUnknown
from cmion_mesh.messages import Code, MigrateChain
from cmion_mesh.migration import custody, signing
from cmion_mesh.migration.bounds import TokenBucket
from cmion_mesh.migration.custody import Link
from cmion_mesh.migration.handshake import Claim
from cmion_mesh.migration.host import Host
from cmion_mesh.migration.ledger import HOSTING
from cmion_mesh.migration.signing import SignatureRefused
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.transport.base import Closeable

log = logging.getLogger(__name__)

#: Seconds a claimant has to back its custody token (``chain``).
CHAIN_TIMEOUT = 2.0
#: Claims waiting to be checked (per claimant, in all) beyond which new ones are dropped, logged.
CLAIMS_PER_CLAIMANT = 8
MAX_CLAIMS = 256
#: Tries to back a claim (the first pause between them, doubling): a refusal or a claim that does
#: not verify is asked once more (the token may be on its way out), a claimant that does not
#: answer a few times.
CLAIM_TRIES = 4
CLAIM_RETRY = 0.25
#: Claims known without asking (``Claims.vouch``, ``receiving``) kept at most: two per handshake.
MAX_KNOWN = 64

ClaimKey = tuple[str, str, int]  # claimant, companion, epoch


class ClaimChecker:
    """One thread that checks custody claims, off the loop and off zenoh's callbacks.

    ``submit`` queues a claim once while it is pending (bounded per claimant and in all);
    ``check(key, tries)``, given, does the work and returns None when done or the seconds after
    which to try again; ``done(key)`` is called once the claim is no longer pending. A context
    manager; ``close`` is idempotent and joins the thread."""

    def __init__(self, check: Callable[[ClaimKey, int], float | None], done: Callable[[ClaimKey], None]) -> None:
        self._check = check
        self._done = done
        self._cond = threading.Condition()
        self._queue: list[tuple[float, int, ClaimKey, int]] = []  # (due, order, key, tries): a heap
        self._pending: set[ClaimKey] = set()
        self._gone: set[ClaimKey] = set()  # pending claims whose token went while they were being checked
        self._order = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="migration-claims", daemon=True)

    def start(self) -> ClaimChecker:
        self._thread.start()
        return self

    def __enter__(self) -> ClaimChecker:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()

    def submit(self, key: ClaimKey) -> bool:
        """Queue ``key`` (once while it is pending); False beyond the bounds: then it is not checked."""
        with self._cond:
            if self._closed or key in self._pending:
                self._gone.discard(key)  # its token is back: keep checking it
                return True
            if len(self._pending) >= MAX_CLAIMS or sum(k[0] == key[0] for k in self._pending) >= CLAIMS_PER_CLAIMANT:
                return False
            self._pending.add(key)
            self._push(0.0, key, 0)
            return True

    def _push(self, due: float, key: ClaimKey, tries: int) -> None:
        self._order += 1
        heapq.heappush(self._queue, (due, self._order, key, tries))
        self._cond.notify()

    def withdraw(self, key: ClaimKey) -> None:
        """``key``'s token went: the claim is no longer pending (a retry waiting for it is dropped,
        a check under way ends with its answer), so that nothing waits for a claim nobody makes."""
        with self._cond:
            if key not in self._pending:
                return
            if not any(queued[2] == key for queued in self._queue):
                self._gone.add(key)  # being checked now
                return
            self._queue = [queued for queued in self._queue if queued[2] != key]
            heapq.heapify(self._queue)
            self._pending.discard(key)
        self._done(key)

    def pending(self, companion: str) -> bool:
        with self._cond:
            return any(k[1] == companion for k in self._pending)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(CHAIN_TIMEOUT + 5.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (not self._queue or self._queue[0][0] > time.monotonic()):
                    self._cond.wait(self._queue[0][0] - time.monotonic() if self._queue else None)
                if self._closed:
                    return
                _, _, key, tries = heapq.heappop(self._queue)
            try:
                again = self._check(key, tries)
            except Exception:  # a bug in one check must not end the checking of all the others
                log.exception("checking the custody claim of %s on %s at epoch %d failed", *key)
                again = None
            with self._cond:
                if again is not None and not self._closed and key not in self._gone:
                    self._push(time.monotonic() + again, key, tries + 1)
                    continue
                self._gone.discard(key)
                self._pending.discard(key)
            self._done(key)


class Claims:
    """The claims of the others, watched and checked; this embodiment's own, backed when asked.

    ``on_backed()`` runs on the loop after a claim was found backed; ``on_checked(companion)`` once
    a claim on ``companion`` is no longer pending (backed or not)."""

    def __init__(self, host: Host, *, on_backed: Callable[[], None], on_checked: Callable[[str], None]) -> None:
        self.host = host
        self._on_backed = on_backed
        self._on_checked = on_checked
        self._lock = threading.Lock()
        self._alive: set[str] = set()  # embodiments whose liveliness token is present (transport worker)
        self._tokens: dict[str, set[tuple[str, int]]] = {}  # companion -> {(holder, epoch)}: hints (transport worker)
        self._backed: dict[str, dict[tuple[str, int], Claim]] = {}  # companion -> claims backed (claim checker)
        self._stood_down: set[ClaimKey] = set()  # claims of branch holders an operator retired: ignored
        #: Claims known here without asking: of the target this embodiment hands a companion to (a
        #: Claim, the chain it extended itself), or None while that target receives it (no claim).
        self._known: dict[ClaimKey, Claim | None] = {}
        self._checker: ClaimChecker | None = None
        self._chain_buckets: dict[str, TokenBucket] = {}  # asker -> chain requests budget (loop)
        self._watches: list[Closeable] = []

    def open(self) -> None:
        """Start the checker and the watches (loop, at attach)."""
        sim = self.host.sim
        self._checker = ClaimChecker(self._check, self._checked).start()
        # Kept current by the transport's worker, so that choosing a target never blocks the loop.
        self._watches = [sim.transport.watch_liveliness(f"{keys.mesh_prefix(sim.mesh)}/{keys.ALIVE}/*", self._on_alive),
                         sim.transport.watch_liveliness(keys.custody_pattern(sim.mesh), self._on_custody)]

    def close(self) -> None:
        """Stop watching, then stop the checker (joined). Idempotent."""
        for watch in self._watches:
            watch.close()
        self._watches = []
        if self._checker is not None:
            self._checker.close()

    # --- what others claim (any thread) -------------------------------------------------------

    def is_alive(self, name: str) -> bool:
        with self._lock:
            return name in self._alive

    def backed(self, companion: str) -> list[Claim]:
        """The other embodiments' claims on ``companion`` that their claimants backed (``chain``): a
        bare custody token is never one."""
        with self._lock:
            backed = self._backed.get(companion, {})
            return [claim for (holder, epoch), claim in sorted(backed.items())
                    if (holder, companion, epoch) not in self._stood_down]

    def pending(self, companion: str) -> bool:
        """Whether claims on ``companion`` are still being checked."""
        checker = self._checker
        return checker is not None and checker.pending(companion)

    def trusted(self, companion: str) -> bytes | None:
        """The identity key trusted here for ``companion``: admitted, or pinned (None: none yet)."""
        admit = self.host.admit
        trusted = admit.get(companion) if admit is not None else None
        record = self.host.records.get(companion)
        if trusted is None and record is not None and record.public_key:
            trusted = signing.decode_public(record.public_key)
        return trusted

    # --- what this embodiment knows without asking (a handshake thread) -------------------------------

    def receiving(self, holder: str, companion: str, epoch: int) -> None:
        """``holder`` is about to receive ``companion`` from here at ``epoch``: its token at that epoch
        is no claim (asked, it would answer "incoming"), so it is not checked."""
        self._know((holder, companion, epoch), None)

    def vouch(self, holder: str, companion: str, epoch: int, chain: list[Link]) -> None:
        """This embodiment handed ``companion`` to ``holder`` (``chain`` ends with the link it signed):
        ``holder``'s claim at ``epoch`` is backed by what this side did, not by asking it."""
        self._know((holder, companion, epoch), Claim(holder, chain))

    def forget(self, holder: str, companion: str) -> None:
        """The handshake with ``holder`` ended without a commit: its claims on ``companion`` are
        checked as anyone's again (a token already there is checked now)."""
        with self._lock:
            keys_ = [key for key in self._known if key[0] == holder and key[1] == companion]
            for key in keys_:
                del self._known[key]
                self._backed.get(companion, {}).pop((holder, key[2]), None)
            present = [key for key in keys_ if (holder, key[2]) in self._tokens.get(companion, ())]
        checker = self._checker
        for key in present:
            if checker is not None:
                checker.submit(key)

    def _know(self, key: ClaimKey, claim: Claim | None) -> None:
        holder, companion, epoch = key
        with self._lock:
            if len(self._known) >= MAX_KNOWN:
                self._known.pop(next(iter(self._known)))  # bounded: the oldest handshake's go first
            self._known[key] = claim
            present = (holder, epoch) in self._tokens.get(companion, ())
            if present and claim is not None:
                self._backed.setdefault(companion, {})[(holder, epoch)] = claim
        checker = self._checker
        if present and checker is not None:
            checker.withdraw(key)  # known now: no need to ask
        if present and claim is not None:
            self.host.post(self._on_backed)

    def retire(self, companion: str, holders: Iterable[str]) -> None:
        """Ignore the claims on ``companion`` of ``holders`` from now on: an operator retired their
        branches (their tokens may linger a moment)."""
        retired = set(holders)
        with self._lock:
            for holder, epoch in self._tokens.get(companion, ()):
                if holder in retired:
                    self._stood_down.add((holder, companion, epoch))

    # --- the mesh as seen by liveliness (transport worker) ----------------------------------------

    def _on_alive(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        with self._lock:
            if alive:
                self._alive.add(name)
            else:
                self._alive.discard(name)

    def _on_custody(self, key: str, alive: bool) -> None:
        """A custody token came or went: a hint, recorded; its claim is checked on the claim checker."""
        try:
            holder, companion, epoch_text = key.split("/")[-3:]
            epoch = int(epoch_text)
        except ValueError:
            if self.host.quiet.allow(f"token:{key.split('/')[-3] if key.count('/') >= 2 else key}") is not None:
                logs.event(log, f"ignored custody token {key}: not <holder>/<companion>/<epoch>", level=logging.WARNING,
                           keyexpr=key)
            return
        unknown = True
        known: Claim | None = None
        with self._lock:
            tokens = self._tokens.setdefault(companion, set())
            if alive:
                tokens.add((holder, epoch))
                if (holder, companion, epoch) in self._known:
                    unknown = False
                    known = self._known[(holder, companion, epoch)]
                    if known is not None:
                        self._backed.setdefault(companion, {})[(holder, epoch)] = known
            else:
                tokens.discard((holder, epoch))
                self._backed.get(companion, {}).pop((holder, epoch), None)  # the token went: its claim goes
                self._stood_down.discard((holder, companion, epoch))
                self._known.pop((holder, companion, epoch), None)
                if not tokens:
                    del self._tokens[companion]
                    self._backed.pop(companion, None)
        checker = self._checker
        if not alive and checker is not None:
            # A claim retried while its token was on its way out (a target that moved on to the next
            # epoch refuses to back the one before) would keep offers on this companion waiting.
            checker.withdraw((holder, companion, epoch))
        if alive and not unknown:
            if known is not None:
                self.host.post(self._on_backed)
            return
        if alive and holder != self.host.sim.embodiment and checker is not None and not checker.submit((holder, companion, epoch)):
            self._ignore(holder, companion, epoch, "too many claims are waiting to be checked")

    # --- claims checked (the claim checker's thread) ----------------------------------------------

    def _token_present(self, holder: str, companion: str, epoch: int) -> bool:
        with self._lock:
            return (holder, epoch) in self._tokens.get(companion, ())

    def _check(self, key: ClaimKey, tries: int) -> float | None:
        """Ask the claimant to back its token, and keep the claim if it does; None when done, or the
        seconds after which to try again."""
        holder, companion, epoch = key
        host = self.host
        if not self._token_present(holder, companion, epoch) or host.stopping.is_set():
            return None  # gone meanwhile: nothing to check
        me = host.sim.embodiment
        nonce = os.urandom(16)  # what secrets.token_bytes gives, without loading hashlib and random at start
        try:
            reply = host.ask(holder, "chain", MigrateChain(companion, epoch, nonce), timeout=CHAIN_TIMEOUT)
        except OutcomeUnknown as exc:
            return self._not_backed(key, tries, f"it does not answer ({exc})", CLAIM_TRIES)
        if reply.status != "accepted":
            return self._not_backed(key, tries, f"it does not back it: {reply.reason}")
        value = reply.value if isinstance(reply.value, dict) else {}
        if value.get("state") == "incoming" and value.get("epoch") == epoch:
            return None  # receiving it: no custody yet, so neither a claim nor an objection to anyone
        try:
            chain = custody.decode_chain(base64.b64decode(str(value.get("chain", "")), validate=True))
            proof = base64.b64decode(str(value.get("proof", "")), validate=True)
            custody.verify_claim(chain, custody.ClaimProof(companion, epoch, holder, me, nonce), proof,
                                 identity=self.trusted(companion))
        except (SignatureRefused, binascii.Error, ValueError) as exc:
            return self._not_backed(key, tries, str(exc))
        with self._lock:
            if (holder, epoch) not in self._tokens.get(companion, ()):
                return None
            self._backed.setdefault(companion, {})[(holder, epoch)] = Claim(holder, chain)
        host.post(self._on_backed)
        return None

    def _not_backed(self, key: ClaimKey, tries: int, why: str, limit: int = 2) -> float | None:
        """A claim not backed this time: asked again shortly (its token may be on its way out), and
        ignored, and logged, if it still is not."""
        if tries + 1 < limit and not self.host.stopping.is_set():
            return CLAIM_RETRY * (1 << tries)
        if self._token_present(*key):
            self._ignore(*key, why)
        return None

    def _ignore(self, holder: str, companion: str, epoch: int, why: str) -> None:
        muted = self.host.quiet.allow(f"claim:{holder}")
        if muted is not None:
            more = f" ({muted} more of its claims ignored since the last report)" if muted else ""
            logs.event(log, f"ignored the custody claim of {holder!r} on {companion!r} at epoch {epoch}: {why}. A custody "
                            f"token is a hint, not proof: only a claim backed by its chain of custody counts{more}",
                       level=logging.WARNING, conflict="unbacked_claim", companion=companion, epoch=epoch, peer=holder,
                       muted=muted)

    def _checked(self, key: ClaimKey) -> None:
        self.host.post(self._on_checked, key[1])

    # --- this embodiment's claim, backed when asked (loop) ------------------------------------------

    def on_chain(self, request: IncomingRequest, msg: MigrateChain) -> None:
        """Back this embodiment's custody token: the chain held here and, when it holds custody, the
        asker's nonce signed by the key at the chain's head."""
        host = self.host
        me = host.sim.embodiment
        record = host.records.get(msg.companion)
        if record is None or record.state not in HOSTING or msg.companion in host.damaged:
            request.reject(f"{me!r} holds no custody of {msg.companion!r}", Code.NOT_FOUND)
            return
        if record.epoch != msg.epoch:
            request.reject(f"{me!r} holds {msg.companion!r} at epoch {record.epoch}, not {msg.epoch}", Code.NOT_FOUND)
            return
        proof = b""
        private = host.records.key(msg.companion) if record.state != "incoming" else None
        if private is not None:
            # Only a signature costs enough to budget: the receiving side's answer ("incoming", once
            # per migration to every peer watching) is a lookup, and refusing it as busy would keep
            # the asker's offers on this companion waiting for a retry (``CLAIM_RETRY``).
            bucket = self._chain_buckets.setdefault(request.requester, TokenBucket())
            if len(self._chain_buckets) > 1024:
                self._chain_buckets = {request.requester: bucket}
            if not bucket.take():
                request.reject(f"busy: too many chain requests from {request.requester!r}; try again later", Code.BUSY)
                return
            proof = custody.sign_claim(private, custody.ClaimProof(msg.companion, record.epoch, me, request.requester,
                                                                   msg.nonce))
        request.accept({"state": record.state, "epoch": record.epoch, "proof": base64.b64encode(proof).decode(),
                        "chain": base64.b64encode(custody.encode_chain(record.chain)).decode()})
