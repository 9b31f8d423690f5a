"""Migration invitations: definite answers, refusals, the rate limit, the minds that take them up,
and the whole CMION scenario end to end between daemons in separate processes (``cmion-mesh invite``)."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from cmion_mesh import keys
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import RequestRejected
from cmion_mesh.messages import AddContainer, Code, Invite
from cmion_mesh.migration import devices, invitation
from cmion_mesh.migration.devices import DeviceTable
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.minds import supersimple
from cmion_mesh.minds.planner.mind import PlannerMind
from cmion_mesh.minds.planner.spec import InvitationPolicy
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.resources import data_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import DATA
from .test_devices import configuration_copy

pytestmark = pytest.mark.timeout(120)

INVITE_DATA = DATA / "invite"
RULES = INVITE_DATA / "send" / "CompManagerRules.xml"  # CMION's "Migration *" -> Migration / DeviceName


class Listener(Mind):
    """Records the remote actions it is given, and does nothing else."""

    def __init__(self) -> None:
        super().__init__("listener")
        self.heard: list[MindAction] = []

    def on_remote_action(self, action: MindAction) -> None:
        self.heard.append(action)


def table(name: str, *known: str) -> DeviceTable:
    return DeviceTable(Path(f"{name}.xml"), name, 1, None, False,
                       tuple(devices.Device(k, "127.0.0.1", 2, None, None) for k in known))


@dataclass
class Bodies:
    network: MemoryNetwork
    mesh: str
    tmp: Path
    made: list[Embodiment]

    def add(self, name: str, *, companion: str | None = None, knows: tuple[str, ...] | None = None,
            minds: tuple[Mind, ...] = ()) -> Embodiment:
        body = Embodiment(name, mesh=self.mesh, transport=MemoryTransport(self.network, name), state_dir=self.tmp / name,
                          companion=companion, rules=RULES, components=minds,
                          devices=None if knows is None else table(name, *knows)).start()
        self.made.append(body)
        return body


@pytest.fixture
def bodies(network: MemoryNetwork, mesh: str, tmp_path: Path) -> Iterator[Bodies]:
    made = Bodies(network, mesh, tmp_path, [])
    yield made
    for body in made.made:
        body.close()
        body.transport.close()


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "cli") as t, MeshClient(t, mesh) as c:
        yield c


def invite(client: MeshClient, target: str, inviter: str, *, sender: str | None = None) -> tuple[str, str, str]:
    outcome = client.request(target, "invitation", "invite", Invite(inviter), sender=sender or inviter)
    return outcome.status, outcome.reason, outcome.code


# --- in one process: the answers -------------------------------------------------------------------


def test_every_invitation_gets_a_definite_answer(bodies: Bodies, client: MeshClient) -> None:
    listener = Listener()
    a = bodies.add("A", companion="spirit", knows=("B",), minds=(listener,))
    bodies.add("B", knows=("A",))
    bodies.add("C")
    wait_for(lambda: a.inhabitant == "spirit" and listener.awake, 5, "spirit born on A")
    seen_alive(a, "B", "C")  # only a live embodiment invites: A must have seen them join
    # a stranger: not in A's device table
    assert invite(client, "A", "C") == ("rejected", "'C' is not in 'A''s device table A.xml (known: B)", Code.INVALID)
    # an empty receiver
    assert invite(client, "B", "C") == ("rejected", "'B' hosts no companion", Code.NOT_FOUND)
    # nobody invites on behalf of another (the key names the sender; access control ties it to a certificate)
    status, reason, _ = invite(client, "A", "B", sender="C")
    assert status == "rejected" and reason == "'C' cannot invite on behalf of 'B'"
    assert listener.heard == []
    status, _, _ = invite(client, "A", "B")
    assert status == "accepted"
    wait_for(lambda: listener.heard, 5, "the invitation reaches the hosting mind")
    assert listener.heard == [MindAction("MigrationInvitation", ("B",), "B")]
    # the sending side: an inhabited embodiment does not invite; an empty one with nobody to ask says so
    with pytest.raises(RequestRejected, match="'A' hosts 'spirit': an inhabited embodiment does not invite"):
        client.invite("A", timeout=10)
    with pytest.raises(RequestRejected, match=r"nobody accepted \(A: 'C' is not in 'A''s device table"):
        client.invite("C", ["A"], timeout=10)
    done = client.invite("B", timeout=10)
    assert done["accepted_by"] == ["A"] and done["answers"]["A"]["status"] == "accepted"


@contextmanager
def alive(network: MemoryNetwork, mesh: str, *names: str) -> Iterator[None]:
    """``names`` alive in the mesh (their liveliness tokens), as inviters need to be."""
    with MemoryTransport(network, "tokens") as transport:
        tokens = [transport.declare_token(keys.alive_key(mesh, name)) for name in names]
        try:
            yield
        finally:
            for token in tokens:
                token.close()


def seen_alive(body: Embodiment, *names: str) -> None:
    assert body.presence is not None
    presence = body.presence
    wait_for(lambda: set(names) <= presence.alive(), 5, f"{', '.join(names)} alive as {body.name} sees it")


def test_an_invitation_from_a_ghost_is_refused(bodies: Bodies, client: MeshClient) -> None:
    """Only an embodiment alive in the mesh invites: a ghost's name is refused before any budget."""
    listener = Listener()
    a = bodies.add("A", companion="spirit", minds=(listener,))
    wait_for(lambda: a.inhabitant == "spirit" and listener.awake, 5, "spirit born on A")
    for _ in range(invitation.INVITE_BURST + 2):
        assert invite(client, "A", "ghost") == ("rejected", f"'ghost' is not alive in mesh {bodies.mesh!r}: only a live "
                                                            "embodiment invites", Code.NOT_FOUND)
    with alive(bodies.network, bodies.mesh, "ghost"):
        seen_alive(a, "ghost")
        assert invite(client, "A", "ghost")[0] == "accepted", "refusals spent none of its budget"
        wait_for(lambda: listener.heard, 5, "the invitation reaches the hosting mind")
    assert listener.heard == [MindAction("MigrationInvitation", ("ghost",), "ghost")]


def test_a_flood_of_invitations_does_not_flood_the_mind(bodies: Bodies, client: MeshClient) -> None:
    listener = Listener()
    a = bodies.add("A", companion="spirit", minds=(listener,))
    bodies.add("B")
    bodies.add("C")
    wait_for(lambda: a.inhabitant == "spirit" and listener.awake, 5, "spirit born on A")
    seen_alive(a, "B", "C")
    answers = [invite(client, "A", "B") for _ in range(20)]
    accepted = [a for a in answers if a[0] == "accepted"]
    assert invitation.INVITE_BURST <= len(accepted) <= invitation.INVITE_BURST + 1  # +1: a token may refill meanwhile
    assert {a[2] for a in answers if a[0] != "accepted"} == {Code.BUSY}
    assert "busy: too many invitations from 'B'" in next(a[1] for a in answers if a[0] != "accepted")
    # another inviter has a budget of its own
    assert invite(client, "A", "C")[0] == "accepted"
    wait_for(lambda: len(listener.heard) == len(accepted) + 1, 5, "every accepted invitation reaches the mind")


def test_a_flood_under_many_names_is_bounded_by_the_hosts_budget(bodies: Bodies, client: MeshClient,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(invitation, "HOST_RATE", 1e-6)  # no refill while the test runs: exact counts
    listener = Listener()
    a = bodies.add("A", companion="spirit", minds=(listener,))
    wait_for(lambda: a.inhabitant == "spirit" and listener.awake, 5, "spirit born on A")
    names = [f"n{i}" for i in range(invitation.HOST_BURST + 5)]
    with alive(bodies.network, bodies.mesh, *names):
        seen_alive(a, *names)
        answers = [invite(client, "A", name) for name in names]
    assert [s for s, _, _ in answers] == ["accepted"] * invitation.HOST_BURST + ["rejected"] * 5
    assert answers[-1][1:] == ("busy: too many invitations to 'A' from all inviters; try again later", Code.BUSY)
    wait_for(lambda: len(listener.heard) == invitation.HOST_BURST, 5, "the accepted ones reach the mind")


def test_inviters_budgets_are_forgotten_least_recent_first(bodies: Bodies, client: MeshClient,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The store of budgets is bounded without forgetting them all at once: a full store forgets the
    inviter seen longest ago, never the one that keeps asking."""
    monkeypatch.setattr(invitation, "MAX_INVITERS", 2)
    monkeypatch.setattr(invitation, "INVITE_RATE", 1e-6)  # no refill while the test runs: exact counts
    a = bodies.add("A", companion="spirit", minds=(Listener(),))
    wait_for(lambda: a.inhabitant == "spirit", 5, "spirit born on A")
    with alive(bodies.network, bodies.mesh, "X", "Y", "Z"):
        seen_alive(a, "X", "Y", "Z")
        assert [invite(client, "A", "X")[0] for _ in range(invitation.INVITE_BURST + 1)] == \
            ["accepted"] * invitation.INVITE_BURST + ["rejected"]
        assert invite(client, "A", "Y")[0] == "accepted"
        assert invite(client, "A", "X")[2] == Code.BUSY  # X is now the most recent
        assert invite(client, "A", "Z")[0] == "accepted"  # the store is full: Y, seen longest ago, is forgotten
        assert invite(client, "A", "X")[2] == Code.BUSY, "X's spent budget is remembered"
        assert invite(client, "A", "Y")[0] == "accepted", "Y starts again (and Z, least recent now, is forgotten)"
        assert invite(client, "A", "X")[2] == Code.BUSY


def test_the_planner_follows_invitations_as_its_spec_says(bodies: Bodies, client: MeshClient) -> None:
    mind = PlannerMind("mind", invitations=InvitationPolicy(follow=True, accept_from=("B",)))
    a = bodies.add("A", companion="spirit", minds=(mind,))
    b = bodies.add("B", minds=(PlannerMind("mind"),))  # its policy comes with the companion
    bodies.add("C")
    wait_for(lambda: a.inhabitant == "spirit" and mind.awake, 5, "spirit born on A")
    seen_alive(a, "B", "C")
    assert client.invite("C", ["A"], timeout=10)["accepted_by"] == ["A"]  # the body passes it on...
    wait_for(lambda: any(e["kind"] == "invitation_declined" for e in mind.memory), 5, "...the mind declines it")
    declined = next(e for e in mind.memory if e["kind"] == "invitation_declined")
    assert declined["details"] == {"inviter": "C", "reason": "'C' is not among ['B']"}
    client.invite("B", timeout=10)
    wait_for(lambda: b.inhabitant == "spirit", 10, "the planner followed B's invitation")
    moved = b.minds[0]
    assert isinstance(moved, PlannerMind) and moved.invitations.accept_from == ("B",)
    assert any(e["kind"] == "invitation_followed" for e in moved.memory)


def test_a_planner_without_the_policy_declines() -> None:
    mind = PlannerMind("mind")
    assert not mind.invitations.follow
    assert mind.invitation_refusal("B") == "the spec does not follow invitations"
    spirit = PlannerMind("mind", str(data_dir("embodiments") / "spirit.json"))
    assert spirit.invitations.follow and spirit.invitations.accept_from == ("robot", "screen", "phone")
    assert spirit.invitation_refusal("robot") == ""


class CountingMind(supersimple.SuperSimpleMind):
    def __init__(self) -> None:
        super().__init__()
        self.sent: list[str] = []

    def act(self, name: str, parameters: list[str] | tuple[str, ...] = (), subject: str = "", *, deadline: float = 0.0) -> str:
        self.sent.append(" ".join((name, *parameters)))
        return super().act(name, parameters, subject, deadline=deadline)


def test_the_supersimple_minds(bodies: Bodies, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(supersimple, "BACK_DELAY", 0.05)
    monkeypatch.setattr(supersimple, "RETRY_DELAY", 0.05)
    # SuperSimpleMigratingMind: born on A, goes to B, and comes back with its mindstate
    b = bodies.add("B", minds=(supersimple.SuperSimpleMigratingMind(),))
    a = bodies.add("A", companion="simple", minds=(supersimple.SuperSimpleMigratingMind(),))
    wait_for(lambda: b.inhabitant == "simple", 10, "the migrating mind went to B")
    wait_for(lambda: a.inhabitant == "simple", 10, "and came back to A")
    back = a.minds[0]
    assert isinstance(back, supersimple.SuperSimpleMigratingMind) and back.goal == supersimple.MIND_GOAL
    assert back.state() == {"goal": "Migrate Mind"} and back.name == "mindstate"
    # SuperSimpleMind: sends TestAction test when it wakes, and again after a failure (no rule matches here)
    counting = CountingMind()
    bodies.add("C", companion="other", minds=(counting,))
    wait_for(lambda: len(counting.sent) >= 3, 5, "the mind acts, and tries again after failing")
    assert set(counting.sent) == {"TestAction test"}


def test_the_by_invite_mind_invites_where_it_sleeps(bodies: Bodies, client: MeshClient) -> None:
    a = bodies.add("A", companion="simple", knows=("B",), minds=(supersimple.SuperSimpleMigratingByInviteMind(),))
    b = bodies.add("B", knows=("A",), minds=(supersimple.SuperSimpleMigratingByInviteMind(),))
    wait_for(lambda: a.inhabitant == "simple", 5, "born on A")
    seen_alive(a, "B")
    seen_alive(b, "A")
    # an entity where the companion is not: B invites, A's mind follows
    client.write("B", "wm", AddContainer("", "User", "agent"))
    wait_for(lambda: b.inhabitant == "simple", 10, "the companion came to B")
    # an entity where it is: nothing happens (an inhabited embodiment does not invite)
    client.write("B", "wm", AddContainer("", "Vase", "object"))
    client.write("A", "wm", AddContainer("", "User", "agent"))
    wait_for(lambda: a.inhabitant == "simple", 10, "and back to A")


# --- between daemons in separate processes ------------------------------------------------------------


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli_argv(*args), capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)


@dataclass
class Pair:
    mesh: str
    ports: dict[str, int]  # embodiment -> its listen port
    daemons: dict[str, Daemon]
    tmp: Path

    @property
    def endpoint(self) -> str:
        """A's endpoint, for tools."""
        return f"tcp/127.0.0.1:{self.ports['A']}"

    def net(self) -> list[str]:
        return ["--mesh", self.mesh, "--connect", self.endpoint, "--no-multicast"]

    def inhabitants(self) -> dict[str, str | None]:
        result = cli("peers", "--json", "--timeout", "2", *self.net())
        assert result.returncode == 0, result.stderr
        return {p["name"]: p.get("inhabitant") for p in json.loads(result.stdout)}

    def up(self, name: str, *args: str) -> Daemon:
        daemon = Daemon(cli_argv("up", *args, "--mesh", self.mesh, "--no-multicast", "--state-dir", str(self.tmp / f"state-{name}")),
                        name=name)
        self.daemons[name] = daemon
        return daemon


def start_pair(tmp: Path, mesh: str, *, java_names: bool) -> Pair:
    """A and B from the MigrationByInvite configurations, on free loopback ports, and a stranger C."""
    ports = {"A": free_port(), "B": free_port()}
    values = {"34871": str(ports["A"]), "34873": str(ports["B"])}
    pair = Pair(mesh, ports, {}, tmp)
    try:
        for name, side in (("A", "send"), ("B", "receive")):
            pair.up(name, str(configuration_copy(INVITE_DATA / side, tmp / side, values, java_names=java_names)))
        pair.up("C", "--name", "C", "--connect", pair.endpoint)
        for daemon in pair.daemons.values():
            daemon.wait_line("up in mesh", 30)
    except BaseException:
        for daemon in pair.daemons.values():
            daemon.kill()
        raise
    return pair


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pair]:
    from cmion_mesh.procs import unique_mesh

    started = start_pair(tmp_path_factory.mktemp("invite"), unique_mesh(), java_names=False)
    yield started
    for daemon in started.daemons.values():
        daemon.stop()


def test_device_tables_name_connect_and_give_birth(pair: Pair) -> None:
    a = pair.daemons["A"]
    line = a.wait_line("device table", 1)
    assert "embodiment 'A', knows B; listen tcp/127.0.0.1:" in line and "companion 'companion' born here" in line
    # B found A only through the endpoints of the tables (no multicast)
    assert wait_for(lambda: (found := pair.inhabitants()) and len(found) == 3 and found, 20, "A, B and C in one mesh") == \
        {"A": devices.DEFAULT_COMPANION, "B": None, "C": None}
    # a second table whose agent is active: the companion lives on A already, so it is not born again
    second = configuration_copy(INVITE_DATA / "send", pair.tmp / "second", {"A": "D", "34871": str(free_port()),
                                                                          "34873": str(pair.ports["B"])})
    with pair.up("D", str(second)) as d:
        d.wait_line("up in mesh", 30)
        assert "companion 'companion' already lives on 'A': it is not born here" in "\n".join(d.lines)
        assert pair.inhabitants() == {"A": devices.DEFAULT_COMPANION, "B": None, "C": None, "D": None}
    del pair.daemons["D"]


def test_an_invitation_from_the_empty_embodiment_moves_the_companion(pair: Pair) -> None:
    wait_for(lambda: len(pair.inhabitants()) == 3, 20, "A, B and C in one mesh")
    refused = cli("invite", "C", "--to", "A", *pair.net())
    assert refused.returncode == 1 and "A: 'C' is not in 'A''s device table MigrationConfig.xml (known: B)" in refused.stderr
    inhabited = cli("invite", "A", *pair.net())
    assert inhabited.returncode == 1 and "an inhabited embodiment does not invite" in inhabited.stderr
    result = cli("invite", "B", "--json", *pair.net())
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["accepted_by"] == ["A"]
    wait_for(lambda: pair.inhabitants() == {"A": None, "B": devices.DEFAULT_COMPANION, "C": None}, 20,
             "the mind on A followed the invitation: the companion lives on B")
    empty = cli("invite", "C", "--to", "A", *pair.net())
    assert empty.returncode == 1 and "A: 'A' hosts no companion" in empty.stderr
    # CMION's own trigger: an entity added where the companion is not makes that embodiment invite
    with ZenohTransport(TransportConfig(connect=(pair.endpoint,), multicast=False)) as t, MeshClient(t, pair.mesh) as client:
        client.join("A", timeout=10)
        assert client.write("A", "wm", AddContainer("", "User", "agent")).status == "accepted"
    wait_for(lambda: pair.inhabitants()["A"] == devices.DEFAULT_COMPANION, 20, "invited back to A")


def test_cmions_java_named_configurations_run_as_they_are(tmp_path: Path, mesh: str) -> None:
    started = start_pair(tmp_path, mesh, java_names=True)
    try:
        wait_for(lambda: started.inhabitants() == {"A": devices.DEFAULT_COMPANION, "B": None, "C": None}, 20, "born on A")
        result = cli("invite", "B", *started.net())
        assert result.returncode == 0, result.stderr
        wait_for(lambda: started.inhabitants()["B"] == devices.DEFAULT_COMPANION, 20, "moved to B")
    finally:
        for daemon in started.daemons.values():
            daemon.stop()
