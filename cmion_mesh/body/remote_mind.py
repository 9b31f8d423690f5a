"""A mind in another process (``cmion-mesh serve-mind``): it starts once it can reach its embodiment,
under a name no other component of that embodiment has.

**When it starts.** ``serve_mind`` is entered once the embodiment is alive in the mesh (the caller
waits for its liveliness token: the daemon declares it after its components, the competency
manager among them, are attached and answer, and zenoh delivers one peer's declarations in order).
Only then is the mind added to its simulation, so ``on_start`` runs when an ``act`` reaches the
manager, as it does in a daemon, where the mind is attached to the simulation that holds the
manager. One hook with one meaning wherever the mind runs ("from here on the body is there"),
rather than a second hook that a mind written for a daemon would not know to use: the same class
moves between a daemon and a process of its own unchanged. ``on_start`` runs once: if the
embodiment leaves and comes back, its ``act`` meanwhile fails (outcome unknown) and the mind is
not started again.

**Its name.** A mind's name is its component name: its requests are ``.../<embodiment>/rq/<name>/...``
and its action ids start with it. Two components of one name on one embodiment would both answer
those requests, each perceiving half of the conversation. So before it serves, ``serve_mind``
asks ``.../rq/<name>/state``: every component answers a query on its requests (a mind accepts
``state``, any other component refuses it as unknown), so any answer means the name is taken,
whether by a mind of the daemon (the shipped planner is ``mind``), another component
(``manager``...) or another process's mind; ``MindNameTaken`` (a configuration error: exit 2)
names the embodiment and the name. Once serving it asks again: two answers mean that another
process started with the same name at the same moment, and it stands down the same way (both
may: neither is left serving unnoticed).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, ProtocolError
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import Code, MindState, Outcome, decode, encode
from cmion_mesh.mind import Mind
from cmion_mesh.transport.base import Reply, Transport

#: How long the name check waits for the components of the embodiment to answer (they answer in a
#: round trip; an embodiment that is alive but silent longer than this is not holding the name).
NAME_CHECK_TIMEOUT = 2.0


class MindNameTaken(ConfigError):
    """The embodiment already has a component (a mind or another) of this mind's name."""


def holder(replies: Sequence[Reply]) -> str | None:
    """What holds a name, from the answers to ``.../rq/<name>/state``: None when nothing answered,
    ``"a mind"`` when one took the request (a mind answers ``state``; one that failed on it still
    had it), else ``"a component"``: something answers there, refusing ``state`` as a request it
    does not have."""
    if not replies:
        return None
    for reply in replies:
        if not reply.ok:
            continue
        try:
            outcome = decode(reply.payload, Outcome, where=reply.key)
        except ProtocolError:
            continue
        if outcome.status == "accepted" or outcome.code not in (Code.UNKNOWN_REQUEST, Code.MALFORMED):
            return "a mind"
    return "a component"


def clash_message(embodiment: str, name: str, held_by: str, *, same_moment: bool = False) -> str:
    """The one line that refuses a mind whose name is taken."""
    when = " (started at the same moment as this one)" if same_moment else ""
    return (f"embodiment {embodiment!r} already has {held_by} named {name!r}{when}: "
            "give this mind another name (serve-mind --name NAME)")


def name_replies(transport: Transport, mesh: str, embodiment: str, name: str, timeout: float = NAME_CHECK_TIMEOUT) -> list[Reply]:
    """Every answer to ``.../<embodiment>/rq/<name>/state``: one per component of that name."""
    return transport.get(keys.request_key(mesh, embodiment, name, "state"), encode(MindState()), timeout=timeout)


@contextlib.contextmanager
def serve_mind(mind: Mind, *, embodiment: str, transport: Transport, mesh: str = keys.DEFAULT_MESH) -> Iterator[Simulation]:
    """Serve ``mind`` for ``embodiment``, which the caller has seen alive (see the module's doc);
    ``MindNameTaken`` when another component of the embodiment has its name."""
    embodiment = keys.check_name(embodiment, "embodiment")
    held_by = holder(name_replies(transport, mesh, embodiment, mind.name))
    if held_by is not None:
        raise MindNameTaken(clash_message(embodiment, mind.name, held_by))
    with Simulation(transport, mesh=mesh, embodiment=embodiment) as sim:
        sim.add(mind)
        # This process's own mind answers too: a second answer is another process's.
        replies = name_replies(transport, mesh, embodiment, mind.name)
        if len(replies) > 1:
            raise MindNameTaken(clash_message(embodiment, mind.name, holder(replies) or "a component", same_moment=True))
        yield sim
