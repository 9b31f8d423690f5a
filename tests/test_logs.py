"""The daemon's logs (cmion_mesh/logs.py): both formats parse back, secrets never reach a line, floods
are bounded. Pure: no network, no process."""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import log_writer, logs
from cmion_mesh.errors import ConfigError, ExitCode, exit_code

LOG = logging.getLogger("cmion_mesh.migration")
#: 2026-11-26T19:00:00.123Z
CREATED = datetime(2026, 11, 26, 19, 0, 0, 123000, tzinfo=UTC).timestamp()
TEXT_LINE = re.compile(r"(?P<ts>\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z) (?P<level>[A-Z]+) (?P<logger>\S+)"
                       r"(?: (?P<embodiment>\"(?:[^\"\\]|\\.)*\"|[^\s\":=]+))?: (?P<msg>.*?)"
                       r"(?P<fields>(?: [\w.-]+=(?:\"(?:[^\"\\]|\\.)*\"|[^\s\"'=\\]+))*)")
FIELD = re.compile(r" ([\w.-]+)=(\"(?:[^\"\\]|\\.)*\"|[^\s\"'=\\]+)")


def parse_text(line: str) -> dict[str, Any]:
    """A text line back into what it says: the documented parts, then the fields."""
    match = TEXT_LINE.fullmatch(line)
    assert match, f"not a text log line: {line!r}"
    out: dict[str, Any] = {k: match.group(k) for k in ("ts", "level", "logger", "msg")}
    if match.group("embodiment"):
        raw = match.group("embodiment")
        out["embodiment"] = json.loads(raw) if raw.startswith('"') else raw
    for name, raw in FIELD.findall(match.group("fields")):
        try:
            out[name] = json.loads(raw)
        except ValueError:
            out[name] = raw
    return out


def strict_json(line: str) -> dict[str, Any]:
    def refuse(constant: str) -> Any:
        raise AssertionError(f"not valid JSON: {constant} in {line!r}")

    value = json.loads(line, parse_constant=refuse)
    assert isinstance(value, dict)
    return value


def record(msg: str, *args: object, level: int = logging.INFO, fields: dict[str, Any] | None = None,
           exc: bool = False, **extra: Any) -> logging.LogRecord:
    exc_info = None
    if exc:
        try:
            raise ValueError("the cause")
        except ValueError:
            import sys

            exc_info = sys.exc_info()
    made = LOG.makeRecord(LOG.name, level, __file__, 1, msg, args, exc_info,
                          extra={**({"fields": fields} if fields is not None else {}), **extra})
    made.created, made.msecs = CREATED, 123.0
    return made


@pytest.fixture(autouse=True)
def clean_logging() -> Iterator[None]:
    yield
    logs.unconfigure()
    logs.set_embodiment(None)


# --- the two formats ------------------------------------------------------------------------------


def test_a_text_line_has_the_time_level_logger_embodiment_message_and_fields() -> None:
    logs.set_embodiment("robot")
    line = logs.TextFormatter().format(record("companion arrived", fields={"epoch": 7, "duration_s": 0.412, "peer": "my phone",
                                                                          "ok": True, "from": None}))
    assert line == ('2026-11-26T19:00:00.123Z INFO cmion_mesh.migration robot: companion arrived epoch=7 duration_s=0.412 '
                    'peer="my phone" ok=true from=null')
    assert parse_text(line) == {"ts": "2026-11-26T19:00:00.123Z", "level": "INFO", "logger": "cmion_mesh.migration",
                                "embodiment": "robot", "msg": "companion arrived", "epoch": 7, "duration_s": 0.412,
                                "peer": "my phone", "ok": True, "from": None}


def test_a_json_line_is_one_object_with_the_documented_fields() -> None:
    logs.set_embodiment("robot")
    line = logs.JsonFormatter().format(record("refused %s", "a request", level=logging.WARNING,
                                              fields={"code": "denied", "from": "phone", "msg": "clash", "ts": 1}))
    assert "\n" not in line
    assert strict_json(line) == {"ts": "2026-11-26T19:00:00.123Z", "level": "WARNING", "logger": "cmion_mesh.migration",
                                 "msg": "refused a request", "embodiment": "robot", "code": "denied", "from": "phone",
                                 "msg_": "clash", "ts_": 1}


def test_an_exception_is_the_text_lines_tail_and_the_json_lines_exc_field() -> None:
    text = logs.TextFormatter().format(record("it broke", level=logging.ERROR, exc=True))
    first, *rest = text.splitlines()
    assert parse_text(first) == {"ts": "2026-11-26T19:00:00.123Z", "level": "ERROR", "logger": "cmion_mesh.migration",
                                 "msg": "it broke"}
    assert rest[0] == "Traceback (most recent call last):" and rest[-1] == "ValueError: the cause"
    data = strict_json(logs.JsonFormatter().format(record("it broke", level=logging.ERROR, exc=True)))
    assert data["exc"].startswith("Traceback (most recent call last):") and data["exc"].endswith("ValueError: the cause")
    assert "embodiment" not in data  # none set: none said


def test_what_a_peer_sends_cannot_forge_a_line_or_break_the_json() -> None:
    sent = "hello\n2026-11-26T19:00:00.000Z ERROR cmion_mesh.x robot: forged\x1b[31m"
    text = logs.TextFormatter().format(record("said %s", sent, fields={"said": sent, "weird": float("nan")}))
    assert len(text.splitlines()) == 1 and "\x1b" not in text
    parsed = parse_text(text)
    assert parsed["said"] == sent and parsed["msg"] == "said " + sent.replace("\n", "\\n").replace("\x1b", "\\x1b")
    data = strict_json(logs.JsonFormatter().format(record("said %s", sent, fields={"said": sent, "weird": float("nan"),
                                                                                   "thing": object()})))
    assert data["msg"] == "said " + sent and data["said"] == sent and data["weird"] == "nan"
    assert data["thing"].startswith("<object object at")


def test_an_embodiment_name_with_spaces_is_quoted_and_a_record_may_name_its_own() -> None:
    logs.set_embodiment("the robot: v2")
    parsed = parse_text(logs.TextFormatter().format(record("up")))
    assert parsed["embodiment"] == "the robot: v2" and parsed["msg"] == "up"
    assert strict_json(logs.JsonFormatter().format(record("up", embodiment="phone")))["embodiment"] == "phone"


# --- secrets --------------------------------------------------------------------------------------


def test_values_of_secret_named_fields_and_url_keys_are_never_written() -> None:
    fields = {"key": "s1", "web_key": "s2", "apikey": "s3", "token": "s4", "db_password": "s5", "client_secret": "s6",
              "private": "s7", "nested": {"session_token": "s8", "peer": "phone"}, "keyexpr": "cmion/mesh/rq/robot",
              "address": "http://127.0.0.1:8080/?key=s9&lang=en", "peer": "phone"}
    for formatter in (logs.TextFormatter(), logs.JsonFormatter()):
        line = formatter.format(record("page at %s", "http://127.0.0.1:8080/?key=s10#top", fields=fields))
        assert "http://127.0.0.1:8080/?key=" in line and "phone" in line
        for secret in ("s1", "s2", "s3", "s4", "s5", "s6", "s7", "s8", "s9", "s10"):
            assert not re.search(rf"\b{secret}\b", line), (secret, line)
    data = strict_json(logs.JsonFormatter().format(record("m", fields=fields)))
    assert data["keyexpr"] == "cmion/mesh/rq/robot" and data["peer"] == "phone" and data["nested"]["peer"] == "phone"
    assert data["token"] == logs.REDACTED and data["nested"]["session_token"] == logs.REDACTED
    assert data["address"] == f"http://127.0.0.1:8080/?key={logs.REDACTED}&lang=en"


# --- configuration --------------------------------------------------------------------------------


def test_configure_writes_both_formats_to_a_file_that_parses_back(tmp_path: Path) -> None:
    file = tmp_path / "daemon.log"
    logs.configure("info", "text", file)
    logs.set_embodiment("robot")
    logs.event(LOG, "peer joined", peer="phone")
    logs.event(LOG, "details", level=logging.DEBUG, peer="phone")  # below the level: not written
    logs.configure("debug", "json", file)  # replaces the text handler: lines are not written twice
    logs.event(LOG, "details", level=logging.DEBUG, peer="phone")
    LOG.warning("custody conflict over %s", "companion", extra={"fields": {"epoch": 3}})
    assert logs.flush()
    lines = file.read_text(encoding="utf-8").splitlines()
    assert len(lines) == 3, lines
    assert {k: v for k, v in parse_text(lines[0]).items() if k != "ts"} == {
        "level": "INFO", "logger": "cmion_mesh.migration", "embodiment": "robot", "msg": "peer joined", "peer": "phone"}
    second, third = strict_json(lines[1]), strict_json(lines[2])
    assert {k: v for k, v in second.items() if k != "ts"} == {"level": "DEBUG", "logger": "cmion_mesh.migration",
                                                               "msg": "details", "embodiment": "robot", "peer": "phone"}
    assert third["msg"] == "custody conflict over companion" and third["epoch"] == 3 and third["level"] == "WARNING"
    now = datetime.now(UTC)
    for stamp in (parse_text(lines[0])["ts"], second["ts"], third["ts"]):
        written = datetime.strptime(stamp, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=UTC)
        assert abs((now - written).total_seconds()) < 600  # UTC, not local time


def test_configure_twice_keeps_one_handler_of_its_own_and_leaves_others_alone(capsys: pytest.CaptureFixture[str]) -> None:
    root = logging.getLogger()
    level_before = root.level
    theirs = logging.NullHandler()
    root.addHandler(theirs)
    try:
        for _ in range(3):
            logs.configure("warning", "text")
        ours = [h for h in root.handlers if isinstance(h.formatter, logs.TextFormatter | logs.JsonFormatter)]
        assert len(ours) == 1 and theirs in root.handlers
        LOG.warning("once")
        LOG.info("not at warning")
        assert logs.flush()
        err = capsys.readouterr().err.splitlines()
        assert [parse_text(line)["msg"] for line in err] == ["once"]
        logs.unconfigure()
        logs.unconfigure()  # idempotent
        assert theirs in root.handlers and root.level == level_before
        assert not [h for h in root.handlers if isinstance(h.formatter, logs.TextFormatter | logs.JsonFormatter)]
    finally:
        root.removeHandler(theirs)


@pytest.mark.parametrize(("args", "says"), [
    (("loud", "text", None), "log level 'loud' is not one of debug, info, warning, error"),
    (("info", "xml", None), "log format 'xml' is not one of text, json"),
])
def test_an_unknown_level_or_format_is_a_configuration_error(args: tuple[Any, ...], says: str) -> None:
    with pytest.raises(ConfigError) as caught:
        logs.configure(*args)
    assert str(caught.value) == says and exit_code(caught.value) == ExitCode.USAGE


def test_a_log_file_that_cannot_be_opened_is_one_line_naming_it(tmp_path: Path) -> None:
    file = tmp_path / "missing-folder" / "daemon.log"
    with pytest.raises(ConfigError) as caught:
        logs.configure("info", "text", file)
    assert str(caught.value) == f"{file}: cannot open the log file: No such file or directory"
    assert exit_code(caught.value) == ExitCode.USAGE


def test_a_rotated_log_file_is_reopened(tmp_path: Path) -> None:
    file = tmp_path / "daemon.log"
    logs.configure("info", "json", file)
    LOG.info("before")
    assert logs.flush()  # written before the file is moved
    file.rename(tmp_path / "daemon.log.1")  # what logrotate does
    LOG.info("after")
    assert logs.flush()
    assert [strict_json(line)["msg"] for line in (tmp_path / "daemon.log.1").read_text().splitlines()] == ["before"]
    assert [strict_json(line)["msg"] for line in file.read_text().splitlines()] == ["after"]


def test_the_parser_options_and_their_defaults() -> None:
    import argparse

    parser = argparse.ArgumentParser()
    logs.add_arguments(parser)
    assert vars(parser.parse_args([])) == {"log_level": "info", "log_format": "text", "log_file": None}
    assert vars(parser.parse_args(["--log-level", "DEBUG", "--log-format", "json", "--log-file", "x.log"])) == {
        "log_level": "debug", "log_format": "json", "log_file": "x.log"}



# --- the writer thread ----------------------------------------------------------------------------


class Gate:
    """Standard error that holds the writer in its first write until opened (and keeps the text)."""

    def __init__(self) -> None:
        self.entered, self.open, self.text = threading.Event(), threading.Event(), []

    def write(self, text: str) -> int:
        self.entered.set()
        assert self.open.wait(10), "the gate was never opened"
        self.text.append(text)
        return len(text)

    def flush(self) -> None:
        pass

    def lines(self) -> list[dict[str, Any]]:
        return [parse_text(line) for line in "".join(self.text).splitlines()]


def writer_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == log_writer.WRITER_THREAD and t.is_alive()]


def test_a_line_is_formatted_and_written_by_the_writer_thread_not_the_caller(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    formatted_on: list[str] = []
    real = logs.TextFormatter.format

    def format(self: logs.TextFormatter, record: logging.LogRecord) -> str:
        formatted_on.append(threading.current_thread().name)
        return real(self, record)

    monkeypatch.setattr(logs.TextFormatter, "format", format)
    logs.configure("info", "text")
    logs.event(LOG, "action One succeeded", action="One", duration_s=0.0002)
    LOG.info("peer %s joined", "phone", extra={"fields": {"peer": "phone"}})
    assert logs.flush()
    assert [parse_text(line)["msg"] for line in capsys.readouterr().err.splitlines()] == [
        "action One succeeded", "peer phone joined"]
    assert formatted_on == [log_writer.WRITER_THREAD] * 2


def test_what_could_change_after_a_line_is_logged_is_written_as_it_was(capsys: pytest.CaptureFixture[str]) -> None:
    logs.configure("info", "json")
    peers, fields = ["phone"], {"peers": ["phone"]}
    LOG.info("peers %s", peers, extra={"fields": fields})
    logs.event(LOG, "joined", peers=fields["peers"])
    peers.append("robot")  # the caller goes on with its lists before the writer gets to the lines
    fields["peers"].append("robot")
    fields["late"] = 1
    assert logs.flush()
    first, second = (strict_json(line) for line in capsys.readouterr().err.splitlines())
    assert first["msg"] == "peers ['phone']" and first["peers"] == ["phone"] and "late" not in first
    assert second["peers"] == ["phone"]


def test_a_full_queue_drops_lines_counts_them_in_a_line_and_never_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    gate = Gate()
    monkeypatch.setattr("sys.stderr", gate)
    monkeypatch.setattr(log_writer, "QUEUE_SIZE", 10)
    logs.configure("info", "text")
    LOG.info("first")
    assert gate.entered.wait(10)  # the writer is held in its write: what comes now waits in the queue
    for i in range(25):
        LOG.info("line %d", i)  # returns at once: 10 queued, 15 dropped
    LOG.error("an error is kept")  # errors may take as much room again
    gate.open.set()
    assert logs.flush()
    msgs = [line["msg"] for line in gate.lines()]
    assert msgs == ["first", *(f"line {i}" for i in range(10)), "an error is kept",
                    "15 log lines dropped: more came than could be written"]
    assert gate.lines()[-1]["dropped"] == 15 and gate.lines()[-1]["level"] == "WARNING"


def test_shutdown_writes_what_is_queued_stops_the_writer_and_later_lines_are_still_written(
        capsys: pytest.CaptureFixture[str]) -> None:
    logs.configure("info", "text")
    assert len(writer_threads()) == 1
    for i in range(100):
        LOG.info("line %d", i)
    logs.shutdown()
    assert writer_threads() == []
    LOG.info("after")  # written by the caller: nobody else is left to
    logs.shutdown()  # idempotent
    assert [parse_text(line)["msg"] for line in capsys.readouterr().err.splitlines()] == [
        *(f"line {i}" for i in range(100)), "after"]
    logs.configure("info", "text")  # configured again: a writer again, stopped by unconfigure
    assert len(writer_threads()) == 1
    logs.unconfigure()
    assert writer_threads() == []


# --- floods ---------------------------------------------------------------------------------------


#: The time between two refusals of a flood: a power of two, so the windows hold whole numbers of them.
STEP = 2.0**-12


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Lines(logging.Handler):
    """The records a logger got, formatted as JSON and parsed back."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.setFormatter(logs.JsonFormatter())
        self.lines: list[dict[str, Any]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(strict_json(self.format(record)))


@pytest.fixture
def lines() -> Iterator[Lines]:
    handler = Lines()
    logger = logging.getLogger("cmion_mesh.test_flood")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    yield handler
    logger.removeHandler(handler)
    logger.setLevel(logging.NOTSET)
    logger.propagate = True


def flood_total(lines: list[dict[str, Any]]) -> int:
    """How many refusals the lines account for: one per first line, ``count`` per summary."""
    return sum(line["count"] if "more refused" in line["msg"] else 1 for line in lines)


def test_a_flood_from_one_sender_is_one_line_then_one_count_per_window(lines: Lines) -> None:
    clock = Clock()
    throttle = logs.Throttle(logging.getLogger("cmion_mesh.test_flood"), "refused", window=5.0, clock=clock)
    written = 0
    for _ in range(100_000):  # 24 s of refusals, 4096 a second (a step the clock adds up exactly)
        written += throttle("phone", "refused a request from %s", "phone", code="denied", sender="phone")
        clock.now += STEP
    throttle.flush()
    assert written == 5  # one first line per window
    assert len(lines.lines) == 10, [line["msg"] for line in lines.lines]
    assert [line["msg"] for line in lines.lines[:2]] == ["refused a request from phone", "20479 more refused from phone in the last 5 s"]
    assert lines.lines[0]["code"] == "denied" and lines.lines[1]["count"] == 20479 and lines.lines[1]["from"] == "phone"
    assert flood_total(lines.lines) == 100_000  # nothing lost: every refusal is in a line or a count


def test_a_flood_from_many_senders_writes_a_bounded_number_of_lines_and_holds_bounded_memory(lines: Lines) -> None:
    clock = Clock()
    budget, window = 10, 5.0
    throttle = logs.Throttle(logging.getLogger("cmion_mesh.test_flood"), "refused", window=window, budget=budget, clock=clock)
    count, senders = 200_000, 50_000  # 49 s, every refusal from another sender in turn
    for i in range(count):
        throttle(f"sender{i % senders}", "refused a request from %s", f"sender{i % senders}", code="denied")
        clock.now += STEP
        if i % 10_000 == 0:
            assert throttle.held <= budget + logs.MAX_OTHERS
    throttle.flush()
    windows = count * STEP / window
    assert len(lines.lines) <= (windows + 1) * (2 * budget + 1), len(lines.lines)
    assert flood_total(lines.lines) == count
    overflow = [line for line in lines.lines if "other" in line["msg"]]
    others = int(window / STEP) - budget  # each window: budget senders with a line, the rest together
    assert overflow and overflow[0]["msg"] == f"{others} more refused from at least {logs.MAX_OTHERS} others in the last 5 s"


def test_a_throttle_whose_level_is_off_does_nothing(lines: Lines) -> None:
    clock = Clock()
    throttle = logs.Throttle(logging.getLogger("cmion_mesh.test_flood"), "refused", level=logging.DEBUG, clock=clock)
    assert not any(throttle("phone", "refused") for _ in range(1000))
    throttle.flush()
    assert lines.lines == [] and throttle.held == 0


def test_shutdown_writes_the_counts_still_held(lines: Lines) -> None:
    clock = Clock()
    throttle = logs.Throttle(logging.getLogger("cmion_mesh.test_flood"), "refused", clock=clock)
    for _ in range(5):
        throttle("phone", "refused a request from %s", "phone")
    clock.now += 1.25
    logs.shutdown()
    assert [line["msg"] for line in lines.lines] == ["refused a request from phone", "4 more refused from phone in the last 1.2 s"]
    logs.shutdown()  # nothing held any more: nothing more said
    assert len(lines.lines) == 2


def test_a_throttle_counts_every_refusal_from_several_threads(lines: Lines) -> None:
    throttle = logs.Throttle(logging.getLogger("cmion_mesh.test_flood"), "refused", budget=3)
    barrier = threading.Barrier(4)

    def flood(n: int) -> None:
        barrier.wait(10)
        for i in range(5000):
            throttle(f"sender{(n + i) % 7}", "refused")

    threads = [threading.Thread(target=flood, args=(n,), name=f"flood-{n}") for n in range(4)]
    began = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    throttle.flush()
    windows = (time.monotonic() - began) / logs.WINDOW + 1
    assert flood_total(lines.lines) == 20_000
    assert len(lines.lines) <= windows * (2 * 3 + 1)
