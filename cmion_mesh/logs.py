"""A daemon's logs: the standard library's ``logging``, configured in one place when it starts.

Modules log as they always do (``log = logging.getLogger(__name__)``); ``configure`` decides once
where the lines go and how they look, for the whole process:

* ``text`` (the default): one line per record, ``2026-11-26T19:00:00.123Z INFO
  cmion_mesh.migration.incoming screen: companion spirit arrived from robot step=active
  companion=spirit peer=robot epoch=7 attempt=30ca... duration_s=0.412``: the time in UTC with
  milliseconds, the level, the logger, the embodiment (when known), the message, then the
  record's fields as ``name=value`` (values with spaces or quotes are JSON strings). Control
  characters in a message are escaped, so what a peer sends cannot forge a line or drive a terminal.
* ``json``: one JSON object per line, always with ``ts`` (as above), ``level`` (``DEBUG``,
  ``INFO``, ``WARNING``, ``ERROR``, ``CRITICAL``), ``logger`` and ``msg``; ``embodiment`` when
  known; each field of the record under its own name (a field named like one of those gets a
  ``_`` appended); ``exc`` with the traceback when the record carries an exception.

Lines go to standard error (which journald captures under systemd) or, with ``file``, to a file
that may be rotated by logrotate (``WatchedFileHandler`` reopens it once it is moved). They are
formatted and written by a thread of their own, ``logs-writer``, in batches (``Writer``): the
thread that logs a line only puts the record in a bounded queue (lines beyond are dropped and
counted, never waited for). ``flush()`` waits until what was logged is written.

What each module writes at info (the catalogue of lines, their messages and fields) is listed in
docs/deploy.md, "Logs".

Fields: ``event(log, "companion arrived", epoch=7, duration_s=0.4)``, or
``log.info("...", extra={"fields": {...}})``. ``event`` builds nothing unless the level is on;
code on a path taken per event or per message must not log at info (debug at most, behind
``log.isEnabledFor(logging.DEBUG)``) and repeats from the network go through a ``Throttle``.

Nothing secret is logged: the value of a field whose name says it holds a secret (``key``,
``*_key``, ``apikey``, or a name containing ``secret``, ``token``, ``password``, ``passwd``,
``passphrase``, ``credential``, ``cookie`` or ``private``) is written ``[redacted]``, nested
tables included, and so is a URL parameter named so in a message (``?key=...``). Name a zenoh
key expression ``keyexpr`` and a public key by its ``fingerprint``. Messages are written by us:
they never carry a secret in the first place.

The embodiment's name is in every line once ``set_embodiment`` is called (a record may name
another with ``extra={"embodiment": ...}``, for processes that host several).

Floods (``Throttle``): a line repeated for the same key (a sender, a code) is written the first
time only; the repeats are counted and said in one summary line per key per window ("1532 more
refused from robot in the last 5 s"), and at most ``budget`` keys get lines of their own per window,
the rest one summary together: a flood writes a bounded number of lines whatever its size or
number of senders, and the memory held is bounded too.

Wiring (the command line, ``up``; each one call):

* ``add_arguments(parser)`` on ``up``'s parser: ``--log-level``, ``--log-format``, ``--log-file``;
* ``configure(args.log_level, args.log_format, args.log_file)`` first in ``up``'s command, after
  the settings file is merged (``ops.settings.apply``), inside the ``try`` that turns a
  ``ConfigError`` into exit code 2 (an unusable log file is one);
* ``set_embodiment(name)`` once the embodiment's name is known;
* ``shutdown()`` on the way out, before ``os._exit`` (and before looking for threads left
  running): the throttles' pending counts and the lines queued are written, the writer stopped.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import re
import sys
import threading
import time
import weakref
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any, Final

from cmion_mesh.errors import ConfigError
from cmion_mesh.log_writer import DRAIN_TIMEOUT, Handoff, Writer

LEVELS: Final = ("debug", "info", "warning", "error")
FORMATS: Final = ("text", "json")
#: The fields every JSON line has (``embodiment`` and ``exc`` when there is one).
FIXED_FIELDS: Final = ("ts", "level", "logger", "msg", "embodiment", "exc")
REDACTED: Final = "[redacted]"
#: A summary line per key at most this often, by default (seconds).
WINDOW: Final = 5.0
#: Keys given lines of their own per window, by default: the rest are summed up together.
BUDGET: Final = 10
#: Other keys counted by name in a window's overflow: beyond, "at least" this many.
MAX_OTHERS: Final = 1000

_SECRET_WORDS: Final = ("secret", "token", "password", "passwd", "passphrase", "credential", "cookie", "private")
_SECRET_PARAMETER: Final = re.compile(
    r"([?&;](?:[\w.-]*(?:key|secret|token|password|passwd|passphrase|credential|cookie|private|auth)[\w.-]*)=)[^&#\s\"']+",
    re.IGNORECASE)
_CONTROL: Final = re.compile(r"[\x00-\x1f\x7f]")
_PLAIN: Final = re.compile(r"[^\s\"'=\\\x00-\x1f\x7f]+")
_PLAIN_NAME: Final = re.compile(r"[^\s\"':=\\\x00-\x1f\x7f]+")

#: Values that are no table, known without asking the ``Mapping`` ABC (a line's usual fields).
_SCALARS: Final = frozenset({int, float, bool, type(None)})

_lock = threading.Lock()
_installed: Handoff | None = None
_root_level: int | None = None  # the root logger's level before ``configure``, for ``unconfigure``
#: What every record notes of its thread and process (``logging.logThreads``...): neither format
#: writes it, and looking it up is a third of what making a record costs. Off while configured.
_RECORD_EXTRAS: Final = ("logThreads", "logProcesses", "logMultiprocessing")
_record_extras: dict[str, Any] = {}  # their values before ``configure``, for ``unconfigure``
_embodiment: str | None = None
_throttles: weakref.WeakSet[Throttle] = weakref.WeakSet()


@functools.lru_cache(maxsize=1024)  # a few names, written again and again
def is_secret(name: str) -> bool:
    """Whether a field of this name holds a secret (its value is never written)."""
    lowered = name.lower()
    return (lowered == "key" or lowered.endswith(("_key", "-key", ".key", "apikey"))
            or any(word in lowered for word in _SECRET_WORDS))


def redact(fields: Mapping[str, Any]) -> dict[str, Any]:
    """``fields`` with the value of every secret-named field (in nested tables too) replaced, and
    secret URL parameters scrubbed from the values that are text."""
    out: dict[str, Any] = {}
    for name, value in fields.items():
        if is_secret(str(name)):
            value = REDACTED
        elif isinstance(value, str):
            value = scrub(value)
        elif type(value) not in _SCALARS and isinstance(value, Mapping):  # the ABC's check is the slow one: last
            value = redact(value)
        out[name] = value
    return out


def scrub(text: str) -> str:
    """``text`` with the values of secret-named URL parameters replaced (a web page's ``?key=``)."""
    return _SECRET_PARAMETER.sub(lambda m: m.group(1) + REDACTED, text) if "=" in text else text


def set_embodiment(name: str | None) -> None:
    """Name the embodiment in every line from now on (None: no name)."""
    global _embodiment
    _embodiment = name


def event(log: logging.Logger, msg: str, /, *, level: int = logging.INFO, **fields: Any) -> None:
    """Log ``msg`` with structured ``fields`` (see the module's description), only when ``level``
    is on for ``log``."""
    if log.isEnabledFor(level):
        # The record is made here rather than by ``log.log``: its caller is the frame above, known,
        # and the standard library's search for it (``findCaller``) is a third of what a line costs.
        caller = sys._getframe(1)
        code = caller.f_code
        log.handle(log.makeRecord(log.name, level, code.co_filename, caller.f_lineno, msg, (), None, code.co_name,
                                  {"fields": fields}))


# --- formats --------------------------------------------------------------------------------------


_second: tuple[int, str] = (-1, "")  # the last whole second written, and its text


def _timestamp(record: logging.LogRecord) -> str:
    global _second
    whole = int(record.created)
    second = _second
    if second[0] != whole:  # a new second: formatted once, not for every line in it
        second = _second = (whole, time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(whole)))
    return f"{second[1]}.{int(record.msecs):03d}Z"


def _parts(record: logging.LogRecord) -> tuple[str, str | None, dict[str, Any]]:
    """The record's message (secrets scrubbed), embodiment and fields (secrets redacted)."""
    embodiment = getattr(record, "embodiment", None) or _embodiment
    fields = getattr(record, "fields", None)
    return scrub(record.getMessage()), embodiment, redact(fields) if isinstance(fields, Mapping) else {}


def _escape(text: str) -> str:
    if text.isprintable():  # no control character in it (the common case, and a fast test)
        return text
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


@functools.lru_cache(maxsize=1024)  # field names are few, and written again and again
def _field_name(name: str) -> str:
    return _escape(name)


def _text_value(value: Any) -> str:
    kind = type(value)  # the common types first, without the general path's work
    if kind is str:
        return value if _PLAIN.fullmatch(value) else json.dumps(value, ensure_ascii=False)
    if kind is int:
        return str(value)
    if value is None:
        return "null"
    if kind is bool:
        return "true" if value else "false"
    if isinstance(value, str):
        return value if _PLAIN.fullmatch(value) else json.dumps(value, ensure_ascii=False)
    if isinstance(value, float):
        return format(value, ".6g")
    try:
        return json.dumps(value, ensure_ascii=False, separators=(",", ":"), default=str)
    except (TypeError, ValueError):
        return json.dumps(str(value), ensure_ascii=False)


@functools.lru_cache(maxsize=64)
def _embodiment_text(name: str) -> str:
    # A name may hold spaces or a colon: then it is quoted, so that the line still parses.
    return name if _PLAIN_NAME.fullmatch(name) else json.dumps(name, ensure_ascii=False)


def _text_field(name: str, value: Any) -> str:
    """A field's value as a text line writes it, redacted as ``redact`` says (one pass: no copy)."""
    if is_secret(name):
        return REDACTED
    if type(value) is str and "=" not in value:  # the common case first: a plain value, no URL in it
        return value if _PLAIN.fullmatch(value) else json.dumps(value, ensure_ascii=False)
    if isinstance(value, str):
        value = scrub(value)
    elif type(value) not in _SCALARS and isinstance(value, Mapping):
        value = redact(value)
    return _text_value(value)


class TextFormatter(logging.Formatter):
    """``2026-11-26T19:00:00.123Z INFO cmion_mesh.migration robot: message name=value``."""

    def format(self, record: logging.LogRecord) -> str:
        # ``_parts`` and ``redact`` unrolled: every line is formatted (on the writer thread, which
        # shares the interpreter with the update loop), so it costs what it must and no more.
        embodiment = getattr(record, "embodiment", None) or _embodiment
        head = f"{_timestamp(record)} {record.levelname} {record.name}"
        if embodiment:
            head += " " + _embodiment_text(embodiment)
        line = f"{head}: {_escape(scrub(record.getMessage()))}"
        fields = getattr(record, "fields", None)
        if fields and isinstance(fields, Mapping):
            line += "".join([f" {_field_name(name)}={_text_field(name, value)}"
                             for name, value in ((str(n), v) for n, v in fields.items())])
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        elif record.stack_info:
            line += "\n" + self.formatStack(record.stack_info)
        return line


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ``ts``, ``level``, ``logger``, ``msg``, ``embodiment``, the fields, ``exc``."""

    def format(self, record: logging.LogRecord) -> str:
        msg, embodiment, fields = _parts(record)
        out: dict[str, Any] = {"ts": _timestamp(record), "level": record.levelname, "logger": record.name, "msg": msg}
        if embodiment:
            out["embodiment"] = embodiment
        for name, value in fields.items():
            name = str(name)
            while name in out or name in FIXED_FIELDS:
                name += "_"
            out[name] = value
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        elif record.stack_info:
            out["exc"] = self.formatStack(record.stack_info)
        try:
            return json.dumps(out, ensure_ascii=False, allow_nan=False, default=str)
        except (TypeError, ValueError):  # NaN, a key that is no string...: still one line of valid JSON
            return json.dumps({k: v if k in FIXED_FIELDS else _json_safe(v) for k, v in out.items()}, ensure_ascii=False)


def _json_safe(value: Any) -> Any:
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    return str(value)


class _Stderr(logging.StreamHandler[IO[str]]):
    """Standard error as it is when a line is written (tests and daemons may replace it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> IO[str]:
        return sys.stderr

    @stream.setter
    def stream(self, _value: IO[str]) -> None:
        pass


# --- configuration --------------------------------------------------------------------------------


def level_number(level: str | int) -> int:
    """``"info"`` (any case) or ``logging.INFO`` as a number; ``ConfigError`` for anything else."""
    if isinstance(level, int) and not isinstance(level, bool):
        return level
    if isinstance(level, str) and level.lower() in LEVELS:
        return int(getattr(logging, level.upper()))
    raise ConfigError(f"log level {level!r} is not one of {', '.join(LEVELS)}")


def configure(level: str | int = "info", fmt: str = "text", file: str | Path | None = None) -> logging.Handler:
    """Send every log line of the process at ``level`` and above to standard error, or to ``file``
    (appended to), in format ``fmt`` (``text`` or ``json``). Called again, it replaces what it
    installed before (nothing else: handlers others added stay). While configured, records do not
    note their thread and process (neither format writes them; ``unconfigure`` restores it).

    The lines are written by a thread of their own (``logs-writer``, a daemon thread): a record
    costs the thread that logs it one put in a queue (see ``Handoff``). ``flush`` waits until
    they are written; ``shutdown`` and ``unconfigure`` stop the writer once it has written them all.
    Returns the handler that formats and writes the lines.
    ``ConfigError`` for an unknown level or format, or a file that cannot be opened."""
    global _installed, _root_level
    number = level_number(level)
    if fmt not in FORMATS:
        raise ConfigError(f"log format {fmt!r} is not one of {', '.join(FORMATS)}")
    target: logging.StreamHandler[Any]
    if file is None or str(file) in ("", "-"):
        target = _Stderr()
    else:
        try:
            from logging.handlers import WatchedFileHandler  # only with a log file: it loads socket and more (start time)

            target = WatchedFileHandler(file, encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot open the log file: {exc.strerror or exc}", path=str(file)) from None
    target.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    handler = Handoff(Writer(target, lambda: _embodiment))
    root = logging.getLogger()
    with _lock:
        old, _installed = _installed, handler
        if old is not None:
            root.removeHandler(old)
        else:
            _root_level = root.level
            _record_extras.update({name: getattr(logging, name) for name in _RECORD_EXTRAS})
            for name in _RECORD_EXTRAS:
                setattr(logging, name, False)
        root.addHandler(handler)
        root.setLevel(number)
    if old is not None:
        _close(old)
    logging.captureWarnings(True)
    _at_exit()
    return target


def _close(handler: Handoff) -> None:
    """Write what ``handler``'s writer holds, stop it, and close the stream (a file)."""
    handler.writer.stop()
    handler.close()
    handler.writer.target.close()


@functools.cache  # once per process
def _at_exit() -> None:
    # A process that leaves without ``shutdown`` (an exception, ``sys.exit``) still writes its last lines.
    import atexit

    atexit.register(shutdown)


def unconfigure() -> None:
    """Remove what ``configure`` installed (its writer stopped once the lines queued are written)
    and restore the root logger's level (idempotent)."""
    global _installed
    with _lock:
        old, _installed = _installed, None
        root = logging.getLogger()
        if old is not None:
            root.removeHandler(old)
            root.setLevel(_root_level if _root_level is not None else logging.WARNING)
            for name, value in _record_extras.items():
                setattr(logging, name, value)
            _record_extras.clear()
    if old is not None:
        _close(old)
        logging.captureWarnings(False)


def flush(timeout: float = DRAIN_TIMEOUT) -> bool:
    """Wait until every line logged before is written (``timeout`` at most): True when it is."""
    handler = _installed
    return handler.writer.flush(timeout) if handler is not None else True


def shutdown() -> None:
    """Write what the throttles still hold and the lines queued, and stop the writer thread:
    before the process leaves (idempotent). Lines logged afterwards are written at once, by the
    thread that logs them, until ``unconfigure`` or ``configure``."""
    for throttle in list(_throttles):
        throttle.flush()
    handler = _installed
    if handler is not None:
        handler.writer.stop()


def add_arguments(parser: Any) -> None:
    """``--log-level``, ``--log-format`` and ``--log-file`` on ``parser`` (an ``argparse`` parser)."""
    group = parser.add_argument_group("logs")
    group.add_argument("--log-level", choices=LEVELS, default="info", type=str.lower,
                       help="the least important lines written (default: %(default)s; debug writes everything)")
    group.add_argument("--log-format", choices=FORMATS, default="text",
                       help="text lines, or one JSON object per line (default: %(default)s)")
    group.add_argument("--log-file", metavar="FILE",
                       help="append the lines to FILE (rotated files are reopened) instead of standard error")


# --- floods ---------------------------------------------------------------------------------------


class Throttle:
    """Lines about repeats from the network, bounded: per key (a sender, say), the first line of
    a window is written and the rest counted; when the window ends (on the next line asked for,
    or ``flush``) each count is one line: ``"<n> more <what> from <key> in the last <s> s"``. At
    most ``budget`` keys get lines in a window; the others are counted together, one line for
    all. So a window writes at most ``2 * budget + 1`` lines and holds at most ``budget`` keys
    (and the names of ``MAX_OTHERS`` others), whatever comes. Thread-safe; nothing is done
    while ``level`` is off for ``log``."""

    def __init__(self, log: logging.Logger, what: str, *, window: float = WINDOW, budget: int = BUDGET,
                 level: int = logging.INFO, clock: Callable[[], float] = time.monotonic) -> None:
        if window <= 0 or budget < 1:
            raise ValueError("a throttle needs a positive window and a budget of at least 1")
        self.log, self.what, self.window, self.budget, self.level, self.clock = log, what, window, budget, level, clock
        self._lock = threading.Lock()
        self._start: float | None = None
        self._counts: dict[str, int] = {}  # key -> repeats not written, this window
        self._others = 0
        self._other_keys: set[str] = set()
        _throttles.add(self)

    def __call__(self, key: str, msg: str, *args: object, **fields: Any) -> bool:
        """Log ``msg % args`` with ``fields`` unless ``key`` already had its line this window
        (then it is counted); True when the line was written."""
        if not self.log.isEnabledFor(self.level):
            return False
        now = self.clock()
        with self._lock:
            due = self._roll(now)
            count = self._counts.get(key)
            first = count is None and len(self._counts) < self.budget
            if count is not None:
                self._counts[key] = count + 1
            elif first:
                self._counts[key] = 0
            else:
                self._others += 1
                if len(self._other_keys) < MAX_OTHERS:
                    self._other_keys.add(key)
        self._write(due)
        if not first:
            return False
        self.log.log(self.level, msg, *args, extra={"fields": fields}, stacklevel=2)
        return True

    @property
    def held(self) -> int:
        """How many keys the throttle holds now (with its window's counts): at most ``budget + MAX_OTHERS``."""
        with self._lock:
            return len(self._counts) + len(self._other_keys)

    def flush(self) -> None:
        """Write the counts of the window under way now, and start a new one."""
        with self._lock:
            due = self._summaries(self.clock()) if self._start is not None else []
            self._reset(None)
        self._write(due)

    def _roll(self, now: float) -> list[tuple[str, dict[str, Any]]]:
        if self._start is None:
            self._start = now
            return []
        if now - self._start < self.window:
            return []
        due = self._summaries(now)
        self._reset(now)
        return due

    def _reset(self, start: float | None) -> None:
        self._start, self._counts, self._others, self._other_keys = start, {}, 0, set()

    def _summaries(self, now: float) -> list[tuple[str, dict[str, Any]]]:
        assert self._start is not None
        seconds = round(max(0.0, now - self._start), 1)
        out = [(f"{count} more {self.what} from {key} in the last {seconds:g} s", {"count": count, "from": key, "seconds": seconds})
               for key, count in self._counts.items() if count]
        if self._others:
            senders = len(self._other_keys)
            many = f"at least {senders}" if senders >= MAX_OTHERS else str(senders)
            out.append((f"{self._others} more {self.what} from {many} other{'s' if senders != 1 else ''} in the last {seconds:g} s",
                        {"count": self._others, "senders": senders, "seconds": seconds}))
        return out

    def _write(self, lines: list[tuple[str, dict[str, Any]]]) -> None:
        for msg, fields in lines:
            self.log.log(self.level, "%s", msg, extra={"fields": fields}, stacklevel=3)
