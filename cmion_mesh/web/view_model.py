"""What the live view (``web/view.py``) knows of the mesh, and what waits for each page: plain
state, touched only on the web server's event loop, with no I/O (the server side feeds it).

* ``Model``: the embodiments (alive, described, greyed once gone), custody of companions,
  migrations put together from both sides' events, plans and their steps, the recent events.
* ``Page``: one connected page's queues; ``TreeWatch``: an embodiment's blackboard and world
  model, followed for the pages that selected it.
* ``event_json``, ``entry_json``: events and store entries as the pages read them.

Times: what the view learns is stamped with when it learnt it (``received``, the view's clock; a
recording played through the view: the recorder's), so that migrations, events and frames lie
on one time axis, the timeline's.

Memory is bounded: the model keeps the last ``RING`` events, ``MIGRATIONS_KEPT`` migrations,
``PLANS_KEPT`` finished plans and ``FRAMES_KEPT`` frames; each page has at most ``PAGE_EVENTS`` stream events waiting for it
(a slow page loses the oldest ones, and is told how many) and at most ``PAGE_CHANGES`` state
changes (beyond that they are dropped and the page gets one fresh snapshot instead). A slow page
therefore never holds up the mesh, the other pages, or the view's memory.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import msgspec

from cmion_mesh import keys
from cmion_mesh.messages import Container, Event, Property
from cmion_mesh.transport.base import Closeable

#: Recent events a page is given when it connects.
RING = 500
#: Stream events waiting for one page; beyond, the oldest are dropped (and counted for the page).
PAGE_EVENTS = 1000
#: State changes waiting for one page; beyond, the page is sent one fresh snapshot instead.
PAGE_CHANGES = 5000
MIGRATIONS_KEPT = 50
PLANS_KEPT = 50
#: Pictures of the mesh kept for the timeline (one each time who is alive, who lives where or
#: who holds custody changed): a page scrubbing back draws the mesh from the last one before.
FRAMES_KEPT = 2000
#: Embodiments that left, still shown (greyed) until this many more have left.
GONE_KEPT = 50
#: Entries of one store kept for the pages; beyond, new entries are left out (and the page says so).
TREE_LIMIT = 20_000
#: Event data larger than this (JSON bytes) is shown as a preview.
DATA_PREVIEW = 4096
#: A handshake's steps in the order they happen (``MigrationStep`` names the durable records).
STEP_ORDER = {step: i for i, step in enumerate(("starting", "prepared", "incoming", "handed", "active", "released"))}
PLAN_ENDS = {"PlanSucceeded": "succeeded", "PlanFailed": "failed", "PlanCancelled": "cancelled"}
STEP_STATES = {"StepStarted": "running", "StepSucceeded": "succeeded", "StepFailed": "failed", "StepCancelled": "cancelled",
               "StepWaiting": "waiting"}
STORES = (keys.BLACKBOARD, keys.WORLD_MODEL)


class Playback(Protocol):
    """What plays a recording through the view (``tools/view_player.py``): the pages' controls."""

    def status(self) -> dict[str, Any]: ...

    def control(self, message: dict[str, Any]) -> str | None:
        """Pause, play, speed or seek; an error for the page, or None."""
        ...

    def page_opened(self) -> None: ...


def entry_json(entry: Property | Container | None) -> dict[str, Any] | None:
    if entry is None:
        return None
    if isinstance(entry, Property):
        return {"kind": "property", "value": entry.value, "persistent": entry.persistent}
    return {"kind": "container", "type": entry.kind}


def event_json(event: Event, received: float) -> dict[str, Any]:
    data: Any = event.data
    encoded = msgspec.json.encode(data)
    if len(encoded) > DATA_PREVIEW:
        data = {"preview": encoded[:DATA_PREVIEW].decode(errors="replace"), "bytes": len(encoded)}
    return {"embodiment": event.embodiment, "component": event.component, "name": event.name, "data": data,
            "seq": event.seq, "time": event.time, "received": received}


class Page:
    """One connected page: what waits to be sent to it, bounded (see the module's doc)."""

    def __init__(self, number: int) -> None:
        self.number = number
        self.events: deque[dict[str, Any]] = deque()
        self.changes: list[dict[str, Any]] = []
        self.dropped = 0
        self.resync = False
        self.selected: str | None = None
        self.wake = asyncio.Event()

    def change(self, item: dict[str, Any]) -> None:
        if self.resync:
            return  # a snapshot is coming anyway
        if len(self.changes) >= PAGE_CHANGES:
            self.changes.clear()
            self.resync = True
        else:
            self.changes.append(item)
        self.wake.set()

    def event(self, item: dict[str, Any]) -> None:
        if len(self.events) >= PAGE_EVENTS:
            self.events.popleft()
            self.dropped += 1
        self.events.append(item)
        self.wake.set()


@dataclass
class TreeWatch:
    """An embodiment's blackboard and world model, followed for the pages that selected it."""

    embodiment: str
    pages: set[Page] = field(default_factory=set)
    entries: dict[str, dict[tuple[str, ...], dict[str, Any]]] = field(default_factory=lambda: {s: {} for s in STORES})
    touched: set[tuple[str, tuple[str, ...]]] = field(default_factory=set)  # changed before the first read came back
    ready: bool = False
    truncated: bool = False
    handles: list[Closeable] = field(default_factory=list)

    def apply(self, store: str, path: tuple[str, ...], entry: dict[str, Any] | None) -> bool:
        """Apply one change; False when it was left out (the store is over ``TREE_LIMIT``)."""
        entries = self.entries[store]
        if entry is None:
            for other in [p for p in entries if p[:len(path)] == path]:
                del entries[other]
            return True
        if path not in entries and len(entries) >= TREE_LIMIT:
            self.truncated = True
            return False
        entries[path] = entry
        return True

    def message(self) -> dict[str, Any]:
        return {"type": "trees", "embodiment": self.embodiment, "ready": self.ready, "truncated": self.truncated,
                "stores": {s: [["/".join(p), e] for p, e in sorted(self.entries[s].items())] for s in STORES}}


class Model:
    """What the view knows of the mesh; touched only on the loop."""

    def __init__(self, mesh: str) -> None:
        self.mesh = mesh
        self.embodiments: dict[str, dict[str, Any]] = {}
        self.custody: dict[str, dict[str, int]] = {}  # companion -> {holder: epoch}
        self.migrations: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self.plans: OrderedDict[str, dict[str, Any]] = OrderedDict()  # "<embodiment>/<run id>"
        self.ring: deque[dict[str, Any]] = deque(maxlen=RING)
        self.frames: deque[dict[str, Any]] = deque(maxlen=FRAMES_KEPT)

    def frame(self, when: float) -> dict[str, Any] | None:
        """A picture of the mesh at ``when`` if it differs from the last one (then kept), else None:
        each embodiment ``[alive, inhabitant]``, and custody of each companion."""
        embodiments = {name: [card["alive"], (card.get("description") or {}).get("inhabitant")]
                       for name, card in self.embodiments.items()}
        custody = {c: dict(h) for c, h in self.custody.items()}
        last = self.frames[-1] if self.frames else None
        if last is not None and last["embodiments"] == embodiments and last["custody"] == custody:
            return None
        # Clocks of two sources may disagree by a little: frames stay in order on the axis.
        frame = {"time": max(when, last["time"]) if last is not None else when, "embodiments": embodiments, "custody": custody}
        self.frames.append(frame)
        return frame

    # --- embodiments ------------------------------------------------------------------------

    def alive(self, name: str, alive: bool) -> dict[str, Any]:
        card = self.embodiments.setdefault(name, {"name": name, "description": None, "error": None})
        card.update(alive=alive, since=time.time())
        if not alive:
            gone = [n for n, c in self.embodiments.items() if not c["alive"]]
            for old in gone[:-GONE_KEPT]:
                del self.embodiments[old]
            for key, plan in list(self.plans.items()):
                if plan["embodiment"] == name and plan["state"] == "running":
                    plan.update(state="vanished", reason=f"{name} left the mesh")
                    del self.plans[key]
                    self._keep_plan(key, plan)
        return card

    def described(self, name: str, description: dict[str, Any] | None, error: str | None) -> dict[str, Any] | None:
        card = self.embodiments.get(name)
        if card is None:
            return None
        if description is not None:
            card["description"] = description
        card["error"] = error
        return card

    def inhabit(self, name: str, companion: str | None) -> dict[str, Any] | None:
        """What an event says at once (the description that follows confirms it)."""
        card = self.embodiments.get(name)
        if card is None:
            return None
        # Not described yet (or a recording that holds no description): what the event says, alone.
        card["description"] = {**(card.get("description") or {}), "inhabitant": companion}
        return card

    def custody_token(self, holder: str, companion: str, epoch: int, alive: bool) -> dict[str, Any]:
        holders = self.custody.setdefault(companion, {})
        if alive:
            holders[holder] = epoch
        elif holders.get(holder) == epoch:
            del holders[holder]
        if not holders:
            del self.custody[companion]
        return {"type": "custody", "companion": companion, "holders": dict(holders)}

    # --- migrations and plans ---------------------------------------------------------------

    def migration_event(self, event: Event, received: float | None = None) -> dict[str, Any] | None:
        """The migration an event of the ``migration`` component moved on, or None."""
        data = event.data if isinstance(event.data, dict) else {}
        companion = str(data.get("companion", ""))
        attempt = str(data.get("attempt", ""))
        here = event.embodiment
        step: str | None = None
        status: str | None = None
        source = target = None
        if event.name == "MigrationStarting":
            step, source, target = "starting", here, str(data.get("target", ""))
        elif event.name == "MigrationStep":
            step = str(data.get("step", ""))
            peer = str(data.get("peer", ""))
            source, target = (here, peer) if step in ("prepared", "handed") else (peer, here)
        elif event.name == "MigrationSucceeded":
            step, status, source, target = "released", "succeeded", here, str(data.get("target", ""))
        elif event.name == "MigrationFailed":
            step, status, source, target = "failed", "failed", here, str(data.get("target", "")) or None
        elif event.name == "MigrationDropped":
            step, status, target, source = "dropped", "dropped", here, str(data.get("source", "")) or None
        elif event.name == "MigrationStuck":
            step, source, target = "stuck", here, str(data.get("target", ""))
        else:
            return None
        if not attempt:  # refused before an attempt was made, or an event that names none: the latest one
            running = [m for m in self.migrations.values() if m["companion"] == companion and m["source"] == here]
            attempt = running[-1]["attempt"] if running and event.name == "MigrationStuck" else f"{here}#{event.seq}"
        migration = self.migrations.get(attempt)
        if migration is None:
            migration = {"attempt": attempt, "companion": companion, "source": source, "target": target,
                         "status": "running", "reason": "", "steps": [], "started": event.time}
            self.migrations[attempt] = migration
            while len(self.migrations) > MIGRATIONS_KEPT:
                self.migrations.popitem(last=False)
        migration["source"] = migration["source"] or source
        migration["target"] = migration["target"] or target
        # The two sides' events come over different links, in either order: the handshake's own
        # order puts each step in its place (clocks of two machines could not).
        steps = migration["steps"]
        rank = STEP_ORDER.get(step, len(STEP_ORDER))
        at = next((i for i, s in enumerate(steps) if STEP_ORDER.get(s["step"], len(STEP_ORDER)) > rank), len(steps))
        steps.insert(at, {"step": step, "embodiment": here, "time": event.time,
                          "received": event.time if received is None else received})
        if "epoch" in data:
            migration["epoch"] = data["epoch"]
        if status is not None and migration["status"] != "succeeded":
            migration["status"] = status
            migration["reason"] = str(data.get("reason", ""))
        return migration

    def plan_event(self, event: Event) -> dict[str, Any] | None:
        data = event.data if isinstance(event.data, dict) else {}
        run_id = str(data.get("run_id", ""))
        if not run_id:
            return None
        key = f"{event.embodiment}/{run_id}"
        plan = self.plans.get(key)
        if event.name == "PlanStarted":
            plan = self._plan(key, event.embodiment, run_id)
            plan.update(action=data.get("action"), size=data.get("steps"), started=event.time)
        elif plan is None:
            if event.name not in STEP_STATES:
                return None
            plan = self._plan(key, event.embodiment, run_id)  # started before the view joined
        if event.name in STEP_STATES:
            step = plan["steps"].setdefault(str(data.get("step", "")), {})
            step.update(status=STEP_STATES[event.name], type=data.get("type"), time=event.time)
            if data.get("competency"):
                step["competency"] = data["competency"]
            if data.get("reason"):
                step["reason"] = data["reason"]
        elif event.name in PLAN_ENDS:
            plan.update(state=PLAN_ENDS[event.name], reason=data.get("reason") or "", ended=event.time)
            del self.plans[key]
            self._keep_plan(key, plan)
        return plan

    def _plan(self, key: str, embodiment: str, run_id: str) -> dict[str, Any]:
        plan: dict[str, Any] = {"key": key, "embodiment": embodiment, "run_id": run_id, "action": None, "state": "running",
                                "reason": "", "steps": {}}
        self.plans[key] = plan
        return plan

    def _keep_plan(self, key: str, plan: dict[str, Any]) -> None:
        self.plans[key] = plan  # finished plans go to the end, and only so many are kept
        ended = [k for k, p in self.plans.items() if p["state"] != "running"]
        for old in ended[:-PLANS_KEPT]:
            del self.plans[old]

    def status(self, name: str, value: Any) -> list[dict[str, Any]]:
        """Plans already running when the view found ``name`` (``execution/status``)."""
        plans = value.get("plans") if isinstance(value, dict) else None
        out = []
        for run_id, steps in (plans or {}).items():
            key = f"{name}/{run_id}"
            if key in self.plans or not isinstance(steps, dict):
                continue
            plan = self._plan(key, name, str(run_id))
            plan["steps"] = {str(s): {"status": str(st)} for s, st in steps.items()}
            out.append(plan)
        return out

    def snapshot(self) -> dict[str, Any]:
        return {"type": "snapshot", "mesh": self.mesh, "embodiments": list(self.embodiments.values()),
                "custody": {c: dict(h) for c, h in self.custody.items()}, "migrations": list(self.migrations.values()),
                "plans": list(self.plans.values()), "events": list(self.ring), "frames": list(self.frames)}
