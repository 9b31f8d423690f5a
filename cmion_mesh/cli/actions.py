"""One-shot commands that ask the mesh or act on it: ``peers``, ``act``, ``cancel``,
``remote-action``, ``migrate``, ``invite``, ``custody``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.cli.common import Spinner, item, join_timeout_option, mesh_options, subverb, table, timeout_option
from cmion_mesh.cli.session import session
from cmion_mesh.client import mesh_problems
from cmion_mesh.errors import ExitCode, RequestRejected
from cmion_mesh.requests import require_accepted
from cmion_mesh.signals import Stopper
from cmion_mesh.transport import security

#: After the first Ctrl-C, how long ``act`` waits for the cancelled outcome.
CANCEL_WAIT = 10.0


def peers_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Without NAME: one row per embodiment alive in the mesh (who inhabits it, its competency "
                     "types, the actions its rules accept, its version, since when it runs); the table wraps to "
                     "the terminal's width. With NAME: everything that embodiment says of itself (describe), "
                     "one field a line. It waits until every live embodiment has answered, at most --timeout.")
    p.add_argument("name", nargs="?", metavar="NAME", help="one embodiment: everything it says of itself")
    timeout_option(p, 3.0, "longest wait for the answers (it returns as soon as every live embodiment has answered)")
    mesh_options(p)


def cmd_peers(args: argparse.Namespace) -> int:
    if args.name:
        return _peer(args, keys.check_name(args.name, "embodiment"))
    with session(args) as client, Spinner("looking for embodiments", enabled=not args.json):
        peers = client.describe_all(timeout=args.timeout)
    for problem in mesh_problems(peers):
        print(f"warning: {problem}", file=sys.stderr)
    if args.json:
        print(json.dumps(peers))
        return ExitCode.OK
    if not peers:
        print(f"(no embodiments found in mesh {args.mesh!r} within {args.timeout:g} s: try `cmion-mesh doctor`)")
        return ExitCode.OK
    rows: list[tuple[str, ...]] = [("EMBODIMENT", "INHABITANT", "COMPETENCY TYPES", "ACTIONS", "VERSION", "UP SINCE")]
    for p in peers:
        since = time.strftime("%H:%M:%S", time.localtime(p.get("started_at", 0))) if p.get("started_at") else "?"
        if p.get("error"):
            rows.append((p["name"], "?", f"({p['error']})", "", "", ""))
            continue
        frozen = [f"{c} (FROZEN: custody fork)" for c, r in (p.get("custody") or {}).items() if isinstance(r, dict) and r.get("frozen")]
        rows.append((p["name"], p.get("inhabitant") or ", ".join(frozen) or "-",
                     ", ".join(map(item, p.get("competency_types", []))) or "-",
                     "; ".join(map(item, p.get("actions", []))) or "-", p.get("version", "?"), since))
    table(rows)
    return ExitCode.OK


#: ``peers NAME``: describe's fields in the order people read them, with their labels.
PEER_FIELDS = (("name", "embodiment"), ("inhabitant", "inhabitant"), ("custody", "custody"), ("actions", "actions"),
               ("competency_types", "competency types"), ("competencies", "competencies"), ("stand_ins", "stand-ins"),
               ("minds", "minds"), ("mind_connections", "mind connections"), ("admits", "admits companions"),
               ("devices", "device table"), ("alive", "sees alive"), ("duplicates", "duplicates"), ("damaged", "damaged"),
               ("migration_transfer", "last migration sent"), ("publications_dropped", "publications dropped"),
               ("mesh", "mesh"), ("host", "host"), ("pid", "pid"), ("version", "version"), ("started_at", "up since"),
               ("zenoh_id", "zenoh id"), ("companion_key", "companion key"))


def _peer(args: argparse.Namespace, name: str) -> int:
    with session(args) as client, Spinner(f"asking {name}", enabled=not args.json):
        client.join(name, timeout=args.timeout)
        described = client.describe(name, timeout=args.timeout)
    if args.json:
        print(json.dumps(described))
        return ExitCode.OK
    known = {field for field, _ in PEER_FIELDS}
    fields = [*PEER_FIELDS, *((f, f.replace("_", " ")) for f in sorted(described) if f not in known)]
    width = max(len(label) for field, label in fields if field in described)
    for field, label in fields:
        if field not in described:
            continue
        value = described[field]
        if field == "admits" and value is None:
            value = "any"  # no --admit: every companion may migrate in
        if field == "started_at" and isinstance(value, int | float):
            value = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(value))
        lines = _readable(value)
        print(f"{label + ':':<{width + 1}} {lines[0]}")
        for line in lines[1:]:
            print(f"{'':<{width + 1}} {line}")
    return ExitCode.OK


def _readable(value: Any) -> list[str]:
    """A describe field as lines: lists joined, maps one entry a line, none as '-'."""
    if value is None or value in ({}, [], ""):
        return ["-"]
    if isinstance(value, list):
        return [", ".join(str(v) if not isinstance(v, dict | list) else json.dumps(v) for v in value)]
    if isinstance(value, dict):
        return [f"{k}: {json.dumps(v) if isinstance(v, dict | list) else v}" for k, v in value.items()]
    return [str(value)]


def act_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Send a mind action and wait for its outcome. Ctrl-C cancels it and waits for the "
                     "cancelled outcome; a second Ctrl-C leaves without waiting.")
    p.add_argument("embodiment", help="the embodiment to act")
    p.add_argument("action", help="the action's name, e.g. GoTo (see `peers` for the actions each embodiment knows)")
    p.add_argument("parameters", nargs="*", help="the action's parameters, e.g. Kitchen")
    p.add_argument("--subject", default="", help="who the action is about (rules may match on it)")
    p.add_argument("--id", help="action id (default: generated)")
    timeout_option(p, 120.0, "seconds to wait for the outcome")
    p.add_argument("--deadline", type=float, default=0.0, help="deadline of each plan tried, seconds (default: the manager's)")
    p.add_argument("--detach", action="store_true", help="print the action's id and leave it running")
    join_timeout_option(p)
    mesh_options(p)


def cmd_act(args: argparse.Namespace) -> int:
    stop = Stopper()  # Ctrl-C is collected by the main thread, whichever thread the signal reaches
    with session(args) as client:
        try:
            run = client.start_action(args.embodiment, args.action, args.parameters, subject=args.subject,
                                      action_id=args.id or "", deadline=args.deadline, join_timeout=args.join_timeout,
                                      on_end=stop.stop)
        except RequestRejected as exc:
            if args.json:  # a script reads the outcome on stdout, a refusal too (the line on stderr as ever)
                print(json.dumps({"action_id": args.id or "", "status": exc.status, "reason": exc.reason, "code": exc.code}))
            raise
        with run:
            if args.detach:
                print(json.dumps({"action_id": run.action_id, "status": "running"}) if args.json else
                      f"{run.action_id} running on {args.embodiment} (cmion-mesh cancel {args.embodiment} {run.action_id})")
                return ExitCode.OK
            deadline = time.monotonic() + args.timeout
            interrupts = 0
            with Spinner(f"{args.embodiment}: {' '.join([args.action, *args.parameters])}", enabled=not args.json):
                for _ in range(1000):  # bounded: each round ends on the outcome, a signal or the deadline
                    left = deadline - time.monotonic()
                    if run.ended.is_set() or left <= 0:
                        break
                    if stop.wait(left) is None:
                        continue
                    interrupts += 1
                    if interrupts > 1:
                        print(f"left without waiting: action {run.action_id} may still be running on {args.embodiment} "
                              f"(cmion-mesh cancel {args.embodiment} {run.action_id})", file=sys.stderr)
                        return ExitCode.INTERRUPTED
                    print(f"cancelling {run.action_id} (Ctrl-C again to leave without waiting)", file=sys.stderr, flush=True)
                    key = keys.request_key(args.mesh, args.embodiment, "manager", "cancel")
                    require_accepted(client.cancel(args.embodiment, run.action_id), key)
                    deadline = min(deadline, time.monotonic() + CANCEL_WAIT)
            report = run.result(args.timeout)
    if args.json:
        print(json.dumps(msgspec.to_builtins(report)))
    else:
        extra = f": {report.reason}" if report.reason else ""
        print(f"{report.action_id} {report.status}{extra}" + (f" (rule {report.rule})" if report.rule else ""))
    return {"succeeded": ExitCode.OK, "cancelled": ExitCode.CANCELLED}.get(report.status, ExitCode.FAILED)


def cancel_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("embodiment", help="the embodiment running it")
    p.add_argument("action_id", help="the action's id (act prints it)")
    join_timeout_option(p)
    mesh_options(p)


def cmd_cancel(args: argparse.Namespace) -> int:
    with session(args) as client:
        client.join(args.embodiment, timeout=args.join_timeout)
        key = keys.request_key(args.mesh, args.embodiment, "manager", "cancel")
        require_accepted(client.cancel(args.embodiment, args.action_id), key)
    print(json.dumps({"action_id": args.action_id, "cancel": "accepted"}) if args.json else f"cancel of {args.action_id} accepted")
    return ExitCode.OK


def remote_action_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Tell an embodiment's minds that another agent did an action: they perceive it as a remote "
                     "action (FAtiMA hears ACTION-FINISHED SUBJECT NAME PARAMETERS), as from a sensor that saw it "
                     "(CMION's RemoteActionSimulator). The name, each parameter and the subject are one word each. "
                     "Unlike `act`, nothing is run: the body only perceives.")
    p.add_argument("embodiment", help="the embodiment whose minds perceive it")
    p.add_argument("action", help="the action's name, e.g. Greet")
    p.add_argument("parameters", nargs="*", help="its parameters, e.g. Spirit")
    p.add_argument("--subject", default="", help="the agent who acted (default: none said; FAtiMA hears World)")
    join_timeout_option(p)
    mesh_options(p)


def cmd_remote_action(args: argparse.Namespace) -> int:
    with session(args) as client:
        client.join(args.embodiment, timeout=args.join_timeout)
        minds = client.remote_action(args.embodiment, args.action, args.parameters, args.subject)
    action = " ".join([args.action, *args.parameters])
    if args.json:
        print(json.dumps({"embodiment": args.embodiment, "name": args.action, "parameters": args.parameters,
                          "subject": args.subject, "minds": minds}))
    elif minds:
        print(f"{args.embodiment}: {', '.join(minds)} perceived {args.subject or 'someone'} do {action}")
    else:
        print(f"{args.embodiment}: raised {args.subject or 'someone'} do {action}; no mind of its own is awake to perceive "
              "it (a mind served from another process hears it)")
    return ExitCode.OK


def migrate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("companion", help="the companion to move (see `peers`: INHABITANT)")
    p.add_argument("--to", required=True, metavar="EMBODIMENT", help="where to")
    timeout_option(p, 60.0, "seconds to wait for the handshake's end")
    join_timeout_option(p)
    mesh_options(p)


def cmd_migrate(args: argparse.Namespace) -> int:
    with session(args) as client, Spinner(f"migrating {args.companion} to {args.to}", enabled=not args.json):
        result = client.migrate(args.companion, args.to, timeout=args.timeout, join_timeout=args.join_timeout)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.companion} migrated from {result['source']} to {result['target']} (epoch {result['epoch']})")
    return ExitCode.OK


def invite_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("EMBODIMENT (which must host no companion) invites the companion: every embodiment of "
                     "its device table, or without a table every live one, is asked; the one hosting the "
                     "companion passes MigrationInvitation EMBODIMENT to its mind, which may migrate. Exit 0 "
                     "when a host accepted the invitation, 1 when nobody did (each answer is listed).")
    p.add_argument("embodiment", help="the inviting embodiment (empty)")
    p.add_argument("--to", action="append", metavar="EMBODIMENT",
                   help="invite only this embodiment; repeatable (default: the device table's, or every live one)")
    timeout_option(p, 30.0, "seconds to wait for every answer")
    join_timeout_option(p)
    mesh_options(p)


def cmd_invite(args: argparse.Namespace) -> int:
    with session(args) as client, Spinner(f"{args.embodiment} invites the companion", enabled=not args.json):
        result = client.invite(args.embodiment, args.to or (), timeout=args.timeout, join_timeout=args.join_timeout)
    if args.json:
        print(json.dumps(result))
    else:
        hosts = ", ".join(result["accepted_by"])
        print(f"invitation from {args.embodiment} accepted by {hosts}: the companion's mind got "
              f"MigrationInvitation {args.embodiment} (`cmion-mesh peers` shows whether it comes)")
    return ExitCode.OK


def custody_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("A companion's custody across the mesh. `custody show COMPANION`: what every live embodiment "
                     "reports of it and of forks of its chain. `custody resolve COMPANION --keep EMBODIMENT`: keep "
                     "one branch of a fork (see each one's --help).")
    actions = p.add_subparsers(dest="custody_command", required=True, metavar="ACTION")
    cp = subverb(actions, "show", "what every embodiment reports of a companion's custody, forks and their evidence",
                 "cmion-mesh custody show spirit --json",
                 description="What every live embodiment reports of COMPANION's custody: who holds which epoch, the "
                             "evidence of a fork (who equivocated) and the command that resolves it.")
    cp.add_argument("companion", help="the companion")
    timeout_option(cp, 3.0, "longest wait for the whole mesh to answer")
    join_timeout_option(cp)
    mesh_options(cp)
    cp = subverb(actions, "resolve", "keep one branch of a fork of a companion's chain of custody; the others stand down",
                 "cmion-mesh custody resolve spirit --keep robot --gone phone",
                 description="Keep EMBODIMENT's branch of a fork of COMPANION's chain of custody: every other branch "
                             "holder stands down first (its copy retired on its disk), then the kept one runs again. "
                             "Refused when a holder of another branch cannot be reached (it would make two), or when "
                             "the evidence shows an equivocator holding the branch kept (--force).")
    cp.add_argument("companion", help="the companion")
    cp.add_argument("--keep", required=True, metavar="EMBODIMENT", help="the embodiment whose branch runs the companion")
    cp.add_argument("--force", action="store_true", help="keep it even though the evidence shows an equivocator holding it")
    cp.add_argument("--gone", action="append", metavar="EMBODIMENT",
                    help="a branch holder that is gone for good (wiped, revoked): not waited for; repeatable")
    timeout_option(cp, 10.0, "seconds to wait for each answer")
    join_timeout_option(cp)
    mesh_options(cp)


def cmd_custody(args: argparse.Namespace) -> int:
    companion = keys.check_name(args.companion, "companion")
    if args.custody_command == "resolve":
        keep = keys.check_name(args.keep, "embodiment")
        gone = [keys.check_name(name, "embodiment") for name in args.gone or ()]
        sender = "cmion-mesh"
        if args.certs:
            sender = security.choose_identity(args.certs, args.identity)
        with session(args) as client, Spinner(f"resolving the fork of {companion}", enabled=not args.json):
            result = client.resolve_fork(companion, keep, force=args.force, gone=gone, sender=sender, timeout=args.timeout,
                                         join_timeout=args.join_timeout)
        if args.json:
            print(json.dumps(result))
        else:
            down = ", ".join(result["retired"]) or "nobody"
            print(f"{companion}: {down} stood down{' (gone: ' + ', '.join(result['gone']) + ')' if result['gone'] else ''}; "
                  f"it runs on {keep} again")
        return ExitCode.OK
    with session(args) as client, Spinner(f"asking the mesh about {companion}", enabled=not args.json):
        reports = client.custody(companion, timeout=args.timeout, join_timeout=args.join_timeout)
    forks = {f["description"]: f for report in reports.values() for f in report.get("forks") or ()}
    equivocators = sorted({str(e) for report in reports.values() for e in report.get("equivocators") or ()})
    branches: dict[str, dict[str, Any]] = {}
    for report in reports.values():
        branches.update(report.get("branches") or {})
    unreachable = sorted(h for h in branches if "error" in reports.get(h, {"error": "not alive"}))
    if args.json:
        print(json.dumps({"companion": companion, "reports": reports, "forks": list(forks.values()),
                          "equivocators": equivocators, "branches": branches, "unreachable": unreachable}))
        return ExitCode.OK
    rows: list[tuple[str, ...]] = [("EMBODIMENT", "STATE", "EPOCH", "CUSTODY")]
    for name, report in sorted(reports.items()):
        if "error" in report:
            rows.append((name, "?", "", f"({report['error']})"))
        elif report:
            held = "FROZEN: fork" if report.get("frozen") else "runs it" if report.get("state") == "active" else "in a migration"
            rows.append((name, str(report.get("state")), str(report.get("epoch")), held))
        else:
            rows.append((name, "-", "", ""))
    for name in unreachable:
        rows.append((name, "?", str(branches[name].get("epoch", "")), "holds a branch: NOT REACHABLE"))
    table(rows)
    if not forks:
        print(f"no fork of {companion}'s chain of custody is reported")
        return ExitCode.OK
    for fork in forks.values():
        print(f"fork at epoch {fork['epoch']}: {fork['description']}")
    for name, info in sorted(branches.items()):
        held = f"; the equivocator {', '.join(map(repr, info.get('equivocators') or ()))} holds it" if info.get("equivocators") else ""
        print(f"  branch of {name}: epoch {info.get('epoch')}{held}")
    if equivocators:
        print(f"equivocated: {', '.join(map(repr, equivocators))}: revoke with `cmion-mesh certs revoke PKI NAME` "
              "(then give the members the new trust.json and restart them)")
    keepable = sorted(h for h, info in branches.items() if not info.get("equivocators"))
    print(f"resolve: cmion-mesh custody resolve {companion} --keep EMBODIMENT "
          f"({'e.g. ' + ', '.join(keepable) if keepable else 'every branch holds an equivocator: --force'}); "
          "every other branch holder stands down first")
    return ExitCode.OK
