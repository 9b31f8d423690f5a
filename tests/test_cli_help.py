"""The command line's manners, in this process: a typo gets one line saying what was meant (exit 2),
every verb's --help has a description and an example, ``record info`` is a verb of its own (its
typo records nothing), tables wrap instead of cutting words, split recordings' parts each say when
they started, and the one meaning of --timeout and --join."""

from __future__ import annotations

import argparse
import contextlib
import io
import time
from pathlib import Path

import pytest

from cmion_mesh import keys
from cmion_mesh.cli import main as cli
from cmion_mesh.cli.common import item, plural, table_lines
from cmion_mesh.messages import Event, encode
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools.recording import Recorder
from cmion_mesh.tools.recording_reader import info
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport


def run(*argv: str) -> tuple[int, str, str]:
    """``cmion-mesh ARGV`` in this process: its exit code, standard output and error."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(list(argv))
        except SystemExit as exc:  # argparse leaves by SystemExit (usage errors, --help)
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize(("argv", "meant"), [
    (["peer"], "'peers'"),
    (["peers", "--mehs", "x"], "'--mesh'"),
    (["peers", "--jsn"], "'--json'"),
    (["bb", "gett", "robot"], "'get'"),
    (["act", "robot", "GoTo", "--timout", "3"], "'--timeout'"),
    (["record", "infoo", "x.mcap"], "'info'"),
])
def test_a_typo_gets_one_line_saying_what_was_meant(argv: list[str], meant: str) -> None:
    code, out, err = run(*argv)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and f"did you mean {meant}?" in err, err


def test_record_infoo_records_nothing_and_a_file_is_no_filter(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert run("record", "infoo", "x.mcap")[0] == 2
    code, _, err = run("record", "visit.mcap")
    assert code == 2 and "record -o visit.mcap" in err and "record info visit.mcap" in err
    assert list(tmp_path.iterdir()) == [], "no recording was started"


def test_record_info_has_its_own_help_and_verb() -> None:
    code, out, _ = run("record", "info", "--help")
    assert code == 0 and out.startswith("usage: cmion-mesh record info [-h] [--json] FILE [FILE ...]")
    assert "Summarise recordings" in out and "FILTER" not in out and "--split-size" not in out
    code, _, err = run("record", "info")
    assert code == 2 and "FILE" in err and err.count("\n") == 1
    code, _, err = run("record", "info", "/nonexistent/a.mcap")
    assert code == 2 and "a.mcap" in err


VERBS = [*([verb] for verb in cli.COMMANDS), *([verb, word] for verb, word in cli.SUBVERBS)]


@pytest.mark.parametrize("verb", VERBS, ids=" ".join)
def test_every_verb_has_a_description_and_an_example_in_its_help(verb: list[str]) -> None:
    described_with_an_example(verb, f"  cmion-mesh {verb[0]} ")


def described_with_an_example(verb: list[str], example: str) -> None:
    """``verb --help`` exits 0 with its usage, a description of four words or more, and an example
    (after a line starting "example") that contains ``example``."""
    code, out, _ = run(*verb, "--help")
    assert code == 0
    usage, _, rest = out.partition("\n\n")
    description = rest.split("\n\n", 1)[0]
    assert usage.startswith(f"usage: cmion-mesh {' '.join(verb)}") and len(description.split()) >= 4, out
    assert "\nexample" in out and example in out.rsplit("\nexample", 1)[1], out


def nested_verbs(parser: argparse.ArgumentParser, words: tuple[str, ...] = ()) -> list[list[str]]:
    """Every verb under a verb (certs init, custody show, wm add...), at any depth."""
    found: list[list[str]] = []
    for action in parser._actions:  # argparse has no public walk of its subparsers
        if isinstance(action, argparse._SubParsersAction):
            for word, sub in action.choices.items():
                if words:
                    found.append([*words, word])
                found += nested_verbs(sub, (*words, word))
    return found


NESTED = nested_verbs(cli.whole_parser())


def test_the_nested_verbs_are_all_found() -> None:
    assert {("certs", "init"), ("custody", "resolve"), ("service", "unit"), ("wm", "add")} <= {tuple(v) for v in NESTED}


@pytest.mark.parametrize("verb", NESTED, ids=" ".join)
def test_every_nested_verb_has_a_description_and_an_example_in_its_help(verb: list[str]) -> None:
    described_with_an_example(verb, f"cmion-mesh {' '.join(verb)} ")


def test_timeout_waits_for_the_outcome_and_join_for_the_peers_everywhere() -> None:
    parser = cli.whole_parser()
    helps = {}

    def walk(p: object, path: str) -> None:
        import argparse

        assert isinstance(p, argparse.ArgumentParser)
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{path} {name}")
            elif "--timeout" in action.option_strings or "--join" in action.option_strings:
                helps[f"{path} {action.option_strings[0]}"] = (action.dest, action.help or "")

    walk(parser, "cmion-mesh")
    joins = {k: v for k, v in helps.items() if k.endswith("--join")}
    timeouts = {k: v for k, v in helps.items() if k.endswith("--timeout")}
    assert joins and timeouts
    assert all(dest == "join_timeout" and "look for" in text for dest, text in joins.values())
    assert not any("found in the mesh" in text or "for the embodiment and" in text for _, text in timeouts.values()), timeouts
    # The older spellings still parse, to the same place.
    for spelling in ("--join", "--join-timeout", "--discover-timeout"):
        args = cli.build_parser("act").parse_args(["act", "robot", "GoTo", spelling, "7"])
        assert args.join_timeout == 7.0 and args.timeout == 120.0
    args = cli.build_parser("bb").parse_args(["bb", "get", "robot", "--timeout", "2", "--join", "9"])
    assert (args.timeout, args.join_timeout) == (2.0, 9.0)
    # Commands that need embodiments take --join too, and keep --timeout for the outcome.
    for argv in (["migrate", "spirit", "--to", "screen"], ["invite", "screen"], ["custody", "show", "spirit"],
                 ["custody", "resolve", "spirit", "--keep", "robot"]):
        args = cli.build_parser(argv[0]).parse_args([*argv, "--join", "2", "--timeout", "7"])
        assert (args.join_timeout, args.timeout) == (2.0, 7.0), argv
    # Where --timeout is the whole wait, --join is no typo of --json: the hint says what to use.
    for verb in ("peers", "doctor"):
        code, _, err = run(verb, "--join", "2")
        assert code == 2 and "use --timeout SECONDS" in err and "--json" not in err and err.count("\n") == 1, err


def test_a_table_wraps_at_spaces_and_never_cuts_a_word() -> None:
    actions = "; ".join(item(a) for a in ["Say * *", "GoTo *", "Greet *", "Express *", "Migrate *", "AVeryLongActionNameIndeed *"])
    types = ", ".join(["Animation", "CommandInput", "LanguageGeneration", "Migration", "Navigation", "SpeechSynthesis"])
    rows = [("EMBODIMENT", "COMPETENCY TYPES", "ACTIONS"), ("robot", types, actions), ("screen", "-", "-")]
    for width in (250, 80, 64, 30):
        lines = table_lines(rows, width)
        # Narrower than its longest words, a table overflows rather than cut one.
        assert all(len(line) <= max(width, 64) for line in lines), (width, lines)
        text = " ".join(" ".join(lines).split())
        for word in [*types.replace(",", "").split(), "AVeryLongActionNameIndeed", "Say * *", "GoTo *"]:
            assert word in text, (width, word, lines)
    assert len(table_lines(rows, 250)) == 3, "wide enough: one line a row"
    assert len(table_lines(rows, 64)) > 3


def test_each_part_of_a_split_recording_says_when_it_started(tmp_path: Path) -> None:
    with MemoryTransport(MemoryNetwork(), "mesh") as t:
        with Recorder(t, "m", tmp_path / "q.mcap", split_bytes=1, flush_interval=0.01) as recorder:
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": 0}, 0, 1.0)))
            wait_for(lambda: (tmp_path / "q-0000.mcap").exists() and recorder.stats.samples == 1, 10, "the first tick")
            between = time.time()
            wait_for(lambda: time.time() > between + 0.002, 1, "the clock to move on")  # parts' stamps are in ms
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": 1}, 1, 2.0)))
            wait_for(lambda: len(recorder.stats.files) == 2, 10, "the second part")
        files = recorder.stats.files
    first, second = info(files[0]), info(files[1])
    assert first["started"] < second["started"], (first["started"], second["started"])
    assert second["started"] >= time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(between)), "the part's own start"


def test_each_part_of_a_split_recording_says_who_inhabited_what_when_it_started(tmp_path: Path) -> None:
    network = MemoryNetwork()
    with MemoryTransport(network, "mesh") as t, MemoryTransport(network, "bodies") as bodies:
        robot = bodies.declare_token(keys.custody_key("m", "robot", "spirit", 1))
        with Recorder(t, "m", tmp_path / "q.mcap", split_bytes=1, flush_interval=0.01) as recorder:
            recorder.describe([{"name": "robot", "inhabitant": "spirit"}, {"name": "screen", "inhabitant": None}])
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": 0}, 0, 1.0)))
            wait_for(lambda: recorder.stats.samples == 2, 10, "the token and the first tick")
            # spirit migrates to the screen: the robot's claim goes, the screen's comes
            robot.close()
            screen = bodies.declare_token(keys.custody_key("m", "screen", "spirit", 2))
            wait_for(lambda: recorder.stats.samples == 4, 10, "the custody moving")
            # A part is full once a flush (every 10 ms) has seen its messages: a tick starts a part
            # of its own, after the migration, at the latest once one has been flushed with it.
            moved = len(recorder.stats.files)
            for i in range(1, 200):
                t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": i}, i, 1.0 + i)))
                wait_for(lambda i=i: recorder.stats.samples == 4 + i, 10, f"tick {i}")
                if len(recorder.stats.files) > moved:
                    break
            assert len(recorder.stats.files) > moved, "a part begun after the migration"
        # The screen's token goes only once the recorder has stopped: with a part per sample, its
        # going would start a part of its own (nobody inhabited) after the one this test reads.
        screen.close()
        files = recorder.stats.files
    # A part starts with whatever comes next once one is full (a token, the description, a tick):
    # an early part holds the description as given, the last one (the tick after the migration)
    # the state after it.
    inhabitants = [{n: d["inhabitant"] for n, d in info(f)["described"].items()} for f in files]
    assert {"robot": "spirit", "screen": ""} in inhabitants[:-1], inhabitants
    assert inhabitants[-1] == {"robot": "", "screen": "spirit"}, inhabitants
    assert dict(metadata_of(files[-1]))["cmion-mesh"]["custody_at_start"] == "screen:spirit@2"


def metadata_of(path: str) -> list[tuple[str, dict[str, str]]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(m.name, dict(m.metadata)) for m in make_reader(f).iter_metadata()]


def test_wm_add_takes_its_properties_on_either_side_of_its_options() -> None:
    parser = cli.build_parser("wm")
    for argv in (["wm", "add", "robot", "Box", "--object", "weight=3.5", "fragile=false"],
                 ["wm", "add", "robot", "Box", "weight=3.5", "--object", "fragile=false", "--persistent"],
                 ["wm", "add", "robot", "Box", "weight=3.5", "fragile=false", "--object"]):
        args = cli.parse(parser, argv)
        assert (args.entity, args.kind, args.properties) == ("Box", "object", ["weight=3.5", "fragile=false"]), argv
    # Anything else left over is still refused, in one line.
    code, _, err = run("wm", "add", "robot", "Box", "--object", "heavy")
    assert code == 2 and "unrecognized arguments: heavy" in err and err.count("\n") == 1, err
    code, _, err = run("bb", "get", "robot", "a", "x=1")
    assert code == 2 and "unrecognized arguments: x=1" in err, err


def test_small_manners() -> None:
    # a missing file is a usage error (exit 2), as the exit-code table says
    code, _, err = run("validate", "/nonexistent/a.xml")
    assert code == 2 and "/nonexistent/a.xml" in err, err
    # act's parameters are optional: the usage error names what is missing only
    code, _, err = run("act", "robot")
    assert code == 2 and err.endswith("required: action\n"), err
    # options before the command: where they go, not "invalid choice"
    code, _, err = run("--mesh", "x", "peers")
    assert code == 2 and "options go after the command: cmion-mesh peers --mesh x" in err and "invalid choice" not in err, err
    assert (plural(1, "competency", "competencies"), plural(2, "rule")) == ("1 competency", "2 rules")
