"""A companion's operations, as a client runs them: find the embodiment it inhabits, migrate it,
invite it, set its policy, read and resolve its custody. ``MeshClient`` offers each as a method
(``client.migrate(...)``); they need only the client's requests, events and view of the mesh."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from cmion_mesh import keys
from cmion_mesh.errors import MeshError, NotAlive, OutcomeUnknown, RequestRejected, Vanished
from cmion_mesh.messages import (
    Code,
    CustodyResume,
    CustodyStandDown,
    Event,
    Message,
    Migrate,
    MigrateChain,
    Outcome,
    SendInvitations,
    SetPolicy,
)
from cmion_mesh.presence import Presence, alive_list, did_you_mean
from cmion_mesh.requests import require_accepted
from cmion_mesh.transport.base import Closeable


class CompanionClient(Protocol):
    """What the companion operations use of a client (``MeshClient``)."""

    @property
    def mesh(self) -> str: ...

    @property
    def presence(self) -> Presence: ...

    def join(self, embodiment: str, *, timeout: float = ...) -> None: ...

    def not_alive(self, embodiment: str, timeout: float) -> NotAlive: ...

    def describe_all(self, *, timeout: float = ...) -> list[dict[str, Any]]: ...

    def events(self, handler: Callable[[Event], None], *, embodiment: str = ..., component: str = ...,
               event: str = ...) -> Closeable: ...

    def request(self, embodiment: str, component: str, name: str, payload: Message, *,
                timeout: float = ..., sender: str | None = ...) -> Outcome: ...


def find_companion(client: CompanionClient, companion: str, *, timeout: float = 2.0) -> str:
    """The embodiment inhabited by ``companion``: ``NotAlive`` if none says so, ``MeshError`` if two do."""
    described = client.describe_all(timeout=timeout)
    hosts = sorted(str(d["name"]) for d in described if d.get("inhabitant") == companion)
    if len(hosts) > 1:
        raise MeshError(f"companion {companion!r} is claimed by {' and '.join(hosts)}: a duplicate! "
                        "(see `cmion-mesh doctor`)")
    if hosts:
        return hosts[0]
    inhabitants = {str(d["inhabitant"]): str(d["name"]) for d in described if d.get("inhabitant")}
    living = ", ".join(f"{c} on {e}" for c, e in sorted(inhabitants.items())) or "none"
    raise NotAlive(f"no embodiment alive in mesh {client.mesh!r} hosts companion {companion!r} "
                   f"(alive: {alive_list(str(d['name']) for d in described)}; companions: {living})"
                   + did_you_mean(companion, inhabitants))


def migrate(client: CompanionClient, companion: str, target: str, *, timeout: float = 60.0,
            join_timeout: float = 5.0) -> dict[str, Any]:
    """Move ``companion`` to ``target``; returns ``{source, target, epoch, attempt}`` once the target committed.

    Raises ``RequestRejected`` with the reason if the migration is refused or fails (the
    companion then keeps running at its source), ``NotAlive`` if the companion or the target
    is nowhere to be found, and ``OutcomeUnknown`` (``Vanished`` when the source or the target
    left the mesh) if its end is not heard. ``join_timeout``: how long to look for the companion's
    host and the target; ``timeout``: how long then to wait for the handshake's end.
    """
    source = find_companion(client, companion, timeout=join_timeout)
    client.join(target, timeout=join_timeout)
    started_at = time.monotonic()
    ended: queue.SimpleQueue[Event | str] = queue.SimpleQueue()

    def on_event(event: Event) -> None:
        if event.name in ("MigrationSucceeded", "MigrationFailed") and isinstance(event.data, dict) \
                and event.data.get("companion") == companion:
            ended.put(event)

    def on_presence(name: str, alive: bool) -> None:
        if not alive and name in (source, target):
            ended.put(name)

    key = keys.request_key(client.mesh, source, "migration", "migrate")
    with client.events(on_event, embodiment=source, component="migration"), client.presence.listen(on_presence):
        if source not in client.presence.alive() or target not in client.presence.alive():
            ended.put(source if source not in client.presence.alive() else target)
        started = client.request(source, "migration", "migrate", Migrate(companion, target), timeout=timeout)
        require_accepted(started, key)
        left = timeout - (time.monotonic() - started_at)
        try:
            end = ended.get(timeout=max(0.0, left))
        except queue.Empty:
            raise OutcomeUnknown(f"migration of {companion} from {source} to {target}: no end heard in {timeout:g} s",
                                 key=key) from None
    if isinstance(end, str):
        raise Vanished(f"migration of {companion} from {source} to {target}: {end} left the mesh after "
                       f"{time.monotonic() - started_at:.1f} s; outcome unknown (see `cmion-mesh peers`)", key=key)
    data = dict(end.data)
    if end.name == "MigrationFailed":
        raise RequestRejected(f"migration of {companion} to {target} failed: {data.get('reason')}", key=key,
                              reason=str(data.get("reason")))
    data["source"] = source
    return data


def invite(client: CompanionClient, inviter: str, to: Sequence[str] = (), *, timeout: float = 30.0,
           join_timeout: float = 5.0) -> dict[str, Any]:
    """Have the empty embodiment ``inviter`` invite the companion (``invitation``): to ``to``, or
    to its device table's embodiments, or without a table to every live one. Returns the
    round's ``InvitationsDone`` data (``round``, ``accepted_by``, ``answers``) when some
    embodiment accepted it (its mind got ``MigrationInvitation <inviter>``).

    Raises ``NotAlive`` if ``inviter`` is not alive, ``RequestRejected`` if it cannot invite
    (inhabited, nobody to invite) or nobody accepted (the reason lists every answer),
    ``OutcomeUnknown`` if no answer was definite (``Vanished`` if the inviter left the mesh).
    ``join_timeout``: how long to look for the inviter; ``timeout``: how long then to wait for the answers.
    """
    client.join(inviter, timeout=join_timeout)
    started_at = time.monotonic()
    ended: queue.SimpleQueue[Event | str] = queue.SimpleQueue()

    def on_event(event: Event) -> None:
        if event.name == "InvitationsDone" and isinstance(event.data, dict):
            ended.put(event)

    def on_presence(name: str, alive: bool) -> None:
        if not alive and name == inviter:
            ended.put(name)

    key = keys.request_key(client.mesh, inviter, "invitation", "send")
    with client.events(on_event, embodiment=inviter, component="invitation", event="InvitationsDone"), \
            client.presence.listen(on_presence):
        started = client.request(inviter, "invitation", "send", SendInvitations(list(to)), timeout=timeout)
        round_id = require_accepted(started, key)["round"]
        for _ in range(10_000):  # bounded: each round ends on an event, a departure or the deadline
            try:
                end = ended.get(timeout=max(0.0, timeout - (time.monotonic() - started_at)))
            except queue.Empty:
                raise OutcomeUnknown(f"invitations from {inviter}: no end heard in {timeout:g} s", key=key) from None
            if isinstance(end, str):
                raise Vanished(f"invitations from {inviter}: {inviter} left the mesh; outcome unknown", key=key)
            if end.data.get("round") == round_id:
                break
        else:
            raise OutcomeUnknown(f"invitations from {inviter}: round {round_id} never ended", key=key)
    data: dict[str, Any] = dict(end.data)
    if data.get("accepted_by"):
        return data
    answers: dict[str, dict[str, Any]] = data.get("answers") or {}
    reasons = "; ".join(f"{t}: {a.get('reason')}" for t, a in sorted(answers.items()))
    if answers and all(a.get("code") == Code.OUTCOME_UNKNOWN for a in answers.values()):
        raise OutcomeUnknown(f"invitations from {inviter}: no definite answer ({reasons})", key=key)
    raise RequestRejected(f"invitations from {inviter}: nobody accepted ({reasons})", key=key, reason=reasons)


def set_policy(client: CompanionClient, companion: str, accepts: Sequence[str] | None) -> None:
    """Say which embodiments ``companion`` accepts (None: any); it travels with the companion."""
    host = find_companion(client, companion)
    payload = SetPolicy(None if accepts is None else list(accepts))
    require_accepted(client.request(host, "migration", "policy", payload), keys.request_key(client.mesh, host, "migration", "policy"))


def custody(client: CompanionClient, companion: str, *, timeout: float = 2.0,
            join_timeout: float | None = None) -> dict[str, dict[str, Any]]:
    """What every live embodiment says of ``companion``'s custody (``describe``'s ``custody``):
    name -> its report ({} when it holds no copy; ``{"error": ...}`` when it did not answer).
    ``join_timeout``: how long to look for embodiments first (none found: ``{}``); ``timeout``:
    how long then to wait for their answers."""
    reports: dict[str, dict[str, Any]] = {}
    if join_timeout is not None and not client.presence.wait(lambda alive: bool(alive), join_timeout):
        return reports
    for d in client.describe_all(timeout=timeout):
        name = str(d.get("name"))
        if d.get("error"):
            reports[name] = {"error": str(d["error"])}
        else:
            held = (d.get("custody") or {}).get(companion)
            reports[name] = dict(held) if isinstance(held, dict) else {}
    return reports


def resolve_fork(client: CompanionClient, companion: str, keep: str, *, force: bool = False, gone: Sequence[str] = (),
                 sender: str = "cmion-mesh", timeout: float = 10.0, join_timeout: float = 5.0) -> dict[str, Any]:
    """Resolve a fork of ``companion``'s chain of custody by keeping ``keep``'s branch: every
    other branch holder stands down first (its copy retired on its disk before it answers), and
    only once all of them did is ``keep`` told to run it again. Refused (``RequestRejected``,
    nothing retired) when a holder of another branch cannot be reached (unless named ``gone``:
    wiped or revoked for good), or when the evidence shows an equivocator holding ``keep``'s
    branch (unless ``force``). Returns ``{"kept", "retired", "gone"}``. ``join_timeout``: how long
    to look for ``keep``; ``timeout``: how long to wait for each answer."""
    client.join(keep, timeout=join_timeout)
    reports = custody(client, companion, timeout=min(timeout, 5.0))
    key = keys.request_key(client.mesh, keep, "migration", "resume")
    alive = {name for name, report in reports.items() if "error" not in report}
    if keep not in reports:
        raise client.not_alive(keep, join_timeout)
    kept = reports[keep]
    if "error" in kept or kept.get("state") != "active":
        raise RequestRejected(f"{keep!r} holds no running copy of {companion!r} to keep "
                              f"({kept.get('error') or kept.get('state') or 'no copy'})", key=key)
    if not any(report.get("frozen") for report in reports.values()):
        raise RequestRejected(f"no embodiment reports a fork of {companion!r}'s chain of custody: nothing to resolve",
                              key=key)
    branches: dict[str, int] = {}
    tainted: dict[str, set[str]] = {}
    for name, report in reports.items():
        if report.get("state") is not None:
            branches[name] = int(report.get("epoch", 0))
        for holder, info in (report.get("branches") or {}).items():
            branches.setdefault(str(holder), int(info.get("epoch", 0)))
            tainted.setdefault(str(holder), set()).update(map(str, info.get("equivocators") or ()))
    if tainted.get(keep) and not force:
        raise RequestRejected(f"the evidence shows {', '.join(map(repr, sorted(tainted[keep])))} (who equivocated) "
                              f"holding the branch of {keep!r}: keeping it would reward the equivocation "
                              "(--force keeps it anyway)", key=key)
    others = sorted(h for h in branches if h != keep)
    unreachable = [h for h in others if h not in alive and h not in gone]
    if unreachable:
        raise RequestRejected(
            f"keeping {keep!r} would make two: {', '.join(f'{h!r} (epoch {branches[h]})' for h in unreachable)} "
            f"{'holds' if len(unreachable) == 1 else 'hold'} a branch of {companion!r} and cannot be reached to stand "
            "down; bring it back, or, if it is gone for good (wiped, or revoked), say so with --gone NAME", key=key)
    import base64  # here: only an operator's resolve needs them, and every one-shot command imports this module
    import secrets

    chain_key = keys.request_key(client.mesh, keep, "migration", "chain", sender)
    answer = require_accepted(client.request(keep, "migration", "chain",
                                           MigrateChain(companion, int(kept.get("epoch", 0)), secrets.token_bytes(16)),
                                           sender=sender, timeout=timeout), chain_key)
    chain = base64.b64decode(str(answer.get("chain", "")) if isinstance(answer, dict) else "")
    retired: list[str] = []
    for holder in others:
        if holder not in alive:
            continue  # gone for good, the operator says
        down_key = keys.request_key(client.mesh, holder, "migration", "stand_down")
        outcome = client.request(holder, "migration", "stand_down", CustodyStandDown(companion, keep, chain), timeout=timeout)
        if outcome.status != "accepted":
            raise RequestRejected(f"{holder!r} did not stand down: {outcome.reason}; "
                                  f"{'; '.join(f'{h!r} stood down' for h in retired) or 'nothing changed'}, "
                                  f"{keep!r} stays frozen", key=down_key, reason=outcome.reason, code=outcome.code)
        retired.append(holder)
    gone_ones = sorted(h for h in others if h not in alive)
    require_accepted(client.request(keep, "migration", "resume", CustodyResume(companion, [*retired, *gone_ones]),
                                  timeout=timeout), key)
    return {"kept": keep, "retired": retired, "gone": gone_ones}


__all__ = ["CompanionClient", "custody", "find_companion", "invite", "migrate", "resolve_fork", "set_policy"]
