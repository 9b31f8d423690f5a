"""``validate``: CMION XML files checked as ``up`` checks them, every problem of every file."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from cmion_mesh.body.validate import FileReport, expand, render, validate_paths
from cmion_mesh.cli.common import json_option
from cmion_mesh.errors import ConfigError, ExitCode


def validate_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Check CMION XML files and list every problem of every file: errors (exit code 1), "
                     "warnings (stand-ins for CMION classes with no equivalent; exit code 0) and notes. A path that "
                     "is not there, or a folder without XML files, is a usage error (exit code 2).")
    p.add_argument("files", nargs="+", metavar="PATH", help="a file, a folder (its *.xml files) or a shipped embodiment's name")
    p.add_argument("--strict", action="store_true", help="warnings count as errors (exit code 1)")
    p.add_argument("--remote-type", action="append", metavar="TYPE",
                   help="a competency type served by another process (serve-competency): rules may use it; repeatable")
    json_option(p)


def cmd_validate(args: argparse.Namespace) -> int:
    reports: list[FileReport] = []
    paths: list[str] = []
    unusable = False  # a path that is not there, or a folder with nothing to check: a usage error (exit 2)
    for given in args.files:
        try:
            found = expand(given)
        except ConfigError as exc:
            failed = FileReport(given)
            failed.diagnostics.problem(exc)
            reports.append(failed)
            unusable = True
            continue
        unusable = unusable or not all(os.path.exists(path) for path in found)
        paths += found
    reports += validate_paths(paths, remote_types=args.remote_type or ())
    strict = bool(args.strict)
    if args.json:
        out = []
        for r in reports:
            entry: dict[str, Any] = {"path": r.path, "ok": r.ok(strict), "kind": r.kind,
                                     "diagnostics": [d.as_dict() for d in r.diagnostics]}
            if r.checked_with:
                entry["checked_with"] = r.checked_with
            failing = [str(d) for d in r.diagnostics if d.severity == "error" or (strict and d.severity == "warning")]
            if failing:
                entry["error"] = "\n".join(failing)
            out.append(entry)
        print(json.dumps(out))
    else:
        for r in reports:
            if r.ok(strict):
                counts = [f"{n} {word}{'s' if n > 1 else ''}" for word, n in
                          (("warning", len(r.diagnostics.warnings)), ("note", len(r.diagnostics.of("info")))) if n]
                print(f"ok: {r.path} ({r.kind}{', ' if counts else ''}{', '.join(counts)})")
            for item in r.diagnostics:
                print(render(item, strict=strict), file=sys.stderr)
        totals = {s: sum(len(r.diagnostics.of(s)) for r in reports) for s in ("error", "warning", "info")}
        if totals["error"] or totals["warning"]:
            failed_files = sum(not r.ok(strict) for r in reports)
            print(f"{len(reports)} files: {failed_files} failed; {totals['error']} errors, {totals['warning']} warnings"
                  f"{' (errors with --strict)' if strict and totals['warning'] else ''}", file=sys.stderr)
    if unusable:
        return ExitCode.USAGE
    return ExitCode.OK if all(r.ok(strict) for r in reports) else ExitCode.FAILED
