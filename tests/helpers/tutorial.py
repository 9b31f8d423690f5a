"""What tests read of docs/tutorial.md and examples/: the tutorial's code blocks, the files' marked
regions, and the commands of examples/blink/tutorial.sh."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
TUTORIAL = ROOT / "docs" / "tutorial.md"
SCRIPT = EXAMPLES / "blink" / "tutorial.sh"
#: Text files of examples/ a code block may quote.
QUOTABLE = ("*.py", "*.xml", "*.sh", "*.toml")

_MARK = re.compile(r"^\s*(?:#|<!--)\s*tutorial: (begin|end) ([\w-]+)\s*(?:-->)?\s*$")
_FENCE = re.compile(r"^```[\w-]*\n(.*?)^```\s*$", re.MULTILINE | re.DOTALL)


def regions(text: str, where: str = "<text>") -> dict[str, str]:
    """The marked regions of a file, by name: the lines between ``tutorial: begin NAME`` and
    ``tutorial: end NAME`` (a ``#`` or ``<!-- -->`` comment line each), without them. A region not
    closed, closed twice or opened twice is a ``ValueError`` naming the line."""
    found: dict[str, str] = {}
    open_at: dict[str, tuple[int, list[str]]] = {}
    for number, line in enumerate(text.splitlines(keepends=True), 1):
        mark = _MARK.match(line)
        if mark is None:
            for _, lines in open_at.values():
                lines.append(line)
            continue
        what, name = mark.groups()
        if what == "begin":
            if name in open_at or name in found:
                raise ValueError(f"{where}:{number}: region {name!r} begins twice")
            open_at[name] = (number, [])
        else:
            if name not in open_at:
                raise ValueError(f"{where}:{number}: region {name!r} ends without beginning")
            found[name] = "".join(open_at.pop(name)[1])
    if open_at:
        name, (number, _) = next(iter(open_at.items()))
        raise ValueError(f"{where}:{number}: region {name!r} never ends")
    return found


def code_blocks(markdown: str) -> list[str]:
    """The text of every fenced code block, in order."""
    return [m.group(1) for m in _FENCE.finditer(markdown)]


def quotable(folder: Path = EXAMPLES) -> dict[str, str]:
    """Every text a code block may be: each file's whole text (by its path under ``folder``), each
    region (``path#name``), and each file's text without its region marks (``path!``)."""
    texts: dict[str, str] = {}
    for pattern in QUOTABLE:
        for path in sorted(folder.rglob(pattern)):
            name = path.relative_to(folder).as_posix()
            text = path.read_text()
            texts[name] = text
            texts[f"{name}!"] = "".join(line for line in text.splitlines(keepends=True) if not _MARK.match(line))
            for region, body in regions(text, name).items():
                texts[f"{name}#{region}"] = body
    return texts


def script_regions() -> dict[str, list[str]]:
    """The command lines of each region of the tutorial's script, in the file's order."""
    return {name: [line for line in body.splitlines() if line.strip() and not line.lstrip().startswith("#")]
            for name, body in regions(SCRIPT.read_text(), SCRIPT.name).items()}
