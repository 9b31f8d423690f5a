"""The one door through which cmion-mesh reads TOML files: bounded, and every error with a line.

Python's ``tomllib`` reads TOML with the standard library, but it keeps no positions and trusts
its input: ``load`` bounds the size, the encoding and the nesting before parsing, turns every
refusal into a ``ConfigError`` naming the file and line, and ``header_lines`` / ``key_line`` find
where a table or key was written, so the checks made after parsing can name a line too.

``what`` names the kind of file in messages ("launch file", "settings file").
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Any

from cmion_mesh.errors import ConfigError

#: Largest file read: a launch or settings file is a few KiB; a bigger one is a mistake.
MAX_FILE = 1024 * 1024
#: Deepest nesting of arrays and inline tables, and most parts of a dotted key. Python's TOML
#: reader recurses once per level (its stack gives out at a few hundred, as a RecursionError) and
#: takes a time growing with the square of a key's parts; our files need two or three.
MAX_NESTING = 32


def load(path: str | Path, what: str) -> tuple[str, dict[str, Any]]:
    """The file's text and what it holds; ``ConfigError`` naming the file (and the line) when it
    cannot be read, is too large, is not UTF-8, nests too deep or is not TOML."""
    path = Path(path)
    text = read_text(path, what)
    return text, parse(path, text, what)


def read_text(path: Path, what: str) -> str:
    """The file's text: ``ConfigError`` naming the file (and the line) when it cannot be."""
    try:
        with path.open("rb") as file:
            raw = file.read(MAX_FILE + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read the {what}: {exc.strerror or exc}", path=str(path)) from None
    if len(raw) > MAX_FILE:
        raise ConfigError(f"the {what} is larger than {MAX_FILE // 1024} KiB: not a {what}", path=str(path))
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise ConfigError(f"not UTF-8 (byte {raw[exc.start]:#04x}: {exc.reason}): a {what} is UTF-8 text",
                          path=str(path), line=line) from None


def parse(path: Path, text: str, what: str) -> dict[str, Any]:
    deep = nesting_problem(text)
    if deep is not None:
        raise ConfigError(f"too deep for a {what}: {deep[1]}", path=str(path), line=deep[0])
    # Imported here: every daemon imports this module (its --settings option), few read a file, and
    # tomllib's import is milliseconds of each start.
    import tomllib

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        at = re.search(r"\(at line (\d+), column \d+\)", message)
        line = int(at.group(1)) if at else max(1, len(text.splitlines()))
        raise ConfigError(f"not valid TOML: {re.sub(r' [(]at .*[)]$', '', message)}", path=str(path), line=line) from None
    except RecursionError:  # nesting the scan above did not see: still the file's fault, not ours
        raise ConfigError(f"too deep for a {what}: arrays, inline tables or keys nested beyond what can be read",
                          path=str(path)) from None


def header_lines(text: str) -> dict[tuple[str, int], int]:
    """Line of each table header: ``("launch", 0)`` for ``[launch]``, ``("embodiment", 1)`` for the
    second ``[[embodiment]]`` (tomllib keeps no positions; errors should still name a line)."""
    found: dict[tuple[str, int], int] = {}
    counts: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), 1):
        match = re.match(r"\s*\[\[?\s*([A-Za-z_-]+)\s*\]\]?", line)
        if match:
            kind = match.group(1)
            found[(kind, counts.get(kind, 0))] = number
            counts[kind] = counts.get(kind, 0) + 1
    return found


@functools.lru_cache(maxsize=4)
def _lines(text: str) -> list[str]:
    """The file's lines, split once (every key's line is looked up in them)."""
    return text.splitlines()


def key_line(text: str, start: int | None, key: str) -> int | None:
    """Line of ``key = ...`` (or of ``key.part = ...``) in the table whose header is on line
    ``start``, or at the top of the file (before any table) for ``start`` 0; the header's line
    when the key is not found (None at the top)."""
    if start is None:
        return None
    lines = _lines(text)
    for number in range(start, len(lines)):
        line = lines[number]
        if line.lstrip().startswith("["):
            break
        if re.match(rf"\s*[\"']?{re.escape(key)}[\"']?\s*[=.]", line):
            return number + 1
    return start or None


def nesting_problem(text: str) -> tuple[int, str] | None:
    """The line where arrays or inline tables nest deeper than ``MAX_NESTING``, or where a dotted
    key has more parts, and which; None when nowhere. Strings and comments are skipped (what is in
    them is no structure); the rest is left to the TOML reader, which reports its own errors."""
    depth = dots = 0
    line, i, end = 1, 0, len(text)
    while i < end:
        c = text[i]
        if c in "\"'":
            quote = c * 3 if text.startswith(c * 3, i) else c
            i += len(quote)
            while i < end and not text.startswith(quote, i):
                if text[i] == "\n":
                    if len(quote) == 1:
                        break  # an unterminated string: the TOML reader says so
                    line += 1
                elif text[i] == "\\" and c == '"' and i + 1 < end:
                    i += 1  # an escape: the next character is not the end of the string
                    if text[i] == "\n":
                        line += 1
                i += 1
            if text.startswith(quote, i):
                i += len(quote)
                while len(quote) == 3 and i < end and text[i] == c and text.startswith(quote, i - 3):
                    i += 1  # up to two more quotes just before the end belong to the string
            continue
        if c == "#":
            comment_end = text.find("\n", i)
            i = end if comment_end < 0 else comment_end
            continue
        if c == ".":
            dots += 1
            if dots >= MAX_NESTING:
                return line, f"a dotted key of more than {MAX_NESTING} parts"
        elif c in "[{":
            depth, dots = depth + 1, 0
            if depth > MAX_NESTING:
                return line, f"arrays or inline tables nested more than {MAX_NESTING} deep"
        elif c in "]}":
            depth, dots = max(0, depth - 1), 0
        elif not (c.isalnum() or c in "_-+: \t"):  # a key's parts, a number's, a date's go on; anything else ends them
            dots = 0
        line += c == "\n"
        i += 1
    return None
