"""One settings file per device (ops/settings.py): every option of ``up``, the command line over
the file over the defaults, and every problem naming the file, the line and the key. Pure: no
network, no process."""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import keys, logs
from cmion_mesh.errors import ConfigError, ExitCode, exit_code
from cmion_mesh.ops import settings
from cmion_mesh.transport.base import LEASE_MS

ROOT = Path(__file__).resolve().parent.parent
#: Options of up whose flag comes with a part built elsewhere: the key is here first.
FLAG_ELSEWHERE = {"metrics"}  # ops/metrics.py adds --metrics


def up_parsers() -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """The command line's parser, and up's own, with the options of ops/ added as the CLI adds them."""
    from cmion_mesh.cli.main import build_parser

    parser = build_parser("up")
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["up"]
    dests = {a.dest for a in sub._actions}
    if "log_level" not in dests:
        logs.add_arguments(sub)
    if "settings" not in dests:
        settings.add_argument(sub)
    return parser, sub


def write(tmp_path: Path, text: str | bytes, name: str = "device.toml") -> Path:
    file = tmp_path / name
    if isinstance(text, bytes):
        file.write_bytes(text)
    else:
        file.write_text(text, encoding="utf-8")
    return file


def uncommented(text: str) -> str:
    """The example with every ``# key = value`` line in force."""
    return re.sub(r"(?m)^# ([a-z][a-z-]*) = ", r"\1 = ", text)


# --- the keys -------------------------------------------------------------------------------------


def test_every_option_of_up_is_a_key_and_every_key_an_option() -> None:
    _, up = up_parsers()
    options = {a.dest for a in up._actions if a.dest not in ("help", "settings")}
    schema = {o.dest for o in settings.OPTIONS}
    assert options - schema == set(), "options of up the settings file cannot give"
    assert schema - options <= FLAG_ELSEWHERE, "keys that are no option of up"
    assert len(schema) == len(settings.OPTIONS) == len(settings.BY_KEY)


def test_the_keys_defaults_and_choices_are_ups() -> None:
    _, up = up_parsers()
    actions = {a.dest: a for a in up._actions}
    for option in settings.OPTIONS:
        action = actions.get(option.dest)
        if action is None:
            continue
        if option.default is not None:
            assert action.default == (not option.default if option.invert else option.default), option.key
        else:
            assert action.default is None, option.key
        if option.choices:
            assert tuple(action.choices or ()) == option.choices, option.key
        if option.invert:
            assert isinstance(action, argparse._StoreTrueAction) and action.option_strings == [f"--no-{option.key}"]
        elif action.option_strings:
            assert f"--{option.key}" in action.option_strings, option.key
    assert settings.BY_KEY["mesh"].default == keys.DEFAULT_MESH


def test_the_shipped_example_parses_and_shows_every_key_once_with_its_default(tmp_path: Path) -> None:
    text = settings.EXAMPLE.read_text(encoding="utf-8")
    assert settings.load(settings.EXAMPLE).values == {}  # every key commented out: nothing changes
    shown = re.findall(r"(?m)^# ([a-z][a-z-]*) = ", text)
    assert sorted(shown) == sorted(settings.BY_KEY), "every key, once"
    loaded = settings.load(write(tmp_path, uncommented(text)), check_files=False)
    assert set(loaded.lines) == set(settings.BY_KEY)
    for option in settings.OPTIONS:
        if option.default is not None:
            value = loaded.values[option.dest]
            assert (not value if option.invert else value) == option.default, option.key
        else:
            assert option.example is not None, f"{option.key}: the example shows a value"


def test_the_example_is_in_the_wheel() -> None:
    """Hatch puts every file of the package's folder in the wheel: the example must live there."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert project["tool"]["hatch"]["build"]["targets"]["wheel"]["packages"] == ["cmion_mesh"]
    assert settings.EXAMPLE.is_file() and settings.EXAMPLE.parent == ROOT / "cmion_mesh" / "ops"


def test_the_deploy_page_describes_every_key() -> None:
    page = (ROOT / "docs" / "deploy.md").read_text(encoding="utf-8")
    section = page.split("## Settings file", 1)[1].split("\n## ", 1)[0]
    missing = [o.key for o in settings.OPTIONS if f"`{o.key}`" not in section]
    assert not missing, f"docs/deploy.md's Settings file section does not name {missing}"


# --- reading --------------------------------------------------------------------------------------


def test_values_come_typed_and_relative_paths_from_the_files_folder(tmp_path: Path) -> None:
    folder = tmp_path / "etc"
    (folder / "certs").mkdir(parents=True)
    (folder / "rules.xml").write_text("<x/>")
    file = write(folder, 'architecture = "robot"\nname = "robot"\nrules = "rules.xml"\ncerts = "certs"\nstate-dir = "state"\n'
                         'log-file = "/var/log/cmion.log"\nlisten = ["tcp/127.0.0.1:7447"]\nmulticast = false\nlease-ms = 500\n'
                         'web = 8080\nlog-level = "DEBUG"\nadmit = ["companion", "other=AAAA"]\n')
    loaded = settings.load(file)
    assert loaded.values == {"path": "robot", "name": "robot", "rules": str(folder / "rules.xml"), "certs": str(folder / "certs"),
                             "state_dir": str(folder / "state"), "log_file": "/var/log/cmion.log",
                             "listen": ["tcp/127.0.0.1:7447"], "no_multicast": True, "lease_ms": 500, "web": "8080",
                             "log_level": "debug", "admit": ["companion", "other=AAAA"]}
    assert loaded.lines["rules"] == 3 and loaded.lines["admit"] == 12
    (folder / "robot").mkdir()  # a folder of that name beside the file: it, not the shipped one
    assert settings.load(file).values["path"] == str(folder / "robot")


def test_the_command_line_wins_over_the_file_which_wins_over_the_defaults(tmp_path: Path) -> None:
    parser, _ = up_parsers()
    file = write(tmp_path, 'mesh = "lab"\nlease-ms = 500\nconnect = ["tcp/127.0.0.1:7001"]\nlisten = ["tcp/127.0.0.1:7002"]\n'
                           'multicast = false\nlog-format = "json"\nname = "robot"\n')
    argv = ["up", "--settings", str(file), "--mesh", keys.DEFAULT_MESH, "--connect", "tcp/127.0.0.1:7003", "--name", "phone"]
    args = parser.parse_args(argv)
    loaded = settings.apply(args, parser, argv)
    assert loaded is not None and loaded.path == file
    # a flag wins even when it says the default; a repeated option replaces the file's list, not adds to it
    assert (args.mesh, args.connect, args.name) == (keys.DEFAULT_MESH, ["tcp/127.0.0.1:7003"], "phone")
    # the file wins over the defaults
    assert (args.lease_ms, args.listen, args.no_multicast, args.log_format) == (500, ["tcp/127.0.0.1:7002"], True, "json")
    # the rest keeps its defaults
    assert (args.log_level, args.verify_names, args.state_dir, args.path) == ("info", False, None, None)
    # the parser is left as it was: parsed again, it has its defaults
    again = parser.parse_args(["up", "--name", "robot"])
    assert (again.mesh, again.lease_ms, again.connect, again.log_level, again.func) == (keys.DEFAULT_MESH, LEASE_MS, None, "info",
                                                                                         args.func)


def test_given_options_are_those_the_command_line_gives() -> None:
    parser, _ = up_parsers()
    argv = ["up", "robot", "--lease-ms", "2000", "--no-multicast", "--listen", "tcp/127.0.0.1:1", "--log-level=debug"]
    assert settings.given_options(parser, argv) == {"command", "path", "lease_ms", "no_multicast", "listen", "log_level"}
    assert settings.given_options(parser, ["up"]) == {"command"}


def test_without_settings_nothing_is_read() -> None:
    parser, _ = up_parsers()
    args = parser.parse_args(["up", "robot"])
    before = dict(vars(args))
    assert settings.apply(args, parser, ["up", "robot"]) is None and vars(args) == before


# --- bad files: the file, the line, the key -------------------------------------------------------


KNOWN = ", ".join(o.key for o in settings.OPTIONS)


@pytest.mark.parametrize(("text", "line", "says"), [
    ('mesh = "lab"\nlog_level = "debug"\n', 2, f"unknown key 'log_level' (did you mean 'log-level'?) (known: {KNOWN})"),
    ('statedir = "x"\n', 1, "unknown key 'statedir' (did you mean 'state-dir'?)"),
    ('name = "robot"\n\n[log]\nlevel = "debug"\n', 3, "unknown key 'log' (known: architecture, name, "),
    ('log.level = "debug"\n', 1, "unknown key 'log' (known: "),
    ('settings = "other.toml"\n', 1, "unknown key 'settings' (known: "),
    ('lease-ms = "2000"\n', 1, "'lease-ms' must be a whole number from 1 to 3600000, not str '2000'"),
    ('lease-ms = 0\n', 1, "'lease-ms' must be a whole number from 1 to 3600000, not int 0"),
    ('multicast = "no"\n', 1, "'multicast' must be true or false, not str 'no'"),
    ('connect = "tcp/127.0.0.1:7447"\n', 1, "'connect' must be a list of strings, e.g. [\"...\"], not str 'tcp/127.0.0.1:7447'"),
    ('listen = ["tcp/127.0.0.1:7447", 7]\n', 1, "'listen' must be a list of strings, not list ['tcp/127.0.0.1:7447', 7]"),
    ('name = "a/b"\n', 1, "'name' must be a valid name (no / * $ # ? or spaces, no leading @), not str 'a/b'"),
    ('admit = ["x=KEY", "bad/name"]\n', 1, "'admit' must be a list of NAME or NAME=PUBLICKEY strings"),
    ('log-level = "loud"\n', 1, "'log-level' must be one of debug, info, warning, error, not str 'loud'"),
    ('log-format = "xml"\n', 1, "'log-format' must be one of text, json, not str 'xml'"),
    ('web = "eighty"\n', 1, "'web' must be a port or \"HOST:PORT\" (port 0 to 65535), not str 'eighty'"),
    ('metrics = 70000\n', 1, "'metrics' must be a port or \"HOST:PORT\" (port 0 to 65535), not int 70000"),
    ('state-dir = ""\n', 1, "'state-dir' must be a string (not empty, no NUL character), not str ''"),
    ('\n\nrules = "missing.xml"\n', 3, "'rules' must be an existing file: no file at "),
    ('certs = "nowhere"\n', 1, "'certs' must be an existing folder: nothing at "),
    ('architecture = "no-such-embodiment"\n', 1, "'architecture' must be a file or folder beside the settings file, "
                                                  "or a shipped embodiment (cmion_test, "),
    ('name = "robot"\nname = "phone"\n', 2, "not valid TOML: Cannot overwrite a value"),
    ('mesh = "lab\n', 1, "not valid TOML: Illegal character"),
    ("connect = " + "[" * 40 + "]" * 40 + "\n", 1, "too deep for a settings file: arrays or inline tables nested more than 32 deep"),
    (b'name = "caf\xe9"\n', 1, "not UTF-8 (byte 0xe9: invalid continuation byte): a settings file is UTF-8 text"),
], ids=["did-you-mean", "did-you-mean-2", "table", "dotted-key", "settings-in-settings", "wrong-type", "zero-lease", "bool",
        "not-a-list", "list-item", "bad-name", "bad-admit", "level", "format", "web", "port-range", "empty-path", "missing-file",
        "missing-folder", "unknown-embodiment", "duplicate", "toml-syntax", "too-deep", "not-utf8"])
def test_every_problem_is_one_line_naming_the_file_line_and_key(tmp_path: Path, text: str | bytes, line: int, says: str) -> None:
    file = write(tmp_path, text)
    with pytest.raises(ConfigError) as caught:
        settings.load(file)
    message = str(caught.value)
    assert message.startswith(f"{file}:{line}: {says}"), message
    assert "\n" not in message and exit_code(caught.value) == ExitCode.USAGE
    assert (caught.value.path, caught.value.line) == (str(file), line)


def test_every_problem_of_a_file_is_reported_at_once(tmp_path: Path) -> None:
    file = write(tmp_path, 'mesh = "lab"\nlogfile = "x.log"\nlease-ms = true\nname = "robot"\nweb = []\n')
    with pytest.raises(ConfigError) as caught:
        settings.load(file)
    lines = str(caught.value).splitlines()
    assert lines[0].startswith(f"{file}:2: unknown key 'logfile' (did you mean 'log-file'?)")
    assert lines[1:] == [f"{file}:3: 'lease-ms' must be a whole number from 1 to 3600000, not bool True",
                         f"{file}:5: 'web' must be a port or \"HOST:PORT\" (port 0 to 65535), not list []"]


@pytest.mark.parametrize("problem", ["missing", "folder", "too-large"])
def test_a_settings_file_that_cannot_be_read_is_one_line_naming_it(tmp_path: Path, problem: str) -> None:
    parser, _ = up_parsers()
    file = tmp_path / "device.toml"
    says = {"missing": "cannot read the settings file: No such file or directory",
            "folder": "cannot read the settings file: Is a directory",
            "too-large": "the settings file is larger than 1024 KiB: not a settings file"}[problem]
    if problem == "folder":
        file.mkdir()
    elif problem == "too-large":
        file.write_text("# " + "x" * (1024 * 1024) + "\n")
    argv = ["up", "robot", "--settings", str(file)]
    with pytest.raises(ConfigError) as caught:
        settings.apply(parser.parse_args(argv), parser, argv)
    assert str(caught.value) == f"{file}: {says}" and exit_code(caught.value) == ExitCode.USAGE


def test_a_value_given_is_a_copy(tmp_path: Path) -> None:
    """The daemon may extend args.listen (its device table): the settings read stay as read."""
    loaded = settings.load(write(tmp_path, 'listen = ["tcp/127.0.0.1:7447"]\n'))
    args: Any = loaded.merge(argparse.Namespace())
    args.listen.append("tcp/127.0.0.1:7448")
    assert loaded.values["listen"] == ["tcp/127.0.0.1:7447"]
