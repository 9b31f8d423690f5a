"""The competency execution system: runs execution plans on the embodiment's competencies.

For each plan run it starts every step whose dependencies have succeeded, in parallel, each on an
available competency of the step's type that has not yet been tried for that step. When a
competency fails, another of the same type is tried; when none is left, the plan fails (running
steps are cancelled and the failure is reported once all have stopped). When every competency of
a type is busy, the step waits for one to become free, bounded by the plan's deadline, instead of
failing at once as CMION did. Several plans run at once. Cancelling a plan cancels its running
steps and reports ``cancelled`` once they have all stopped.

Runs on the update loop; competencies report back through ``Simulation.call``. Every transition
is raised as an event (``PlanStarted``, ``StepStarted``, ``StepSucceeded``, ``StepFailed``,
``StepCancelled``, ``PlanSucceeded``, ``PlanFailed``, ``PlanCancelled``) so monitors see it all.
"""

from __future__ import annotations

import functools
import itertools
import logging
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any, Literal

import msgspec

from cmion_mesh import keys
from cmion_mesh.body.remote import RemoteCompetency
from cmion_mesh.body.rules import Plan, Step, substitute_step
from cmion_mesh.body.standin import StandIn, unavailable_reason
from cmion_mesh.competency import Competency, RunResult
from cmion_mesh.errors import MeshError, PlanError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import ExecutionStatus, RunStatus
from cmion_mesh.mind import MindAction
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.storage import Store
from cmion_mesh.timers import Timer
from cmion_mesh.transport.base import Closeable

log = logging.getLogger(__name__)

DEFAULT_PLAN_DEADLINE = 300.0
PlanDone = Callable[[RunStatus, str], None]  # (status, reason)
StepState = Literal["pending", "waiting", "running", "succeeded", "failed", "cancelled"]
#: ``failing`` and ``cancelling``: running steps are being stopped before the plan reports its end.
PlanState = Literal["running", "failing", "cancelling", "done"]


class _StepRun(msgspec.Struct, eq=False):
    step: Step
    status: StepState = "pending"
    tried: set[str] = msgspec.field(default_factory=set)
    competency: Competency | None = None
    run_id: str = ""
    reasons: list[str] = msgspec.field(default_factory=list)


class PlanRun(msgspec.Struct, eq=False):
    id: str
    plan: Plan
    action: MindAction
    on_done: PlanDone
    steps: dict[str, _StepRun]
    state: PlanState = "running"
    reason: str = ""
    deadline: Timer | None = None

    def running(self) -> list[_StepRun]:
        return [s for s in self.steps.values() if s.status == "running"]


class ExecutionSystem(Component):
    requests = {"status": ExecutionStatus}
    built_by_embodiment = True

    def __init__(self, competencies: Iterable[Competency] = (), name: str = "execution") -> None:
        super().__init__(name)
        self._competencies: dict[str, Competency] = {}
        for competency in competencies:
            self.add_competency(competency)
        self._plans: dict[str, PlanRun] = {}
        self._waiting: deque[tuple[PlanRun, _StepRun]] = deque()
        self._run_ids = itertools.count(1)
        self._remote_watch: Closeable | None = None

    # --- competencies -------------------------------------------------------------------------

    def add_competency(self, competency: Competency) -> None:
        if competency.name in self._competencies:
            raise MeshError(f"a competency named {competency.name!r} is already loaded")
        self._competencies[competency.name] = competency
        if self._sim is not None:
            competency.start(self._sim)

    def remove_competency(self, name: str) -> None:
        """Take a competency out (e.g. a remote one that vanished); its running step fails."""
        competency = self._competencies.pop(name, None)
        if competency is None:
            return
        for plan in list(self._plans.values()):
            for step in plan.running():
                if step.competency is competency:
                    self._on_result(plan, step, competency, RunResult(step.run_id, "failed", f"competency {name!r} vanished"))
        competency.stop(timeout=1.0)

    @property
    def competencies(self) -> list[Competency]:
        return list(self._competencies.values())

    def types(self) -> set[str]:
        return {c.type for c in self._competencies.values()}

    def attach(self, sim: Simulation) -> None:
        for competency in self._competencies.values():
            competency.start(sim)
        self._remote_watch = sim.transport.watch_liveliness(
            keys.competency_alive_pattern(sim.mesh, sim.embodiment), self._on_remote_token
        )

    def _on_remote_token(self, key: str, alive: bool) -> None:
        # On the transport's worker: hand over to the loop.
        *_, competency_type, name = key.split("/")
        self.sim.post(functools.partial(self._remote_changed, name, competency_type, alive))

    def _remote_changed(self, name: str, competency_type: str, alive: bool) -> None:
        existing = self._competencies.get(name)
        if alive:
            if existing is None:
                self.add_competency(RemoteCompetency(name, competency_type))
                self.raise_event("CompetencyAppeared", {"competency": name, "type": competency_type})
                self._retry_waiting(competency_type)
            elif not isinstance(existing, RemoteCompetency):
                log.warning("remote competency %s ignored: a local competency has that name", name)
        elif isinstance(existing, RemoteCompetency):
            self.remove_competency(name)
            self.raise_event("CompetencyVanished", {"competency": name, "type": competency_type})

    def detach(self) -> None:
        if self._remote_watch is not None:
            self._remote_watch.close()
            self._remote_watch = None
        for plan in list(self._plans.values()):
            self.cancel(plan.id)
        for competency in self._competencies.values():
            competency.stop()

    # --- plans (loop thread) ------------------------------------------------------------------

    def execute(self, plan: Plan, action: MindAction, on_done: PlanDone, *, deadline: float = DEFAULT_PLAN_DEADLINE,
                run_id: str | None = None) -> str:
        """Start a plan; ``on_done(status, reason)`` is called on the loop once it has ended."""
        plan_id = run_id or f"plan-{next(self._run_ids)}"
        if plan_id in self._plans:
            raise MeshError(f"plan run {plan_id!r} is already running")
        run = PlanRun(plan_id, plan, action, on_done, {s.id: _StepRun(s) for s in plan.steps})
        self._plans[plan_id] = run
        self.raise_event("PlanStarted", {"run_id": plan_id, "action": action.describe(), "steps": len(plan.steps)})
        if deadline > 0:
            run.deadline = self.sim.call_later(deadline, functools.partial(self._deadline, run, deadline))
        self._advance(run)
        return plan_id

    def running_plans(self, competency_type: str) -> list[str]:
        """Ids of the plan runs with a step of ``competency_type`` running (loop thread)."""
        return [run.id for run in self._plans.values() if any(s.step.type == competency_type for s in run.running())]

    def cancel(self, plan_id: str) -> bool:
        run = self._plans.get(plan_id)
        if run is None or run.state == "done":
            return False
        run.state, run.reason = "cancelling", "cancelled"
        self._stop_steps(run)
        self._maybe_finish(run)
        return True

    def _deadline(self, run: PlanRun, seconds: float) -> None:
        if run.state == "running":
            self._fail(run, f"plan deadline of {seconds:g} s passed")

    def _advance(self, run: PlanRun) -> None:
        if run.state != "running":
            return
        for step_run in run.steps.values():
            if step_run.status == "pending" and all(run.steps[d].status == "succeeded" for d in step_run.step.dependencies):
                self._start_step(run, step_run)
                if run.state != "running":
                    return
        self._maybe_finish(run)

    def _start_step(self, run: PlanRun, step_run: _StepRun, *, announce: bool = True) -> None:
        step = step_run.step
        of_type = [c for c in self._competencies.values() if c.type == step.type]
        untried = [c for c in of_type if c.name not in step_run.tried]
        ready = [c for c in untried if c.available and not c.busy]
        if not ready:
            if any(c.busy and c.available for c in untried):
                step_run.status = "waiting"
                self._waiting.append((run, step_run))
                if announce:
                    self.raise_event("StepWaiting", {"run_id": run.id, "step": step.id, "type": step.type})
                return
            why = "; ".join(step_run.reasons) or _unavailable(step.type, of_type)
            step_run.status = "failed"
            self.raise_event("StepFailed", {"run_id": run.id, "step": step.id, "type": step.type, "reason": why})
            self._fail(run, f"step {step.id} ({step.type}) failed: {why}")
            return
        competency = ready[0]
        try:
            parameters = substitute_step(step, run.action, bb=self._bb, wm=self._wm)
        except PlanError as exc:
            step_run.status = "failed"
            self.raise_event("StepFailed", {"run_id": run.id, "step": step.id, "type": step.type, "reason": str(exc)})
            self._fail(run, str(exc))
            return
        step_run.status = "running"
        step_run.competency = competency
        step_run.tried.add(competency.name)
        step_run.run_id = f"{run.id}/{step.id}/{len(step_run.tried)}"
        self.raise_event("StepStarted", {"run_id": run.id, "step": step.id, "type": step.type, "competency": competency.name,
                                         "parameters": {k: v for k, v in parameters.items()}})
        sim = self.sim
        done = functools.partial(self._report, sim, run, step_run, competency)
        competency.execute(step_run.run_id, parameters, done)

    def _report(self, sim: Simulation, run: PlanRun, step_run: _StepRun, competency: Competency, result: RunResult) -> None:
        # On the competency's thread: hand the result to the loop.
        sim.post(functools.partial(self._on_result, run, step_run, competency, result))

    def _on_result(self, run: PlanRun, step_run: _StepRun, competency: Competency, result: RunResult) -> None:
        if step_run.status != "running" or step_run.run_id != result.run_id:
            self._retry_waiting(competency.type)
            return  # stale: already decided (competency removed, plan ended)
        step = step_run.step
        data = {"run_id": run.id, "step": step.id, "type": step.type, "competency": competency.name, "reason": result.reason}
        if result.status == "succeeded":
            step_run.status = "succeeded"
            self.raise_event("StepSucceeded", data)
            self._advance(run)
        elif result.status == "cancelled" or run.state in ("cancelling", "failing"):
            step_run.status = "cancelled"
            self.raise_event("StepCancelled", data)
            self._maybe_finish(run)
        else:
            step_run.reasons.append(f"{competency.name}: {result.reason}")
            self.raise_event("StepFailed", data)
            step_run.status = "pending"
            self._start_step(run, step_run)  # another competency of the same type, if any
        self._retry_waiting(competency.type)

    def _retry_waiting(self, competency_type: str) -> None:
        # Oldest first; a step that still finds nothing free goes back in the same order.
        queued, self._waiting = list(self._waiting), deque()
        for run, step_run in queued:
            if run.state != "running" or step_run.status != "waiting":
                continue
            if step_run.step.type == competency_type:
                self._start_step(run, step_run, announce=False)
            else:
                self._waiting.append((run, step_run))

    def _fail(self, run: PlanRun, reason: str) -> None:
        if run.state != "running":
            return
        run.state, run.reason = "failing", reason
        self._stop_steps(run)
        self._maybe_finish(run)

    def _stop_steps(self, run: PlanRun) -> None:
        for step_run in run.steps.values():
            if step_run.status == "running" and step_run.competency is not None:
                step_run.competency.cancel(step_run.run_id)
            elif step_run.status == "waiting":
                step_run.status = "cancelled"

    def _maybe_finish(self, run: PlanRun) -> None:
        if run.state == "done" or run.running():
            return
        status: RunStatus
        if run.state == "running":
            if not all(s.status == "succeeded" for s in run.steps.values()):
                return
            status, event = "succeeded", "PlanSucceeded"
        elif run.state == "cancelling":
            status, event = "cancelled", "PlanCancelled"
        else:
            status, event = "failed", "PlanFailed"
        run.state = "done"
        self._plans.pop(run.id, None)
        if run.deadline is not None:
            run.deadline.cancel()  # or the finished run would be held until its deadline
        self.raise_event(event, {"run_id": run.id, "action": run.action.describe(), "reason": run.reason})
        run.on_done(status, run.reason)

    # --- substitutions read the stores when the step starts -----------------------------------

    def _bb(self, name: str) -> Any:
        container, _, prop = name.rpartition("/")
        return self._read(keys.BLACKBOARD, container, prop, f"$BB({name})")

    def _wm(self, entity: str, prop: str) -> Any:
        return self._read(keys.WORLD_MODEL, entity, prop, f"$WM({entity}.{prop})")

    def _read(self, store_name: str, container: str, prop: str, token: str) -> Any:
        store = self.sim.component(store_name)
        assert isinstance(store, Store)
        missing = object()
        value = store.get(container, prop, missing)
        if value is missing:
            raise KeyError(token)
        return value

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            request.accept({
                "plans": {p.id: {s.step.id: s.status for s in p.steps.values()} for p in self._plans.values()},
                "competencies": [
                    {"name": c.name, "type": c.type, "available": c.available, "busy": c.busy, "background": c.background}
                    for c in self._competencies.values()
                ],
            })



def _unavailable(competency_type: str, of_type: list[Competency]) -> str:
    """Why no competency can run a step of ``competency_type``, naming the CMION classes that only
    stand-ins replace (``standin``)."""
    if not of_type:
        return f"no competency of type {competency_type!r}"
    stand_ins = [c for c in of_type if isinstance(c, StandIn)]
    reasons = unavailable_reason(stand_ins)
    if len(stand_ins) == len(of_type):
        return f"competency type {competency_type!r} is provided only by {reasons}"
    if stand_ins:
        return f"no available competency of type {competency_type!r} (the others: {reasons})"
    return f"no available competency of type {competency_type!r}"
