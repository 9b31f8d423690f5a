"""MCP tool call -> outcome over stdio, beside ``MeshClient.act`` of the same action in the same run.

Processes (all on loopback): a daemon ``cmion-mesh up`` of the bench embodiment (rules ``One`` ->
one ``Instant`` step, ``Multi`` -> four; competencies that succeed at once) with the companion
living there; ``cmion-mesh mcp bench --allow-actions`` spawned by the MCP SDK's own client over
stdio (``mode="legacy"``: the initialize handshake, as desktop clients speak it); the measuring
process, which holds that client and a ``MeshClient``.

Metrics:

* ``base_act_one`` / ``base_act_multi``: ``MeshClient.act`` from the measuring process (the
  path the MCP server takes, minus the protocol): the baseline.
* ``mcp_ping_stdio``: an MCP ``ping`` answered by the server, for context: what the protocol
  and the SDK cost by themselves on every call.
* ``mcp_one_stdio`` / ``mcp_multi_stdio``: ``tools/call`` of the tool ``One`` (``Multi``) ->
  its ``CallToolResult``, timed in the client's event loop (``time.perf_counter`` around
  ``call_tool``): JSON-RPC over the pipes both ways, the server's worker-thread hop, the action.

The ratios are against the ``MeshClient.act`` of the same plan (context; the issue sets no bound).
"""

from __future__ import annotations

import os
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from bench.actions import COMPANION, EMBODIMENT, ClientAct
from bench.daemons import Node, up_with_client
from bench.harness import Probe, interleaved
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import cli_argv, unique_mesh

LABELS = {
    "mcp_ping_stdio": "MCP ping -> answer, over stdio (the protocol's own round trip: context)",
    "base_act_one": "MeshClient.act One -> succeeded, other process (baseline)",
    "mcp_one_stdio": "MCP tools/call One -> result, over stdio",
    "base_act_multi": "MeshClient.act Multi -> succeeded, other process (baseline)",
    "mcp_multi_stdio": "MCP tools/call Multi -> result, over stdio",
}
PAIRS = {"mcp_one_stdio": "base_act_one", "mcp_multi_stdio": "base_act_multi"}


def log(text: str) -> None:
    print(f"  [mcp] {text}", flush=True)


class McpCall:
    """``tools/call`` of one tool (``tool`` empty: a ``ping``) through the SDK's client, timed inside
    its event loop."""

    def __init__(self, portal: Any, client: Any, tool: str, metric: str) -> None:
        self.portal = portal
        self.client = client
        self.tool = tool
        self.metric = metric

    async def _timed(self, count: int) -> list[float]:
        out = []
        for _ in range(count):
            t0 = time.perf_counter()
            if self.tool:
                result = await self.client.call_tool(self.tool, {})
            else:
                await self.client.send_ping()
            out.append(time.perf_counter() - t0)
            if self.tool and result.is_error:
                raise MeshError(f"{self.tool}: {result.content}")
        return out

    def contact(self) -> None:
        self.portal.call(self._timed, 1)

    def measure(self, count: int) -> list[float]:
        samples: list[float] = self.portal.call(self._timed, count)
        return samples


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    from anyio.from_thread import start_blocking_portal
    from mcp import Client, StdioServerParameters

    mesh = unique_mesh("bench")
    started = time.monotonic()
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-mcp-")))
        node = Node(EMBODIMENT, mesh, tmp / EMBODIMENT, companion=COMPANION)
        client = up_with_client(stack, node, log)

        argv = cli_argv("mcp", COMPANION, "--allow-actions", "--mesh", mesh, "--no-multicast", "--connect", node.listen)
        portal = stack.enter_context(start_blocking_portal())
        params = StdioServerParameters(command=argv[0], args=argv[1:], env=dict(os.environ))
        session = stack.enter_context(portal.wrap_async_context_manager(Client(params, mode="legacy")))
        log(f"daemon and MCP server up after {time.monotonic() - started:.2f} s (mesh {mesh})")
        probes: list[Probe] = [McpCall(portal, session, "", "mcp_ping_stdio"),
                               ClientAct(client, "One", "base_act_one"), McpCall(portal, session, "One", "mcp_one_stdio"),
                               ClientAct(client, "Multi", "base_act_multi"), McpCall(portal, session, "Multi", "mcp_multi_stdio")]
        pooled = interleaved(probes, samples=options.samples, warmup=options.warmup, rounds=options.rounds,
                             rewarm=options.rewarm, log=log)
        log(f"measured in {time.monotonic() - started:.1f} s")
    rows = [Row(m, LABELS[m], summarize(pooled[m]), extra={"rounds": options.rounds}) for m in LABELS]
    compare(rows, PAIRS, None)
    return rows
