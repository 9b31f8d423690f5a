"""Competencies: the units of work a body can do, and what a running one sees (``RunContext``).

A competency has a unique name, a type (plans ask for types, several competencies may share
one), an availability flag and the constructor parameters it was built with. Each competency runs
one execution at a time (it is bound to a sensor or actuator), on a worker thread of its own that
is there only while it has work: started by an ``execute``, it ends once no execution waits (an
idle body holds no thread per competency). Its ``run`` gets the step's run parameters and a
``RunContext`` and returns True (succeeded) or False (failed); an exception counts as failure with
its message as the reason. Cancellation is cooperative: ``ctx.cancelled`` is set and ``ctx.wait``
returns early; a run that ends after a cancel is reported as cancelled whatever it returns.

**Background competencies** (sensors) have ``background = True``: they start when the embodiment
loads and run until it stops. One that crashes or returns is reported with a
``CompetencyCrashed`` event and restarted with exponential backoff; never silently dead.

The library that names a body's competencies is read and built by ``body.library``.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cmion_mesh import keys
from cmion_mesh.errors import InvalidName, MeshError

if TYPE_CHECKING:
    from cmion_mesh.ion import Simulation
    from cmion_mesh.messages import RunStatus, StorageWrite
    from cmion_mesh.storage import Store

# Start time: the client, the update loop, the stores and the messages (msgspec) are imported where
# they are used. ``up`` reads the library (``body.library``, which names this class) for its device
# table before it opens its session, and needs none of them for that.

log = logging.getLogger(__name__)

#: Backoff for restarting a crashed background competency: first delay, cap.
RESTART_BACKOFF = (0.05, 10.0)


class Cancelled(MeshError):
    """Raised by ``RunContext.check`` inside a run that was cancelled."""


class RunContext:
    """What a running competency sees: its parameters, cancellation, and the embodiment's stores."""

    def __init__(self, competency: Competency, run_id: str, parameters: dict[str, Any]) -> None:
        self.competency = competency
        self.run_id = run_id
        self.parameters = parameters
        self.cancelled = threading.Event()
        self.reason = ""

    def wait(self, seconds: float) -> bool:
        """Wait up to ``seconds``; False if cancelled meanwhile (then stop promptly)."""
        return not self.cancelled.wait(seconds)

    def check(self) -> None:
        if self.cancelled.is_set():
            raise Cancelled(f"{self.competency.name}: cancelled")

    def fail(self, reason: str) -> bool:
        """Record why the run failed; returns False so ``return ctx.fail("...")`` reads well."""
        self.reason = reason
        return False

    # -- stores and events, thread-safe: writes are requests to the embodiment's stores --------

    def store(self, name: str) -> Store:
        """A local store, for reads (thread-safe); write through ``write`` so that writes are mediated."""
        from cmion_mesh.storage import Store

        store = self.competency.sim.component(name)
        assert isinstance(store, Store)
        return store

    def read(self, store: str, container: str, name: str, default: Any = None) -> Any:
        """A property's value: from the local store, or over the mesh when this competency is remote."""
        from cmion_mesh.client import MeshClient
        from cmion_mesh.storage import Store

        sim = self.competency.sim
        local = sim.components_by_name().get(store)
        if isinstance(local, Store):
            return local.get(container, name, default)
        try:
            return MeshClient(sim.transport, sim.mesh).get_property(sim.embodiment, store, container, name).value
        except MeshError:
            return default

    def bb_get(self, path: str, default: Any = None) -> Any:
        container, _, name = path.rpartition("/")
        return self.read(keys.BLACKBOARD, container, name, default)

    def wm_get(self, entity: str, prop: str, default: Any = None) -> Any:
        return self.read(keys.WORLD_MODEL, entity, prop, default)

    def write(self, store: str, message: StorageWrite, timeout: float = 10.0) -> None:
        """Send a write request to a local store and wait for its outcome; ``RequestRejected``
        (whose ``code`` says why) unless accepted."""
        from cmion_mesh.messages import tag
        from cmion_mesh.requests import require_accepted

        require_accepted(self.competency.sim.request(store, tag(type(message)), message).result(timeout), store)

    def bb_set(self, path: str, value: Any, *, persistent: bool = False) -> None:
        """Set the blackboard property at ``path`` (``container/.../name``), adding the containers
        that are missing on the way in the same write (``SetProperty.create``)."""
        from cmion_mesh.messages import SetProperty

        container, name = keys.property_path(keys.BLACKBOARD, path)
        self.write(keys.BLACKBOARD, SetProperty(container, name, value, persistent, create=True))

    def bb_remove(self, path: str) -> None:
        from cmion_mesh.messages import RemoveProperty

        container, name = keys.property_path(keys.BLACKBOARD, path)
        self.write(keys.BLACKBOARD, RemoveProperty(container, name))

    def wm_set(self, entity: str, prop: str, value: Any, *, persistent: bool = False) -> None:
        """Set a property of the world-model entity ``entity``, which must be there (``wm_add``)."""
        from cmion_mesh.messages import SetProperty

        self.write(keys.WORLD_MODEL, SetProperty(entity, prop, value, persistent))

    def wm_add(self, entity: str, properties: dict[str, Any] | None = None, *, kind: str = "agent",
               persistent: bool = False) -> None:
        """Add the world-model entity ``entity`` (``agent`` or ``object``) with ``properties``, in one
        write: minds hear the entity added, then each property set. ``RequestRejected`` with code
        ``exists`` if it is there already."""
        from cmion_mesh.messages import AddEntity

        self.write(keys.WORLD_MODEL, AddEntity(entity, kind, dict(properties or {}), persistent))

    def wm_remove(self, entity: str) -> None:
        """Remove the world-model entity ``entity`` and everything it holds (code ``not_found`` if absent)."""
        from cmion_mesh.messages import RemoveContainer

        self.write(keys.WORLD_MODEL, RemoveContainer("", entity))

    def remote_action(self, name: str, parameters: tuple[str, ...] | list[str] = (), subject: str = "") -> None:
        """Tell the embodiment's minds that another agent (``subject``) did ``name parameters``: a
        ``RemoteAction`` event, as a sensor perceiving it raises it. ``InvalidName`` for an action
        minds cannot be told (``mind.remote_action_problem``)."""
        import msgspec

        from cmion_mesh.messages import RemoteAction
        from cmion_mesh.mind import remote_action_problem

        action = RemoteAction(name, list(parameters), subject)
        problem = remote_action_problem(action)
        if problem:
            raise InvalidName(problem)
        self.raise_event("RemoteAction", msgspec.to_builtins(action))

    def raise_event(self, name: str, data: Any = None) -> None:
        self.competency.sim.raise_event(self.competency.name, name, data)

    def progress(self, data: Any) -> None:
        self.raise_event("Progress", {"run_id": self.run_id, "progress": data})


@dataclass(frozen=True, slots=True)
class RunResult:
    run_id: str
    status: RunStatus
    reason: str = ""


Done = Callable[[RunResult], None]


class Competency:
    """Base class of every competency. Subclasses set ``type`` (and ``name``) and override ``run``."""

    type: str = ""
    background: bool = False

    def __init__(self, *constructor_parameters: str, name: str | None = None, type: str | None = None) -> None:
        self.name = keys.check_name(name or type_name(self), "competency name")
        self.type = keys.check_name(type or self.type or self.name, "competency type")
        self.constructor_parameters = constructor_parameters
        self.available = True
        self._sim: Simulation | None = None
        self._pending: collections.deque[tuple[RunContext, Done]] = collections.deque()  # under _lock
        self._thread: threading.Thread | None = None  # the worker, while there is work (or the background run)
        self._current: RunContext | None = None
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} type={self.type}>"

    @property
    def sim(self) -> Simulation:
        if self._sim is None:
            raise MeshError(f"competency {self.name!r} is not loaded in an embodiment")
        return self._sim

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        """The competency's work; runs on its own thread. Return True on success."""
        raise NotImplementedError(f"{type(self).__name__}.run")

    # -- life cycle (called by the execution system) -----------------------------------------

    def start(self, sim: Simulation) -> None:
        self._sim = sim
        if self.background and self._thread is None:
            self._thread = threading.Thread(target=self._run_background, name=f"competency-{self.name}", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stopping.set()
        with self._lock:
            if self._current is not None:
                self._current.cancelled.set()
        self._interrupt()
        with self._lock:
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            if thread.is_alive():
                log.warning("competency %s did not stop within %.0f s", self.name, timeout)

    @property
    def busy(self) -> bool:
        return self._current is not None

    def execute(self, run_id: str, parameters: dict[str, Any], done: Done) -> RunContext:
        """Queue one execution on this competency's thread; ``done`` is called from that thread."""
        ctx = RunContext(self, run_id, parameters)
        with self._lock:
            self._current = ctx
            self._pending.append((ctx, done))
            if self._thread is None and not self._stopping.is_set():
                self._thread = threading.Thread(target=self._work, name=f"competency-{self.name}", daemon=True)
                self._thread.start()
        return ctx

    def cancel(self, run_id: str) -> None:
        with self._lock:
            if self._current is not None and self._current.run_id == run_id:
                self._current.cancelled.set()
                self._interrupt()

    def _interrupt(self) -> None:
        """Wake a run blocked on something other than ``ctx.wait`` (after cancel or stop)."""

    def _work(self) -> None:
        """The worker: runs what is pending, and ends when nothing is (``execute`` starts another)."""
        while True:
            with self._lock:
                if not self._pending:
                    self._thread = None
                    return
                ctx, done = self._pending.popleft()
            result = self._execute_once(ctx)
            with self._lock:
                if self._current is ctx:
                    self._current = None
            try:
                done(result)
            except Exception:
                log.exception("reporting the result of %s failed", self.name)

    def _execute_once(self, ctx: RunContext) -> RunResult:
        try:
            ok = bool(self.run(ctx.parameters, ctx))
            reason = ctx.reason
        except Cancelled:
            ok, reason = False, "cancelled"
        except MeshError as exc:  # a refused write, an unknown outcome: the reason says which
            ok, reason = False, str(exc)
        except Exception as exc:
            log.exception("competency %s raised", self.name)
            ok, reason = False, f"{type(exc).__name__}: {exc}"
        if ctx.cancelled.is_set():
            return RunResult(ctx.run_id, "cancelled", reason or "cancelled")
        if ok:
            return RunResult(ctx.run_id, "succeeded")
        return RunResult(ctx.run_id, "failed", reason or f"{self.name} failed")

    def _run_background(self) -> None:
        delay, cap = RESTART_BACKOFF
        attempt = 0
        while not self._stopping.is_set():
            attempt += 1
            ctx = RunContext(self, f"{self.name}#{attempt}", {})
            with self._lock:
                self._current = ctx
            if self._stopping.is_set():  # stop() may have run before _current was set
                ctx.cancelled.set()
            result = self._execute_once(ctx)
            with self._lock:
                self._current = None
            if self._stopping.is_set():
                return
            reason = result.reason if result.status != "succeeded" else "returned"
            try:
                self.sim.raise_event(self.name, "CompetencyCrashed",
                                     {"competency": self.name, "type": self.type, "reason": reason, "restart_in": delay,
                                      "attempt": attempt})
            except MeshError:
                return  # the simulation is closing
            if self._stopping.wait(delay):
                return
            delay = min(cap, delay * 2)


def type_name(obj: object) -> str:
    return type(obj).__name__
