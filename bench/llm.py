"""A language-model mind's tool call -> the action's result back at the model, beside ``MeshClient.act``.

Processes (all on loopback): a daemon ``cmion-mesh up`` of the bench embodiment (rules ``One`` ->
one ``Instant`` step) whose mind is ``cmion_mesh.minds.llm.mind:LlmMind`` (component ``llm``), the
companion living there so it is awake; the chat-completions stand-in of the tests
(``tests/helpers/chat_standin.py``, another process) answering at once, over HTTP; the measuring
process.

Metrics:

* ``llm_tool_one``: measured in the stand-in, on its own clock: from the moment it has written an
  answer holding a tool call ``One`` to the moment the request carrying that call's result has
  arrived. That is the mind's whole path: the client library reading the answer, the loop turning
  the call into ``act``, the plan, the result, the next request built and sent. The mind loops:
  each result brings the next call, with the default context window (a summary request every
  twenty or so calls, as a real model's would be: it is in the p99).
* ``llm_act_client``: ``MeshClient.act One`` from the measuring process to the same daemon, in the
  same run (the issue's target: the tool call within 1 ms of it; ``extra["minus_act_ms"]``).
"""

from __future__ import annotations

import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from bench import actions
from bench.daemons import LIBRARY, RULES, Node, up_with_client
from bench.harness import interleaved
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import MindMessage
from cmion_mesh.procs import unique_mesh
from cmion_mesh.testing.wait import wait_for
from tests.helpers.chat_standin import StandIn

EMBODIMENT = "bench-llm"
COMPANION = "bench"
MIND = "llm"
LABELS = {
    "llm_act_client": "MeshClient.act One -> succeeded, other process (same run)",
    "llm_tool_one": "LLM mind: tool call One received -> its result back at the model (stand-in's clock)",
}
SETTINGS = """
[endpoint]
model = "standin"
timeout = 30
[budget]
requests_per_minute = 1000000
tokens_per_minute = 1000000000000
tool_calls_per_turn = 1000000
"""


def log(text: str) -> None:
    print(f"  [llm] {text}", flush=True)


def write_config(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    settings = folder / "llm.toml"
    settings.write_text(SETTINGS)
    config = folder / "ArchitectureConfiguration.xml"
    mind = f'<ArchitectureComponent ClassName="cmion_mesh.minds.llm.mind:LlmMind" ConstructorParameters="{MIND},{settings}"/>'
    config.write_text(f'<ArchitectureConfiguration Embodiment="{EMBODIMENT}" CompetencyManagerRulesFile="{RULES}"'
                      f' CompetencyLibraryConfigurationFile="{LIBRARY}">\n  {mind}\n</ArchitectureConfiguration>\n')
    return config


class ClientAct(actions.ClientAct):
    """``MeshClient.act`` as the actions benchmark times it, to this benchmark's embodiment."""

    def once(self) -> None:
        report = self.client.act(EMBODIMENT, self.action, timeout=10.0)
        if report.status != "succeeded":
            raise MeshError(f"{self.action}: {report.status}: {report.reason}")


class ToolCalls:
    """One chunk: the stand-in scripted with ``count`` tool calls ``One`` then words; a message to
    the mind starts the turn; the samples are read from the stand-in's times."""

    metric = "llm_tool_one"

    def __init__(self, client: MeshClient, standin: StandIn) -> None:
        self.client, self.standin = client, standin

    def contact(self) -> None:
        self.measure(1)

    def measure(self, count: int) -> list[float]:
        since = int(self.standin.timings(0)["requests"])
        one = {"tool_calls": [{"name": "One", "arguments": {}}]}
        self.standin.script(*([one] * count), {"content": "done"})
        outcome = self.client.request(EMBODIMENT, MIND, "message", MindMessage({"text": "go"}))
        if outcome.status != "accepted":
            raise MeshError(f"the mind refused the message: {outcome.reason}")
        done = wait_for(lambda: (t := self.standin.timings(since))["steps_left"] == 0 and t, 30.0 + 0.05 * count,
                        "the stand-in's script played out", interval=0.05)
        return samples(done["timings"])


def samples(timings: list[dict[str, Any]]) -> list[float]:
    """For each answer holding a call: until the request answering that call arrived."""
    answered_at = {call: t["answered"] for t in timings for call in t["calls"] if t["answered"] is not None}
    out = []
    for t in timings:
        for call in t["answers"]:
            if call in answered_at:
                out.append(t["received"] - answered_at.pop(call))
    return out


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    mesh = unique_mesh("bench")
    started = time.monotonic()
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-llm-")))
        standin = stack.enter_context(StandIn())
        node = Node(EMBODIMENT, mesh, tmp / EMBODIMENT, companion=COMPANION, architecture=str(write_config(tmp / "config")),
                    extra_env={"CMION_MESH_LLM_BASE_URL": standin.base_url})
        client = up_with_client(stack, node, log)
        wait_for(lambda: standin.timings(0)["requests"] >= 1, 30.0, "the mind's first turn (its arrival)")
        log(f"daemon and stand-in up after {time.monotonic() - started:.2f} s (mesh {mesh})")
        pooled = interleaved([ClientAct(client, "One", "llm_act_client"), ToolCalls(client, standin)], samples=options.samples,
                             warmup=options.warmup, rounds=options.rounds, rewarm=options.rewarm, log=log)
        log(f"measured in {time.monotonic() - started:.1f} s")
    rows = [Row(m, LABELS[m], summarize(pooled[m]), extra={"rounds": options.rounds}) for m in LABELS]
    compare(rows, {"llm_tool_one": "llm_act_client"}, None)
    act, tool = rows[0].summary, rows[1].summary
    rows[1].extra.update({"minus_act_ms": tool.median_ms - act.median_ms, "p99_minus_act_ms": tool.p99_ms - act.p99_ms,
                          "target": "median within 1 ms of MeshClient.act (issue 29)",
                          "meets_1ms": tool.median_ms - act.median_ms <= 1.0})
    log(f"tool call -> result: median {tool.median_ms:.3f} ms, p99 {tool.p99_ms:.3f} ms; MeshClient.act: median "
        f"{act.median_ms:.3f} ms, p99 {act.p99_ms:.3f} ms; difference of medians {tool.median_ms - act.median_ms:+.3f} ms "
        f"({'within' if tool.median_ms - act.median_ms <= 1.0 else 'NOT within'} 1 ms)")
    return rows
