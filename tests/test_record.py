"""Recording a mesh to MCAP, reading it back, replaying it: the demo recorded once for the module."""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import Event, decode, encode
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools import recording
from cmion_mesh.tools.demo import Timeline, run_scenario, start_bodies, stop_bodies
from cmion_mesh.tools.recording import OPEN_END, Recorder, parse_size
from cmion_mesh.tools.recording_format import EVENT_SCHEMA, RAW_SCHEMA, mesh_filter
from cmion_mesh.tools.recording_reader import RecordingReader, format_info, info
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(240)

#: Events the demo reacts to and prints (``demo._react``), and the handshake's steps.
STORY = {"MindDecision", "ActionStarted", "ActionFailed", "MigrationStarting", "MigrationOccurred", "MigrationSucceeded",
         "StepStarted", "Spoke", "MigrationStep"}


def ident(event: dict[str, Any]) -> tuple[str, str, str, int]:
    return event["embodiment"], event["component"], event["name"], event["seq"]


@dataclass
class Session:
    mesh: str
    clean: Path
    killed: Path
    lines: list[str]
    seen: list[Event]
    recorder_output: list[str] = field(default_factory=list)
    recorder_exit: int = -1


def events_in(path: Path) -> list[dict[str, Any]]:
    with RecordingReader(path) as reader:
        return [m.decoded() for m in reader.messages() if m.schema == EVENT_SCHEMA]


def metadata_in(path: Path) -> list[str]:
    with RecordingReader(path) as reader:
        for _ in reader.messages():
            pass
        return [name for name, _ in reader.metadata]


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    """The demo's story, recorded by two recorders: one stopped with Ctrl-C, one killed with SIGKILL."""
    tmp = tmp_path_factory.mktemp("record")
    mesh = unique_mesh("rec")
    scenario = start_bodies(mesh, tmp / "state")
    recorders: list[Daemon] = []
    try:
        net = [a for e in scenario.endpoints.values() for a in ("--connect", e)] + ["--no-multicast"]
        done = Session(mesh, tmp / "clean.mcap", tmp / "killed.mcap", [], [])
        for path in (done.clean, done.killed):
            recorders.append(Daemon(cli_argv("record", "--mesh", mesh, "-o", str(path), *net), name=path.stem))
        for recorder in recorders:
            line = recorder.wait_line("recording mesh", 30)
            assert "phone, robot, screen" in line, line
        with ZenohTransport(TransportConfig(connect=tuple(scenario.endpoints.values()), multicast=False)) as t:
            client = MeshClient(t, mesh)
            with client.events(done.seen.append):
                run_scenario(client, scenario, Timeline(done.lines.append), timeout=90)
                steps = {ident(_builtins(e)) for e in done.seen if e.name == "MigrationStep"}
                assert len(steps) == 12, "three migrations of four steps each"
            # The killed one is killed once its file holds every step (its chunks reach the disk on their own).
            wait_for(lambda: steps <= {ident(e) for e in events_in(done.killed)}, 20, "the handshake's steps on disk")
            recorders[1].kill()
        done.recorder_exit = recorders[0].stop(signal.SIGINT)
        done.recorder_output = recorders[0].lines
        yield done
    finally:
        for recorder in recorders:
            recorder.kill()
        stop_bodies(scenario)


def _builtins(event: Event) -> dict[str, Any]:
    return {"embodiment": event.embodiment, "component": event.component, "name": event.name, "seq": event.seq}


def test_the_recording_opens_with_the_mcap_reader_and_holds_the_story(session: Session) -> None:
    assert session.recorder_exit == 0, session.recorder_output
    assert any(line.startswith("recorded ") for line in session.recorder_output), session.recorder_output
    with open(session.clean, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        recorded = [(ch.topic, json.loads(m.data)) for _, ch, m in reader.iter_messages(log_time_order=False)]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata["cmion-mesh"]["mesh"] == session.mesh
    assert {"embodiment:robot", "embodiment:screen", "embodiment:phone"} <= metadata.keys()
    assert metadata["cmion-mesh.end"]["dropped"] == "0"
    events = [e for topic, e in recorded if "/ev/" in topic]
    assert all(topic == f"cmion/{session.mesh}/{e['embodiment']}/ev/{e['component']}/{e['name']}"
               for topic, e in recorded if "/ev/" in topic)
    # Every event of the story the demo followed (and printed from) is in the file.
    story = [ident(_builtins(e)) for e in session.seen if e.name in STORY]
    assert set(story) <= {ident(e) for e in events}
    printed_actions = [line for line in session.lines if ": action " in line]
    assert len(printed_actions) == sum(e["name"] == "ActionStarted" and e["component"] == "manager" for e in events) > 0
    steps = [(e["embodiment"], e["data"]["step"]) for e in events if e["name"] == "MigrationStep"]
    hops = (("robot", "screen"), ("screen", "phone"), ("phone", "robot"))
    assert sorted(steps) == sorted(step for source, target in hops for step in
                                   ((source, "prepared"), (target, "incoming"), (source, "handed"), (target, "active")))
    # How requests were answered: the operator's command, the migration handshake's steps.
    answers = [e for topic, e in recorded if "/@outcome/" in topic]
    assert {"embodiment": "robot", "component": "bb", "request": "set_property", "status": "accepted"}.items() \
        <= next(a for a in answers if a["component"] == "bb" and a["embodiment"] == "robot").items()
    handshake = {(a["embodiment"], a["request"], a["sender"], a["status"]) for a in answers if a["component"] == "migration"}
    assert {("screen", "prepare", "robot", "accepted"), ("screen", "commit", "robot", "accepted"),
            ("robot", "commit", "phone", "accepted")} <= handshake
    # Storage changes and liveliness are there too.
    assert any(topic == f"cmion/{session.mesh}/screen/bb/**" for topic, _ in recorded)
    assert {e["name"] for t, e in recorded if t.endswith("/@alive/*")} >= {"robot", "screen", "phone"}


def test_record_info_summarises_the_migrations(session: Session) -> None:
    result = subprocess.run(cli_argv("record", "info", str(session.clean), "--json"), capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["mesh"] == session.mesh and not summary["truncated"] and summary["dropped"] == 0
    assert {"robot", "screen", "phone"} <= set(summary["embodiments"])
    journey = [(m["source"], m["target"], m["outcome"], len(m["steps"])) for m in summary["migrations"]]
    assert journey == [("robot", "screen", "succeeded", 4), ("screen", "phone", "succeeded", 4), ("phone", "robot", "succeeded", 4)]
    assert summary["duration"] > 0 and summary["messages"] == sum(summary["channels"].values())
    # Described as they were when recording began: the companion on the robot, the others empty.
    assert {n: d["inhabitant"] for n, d in summary["described"].items()} == {"robot": "spirit", "screen": "", "phone": ""}
    text = format_info(info(session.clean))
    assert "migrations: 3" in text and "TRUNCATED" not in text and "inhabitant null" not in text
    assert "inhabitant -" in text


def test_a_killed_recorder_leaves_a_file_the_reader_opens(session: Session) -> None:
    got: list[dict[str, Any]] = []
    with open(session.killed, "rb") as f:  # as any MCAP user opens a file
        reader = make_reader(f)
        assert reader.get_summary() is None  # the recorder never finished it: its open end names no summary
        for _, channel, message in reader.iter_messages():
            if "/ev/" in channel.topic:
                got.append(json.loads(message.data))
    steps = {ident(_builtins(e)) for e in session.seen if e.name == "MigrationStep"}
    assert steps <= {ident(e) for e in got}
    summary = info(session.killed)
    assert summary["truncated"] and summary["truncation"]
    assert len(summary["migrations"]) == 3
    assert "TRUNCATED" in format_info(summary)


def test_replay_into_a_fresh_mesh_shows_a_listener_the_same_events(session: Session) -> None:
    recorded = events_in(session.clean)
    fresh = unique_mesh("replay")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # As in a mesh with daemons: the replay reaches another subscriber first (this hub, which it
    # connects to, as a daemon that follows the mesh), and the listener only through gossip, over a
    # link of its own.
    first = recorded[0]
    first_key = f"cmion/{fresh}/{first['embodiment']}/ev/{first['component']}/{first['name']}"
    with ZenohTransport(TransportConfig(listen=(endpoint,), multicast=False)) as hub, hub.subscribe(first_key, lambda _: None), \
            Daemon(cli_argv("events", "--json", "--mesh", fresh, "--connect", endpoint, "--no-multicast", "--count",
                            str(len(recorded)), "--join-timeout", "0.1"), name="listener") as listener:
        assert hub.wait_subscribers(f"cmion/{fresh}/nobody/ev/only/TheListener", 30), "the listener subscribes"
        replay = subprocess.run(cli_argv("replay", str(session.clean), "--mesh", fresh, "--connect", endpoint, "--no-multicast",
                                         "--rate", "20", "--join-timeout", "20", "--json"),
                                capture_output=True, text=True, timeout=120)
        assert replay.returncode == 0, replay.stderr
        assert json.loads(replay.stdout)["published"] == len(recorded)
        assert listener.proc.wait(60) == 0
        heard = [json.loads(line) for line in listener.lines if line.startswith("{")]
    assert [(ident(e), e["data"]) for e in heard] == [(ident(e), e["data"]) for e in recorded]


def test_replay_filters_and_rejects_a_bad_rate(session: Session, tmp_path: Path) -> None:
    network = MemoryNetwork()
    with MemoryTransport(network, "listener") as listener_t, MemoryTransport(network, "replay") as t:
        heard: list[Event] = []
        listen = MeshClient(listener_t, "fresh")
        with listen.events(heard.append):
            from cmion_mesh.tools.replay import replay

            stats = replay(MeshClient(t, "fresh"), session.clean, rate=0, filters=["*/ev/migration/MigrationStep"])
            wait_for(lambda: len(heard) == stats.published, 10, "the replayed steps")
        assert stats.published == 12 and {e.name for e in heard} == {"MigrationStep"}
        with pytest.raises(ConfigError):
            replay(MeshClient(t, "fresh"), session.clean, rate=-1)


@pytest.mark.parametrize("waiting_for", ["a subscriber", "an embodiment"])
def test_replay_stops_at_once_while_it_waits_to_join(session: Session, waiting_for: str) -> None:
    """Ctrl-C (``stop``) ends replay's join wait at once, not when --join-timeout has passed."""
    import threading

    from cmion_mesh.tools.replay import replay

    with MemoryTransport(MemoryNetwork(), "replay") as t:
        client = MeshClient(t, "empty")
        waiting = threading.Event()
        if waiting_for == "a subscriber":
            wait = t.wait_subscribers
            t.wait_subscribers = lambda key, timeout: (waiting.set(), wait(key, timeout))[-1]  # type: ignore[method-assign]
        else:
            wait_alive = client.presence.wait
            client.presence.wait = lambda predicate, timeout: (waiting.set(), wait_alive(predicate, timeout))[-1]  # type: ignore[method-assign]
        stop = threading.Event()
        done: list[Any] = []
        worker = threading.Thread(target=lambda: done.append(replay(client, session.clean, join_timeout=120, stop=stop,
                                                                    wait_for=["robot"] if waiting_for == "an embodiment" else ())))
        worker.start()
        assert waiting.wait(30), "replay waits to join"
        stop.set()
        worker.join(10)
        assert not worker.is_alive(), "still waiting after the stop"
    assert done[0].published == 0


def test_replay_publishes_the_events_of_the_overflow_channel_on_their_own_keys(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Past ``MAX_CHANNELS`` event keys, events share one channel whose topic is a pattern; replay
    still publishes each on its own key."""
    from cmion_mesh.tools.replay import replay

    monkeypatch.setattr(recording, "MAX_CHANNELS", 2)
    network = MemoryNetwork()
    sent = [Event("robot", "c", f"E{i}", {"i": i}, i, 1.0 + i) for i in range(5)]
    with MemoryTransport(network, "mesh") as t, Recorder(t, "m", tmp_path / "o.mcap") as recorder:
        for event in sent:
            t.publish(f"cmion/m/robot/ev/c/{event.name}", encode(event))
        wait_for(lambda: _count(recorder) == 5, 10, "five events written")
    assert "cmion/m/*/ev/**" in info(tmp_path / "o.mcap")["channels"]
    heard: list[tuple[str, Event]] = []
    with MemoryTransport(network, "listener") as listener_t, MemoryTransport(network, "replay") as replay_t, \
            listener_t.subscribe("cmion/fresh/**", lambda s: heard.append((s.key, decode(s.payload, Event)))):
        stats = replay(MeshClient(replay_t, "fresh"), tmp_path / "o.mcap", rate=0)
        wait_for(lambda: len(heard) == 5, 10, "five replayed events")
    assert stats.published == 5
    assert sorted(heard, key=lambda h: h[1].seq) == [(f"cmion/fresh/robot/ev/c/{e.name}", e) for e in sent]


def test_answers_are_told_only_while_someone_listens() -> None:
    from cmion_mesh import keys
    from cmion_mesh.ion import Component, Simulation
    from cmion_mesh.messages import Describe, RequestAnswered, decode
    from cmion_mesh.requests import send_request

    class Asked(Component):
        requests = {"describe": Describe}

        def on_request(self, request: Any) -> None:
            request.accept({"ok": True})

    network = MemoryNetwork()
    with MemoryTransport(network, "daemon") as daemon_t, MemoryTransport(network, "tool") as tool_t, \
            Simulation(daemon_t, mesh="m", embodiment="robot") as sim:
        sim.add(Asked("asked"))
        told: list[RequestAnswered] = []
        published: list[str] = []
        publish = daemon_t.publish
        daemon_t.publish = lambda key, payload, block=True: (published.append(key), publish(key, payload, block=block))[-1]  # type: ignore[method-assign]
        key = keys.request_key("m", "robot", "asked", "describe")
        assert send_request(tool_t, key, Describe()).status == "accepted"
        assert not [k for k in published if "@outcome" in k], "nobody listens: nothing told"
        # What `cmion-mesh echo '*/@outcome/**'` does: a subscription (not a liveliness watch).
        from cmion_mesh.tools.hz_echo import Tap, resolve

        with Tap(tool_t, resolve("m", "*/@outcome/**"), lambda seen: told.append(decode(seen.payload, RequestAnswered))):
            assert send_request(tool_t, key, Describe()).status == "accepted"
            assert send_request(tool_t, keys.request_key("m", "robot", "asked", "nothing"), Describe()).status == "rejected"
            wait_for(lambda: len(told) == 2, 10, "two answers told")
    assert [(t.component, t.request, t.status, t.code) for t in told] == \
        [("asked", "describe", "accepted", ""), ("asked", "nothing", "rejected", "unknown_request")]
    assert told[1].reason and told[0].embodiment == "robot"


# --- the recorder alone, on the in-memory transport ------------------------------------------------


def test_undecodable_payloads_go_to_a_raw_channel_and_drops_are_counted(tmp_path: Path) -> None:
    network = MemoryNetwork()
    said: list[str] = []
    with MemoryTransport(network, "mesh") as t:
        with Recorder(t, "m", tmp_path / "r.mcap", report=said.append) as recorder:
            t.publish("cmion/m/robot/ev/manager/ActionStarted", b"\xc1 not msgpack")
            t.publish("cmion/m/robot/other/thing", b"anything")
            event = Event("robot", "manager", "Ping", {"n": 1}, 7, 1.5)
            t.publish("cmion/m/robot/ev/manager/Ping", encode(event))
            wait_for(lambda: _count(recorder) >= 3, 10, "three samples written")
        with Recorder(t, "m", tmp_path / "dropped.mcap", max_queued=0, report=said.append) as dropping:
            for i in range(5):
                t.publish(f"cmion/m/robot/ev/manager/E{i}", encode(event))
            wait_for(lambda: dropping.dropped >= 5, 10, "five drops")
    summary = info(tmp_path / "r.mcap")
    # The log lines: the manager's event (an action's story) and the payload not understood.
    assert summary["channels"] == {"cmion/m/robot/ev/manager/Ping": 1, "raw:cmion/m/robot/ev/**": 1, "raw:cmion/m/robot/other/**": 1,
                                   "log:cmion/m": 2}
    with RecordingReader(tmp_path / "r.mcap") as reader:
        raw = [m.decoded() for m in reader.messages() if m.schema == RAW_SCHEMA]
    assert {r["key"] for r in raw} == {"cmion/m/robot/ev/manager/ActionStarted", "cmion/m/robot/other/thing"}
    assert all(r["payload_base64"] for r in raw) and "malformed" in raw[0]["error"]
    assert info(tmp_path / "dropped.mcap")["dropped"] >= 5
    assert any("dropped" in line for line in said)


def _count(recorder: Recorder) -> int:
    return recorder.stats.samples


def test_split_by_size_makes_parts_that_each_open(tmp_path: Path) -> None:
    network = MemoryNetwork()
    with MemoryTransport(network, "mesh") as t:
        with Recorder(t, "m", tmp_path / "s.mcap", split_bytes=2000, flush_interval=0.01) as recorder:
            for i in range(200):
                t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": i, "pad": "x" * 100}, i, 1.0)))
                if i % 50 == 49:
                    wait_for(lambda i=i: _count(recorder) > i, 10, "written")
        files = recorder.stats.files
    assert len(files) > 1 and files[0].endswith("s-0000.mcap")
    ticks = []
    for path in files:
        summary = info(path)
        assert not summary["truncated"]
        ticks += [e["data"]["i"] for e in events_in(Path(path))]
    assert ticks == list(range(200))


def test_what_a_killed_recorder_leaves_opens_in_any_mcap_reader(tmp_path: Path) -> None:
    """The file as it is on disk while the recorder runs is what SIGKILL leaves: after each write,
    a valid MCAP file with no summary; cut in the middle of a write, readable up to its last chunk."""
    live = tmp_path / "live.mcap"
    with MemoryTransport(MemoryNetwork(), "mesh") as t, Recorder(t, "m", live, flush_interval=0.01) as recorder:
        for i in range(30):
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": i}, i, 1.0)))
        wait_for(lambda: len(events_in(live)) == 30, 10, "the ticks on disk")
        left = live.read_bytes()
        assert recorder.stats.samples == recorder.stats.messages == 30  # no log line: component c is not the story
    (tmp_path / "killed.mcap").write_bytes(left)
    with open(tmp_path / "killed.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is None
        assert [json.loads(m.data)["data"]["i"] for _, _, m in reader.iter_messages()] == list(range(30))
    summary = info(tmp_path / "killed.mcap")
    assert summary["truncated"] and summary["messages"] >= 30
    (tmp_path / "cut.mcap").write_bytes(left[: len(left) - len(OPEN_END) - 5])  # killed while writing
    cut = info(tmp_path / "cut.mcap")
    assert cut["truncated"] and cut["mesh"] == "m"
    # Closed, the file has its real end: a summary, nothing of an open end left after it.
    assert not info(live)["truncated"]
    with open(live, "rb") as f:
        assert make_reader(f).get_summary() is not None


def test_a_split_recording_makes_no_empty_part(tmp_path: Path) -> None:
    """A part past its size starts a new one with the next message only: none came, none made."""
    with MemoryTransport(MemoryNetwork(), "mesh") as t:
        with Recorder(t, "m", tmp_path / "q.mcap", split_bytes=1, flush_interval=0.01) as recorder:
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": 0}, 0, 1.0)))
            wait_for(lambda: len(events_in(tmp_path / "q-0000.mcap")) == 1, 10, "the tick on disk")
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": 1}, 1, 2.0)))
            wait_for(lambda: len(recorder.stats.files) == 2 and len(events_in(tmp_path / "q-0001.mcap")) == 1, 10,
                     "the second tick in a second part")
        files = recorder.stats.files
    assert [Path(f).name for f in files] == ["q-0000.mcap", "q-0001.mcap"]
    assert [len(events_in(Path(f))) for f in files] == [1, 1]


def test_a_part_holding_no_message_is_never_full(tmp_path: Path) -> None:
    """A part's header and metadata pass any split size: only a message fills it, so the first
    message goes to the first part however long the recorder waited for it."""
    with MemoryTransport(MemoryNetwork(), "mesh") as t:
        # flush_interval 0: the writer checks the part's size on every pass, so it has checked it
        # (metadata only, past 1 byte) before the tick can come.
        with Recorder(t, "m", tmp_path / "q.mcap", split_bytes=1, flush_interval=0.0) as recorder:
            recorder.describe([{"name": "robot"}])
            wait_for(lambda: any("embodiment:robot" in metadata_in(Path(f)) for f in recorder.stats.files), 10,
                     "the description on disk")
            t.publish("cmion/m/robot/ev/c/Tick", encode(Event("robot", "c", "Tick", {"i": 0}, 0, 1.0)))
            wait_for(lambda: sum(len(events_in(Path(f))) for f in recorder.stats.files) == 1, 10, "the tick on disk")
        files = recorder.stats.files
    assert [(Path(f).name, len(events_in(Path(f)))) for f in files] == [("q-0000.mcap", 1)]


def test_bad_input_is_named(tmp_path: Path) -> None:
    (tmp_path / "not.mcap").write_bytes(b"hello, this is not mcap at all")
    with pytest.raises(ConfigError, match=r"not\.mcap"):
        info(tmp_path / "not.mcap")
    with pytest.raises(ConfigError, match=r"missing\.mcap"):
        info(tmp_path / "missing.mcap")
    with pytest.raises(ConfigError, match="size"):
        parse_size("lots")
    assert parse_size("100M") == 100 * 1024**2
    with pytest.raises(ConfigError, match="filter"):
        mesh_filter("m", "/abs")


def test_a_recording_is_never_overwritten_unless_asked(tmp_path: Path) -> None:
    (tmp_path / "kept.mcap").write_bytes(b"evidence")
    with MemoryTransport(MemoryNetwork(), "mesh") as t:
        with pytest.raises(ConfigError, match="exists already"):
            Recorder(t, "m", tmp_path / "kept.mcap", overwrite=False)
        assert (tmp_path / "kept.mcap").read_bytes() == b"evidence"
        with Recorder(t, "m", tmp_path / "kept.mcap", overwrite=True):
            pass
    assert not info(tmp_path / "kept.mcap")["truncated"]
    with MemoryTransport(MemoryNetwork(), "mesh") as t, pytest.raises(ConfigError, match="is a folder"):
        Recorder(t, "m", tmp_path, overwrite=True)
