"""The language-model mind's pure parts: the budget, the conversation (window, summary, inbox,
tool calls, what migrates), the settings, and how a streamed answer is put together."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import msgspec
import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import ActionReport, Event, MindMessage
from cmion_mesh.minds.llm.budget import Budget, Limits, TurnCount, backoff, estimate_tokens
from cmion_mesh.minds.llm.chat import EndpointError, _assemble, _reply
from cmion_mesh.minds.llm.conversation import MAX_INBOX, Conversation, render, tools_text, world_text
from cmion_mesh.minds.llm.mind import LlmMind
from cmion_mesh.minds.llm.settings import ENV_BASE_URL, ENV_KEY, ENV_MODEL, OPENAI_BASE_URL, load_settings, shown_url
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

ROBOT_RULES = embodiment_dir("robot") / "CompetencyManagerRules.xml"


@pytest.fixture(autouse=True)
def no_llm_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in (ENV_BASE_URL, ENV_MODEL, ENV_KEY, OPENAI_BASE_URL, "OPENAI_API_KEY"):
        monkeypatch.delenv(name, raising=False)


# --- budget -----------------------------------------------------------------------------------


def test_requests_per_minute_make_the_next_request_wait_for_the_oldest_to_leave_the_window() -> None:
    budget = Budget(Limits(requests_per_minute=3, tokens_per_minute=10**9))
    for t in (0.0, 1.0, 2.0):
        assert budget.wait(t, 10) == 0
        budget.spend(t, 10)
    assert budget.wait(5.0, 10) == pytest.approx(55.0)  # the one sent at 0 leaves at 60
    assert budget.wait(60.0, 10) == 0 and budget.requests(60.0) == 2


def test_tokens_per_minute_count_what_the_endpoint_reported() -> None:
    budget = Budget(Limits(requests_per_minute=100, tokens_per_minute=1000))
    first = budget.spend(0.0, 900)  # estimated
    assert budget.wait(1.0, 200) == pytest.approx(59.0)
    budget.settle(first, 300)  # the endpoint said 300
    assert budget.wait(1.0, 200) == 0 and budget.tokens(1.0) == 300
    big = Budget(Limits(requests_per_minute=100, tokens_per_minute=100))
    assert big.wait(0.0, 5000) == 0, "a request larger than the budget goes into an empty window"
    big.spend(0.0, 5000)
    assert big.wait(1.0, 10) == pytest.approx(59.0)


def test_backoff_doubles_up_to_the_cap_and_honours_retry_after() -> None:
    limits = Limits(backoff_first=0.5, backoff_cap=4.0)
    assert [backoff(n, limits) for n in (1, 2, 3, 4, 5, 100)] == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    assert backoff(1, limits, retry_after=3.0) == 3.0 and backoff(1, limits, retry_after=30.0) == 4.0
    assert Limits(requests_per_minute=0).problem() and Limits(backoff_first=5, backoff_cap=1).problem()
    assert estimate_tokens(4000) == 1000


def test_the_cap_of_tool_calls_counts_a_turn() -> None:
    turn = TurnCount(2)
    assert turn.take() and turn.take() and not turn.take() and turn.exhausted
    turn.new_turn()
    assert not turn.exhausted and turn.take()


# --- conversation -----------------------------------------------------------------------------


def assistant(*calls: tuple[str, str, str], content: str | None = None) -> dict[str, Any]:
    message: dict[str, Any] = {"role": "assistant", "content": content}
    if calls:
        message["tool_calls"] = [{"id": i, "type": "function", "function": {"name": n, "arguments": a}} for i, n, a in calls]
    return message


def test_perceptions_wait_in_the_inbox_until_an_answer_is_committed() -> None:
    c = Conversation()
    c.perceive("Visitor appeared")
    messages, taken = c.request("persona")
    assert messages == [{"role": "system", "content": "persona"}, {"role": "user", "content": "Visitor appeared"}]
    c.perceive("Visitor.present = true")  # while the request is out
    c.commit(taken, assistant(content="hello"))
    assert c.inbox == ["Visitor.present = true"], "what came meanwhile waits for the next turn"
    assert c.messages == [{"role": "user", "content": "Visitor appeared"}, {"role": "assistant", "content": "hello"}]
    c.summary = "I met Ada."
    assert c.request("persona")[0][0]["content"] == "persona\n\nWhat happened before (your own summary):\nI met Ada."


def test_tool_results_join_the_window_in_the_order_of_the_calls_once_all_are_in() -> None:
    c = Conversation()
    c.commit(0, assistant(("a", "GoTo", '{"location": "Kitchen"}'), ("b", "Express", "{}")))
    assert c.waiting and not c.close_calls()
    c.resolve("b", "succeeded")
    assert not c.close_calls()
    assert not c.resolve("zzz", "x")
    c.resolve("a", "failed: blocked")
    assert c.close_calls() and not c.waiting
    assert c.messages[-2:] == [{"role": "tool", "tool_call_id": "a", "content": "failed: blocked"},
                               {"role": "tool", "tool_call_id": "b", "content": "succeeded"}]


def test_the_window_is_cut_where_a_user_message_starts_and_the_summary_takes_its_place() -> None:
    c = Conversation()
    c.perceive("p0")
    c.commit(1, assistant(("c1", "Express", "{}")))
    c.resolve("c1", "succeeded")
    c.close_calls()
    c.commit(0, assistant(content="a0"))
    for i in range(1, 4):
        c.perceive(f"p{i}")
        c.commit(1, assistant(content=f"a{i}"))
    assert c.overflow(100, 10**6) == 0
    assert c.overflow(10, 10**6) == 0
    cut = c.overflow(8, 10**6)  # over: down to half, 4, from a user message
    assert cut == 6 and c.messages[cut] == {"role": "user", "content": "p2"}
    request = c.summary_request(cut, 50)
    assert "at most 50 words" in request[0]["content"] and "I called: Express({})" in request[1]["content"]
    kept = c.messages[cut:]
    c.apply_summary(cut, "  I nodded.  ", 1000)
    assert c.summary == "I nodded." and c.messages == kept and c.generation == 1
    c.drop_oldest(2)
    assert c.messages == kept[2:] and "2 older messages were dropped" in c.summary


def test_a_long_run_of_tool_calls_is_cut_before_an_assistant_message_never_before_a_result() -> None:
    c = Conversation()
    c.perceive("go")
    for i in range(5):
        c.commit(1 if i == 0 else 0, assistant((f"c{i}", "One", "{}")))
        c.resolve(f"c{i}", "succeeded")
        c.close_calls()
    assert [m["role"] for m in c.messages] == ["user"] + ["assistant", "tool"] * 5
    assert c.overflow(8, 10**6) == 7 and c.messages[7]["role"] == "assistant"
    assert c.overflow(1, 10**6) == 9, "nothing fits: the last exchange is kept whole"


def test_the_inbox_is_bounded_and_says_how_much_it_dropped() -> None:
    c = Conversation()
    for i in range(MAX_INBOX + 5):
        c.perceive(f"line {i}")
    c.perceive("x" * 10_000)
    assert len(c.inbox) == MAX_INBOX and len(c.inbox[-1]) < 1000
    messages, taken = c.request("p")
    assert messages[-1]["content"].startswith("(6 earlier perceptions were not kept)\nline 6")
    c.commit(taken, assistant(content="ok"))
    assert c.inbox == [] and c.dropped == 0
    c.perceive("b")
    c.perceive("arrival", at=0)
    assert c.inbox == ["arrival", "b"]


def test_the_state_round_trips_exactly_and_refuses_what_is_not_one() -> None:
    c = Conversation(summary="s", body="robot")
    c.perceive("p")
    c.commit(1, assistant(("x", "Migrate", '{"target": "screen"}')))
    c.calls[0].action, c.calls[0].action_id = "Migrate", "mind-1"
    c.perceive("later")
    state = c.state()
    again = Conversation.from_state(msgspec.msgpack.decode(msgspec.msgpack.encode(state)))
    assert msgspec.msgpack.encode(again.state()) == msgspec.msgpack.encode(state)
    assert again.calls[0].action == "Migrate" and again.calls[0].result is None
    state["messages"].append({"role": "user", "content": "changed"})
    assert c.messages[-1]["role"] == "assistant", "the state is a copy"
    for bad in ({"version": 2}, {"version": 1, "messages": "x", "inbox": []}, {"version": 1, "messages": [], "inbox": [3]},
                {"version": 1, "messages": [], "inbox": [], "calls": ["x"]}):
        with pytest.raises(ValueError):
            Conversation.from_state(bad)


def test_world_and_tools_as_text() -> None:
    tree = {"kind": "root", "properties": {}, "children": {
        "Self": {"kind": "agent", "properties": {"location": {"value": "Office", "persistent": False}}, "children": {}},
        "Kitchen": {"kind": "object", "properties": {"isLocation": {"value": True, "persistent": False}}, "children": {}}}}
    assert world_text(tree, 1000) == "Self (agent): location=Office\nKitchen (object): isLocation=true"
    assert world_text(tree, 40) == "Self (agent): location=Office\n... and 1 more entities"
    tools = [{"type": "function", "function": {"name": "GoTo", "parameters": {"properties": {"location": {}}}}}]
    assert tools_text(tools) == "GoTo(location)" and tools_text([]) == "(none)"
    assert render({"role": "tool", "content": "succeeded"}) == "Result: succeeded"


# --- settings ---------------------------------------------------------------------------------


def test_settings_come_from_the_file_with_the_environment_over_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "llm.toml"
    path.write_text('[endpoint]\nbase_url = "http://127.0.0.1:8080/v1"\nmodel = "m"\ntimeout = 5\n[budget]\ntool_calls_per_turn = 2\n')
    s = load_settings(path)
    assert (s.base_url, s.model, s.timeout, s.limits.tool_calls_per_turn) == ("http://127.0.0.1:8080/v1", "m", 5.0, 2)
    monkeypatch.setenv(OPENAI_BASE_URL, "http://127.0.0.1:1/v1")
    assert load_settings(path).base_url == "http://127.0.0.1:8080/v1", "the file wins over OPENAI_BASE_URL"
    monkeypatch.setenv(ENV_BASE_URL, "http://user:pw@127.0.0.1:9/v1?k=1")
    monkeypatch.setenv(ENV_MODEL, "other")
    monkeypatch.setenv(ENV_KEY, "sk-secret")
    s = load_settings(path)
    assert s.model == "other" and s.endpoint == "http://127.0.0.1:9/v1"
    assert "sk-secret" not in repr(s), "the key is not a setting"
    assert shown_url("http://[::1") == "<a malformed URL>"


def test_bad_settings_name_the_file_line_and_key(tmp_path: Path) -> None:
    path = tmp_path / "llm.toml"
    path.write_text('[endpoint]\nmodel = "m"\ntimout = 5\nstream = "yes"\n[budget]\nrequests_per_minute = 0\n[other]\nx = 1\n')
    with pytest.raises(ConfigError) as caught:
        load_settings(path)
    text = str(caught.value)
    assert str(path) in text and "line 3: [endpoint] unknown key 'timout'" in text
    assert "line 4: [endpoint] stream must be true or false" in text
    assert "line 6: [budget] requests_per_minute must be an integer from 1" in text
    assert "unknown table [other]" in text
    with pytest.raises(ConfigError, match="no model"):
        load_settings(None)
    path.write_text('[endpoint]\nmodel = "m"\nbase_url = "file:///etc/passwd"\n')
    with pytest.raises(ConfigError, match="not an http"):
        load_settings(path)


# --- a streamed answer --------------------------------------------------------------------------


def chunk(content: str | None = None, calls: list[dict[str, Any]] | None = None, usage: int | None = None) -> Any:
    deltas = [SimpleNamespace(index=c["index"], id=c.get("id"),
                              function=SimpleNamespace(name=c.get("name"), arguments=c.get("arguments")))
              for c in calls or ()]
    choices = [] if usage is not None else [SimpleNamespace(delta=SimpleNamespace(content=content, tool_calls=deltas))]
    return SimpleNamespace(choices=choices, usage=SimpleNamespace(total_tokens=usage) if usage is not None else None)


def test_a_streamed_answer_is_put_together_piece_by_piece() -> None:
    chunks = [chunk(""), chunk("Hel"), chunk("lo"), chunk(calls=[{"index": 0, "id": "c1", "name": "GoTo", "arguments": ""}]),
              chunk(calls=[{"index": 0, "arguments": '{"loca'}]), chunk(calls=[{"index": 1, "id": "c2", "name": "Express"}]),
              chunk(calls=[{"index": 0, "arguments": 'tion": "Kitchen"}'}]), chunk(usage=42)]
    async def stream() -> AsyncIterator[Any]:
        for c in chunks:
            yield c

    reply = asyncio.run(_assemble(stream()))
    assert reply.tokens == 42
    assert reply.message == {"role": "assistant", "content": "Hello", "tool_calls": [
        {"id": "c1", "type": "function", "function": {"name": "GoTo", "arguments": '{"location": "Kitchen"}'}},
        {"id": "c2", "type": "function", "function": {"name": "Express", "arguments": ""}}]}


def test_a_whole_answer_is_decoded_by_its_schema_and_anything_else_is_an_endpoint_error() -> None:
    body = {"id": "x", "object": "chat.completion", "created": 0, "model": "m", "choices": [{"index": 0, "finish_reason": "tool_calls",
            "message": {"role": "assistant", "content": None, "refusal": None, "tool_calls": [
                {"id": "c1", "type": "function", "function": {"name": "GoTo", "arguments": "{}"}},
                {"id": "c2", "type": "custom", "custom": {"name": "x", "input": "y"}}]}}],
            "usage": {"prompt_tokens": 1, "completion_tokens": 2, "total_tokens": 3}}
    reply = _reply(msgspec.json.encode(body))
    assert reply.tokens == 3
    assert reply.message == {"role": "assistant", "content": None, "tool_calls": [
        {"id": "c1", "type": "function", "function": {"name": "GoTo", "arguments": "{}"}}]}
    for bad in (b"<html>", b'{"choices": "no"}', b'{"choices": []}'):
        with pytest.raises(EndpointError):
            _reply(bad)


# --- the mind in a body on the in-memory transport (its endpoint unreachable) -----------------------


def unreachable_mind(tmp_path: Path, settings: str) -> LlmMind:
    """A mind whose endpoint nobody answers (port 1 on loopback); ``settings`` follow its endpoint's
    base_url and model in its settings file."""
    path = tmp_path / "llm.toml"
    path.write_text('[endpoint]\nbase_url = "http://127.0.0.1:1/v1"\nmodel = "m"\n' + settings)
    return LlmMind("mind", str(path))


@pytest.mark.mesh  # the client library runs `uname -p` once (its platform headers): a child process
def test_an_unreachable_endpoint_is_one_event_the_body_keeps_the_mind_and_close_stops_the_worker(
        tmp_path: Path, network: MemoryNetwork, mesh: str) -> None:
    mind = unreachable_mind(tmp_path, "timeout = 2\n[budget]\nbackoff_first = 0.05\nbackoff_cap = 0.2\n")
    events: list[Event] = []
    with MemoryTransport(network, "robot") as t, MemoryTransport(network, "watcher") as w:
        client = MeshClient(w, mesh)
        client.events(events.append, embodiment="robot", component="mind")
        body = Embodiment("robot", mesh=mesh, transport=t, rules=ROBOT_RULES, components=[mind]).start()
        try:
            wait_for(lambda: sum(e.name == "LlmEndpointDown" for e in events) == 1 and mind.failures >= 3, 10,
                     "the endpoint failed three times, one event")
            assert "cannot reach it" in str(events[0].data) and events[0].data["endpoint"] == "http://127.0.0.1:1/v1"  # type: ignore[index]
            inbox = mind.conversation.inbox
            assert inbox and inbox[0].startswith("You are now in the body robot. Your tools here: Say(speechAct, addressee)")
            assert mind.conversation.messages == [], "nothing committed, nothing lost: the arrival waits in the inbox"
            client.request("robot", "mind", "message", MindMessage({"text": "hello"}))
            wait_for(lambda: mind.conversation.inbox[-1:] == ["message: hello"], 5, "the message joins the inbox")
            assert sum(e.name == "LlmEndpointDown" for e in events) == 1
        finally:
            body.close()
    assert not mind.running
    mind.close()  # again: nothing happens


@pytest.mark.mesh  # as above: the client library's `uname -p`
def test_migrate_is_offered_to_the_embodiments_alive_that_the_companions_policy_accepts(
        tmp_path: Path, network: MemoryNetwork, mesh: str) -> None:
    mind = unreachable_mind(tmp_path, "[budget]\nbackoff_first = 1\n")
    with MemoryTransport(network, "w") as w:
        client = MeshClient(w, mesh)
        bodies = [Embodiment(name, mesh=mesh, transport=MemoryTransport(network, name), state_dir=tmp_path / name, rules=ROBOT_RULES,
                             companion="spirit" if name == "robot" else None, components=[mind] if name == "robot" else [])
                  for name in ("robot", "screen", "phone")]
        try:
            for body in bodies:
                body.start()

            def targets() -> list[str] | None:
                bodies[0].sim.call(mind.refresh_tools)
                tool = next((t for t in mind.tools if t["function"]["name"] == "Migrate"), None)
                return tool["function"]["parameters"]["properties"]["target"]["enum"] if tool else None

            wait_for(lambda: targets() == ["phone", "screen"], 10, "Migrate offered to both peers")
            client.set_policy("spirit", ["phone"])
            wait_for(lambda: targets() == ["phone"], 10, "the policy leaves the phone only")
            client.set_policy("spirit", ["robot"])
            wait_for(lambda: targets() is None, 10, "no body it accepts: no Migrate tool")
        finally:
            for body in bodies:
                body.close()
                body.transport.close()


@pytest.mark.mesh  # as above: the client library's `uname -p`
def test_an_action_that_ends_while_the_mind_sleeps_leaves_the_conversation_as_it_was_until_it_wakes(
        tmp_path: Path, network: MemoryNetwork, mesh: str) -> None:
    mind = unreachable_mind(tmp_path, "[budget]\nbackoff_first = 60\n")
    seen: dict[str, Any] = {}
    with MemoryTransport(network, "robot") as t, Embodiment("robot", mesh=mesh, transport=t, rules=ROBOT_RULES,
                                                            components=[mind]) as body:
        def play() -> None:
            mind.conversation.commit(0, assistant(("c1", "Express", '{"animation": "nod"}')))
            mind.conversation.calls[0].action_id = "a1"
            mind.sleep()
            mind.on_action_succeeded(ActionReport("a1", "Express", ["nod"], status="succeeded"))
            seen["asleep"] = mind.conversation.state()
            mind.wake()
            seen["awake"] = mind.conversation.state()

        body.sim.call(play)
        wait_for(lambda: "awake" in seen, 5, "played on the loop")
    assert seen["asleep"]["calls"][0]["result"] is None, "asleep: the state stays what a migration would have packed"
    assert seen["awake"]["calls"] == [] and seen["awake"]["messages"][-1] == {"role": "tool", "tool_call_id": "c1",
                                                                              "content": "succeeded"}


def test_without_the_client_library_the_configuration_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util

    from cmion_mesh.classes import construct
    from cmion_mesh.ion import Component

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "openai" else real(name, *a))
    with pytest.raises(ConfigError, match=r"robot.xml:3: .*needs the openai package: pip install 'cmion-mesh\[llm\]'"):
        construct("cmion_mesh.minds.llm.mind:LlmMind", Component, ["mind", str(embodiment_dir("llm.toml"))], path="robot.xml", line=3)
