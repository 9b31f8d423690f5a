"""A language-model mind: any OpenAI-compatible chat-completions endpoint drives the body it lives in.

Configured like any component (``ConstructorParameters="mind,llm.toml"``: its name and its
settings file, ``minds.llm.settings``). What it does, all on the update loop except the HTTP:

* **tools**: the abilities of the body it lives in (``body.abilities``, read from the embodiment's
  ``describe``, so a mind in another process gets the same), as chat-completions function tools;
  ``Migrate``'s ``target`` is offered as the embodiments alive in the mesh that the companion's
  policy accepts. Read when it wakes, on arrival, and again before a turn when older than
  ``TOOLS_TTL``.
* **a turn**: the perceptions gathered (``conversation``) go to the model with the window and the
  summary; a tool call becomes ``act``; each outcome (succeeded, failed with its reason,
  cancelled, refused because the body has no such tool, bad arguments, over the cap of calls per
  turn) is the tool's result; once every call of an answer has its result, the model is asked
  again. The turn ends when the model answers without calling a tool. Past ``tool_calls_per_turn``
  the model is asked without tools, so it must answer in words.
* **perceptions**: world-model changes, entities added and removed, remote actions (a person's
  words), and messages (``{"text": ...}`` to ``.../rq/<mind>/message``) become lines of one user
  message per turn; everything that arrives in one update is in the same turn.
* **memory**: the conversation and the model-written summary are the mind's state, its identity
  section: they migrate. On arrival it resolves the tool calls the move interrupted, re-reads the
  new body's tools and world model and tells the model.
* **safety**: the model's output is data (a tool's name looked up among the body's abilities,
  its arguments parsed as JSON and checked against the ability's parameters), never code; the
  HTTP runs on a worker thread (``worker``) within a budget of requests and tokens per minute;
  a failure is one event ``LlmEndpointDown`` and one log line, the turn is asked again later
  (back-off), the companion keeps its body and the inbox keeps every perception; the key is read
  from the environment by the adapter only (``chat``).
"""

from __future__ import annotations

import importlib.util
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import msgspec

from cmion_mesh import keys, logs
from cmion_mesh.body.abilities import Ability, Parameter
from cmion_mesh.errors import ConfigError, InvalidArguments, MeshError
from cmion_mesh.messages import ActionReport, Describe, Outcome
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.minds.llm.budget import TurnCount, backoff
from cmion_mesh.minds.llm.conversation import Conversation, OpenCall, tools_text, value_text, world_text
from cmion_mesh.minds.llm.settings import LlmSettings, load_settings
from cmion_mesh.storage import Store
from cmion_mesh.timers import Timer

if TYPE_CHECKING:
    from cmion_mesh.minds.llm.chat import EndpointError, Reply
    from cmion_mesh.minds.llm.worker import Worker

log = logging.getLogger(__name__)

#: The action that moves the companion (the built-in rule ``Migrate <target>``).
MIGRATE_ACTION = "Migrate"
#: Seconds the body's tools are trusted before a turn reads them again (peers come and go); a turn
#: that brings new perceptions reads them when they are older than ``TOOLS_FRESH`` (tool results
#: of a turn under way use them as they are: that is the path whose latency counts).
TOOLS_TTL = 10.0
TOOLS_FRESH = 1.0
#: Most tool calls of one answer looked at (the rest are refused unread).
MAX_CALLS_PER_ANSWER = 32


class LlmMind(Mind):
    """See the module's description. ``settings``: the settings file (a lone ``"llm.toml"`` in the
    name's place works too); the environment completes or overrides it."""

    def __init__(self, name: str = "mind", settings: str = "", *, awake: bool = True) -> None:
        if name.strip().lower().endswith(".toml") and not settings:
            name, settings = "mind", name.strip()
        super().__init__(name, awake=awake)
        if importlib.util.find_spec("openai") is None:
            raise ConfigError("the language-model mind needs the openai package: pip install 'cmion-mesh[llm]'")
        self.settings: LlmSettings = load_settings(settings.strip() or None)
        self.conversation = Conversation()
        self.tools: list[dict[str, Any]] = []
        self.abilities: dict[str, Ability] = {}
        self.turn = TurnCount(self.settings.limits.tool_calls_per_turn)
        self._worker: Worker | None = None
        self._busy = False  # a request in flight
        self._continue = False  # tool results the model has not seen yet
        self._offered_tools = True  # whether the request in flight offered tools
        self._failures = 0
        self._down = False
        self._retry: Timer | None = None
        self._tools_at: float | None = None
        self._describing = False
        self._kick_posted = False
        self._restored_from = ""  # the body a restored conversation was last in ("" when not restored)
        self._announced = False
        self._pending_arrival = False  # an arrival to tell once the new body's tools are read
        self._arrival_world = ""
        self._arrival_from = ""
        self._arrival_at = 0
        self._ended_asleep: dict[str, str] = {}  # action id -> result, for actions that ended while it slept
        self._closed = False

    # --- life cycle ---------------------------------------------------------------------------

    def on_start(self) -> None:
        from cmion_mesh.minds.llm.worker import Worker  # the client library loads only when a mind runs

        self._worker = Worker(self.settings, name=self.name, on_wait=self._budget_wait)
        logs.event(log, f"mind {self.name} talks to {self.settings.endpoint} (model {self.settings.model})",
                   mind=self.name, endpoint=self.settings.endpoint, model=self.settings.model)
        if self.awake:
            self.sim.post(self._first_arrival)

    def _first_arrival(self) -> None:
        # A body without migration (no companion, or a mind in another process) never calls
        # ``on_arrived``: the mind arrives when it starts.
        if self.awake and not self._announced:
            self.on_arrived(self._local_world())

    def detach(self) -> None:
        self.close()

    def close(self) -> None:
        """Stop the worker (idempotent): a request in flight ends, nothing of the conversation is lost."""
        if self._closed:
            return
        self._closed = True
        if self._retry is not None:
            self._retry.cancel()
        if self._worker is not None:
            self._worker.close()

    @property
    def failures(self) -> int:
        """Requests that failed in a row (0 while the endpoint answers)."""
        return self._failures

    @property
    def running(self) -> bool:
        """Whether its worker thread runs (from ``on_start`` until ``close``)."""
        return self._worker is not None and self._worker.alive

    def __enter__(self) -> LlmMind:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def on_sleep(self) -> None:
        if self._retry is not None:
            self._retry.cancel()
            self._retry = None

    def on_wake(self) -> None:
        self._tools_at = None
        ended, self._ended_asleep = self._ended_asleep, {}
        for call in self.conversation.calls:
            if call.result is None and call.action_id in ended:
                self._result(call, ended[call.action_id])
        if self.conversation.close_calls():
            self._continue = self._offered_tools
        if self._sim is not None:
            self.sim.post(self._kick)

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        """Restored in a body (or started): resolve what the move interrupted, re-read the tools and
        tell the model where it is now and what it can do and see."""
        here = self.sim.embodiment
        came_from = self._restored_from
        self._restored_from = ""
        if self._announced and not came_from and self.conversation.body == here:
            self._tools_at = None
            self._kick()
            return
        self._announced = True
        for call in self.conversation.calls:
            if call.result is None:
                self._result(call, self._interrupted(call, came_from or self.conversation.body, here))
        if self.conversation.close_calls():
            self._continue = True
        self.conversation.body = here
        self._arrival_world = world_text(world_model, self.settings.context.world_chars) if world_model else ""
        self._arrival_from = came_from
        self._arrival_at = len(self.conversation.inbox)  # the note goes before what is perceived from now on
        self._pending_arrival = True
        self._tools_at = None
        self._kick()

    def _interrupted(self, call: OpenCall, before: str, here: str) -> str:
        if call.action == MIGRATE_ACTION:
            return (f"succeeded: you migrated from {before} and now live in {here}" if before and before != here else
                    f"interrupted: the companion restarted while migrating; you still live in {here}")
        return (f"interrupted: you left {before} while this ran there; whether it finished is unknown"
                if before and before != here else "interrupted: the companion restarted while this ran; outcome unknown")

    def _announce(self) -> None:
        """The arrival note, once the new body's tools are known."""
        self._pending_arrival = False
        here = self.sim.embodiment
        moved = f" (you came from {self._arrival_from})" if self._arrival_from and self._arrival_from != here else ""
        world = self._arrival_world or "(not known here: you will perceive its changes)"
        self.conversation.perceive(f"You are now in the body {here}{moved}. Your tools here: {tools_text(self.tools)}. "
                                   f"The world model here:\n{world}", at=self._arrival_at)

    def _local_world(self) -> dict[str, Any]:
        store = self.sim.components_by_name().get(keys.WORLD_MODEL)
        return store.tree() if isinstance(store, Store) else {}

    # --- what migrates ------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        return self.conversation.state()

    def restore(self, state: dict[str, Any]) -> None:
        try:
            conversation = Conversation.from_state(state)
        except (ValueError, TypeError) as exc:
            logs.event(log, f"mind {self.name}: its conversation could not be read ({exc}); it starts a new one",
                       level=logging.WARNING, mind=self.name, reason=str(exc))
            return
        for call in self.conversation.calls:  # actions of the conversation this one replaces
            if call.action_id:
                self.pending.pop(call.action_id, None)
        # An answer to a request of the replaced conversation must not be committed to this one.
        conversation.generation = self.conversation.generation + 1
        self.conversation = conversation
        self._ended_asleep = {}
        self._restored_from = conversation.body or "?"
        self._announced = False
        self._continue = False
        self._busy = False

    # --- perceptions --------------------------------------------------------------------------

    def _perceive(self, line: str) -> None:
        if not self.awake:
            return
        self.conversation.perceive(line)
        if not self._kick_posted and self._sim is not None:
            # After the rest of this update: what arrives together is told together.
            self._kick_posted = self.sim.post(self._posted_kick)

    def _posted_kick(self) -> None:
        self._kick_posted = False
        self._kick()

    def on_entity_added(self, name: str, kind: str) -> None:
        self._perceive(f"{kind} {name} appeared")

    def on_entity_removed(self, name: str, kind: str) -> None:
        self._perceive(f"{kind} {name} is gone")

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        self._perceive(f"{entity}.{name} = {value_text(value)}")

    def on_property_removed(self, entity: str, name: str, persistent: bool) -> None:
        self._perceive(f"{entity}.{name} was removed")

    def on_remote_action(self, action: MindAction) -> None:
        who = action.subject or "someone"
        self._perceive(f"{who} did: {action.describe()}")

    def on_message(self, data: dict[str, Any]) -> None:
        text = data.get("text")
        if not isinstance(text, str) or not text.strip():
            raise InvalidArguments('a message to a language-model mind is {"text": "..."}')
        self._perceive(f"message: {text.strip()}")

    # --- the body's tools ---------------------------------------------------------------------

    def refresh_tools(self) -> None:
        """Read the body's abilities again (loop); the tools change when the answer comes."""
        if self._describing:
            return
        self._describing = True
        self.sim.request("embodiment", "describe", Describe(), on_outcome=self._described)

    def _described(self, outcome: Outcome) -> None:
        self._describing = False
        self._tools_at = time.monotonic()
        if outcome.status != "accepted" or not isinstance(outcome.value, dict):
            logs.event(log, f"mind {self.name}: the body's abilities could not be read ({outcome.reason}); keeping "
                            f"{len(self.tools)} tools", level=logging.WARNING, mind=self.name, reason=outcome.reason)
        else:
            self._set_tools(outcome.value)
        if self._pending_arrival:
            self._announce()
        self._kick()

    def _set_tools(self, description: dict[str, Any]) -> None:
        found: dict[str, Ability] = {}
        for data in description.get("abilities") or ():
            try:
                ability = Ability.from_json(data)
            except InvalidArguments:
                continue
            if ability.action == MIGRATE_ACTION and len(ability.parameters) == 1:
                targets = self._migration_targets(description)
                if not targets:
                    continue
                ability = Ability(ability.tool, ability.action, (Parameter(ability.parameters[0].name, tuple(targets)),),
                                  ability.description, ability.patterns)
            found[ability.tool] = ability
        self.abilities = found
        self.tools = [{"type": "function", "function": {"name": a.tool, "description": a.description,
                                                        "parameters": a.input_schema()}} for a in found.values()]

    def _migration_targets(self, description: dict[str, Any]) -> list[str]:
        here = self.sim.embodiment
        alive = [str(n) for n in description.get("alive") or () if n != here]
        accepts = self._policy()
        return sorted(n for n in alive if accepts is None or n in accepts)

    def _policy(self) -> set[str] | None:
        """The embodiments the companion's policy accepts (None: any, or not known from here)."""
        from cmion_mesh.migration.handshake import POLICY_SECTION
        from cmion_mesh.migration.manager import MigrationManager

        manager = self.sim.components_by_name().get("migration")
        identity = manager.identity if isinstance(manager, MigrationManager) else None
        policy = identity.sections.get(POLICY_SECTION) if identity is not None else None
        accepts = policy.get("accepts") if isinstance(policy, dict) else None
        return {str(a) for a in accepts} if isinstance(accepts, list) else None

    # --- turns --------------------------------------------------------------------------------

    def _due(self) -> bool:
        c = self.conversation
        if c.waiting:
            return False
        return bool(c.inbox or c.dropped or self._continue)

    def _kick(self) -> None:
        """Ask the model if there is something to tell it and nothing in the way (loop)."""
        if self._closed or not self.awake or self._busy or self._worker is None or self._retry is not None:
            return
        if not (self._due() or self._pending_arrival):
            return
        age = None if self._tools_at is None else time.monotonic() - self._tools_at
        if age is None or age > TOOLS_TTL or (age > TOOLS_FRESH and self.conversation.inbox):
            self.refresh_tools()
            return
        if self._pending_arrival:  # tools read since the arrival (a failed describe keeps the old ones)
            self._announce()
        if self._trim():
            return
        c = self.conversation
        messages, taken = c.request(self.settings.persona)
        offer = not self.turn.exhausted and bool(self.tools)
        self._busy, self._offered_tools = True, offer
        generation = c.generation
        from cmion_mesh.minds.llm.worker import Job

        self._worker.submit(Job(messages, lambda result: self._post(lambda: self._answered(generation, taken, result)),
                                self.tools if offer else [], self.settings.max_tokens))

    def _post(self, fn: Callable[[], None]) -> None:
        sim = self._sim
        if sim is not None:
            sim.post(fn)

    def _answered(self, generation: int, taken: int, result: Reply | EndpointError) -> None:
        from cmion_mesh.minds.llm.chat import EndpointError

        self._busy = False
        if self._closed or not self.awake or generation != self.conversation.generation:
            return  # the mind moved on (asleep, migrated, restored): the perceptions are still in the inbox
        if isinstance(result, EndpointError):
            self._failed(result)
            return
        self._recovered()
        c = self.conversation
        c.commit(taken, result.message)
        self._continue = False
        calls = c.calls
        if not calls:
            self.turn.new_turn()
        for i, call in enumerate(calls):
            self._call(call, refuse="" if i < MAX_CALLS_PER_ANSWER else f"refused: more than {MAX_CALLS_PER_ANSWER} calls in one answer")
        if c.close_calls():
            self._continue = self._offered_tools
        self._kick()

    def _call(self, call: OpenCall, refuse: str = "") -> None:
        """A tool call becomes an action, or its result at once (refused, bad arguments)."""
        if refuse:
            self._result(call, refuse)
            return
        if not self.turn.take():
            self._result(call, f"refused: the cap of {self.turn.limit} tool calls per turn is reached; "
                               "answer in words, or wait for new perceptions")
            return
        ability = self.abilities.get(call.tool)
        if ability is None:
            known = ", ".join(self.abilities) or "none"
            self._result(call, f"refused: this body ({self.sim.embodiment}) has no tool {call.tool[:64]!r}; its tools: {known}")
            return
        try:
            arguments = msgspec.json.decode(call.arguments.encode() or b"{}") if call.arguments.strip() else {}
            if not isinstance(arguments, dict):
                raise InvalidArguments(f"{call.tool}: the arguments must be a JSON object")
            parameters = ability.positional(arguments)
        except msgspec.DecodeError as exc:
            self._result(call, f"bad arguments: not JSON ({exc})")
            return
        except InvalidArguments as exc:
            self._result(call, f"bad arguments: {exc}")
            return
        call.action = ability.action
        try:
            call.action_id = self.act(ability.action, parameters)
        except MeshError as exc:
            self._result(call, f"failed: {exc}")

    def _result(self, call: OpenCall, text: str) -> None:
        self.conversation.resolve(call.id, text)
        self.raise_event("LlmToolResult", {"tool": call.tool, "action_id": call.action_id, "result": text})

    def _ended(self, report: ActionReport, text: str) -> None:
        if not self.awake:
            # Asleep: the conversation stays as it is (if the companion left, it is what was packed).
            # Kept for a wake on this body (``on_wake``); a conversation arriving drops it.
            self._ended_asleep[report.action_id] = text
            return
        call = self.conversation.call_for_action(report.action_id)
        if call is None:
            return
        self._result(call, text)
        if self.conversation.close_calls():
            self._continue = self._offered_tools
            self._kick()

    def on_action_succeeded(self, report: ActionReport) -> None:
        self._ended(report, "succeeded" + (f": {report.reason}" if report.reason else ""))

    def on_action_failed(self, report: ActionReport) -> None:
        self._ended(report, f"failed: {report.reason or 'no reason given'}")

    def on_action_cancelled(self, report: ActionReport) -> None:
        self._ended(report, f"cancelled: {report.reason or 'no reason given'}")

    # --- the window's bound -------------------------------------------------------------------

    def _trim(self) -> bool:
        """Keep the window bounded: ask the model for a summary of the oldest messages (True: a
        request went out instead of a turn)."""
        ctx = self.settings.context
        c = self.conversation
        cut = c.overflow(ctx.window_messages, ctx.window_chars)
        if not cut:
            return False
        if self._failures and (len(c.messages) > 2 * ctx.window_messages or c.size() > 2 * ctx.window_chars):
            c.drop_oldest(cut)
            return False
        assert self._worker is not None
        from cmion_mesh.minds.llm.worker import Job

        self._busy = True
        generation = c.generation
        self._worker.submit(Job(c.summary_request(cut, ctx.summary_words),
                                lambda result: self._post(lambda: self._summarised(generation, cut, result)),
                                [], max(64, ctx.summary_words * 2)))
        return True

    def _summarised(self, generation: int, cut: int, result: Reply | EndpointError) -> None:
        from cmion_mesh.minds.llm.chat import EndpointError

        self._busy = False
        if self._closed or not self.awake or generation != self.conversation.generation:
            return
        if isinstance(result, EndpointError):
            self._failed(result)
            return
        self._recovered()
        text = result.message.get("content")
        self.conversation.apply_summary(cut, text if isinstance(text, str) else "", self.settings.context.window_chars // 4)
        self._kick()

    # --- failures -----------------------------------------------------------------------------

    def _failed(self, error: EndpointError) -> None:
        self._failures += 1
        delay = backoff(self._failures, self.settings.limits, error.retry_after)
        fields = {"mind": self.name, "endpoint": self.settings.endpoint, "reason": error.reason, "retry_in": delay,
                  "failures": self._failures}
        if not self._down:
            self._down = True
            self.raise_event("LlmEndpointDown", fields)
        logs.event(log, f"mind {self.name}: the language-model endpoint {self.settings.endpoint} failed ({error.reason}); "
                        f"the companion keeps its body and the turn is asked again in {delay:g} s",
                   level=logging.WARNING, **fields)
        self._retry = self.sim.call_later(delay, self._retry_due)

    def _retry_due(self) -> None:
        self._retry = None
        self._kick()

    def _recovered(self) -> None:
        if self._down:
            self._down = False
            logs.event(log, f"mind {self.name}: the language-model endpoint {self.settings.endpoint} answers again "
                            f"after {self._failures} failures", mind=self.name, endpoint=self.settings.endpoint,
                       failures=self._failures)
            self.raise_event("LlmEndpointUp", {"mind": self.name, "endpoint": self.settings.endpoint, "failures": self._failures})
        self._failures = 0

    def _budget_wait(self, seconds: float) -> None:
        # Worker thread: the event is raised on the loop.
        self._post(lambda: self.raise_event("LlmBudgetWait", {"mind": self.name, "seconds": round(seconds, 3)}))
