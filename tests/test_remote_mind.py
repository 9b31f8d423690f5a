"""A mind in another process (``body.remote_mind``): it starts once its embodiment is reachable,
and never under a name the embodiment already has. Logic on the in-memory transport; the same over
real zenoh and processes: tests/test_tutorial.py."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.remote_mind import MindNameTaken, clash_message, holder, serve_mind
from cmion_mesh.messages import Code, Outcome, encode
from cmion_mesh.mind import Mind
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import Reply
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def answer(outcome: Outcome) -> Reply:
    return Reply("cmion/default/lamp/rq/x/state", encode(outcome))


def test_what_holds_a_name_comes_from_the_answers() -> None:
    assert holder([]) is None
    assert holder([answer(Outcome("accepted", value={}))]) == "a mind"
    assert holder([answer(Outcome("rejected", "no state", code=Code.UNKNOWN_REQUEST))]) == "a component"
    assert holder([answer(Outcome("rejected", "asleep", code=Code.BUSY))]) == "a mind"  # it has the request
    assert holder([Reply("k", b"not msgpack")]) == "a component"  # something answers there all the same
    assert holder([Reply("k", b"", ok=False)]) == "a component"
    assert clash_message("desk", "keeper", "a mind") == (
        "embodiment 'desk' already has a mind named 'keeper': give this mind another name (serve-mind --name NAME)")


@pytest.fixture
def lamp(network: MemoryNetwork, monkeypatch: pytest.MonkeyPatch) -> Iterator[Embodiment]:
    """The example's lamp on the in-memory mesh, its own mind named ``mind`` (as the shipped planner is)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    from blink.competency import Blink
    from blink.mind import Keeper

    embodiment = Embodiment("lamp", transport=MemoryTransport(network, "lamp"), rules=EXAMPLES / "blink" / "CompetencyManagerRules.xml",
                            competencies=[Blink("0.01")], components=[Keeper("1", "mind")])
    with embodiment:
        wait_for(lambda: embodiment.blackboard.get("light", "last") == 1, 10, "the lamp's own mind blinked")
        yield embodiment
    embodiment.transport.close()


def keeper(times: str, name: str) -> Mind:
    from blink.mind import Keeper

    return Keeper(times, name)


def refusal(mind: Mind, transport: MemoryTransport) -> str:
    """Why ``serve_mind`` refuses ``mind`` for the lamp (it must)."""
    with pytest.raises(MindNameTaken) as refused, serve_mind(mind, embodiment="lamp", transport=transport):
        pass
    return str(refused.value)


@pytest.mark.parametrize(("name", "held_by"), [("mind", "a mind"), ("manager", "a component")])
def test_a_name_the_embodiment_has_is_refused(lamp: Embodiment, network: MemoryNetwork, name: str, held_by: str) -> None:
    with MemoryTransport(network, "remote") as transport:
        assert refusal(keeper("4", name), transport) == clash_message("lamp", name, held_by)


def test_a_free_name_serves_and_its_first_act_reaches_the_body(lamp: Embodiment, network: MemoryNetwork) -> None:
    with MemoryTransport(network, "remote") as transport, serve_mind(keeper("4", "watcher"), embodiment="lamp", transport=transport):
        wait_for(lambda: lamp.blackboard.get("light", "last") == 4, 10, "the remote mind's on_start action ran")
        # a second process with the same name is refused while the first serves
        with MemoryTransport(network, "second") as other:
            assert refusal(keeper("2", "watcher"), other) == clash_message("lamp", "watcher", "a mind")


class Unseen(MemoryTransport):
    """A session that does not yet see the other's mind when it first asks (both started at once)."""

    asked = 0

    def get(self, selector: str, payload: bytes | None = None, **kwargs: object) -> list[Reply]:  # type: ignore[override]
        self.asked += 1
        return [] if self.asked == 1 else super().get(selector, payload, **kwargs)  # type: ignore[arg-type]


def test_two_started_at_the_same_moment_do_not_both_serve_unnoticed(lamp: Embodiment, network: MemoryNetwork) -> None:
    with MemoryTransport(network, "remote") as transport, Unseen(network, "second") as other, \
            serve_mind(keeper("4", "watcher"), embodiment="lamp", transport=transport):
        assert refusal(keeper("2", "watcher"), other) == clash_message("lamp", "watcher", "a mind", same_moment=True)
