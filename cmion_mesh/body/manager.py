"""The competency manager: turns mind actions into execution plans, with fallback.

Requests (on ``.../rq/manager/<name>``):

* ``act`` (``Act``): accepted at once with ``{"action_id": ...}`` when some rule matches,
  rejected with the reason otherwise (unknown action, duplicate id). The outcome of the action
  itself comes later as an event.
* ``cancel`` (``CancelAction``): stops the action's running plan; it ends ``ActionCancelled``.
* ``status`` (``ActionStatus``): an ``ActionReport`` - ``running`` (which rule, which attempt),
  or the final report of one of the last ``HISTORY`` finished actions; with no id, the ids of the
  running actions (``{"running": [...]}``).

Events (data: ``ActionReport``, its ``status`` saying which): ``ActionStarted`` (``started``),
``ActionAttempt`` (``attempt``: a plan is tried, ``rule`` and ``attempt`` say which),
``ActionSucceeded``, ``ActionFailed``, ``ActionCancelled``, each carrying the action id.

Rules are tried most specific first (see ``rules``); within a rule its plans in file order. A
plan that needs a competency type this embodiment does not have is skipped (as CMION did), its
reason the words ``validate`` and ``up`` warned with (``rules.missing_types``); when a
plan fails, the next untried candidate runs; when none is left the action fails with every
reason collected.

Each action's end is one log line at info (``action <name> <outcome>``, fields ``action``,
``action_id``, ``outcome``, ``duration_s``, ``rule``, ``attempts``, ``reason``); an action that
fails at once (no rule, no executable plan) ends the same way, through a throttle keyed by its
name, since a peer can send those as fast as it likes. Nothing is logged per attempt at info.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections import OrderedDict, deque

import msgspec

from cmion_mesh import keys, logs
from cmion_mesh.body.execution import DEFAULT_PLAN_DEADLINE, ExecutionSystem
from cmion_mesh.body.rules import Plan, Rule, RuleSet, missing_types
from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Component
from cmion_mesh.messages import Act, ActionReport, ActionState, ActionStatus, CancelAction, Code, RunStatus
from cmion_mesh.mind import MindAction
from cmion_mesh.requests import IncomingRequest

log = logging.getLogger(__name__)


class _Active(msgspec.Struct, eq=False):
    act: Act
    action: MindAction
    candidates: deque[tuple[Rule, Plan]]
    run_id: str = ""
    rule: str = ""
    attempts: int = 0
    reasons: list[str] = msgspec.field(default_factory=list)
    cancel_requested: bool = False
    started: float = msgspec.field(default_factory=time.monotonic)


#: Longest plan deadline an action may ask for (a day).
MAX_DEADLINE = 24 * 3600.0
#: Actions running at once; more are refused ``busy`` (a flood of actions must not queue for minutes).
MAX_RUNNING = 64


class CompetencyManager(Component):
    requests = {"act": Act, "cancel": CancelAction, "status": ActionStatus}
    built_by_embodiment = True
    #: Finished actions remembered for ``status`` (a requester that missed the end event asks).
    HISTORY = 1024

    def __init__(self, rules: RuleSet, execution: ExecutionSystem, name: str = "manager",
                 default_deadline: float = DEFAULT_PLAN_DEADLINE) -> None:
        super().__init__(name)
        self.rules = rules
        self.execution = execution
        self.default_deadline = default_deadline
        self._active: dict[str, _Active] = {}
        self._finished: OrderedDict[str, ActionReport] = OrderedDict()
        self._ids = itertools.count(1)
        self._failed_at_once = logs.Throttle(log, "actions failed at once")

    @property
    def active(self) -> list[str]:
        return list(self._active)

    def actions_running(self, competency_type: str) -> list[str]:
        """Ids of the actions whose current plan has a step of ``competency_type`` running (loop thread)."""
        runs = set(self.execution.running_plans(competency_type))
        return [action_id for action_id, active in self._active.items() if active.run_id in runs]

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            match request.payload:
                case Act() as act:
                    self._act(request, act)
                case CancelAction(action_id=action_id):
                    self._cancel(request, action_id)
                case ActionStatus(action_id=action_id):
                    self._status(request, action_id)

    def _status(self, request: IncomingRequest, action_id: str) -> None:
        if action_id in self._active:
            active = self._active[action_id]
            act = active.act
            running = ActionReport(action_id, act.name, list(act.parameters), act.subject, "running", "", active.rule,
                                   active.attempts)
            request.accept(msgspec.to_builtins(running))
        elif action_id in self._finished:
            request.accept(msgspec.to_builtins(self._finished[action_id]))
        elif not action_id:
            request.accept({"running": sorted(self._active)})
        else:
            request.reject(f"no action with id {action_id!r} is running or recently finished", Code.NOT_FOUND)

    def _act(self, request: IncomingRequest, act: Act) -> None:
        if not (math.isfinite(act.deadline) and 0.0 <= act.deadline <= MAX_DEADLINE):
            request.reject(f"deadline {act.deadline!r} is not a number of seconds from 0 (the default) to {MAX_DEADLINE:g}",
                           Code.INVALID)
            return
        if len(act.action_id) > keys.MAX_NAME:
            request.reject(f"action id {act.action_id[:40]!r}... is longer than {keys.MAX_NAME} characters", Code.INVALID)
            return
        if len(self._active) >= MAX_RUNNING:
            request.reject(f"busy: {MAX_RUNNING} actions are running on {self.sim.embodiment!r}; try again later", Code.BUSY)
            return
        action = MindAction(act.name, tuple(act.parameters), act.subject)
        action_id = act.action_id or f"{self.sim.embodiment}-{next(self._ids)}"
        if action_id in self._active:
            request.reject(f"action id {action_id!r} is already running", Code.EXISTS)
            return
        act = msgspec.structs.replace(act, action_id=action_id)
        rules = self.rules.candidates(action)
        if not rules:
            reason = f"no rule matches action {action.describe()!r}: {self.rules.why_no_match(action)}"
            request.reject(reason, Code.NOT_FOUND)
            self._report("ActionFailed", act, "failed", reason)
            self._log_failed_at_once(act, reason)
            return
        types = self.execution.types()
        candidates: deque[tuple[Rule, Plan]] = deque()
        skipped = []
        for rule in rules:
            for number, plan in enumerate(rule.plans, start=1):
                missing = missing_types(plan, types)
                if missing is not None:
                    skipped.append(f"rule at line {rule.line}, plan {number}: {missing}")
                else:
                    candidates.append((rule, plan))
        if not candidates:
            reason = f"no executable plan for {action.describe()!r}: " + "; ".join(skipped)
            request.reject(reason, Code.NOT_FOUND)
            self._report("ActionFailed", act, "failed", reason)
            self._log_failed_at_once(act, reason)
            return
        active = _Active(act, action, candidates, reasons=skipped)
        self._active[action_id] = active
        request.accept({"action_id": action_id})
        self._report("ActionStarted", act, "started")
        self._next(active)

    def _next(self, active: _Active) -> None:
        if active.cancel_requested:
            self._end(active, "ActionCancelled", "cancelled", "cancelled")
            return
        if not active.candidates:
            self._end(active, "ActionFailed", "failed", "; ".join(active.reasons) or "every plan failed")
            return
        rule, plan = active.candidates.popleft()
        active.attempts += 1
        active.rule = f"{rule.path}:{rule.line}"
        active.run_id = f"{active.act.action_id}#{active.attempts}"
        deadline = active.act.deadline or self.default_deadline
        self._report("ActionAttempt", active.act, "attempt", "", active.rule, active.attempts)

        def done(status: RunStatus, reason: str) -> None:
            if status == "succeeded":
                self._end(active, "ActionSucceeded", "succeeded", "")
            elif status == "cancelled" or active.cancel_requested:
                self._end(active, "ActionCancelled", "cancelled", reason or "cancelled")
            else:
                active.reasons.append(f"rule at line {rule.line}: {reason}")
                self._next(active)

        try:
            self.execution.execute(plan, active.action, done, deadline=deadline, run_id=active.run_id)
        except MeshError as exc:
            active.reasons.append(str(exc))
            self._next(active)

    def _cancel(self, request: IncomingRequest, action_id: str) -> None:
        active = self._active.get(action_id)
        if active is None:
            request.reject(f"no running action with id {action_id!r}", Code.NOT_FOUND)
            return
        active.cancel_requested = True
        request.accept({"action_id": action_id})
        if not self.execution.cancel(active.run_id):
            self._end(active, "ActionCancelled", "cancelled", "cancelled")

    def _end(self, active: _Active, event: str, status: ActionState, reason: str) -> None:
        if self._active.pop(active.act.action_id, None) is None:
            return
        self._report(event, active.act, status, reason, active.rule, active.attempts)
        if log.isEnabledFor(logging.INFO):
            act = active.act
            logs.event(log, f"action {act.name} {status}", action=act.name, action_id=act.action_id, outcome=status,
                       duration_s=round(time.monotonic() - active.started, 4), rule=active.rule or None,
                       attempts=active.attempts, reason=reason or None)

    def detach(self) -> None:
        self._failed_at_once.flush()

    def _log_failed_at_once(self, act: Act, reason: str) -> None:
        self._failed_at_once(act.name, "action %s failed", act.name, action=act.name, action_id=act.action_id,
                             outcome="failed", duration_s=0.0, rule=None, attempts=0, reason=reason)

    def _report(self, event: str, act: Act, status: ActionState, reason: str = "", rule: str = "", attempt: int = 0) -> None:
        report = ActionReport(act.action_id, act.name, list(act.parameters), act.subject, status, reason, rule, attempt)
        if status in ("succeeded", "failed", "cancelled"):
            self._finished[act.action_id] = report
            while len(self._finished) > self.HISTORY:
                self._finished.popitem(last=False)
        self.raise_event(event, msgspec.to_builtins(report))

