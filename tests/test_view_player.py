"""A recording played through the view (``tools/view_player.py``), without a browser: what the
view's model holds after playing, seeking back and forth; and what the model makes of the
events that move a companion. The view has no mesh (a recording's); its loop is this thread."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from cmion_mesh.messages import Event
from cmion_mesh.tools.view_player import RecordingPlayer, description_from, load
from cmion_mesh.web.view import MeshView
from cmion_mesh.web.view_model import Page

FORMAT_1 = Path(__file__).parent / "data" / "recording-format-1.mcap"


def run_now(fn: Any, *args: Any) -> None:
    fn(*args)


def test_a_recording_plays_through_the_view_and_a_seek_back_rebuilds_the_mesh_as_it_was() -> None:
    mesh, items, cut = load(FORMAT_1)
    assert (mesh, cut) == ("lab", False)
    with MeshView(None, mesh=mesh) as view:
        view.start(run_now)
        page = Page(1)
        view.pages.add(page)
        player = RecordingPlayer(view, items, path=str(FORMAT_1))  # not entered: no thread, the controls only
        assert view.playback is player and player.status()["playing"] is False
        assert player.control({"type": "playback", "action": "seek", "position": player.end / 1e9}) is None
        (migration,) = view.model.migrations.values()
        assert (migration["source"], migration["target"], migration["status"]) == ("robot", "screen", "succeeded")
        assert [s["step"] for s in migration["steps"]] == ["starting", "prepared", "incoming", "handed", "active", "released"]
        assert all(s["received"] == items[-1][0] / 1e9 for s in migration["steps"])  # the recorder's clock
        assert page.resync, "a seek gives each page one snapshot, not each change"
        assert view.model.frames[-1]["custody"] == {"spirit": {"robot": 1}}

        # Back to before the migration: the view rebuilt from the start, up to there.
        before = items[2][0] / 1e9  # the custody token, just before the migration's first event
        assert player.control({"type": "playback", "action": "seek", "position": before}) is None
        assert not view.model.migrations
        assert {n: c["alive"] for n, c in view.model.embodiments.items()} == {"robot": True, "screen": True}
        assert view.model.custody == {"spirit": {"robot": 1}}
        status = player.status()
        assert (status["position"], status["played"], status["playing"]) == (before, 3, False)

        assert player.control({"type": "playback", "action": "speed", "speed": 3}) == "speed: one of 0.1, 0.25, 0.5, 1, 2, 4, 10"
        assert player.control({"type": "playback", "action": "seek", "position": "soon"}) is not None
        assert player.control({"type": "playback", "action": "rewind"}) is not None


def test_the_recorders_descriptions_read_back_as_the_embodiments_said_them() -> None:
    written = {"name": "phone", "alive": '["phone", "robot"]', "inhabitant": "null", "host": "vm", "pid": "12",
               "competency_types": '["Migration"]', "version": "0.1.0"}
    assert description_from(written) == {"name": "phone", "alive": ["phone", "robot"], "inhabitant": None, "host": "vm",
                                         "pid": 12, "competency_types": ["Migration"], "version": "0.1.0"}
    assert description_from({"inhabitant": "spirit"}) == {"inhabitant": "spirit"}


def test_the_source_is_empty_from_its_handed_step_and_each_change_of_who_lives_where_is_a_frame() -> None:
    with MeshView(None, mesh="m") as view:
        view.start(run_now)
        t = time.time()
        view.feed_alive("robot", True, t)
        view.feed_alive("screen", True, t)
        view.feed_description("robot", {"name": "robot", "inhabitant": "spirit", "alive": ["robot", "screen"]}, t)
        frames = len(view.model.frames)
        step = {"companion": "spirit", "attempt": "a1", "peer": "screen"}
        view.feed_event(Event("robot", "migration", "MigrationStep", {**step, "step": "prepared"}, 1, t + 1), t + 1)
        assert len(view.model.frames) == frames, "nothing changed who lives where: no frame"
        view.feed_event(Event("screen", "migration", "MigrationOccurred", {"companion": "spirit", "epoch": 2}, 2, t + 2), t + 2)
        view.feed_event(Event("robot", "migration", "MigrationStep", {**step, "step": "handed"}, 3, t + 3), t + 3)
        assert [f["embodiments"] for f in list(view.model.frames)[frames:]] == [
            {"robot": [True, "spirit"], "screen": [True, "spirit"]},  # both, for a moment: the arrival came first
            {"robot": [True, None], "screen": [True, "spirit"]},
        ]
        assert [f["time"] for f in list(view.model.frames)[frames:]] == [t + 2, t + 3]
