"""Simulated competencies for LIREC's "Spirit of the Building" showcase.

One companion, the building's spirit, lives in a robot that roams the office; it can migrate to a
screen at the entrance to greet a guest and to a phone to accompany someone. These competencies
stand in for the real sensors and actuators: every effect shows on the blackboard (BB) and the
world model (WM), durations are a few tens of milliseconds (constructor parameters), and every
wait is cut short by a cancel.

What each competency reads and writes (``a/b`` is container ``a``, property ``b``; the WM agent
``Self`` is this body's idea of the companion, renamed by a constructor parameter):

* ``Navigation``: run parameter ``Location``; reads WM ``<loc>.isLocation`` and the optional
  ``<loc>.travelSteps``; writes BB ``navigation/target`` and ``navigation/state`` (moving,
  arrived, stopped), WM ``Self.location`` on arrival; raises ``Progress`` events.
* ``LanguageGeneration``: ``SpeechActID``, ``Addressee``, ``TextOutName``; reads WM
  ``<addressee>.displayName`` and ``Self.displayName``; writes BB ``<TextOutName>``.
* ``SpeechSynthesis``: ``TextInName`` (a BB name); writes BB ``speech/current`` while speaking,
  then ``speech/last`` and WM ``Self.lastUtterance``; raises a ``Spoke`` event.
* ``Animation``: ``AnimationName``; writes BB ``animation/current`` while playing, then
  ``animation/last``.
* ``UserDetection`` (background): reads BB ``sim/userPresent`` (a name, a comma list or a list;
  removed or empty = nobody); writes WM agent ``<user>``: ``present`` true and ``location`` =
  ``Self.location`` on arrival, ``present`` false once gone.
* ``GestureDetect``: ``PersonID``, ``Timeout`` (s); consumes BB ``sim/gesture``; writes BB
  ``gesture/waitingFor`` while waiting, WM ``<user>.answer``; raises a ``RemoteAction`` event
  (``Gesture <gesture>``, subject the user).
* ``CommandInput`` (background): consumes BB ``sim/command`` (e.g. ``"greet Guest"``); writes WM
  object ``Command``: ``text``, ``object``, ``count``, ``<verb> = <object>``, then ``verb``.

The ``sim`` blackboard container is how a test or the demo plays the world (the user walking in,
nodding, the operator typing); the background competencies create it when they start, so
``cmion-mesh bb set screen sim/userPresent Visitor`` works as soon as the embodiment is up.

Sensors do not poll: they subscribe to the blackboard's change events and sleep until one of
their inputs changes or they are cancelled (``_interrupt``). Their ``interval`` constructor
parameter is an optional fallback re-check for a competency hosted remotely over a lossy link;
the default, 0, means none: an idle embodiment uses no CPU.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterable, Iterator
from typing import Any, ClassVar

from cmion_mesh import keys
from cmion_mesh.competencies.common import (
    BB_CONTAINER,
    SELF,
    SIM,
    bb_remove,
    bb_set,
    ensure_container,
    local_store,
    parse_count,
    parse_seconds,
    quietly,
    remove_property,
    text_parameter,
    truthy,
    wm_set,
)
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import Event

__all__ = [
    "Animation",
    "CommandInput",
    "GestureDetect",
    "LanguageGeneration",
    "Navigation",
    "SimulatedCompetency",
    "SpeechSynthesis",
    "UserDetection",
]

log = logging.getLogger(__name__)

# --- the base -------------------------------------------------------------------------------------


class SimulatedCompetency(Competency):
    """Base of the simulated competencies: a wake-up event for blackboard-driven inputs.

    ``watching(paths)`` subscribes to the blackboard's change events and sets ``_wake`` when one
    of ``paths`` (or a container above it) changes; a cancel or a stop sets it too, so a run
    blocked in ``_wake.wait`` stops at once.
    """

    def __init__(self, *constructor_parameters: str, name: str | None = None) -> None:
        super().__init__(*constructor_parameters, name=name)
        self._wake = threading.Event()

    def _interrupt(self) -> None:
        self._wake.set()

    def _rearm(self, ctx: RunContext) -> bool:
        """Clear the wake-up, then report whether to go on: clearing first means a change or a
        cancel that happens after this call is never lost, and one before it is seen by the read
        that follows."""
        self._wake.clear()
        return not ctx.cancelled.is_set()

    @contextlib.contextmanager
    def watching(self, paths: Iterable[str]) -> Iterator[None]:
        wanted = [keys.split_path(p) for p in paths]

        def on_change(event: Event) -> None:  # on the update loop: only sets a flag
            data = event.data
            if not isinstance(data, dict):
                return
            container, name = data.get("container"), data.get("name")
            if not isinstance(container, str) or not isinstance(name, str):
                return
            changed = (*(c for c in container.split("/") if c), name)
            if any(path[: len(changed)] == changed for path in wanted):
                self._wake.set()

        subscription = self.sim.on_event(on_change, component=keys.BLACKBOARD)
        try:
            yield
        finally:
            subscription.close()


# --- actuators -------------------------------------------------------------------------------------


class Navigation(SimulatedCompetency):
    """Moves the body to the location named by the run parameter ``Location``.

    Constructor parameters: seconds per step (``0.05``), the WM agent that is this body's self
    (``Self``), steps per trip (``4``) unless the location's WM property ``travelSteps`` says
    otherwise. A location is a WM *object* whose ``isLocation`` is true; anything else fails with
    the list of known locations. Going where the body already is takes no step. A cancelled trip
    leaves ``Self.location`` unchanged (the simulation has no "in between").
    """

    type = "Navigation"

    def __init__(self, step: str = "0.05", agent: str = SELF, steps: str = "4", *, name: str | None = None) -> None:
        super().__init__(step, agent, steps, name=name)
        self.step = parse_seconds(step, "Navigation: seconds per step")
        self.agent = keys.check_name(agent, "Navigation: self agent")
        self.steps = parse_count(steps, "Navigation: steps per trip")

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        target = text_parameter(parameters, "Location")
        if not target:
            return ctx.fail("Navigation needs a Location parameter")
        if not keys.is_name(target) or not self._is_location(ctx, target):
            known = self._known_locations(ctx)
            listing = f" (known locations: {', '.join(known)})" if known else ""
            return ctx.fail(f"unknown location {target!r}: the world model has no object {target!r} with isLocation = true{listing}")
        here = ctx.wm_get(self.agent, "location")
        steps = 0 if here == target else self._steps_to(ctx, target)
        bb_set(ctx, "navigation/target", target)
        bb_set(ctx, "navigation/state", "moving")
        for done in range(1, steps + 1):
            if not ctx.wait(self.step):
                quietly("navigation/state", bb_set, ctx, "navigation/state", "stopped")
                return False
            ctx.progress({"location": target, "step": done, "steps": steps})
        wm_set(ctx, self.agent, "location", target)
        bb_set(ctx, "navigation/state", "arrived")
        return True

    def _is_location(self, ctx: RunContext, name: str) -> bool:
        local = local_store(ctx, keys.WORLD_MODEL)
        if local is not None:
            if not local.has_container(name) or local.node(name).kind != "object":
                return False
            return truthy(local.get(name, "isLocation"))
        return truthy(ctx.wm_get(name, "isLocation"))  # hosted remotely: one read over the mesh

    def _known_locations(self, ctx: RunContext) -> list[str]:
        local = local_store(ctx, keys.WORLD_MODEL)
        if local is None:
            return []  # listing would mean reading the whole remote world model for an error message
        children = local.tree()["children"]
        return sorted(
            n for n, c in children.items() if c["kind"] == "object" and truthy(c["properties"].get("isLocation", {}).get("value"))
        )

    def _steps_to(self, ctx: RunContext, target: str) -> int:
        raw = ctx.wm_get(target, "travelSteps")
        if raw is None:
            return self.steps
        try:
            return parse_count(raw, f"{target}.travelSteps")
        except ConfigError as exc:
            log.warning("%s; using %d steps", exc, self.steps)
            return self.steps


class LanguageGeneration(SimulatedCompetency):
    """Turns a speech act into text from a template table; writes it to the BB name ``TextOutName``.

    Run parameters (CMION's example rules): ``SpeechActID``, ``Addressee`` (a WM agent; its
    ``displayName`` is used when it has one), ``TextOutName``. Constructor parameters: seconds
    to "think" (``0.02``), the self agent (``Self``, whose ``displayName`` is ``{self}``).
    An unknown speech act fails, naming the known ones: a mind learns the body cannot say it.
    """

    type = "LanguageGeneration"
    TEMPLATES: ClassVar[dict[str, str]] = {
        "hello": "Hello, {addressee}.",
        "greeting": "Hello {addressee}, welcome to the building! I am {self}.",
        "askIsGuest": "Hello {addressee}, are you the guest I am expecting? Please nod if you are.",
        "welcome": "Welcome, {addressee}! I will let your host know that you are here.",
        "followMe": "{addressee}, please follow me.",
        "accompany": "{addressee}, I am with you on your phone now; I will show you the way.",
        "acknowledge": "Okay, {addressee}, I am on it.",
        "sorry": "Sorry {addressee}, I could not do that.",
        "goodbye": "Goodbye {addressee}, see you soon!",
    }

    def __init__(self, step: str = "0.02", agent: str = SELF, *, name: str | None = None) -> None:
        super().__init__(step, agent, name=name)
        self.step = parse_seconds(step, "LanguageGeneration: seconds per sentence")
        self.agent = keys.check_name(agent, "LanguageGeneration: self agent")

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        act = text_parameter(parameters, "SpeechActID")
        out = text_parameter(parameters, "TextOutName")
        if not out:
            return ctx.fail("LanguageGeneration needs a TextOutName parameter (the blackboard name to write the text to)")
        template = self.TEMPLATES.get(act)
        if template is None:
            return ctx.fail(f"no template for speech act {act!r} (known: {', '.join(sorted(self.TEMPLATES))})")
        if not ctx.wait(self.step):
            return False
        addressee = self._display(ctx, text_parameter(parameters, "Addressee"), "there")
        text = template.format(addressee=addressee, self=self._display(ctx, self.agent, "the spirit of the building"))
        bb_set(ctx, out, text)
        return True

    @staticmethod
    def _display(ctx: RunContext, entity: str, fallback: str) -> str:
        if not entity:
            return fallback
        if not keys.is_name(entity):
            return entity  # not a WM name, so it has no displayName: say it as given
        shown = ctx.wm_get(entity, "displayName")
        return str(shown) if shown not in (None, "") else entity


class SpeechSynthesis(SimulatedCompetency):
    """Speaks (in simulation) the text on the blackboard under ``TextInName``; fails if there is none.

    Constructor parameters: seconds per utterance (``0.05``), the self agent (``Self``).
    """

    type = "SpeechSynthesis"

    def __init__(self, step: str = "0.05", agent: str = SELF, *, name: str | None = None) -> None:
        super().__init__(step, agent, name=name)
        self.step = parse_seconds(step, "SpeechSynthesis: seconds per utterance")
        self.agent = keys.check_name(agent, "SpeechSynthesis: self agent")

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        source = text_parameter(parameters, "TextInName")
        if not source:
            return ctx.fail("SpeechSynthesis needs a TextInName parameter (the blackboard name of the text)")
        value = ctx.bb_get(source)
        if value is None or str(value).strip() == "":
            return ctx.fail(f"nothing to say: no text on the blackboard under {source!r}")
        text = str(value)
        bb_set(ctx, "speech/current", text)
        try:
            if not self._speak(text, ctx):
                return False
        finally:
            quietly("speech/current", bb_remove, ctx, "speech/current")
        bb_set(ctx, "speech/last", text)
        wm_set(ctx, self.agent, "lastUtterance", text)
        ctx.raise_event("Spoke", {"text": text, "source": source})
        return True

    def _speak(self, text: str, ctx: RunContext) -> bool:
        """Say ``text``; False if cancelled meanwhile. Simulated: it takes the constructor's time."""
        return ctx.wait(self.step)


class Animation(SimulatedCompetency):
    """Plays the animation named by ``AnimationName``.

    Constructor parameters: seconds per animation (``0.05``), then the animations this body can
    play (none listed: any). An animation the body cannot play fails, naming those it can.
    """

    type = "Animation"

    def __init__(self, step: str = "0.05", *animations: str, name: str | None = None) -> None:
        super().__init__(step, *animations, name=name)
        self.step = parse_seconds(step, "Animation: seconds per animation")
        self.animations = tuple(a for a in animations if a)

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        animation = text_parameter(parameters, "AnimationName")
        if not animation:
            return ctx.fail("Animation needs an AnimationName parameter")
        if self.animations and animation not in self.animations:
            return ctx.fail(f"this body cannot play animation {animation!r} (it plays: {', '.join(self.animations)})")
        bb_set(ctx, "animation/current", animation)
        try:
            if not self._play(animation, ctx):
                return False
        finally:
            quietly("animation/current", bb_remove, ctx, "animation/current")
        bb_set(ctx, "animation/last", animation)
        return True

    def _play(self, animation: str, ctx: RunContext) -> bool:
        """Play ``animation``; False if cancelled meanwhile. Simulated: it takes the constructor's time."""
        return ctx.wait(self.step)


# --- sensors ------------------------------------------------------------------------------------


class UserDetection(SimulatedCompetency):
    """A simulated people sensor (background): who is in front of this body.

    Input: BB ``sim/userPresent``, a user name, a comma-separated list or a list of names;
    removed, empty or null means nobody. Each user who appears gets WM agent ``<user>`` (created
    if unknown) with ``present = true`` and ``location`` = this body's ``Self.location`` (if it
    has one); each who leaves gets ``present = false``. Names that cannot be WM entity names are
    skipped with a warning. Constructor parameters: fallback re-check interval (``0``: none), the
    self agent (``Self``).
    """

    type = "UserDetection"
    background = True
    INPUT = f"{SIM}/userPresent"

    def __init__(self, interval: str = "0", agent: str = SELF, *, name: str | None = None) -> None:
        super().__init__(interval, agent, name=name)
        self.interval = parse_seconds(interval, "UserDetection: re-check interval")
        self.agent = keys.check_name(agent, "UserDetection: self agent")
        self._warned: set[str] = set()

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        ensure_container(ctx, keys.BLACKBOARD, SIM, BB_CONTAINER)
        present: set[str] = set()
        with self.watching([self.INPUT]):
            while self._rearm(ctx):
                seen = self._users(ctx.bb_get(self.INPUT)) | self._sensed(ctx)
                for user in sorted(present - seen):
                    wm_set(ctx, user, "present", False)
                    present.discard(user)
                for user in sorted(seen - present):
                    wm_set(ctx, user, "present", True)
                    location = ctx.wm_get(self.agent, "location")
                    if location is not None:
                        wm_set(ctx, user, "location", location)
                    present.add(user)
                self._wake.wait(self.interval or None)
        return True

    def _sensed(self, ctx: RunContext) -> set[str]:
        """Users a real sensor sees besides the simulated input (none here); a change wakes ``_wake``."""
        return set()

    def _users(self, raw: Any) -> set[str]:
        if raw is None:
            return set()
        items = [str(i) for i in raw] if isinstance(raw, list) else str(raw).split(",")
        users = set()
        for item in (i.strip() for i in items):
            if not item:
                continue
            if keys.is_name(item):
                users.add(item)
            elif item not in self._warned:  # once per name: the fallback re-check would repeat it
                self._warned.add(item)
                log.warning("%s: ignored user %r: not a valid world-model name", self.name, item)
        return users


class GestureDetect(SimulatedCompetency):
    """Waits for the user's gesture (one-shot): "are you the guest?" - a nod answers.

    Run parameters: ``PersonID`` (the user asked), ``Timeout`` (seconds; default the constructor
    parameter, ``10``). The simulated user answers by setting BB ``sim/gesture`` (e.g. ``yes``);
    the gesture is consumed (removed) so one gesture answers one question; one set before the
    question counts too. While waiting, BB ``gesture/waitingFor`` names the user. On a gesture:
    WM ``<user>.answer = <gesture>`` and a ``RemoteAction`` event (name ``Gesture``, parameters
    ``[gesture]``, subject the user) that minds perceive as the user's action. A previous
    ``answer`` is removed when the question starts; no gesture within the timeout fails.
    """

    type = "GestureDetect"
    INPUT = f"{SIM}/gesture"

    def __init__(self, timeout: str = "10", *, name: str | None = None) -> None:
        super().__init__(timeout, name=name)
        self.timeout = parse_seconds(timeout, "GestureDetect: default timeout")

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        user = text_parameter(parameters, "PersonID")
        if not user or not keys.is_name(user):
            return ctx.fail(f"GestureDetect needs a PersonID parameter that is a world-model agent name, got {user!r}")
        try:
            timeout = parse_seconds(parameters.get("Timeout", self.timeout), "GestureDetect: Timeout")
        except ConfigError as exc:
            return ctx.fail(str(exc))
        ensure_container(ctx, keys.BLACKBOARD, SIM, BB_CONTAINER)  # so the simulated user can answer
        remove_property(ctx, keys.WORLD_MODEL, user, "answer")  # a new question voids the last answer
        bb_set(ctx, "gesture/waitingFor", user)
        try:
            gesture = self._await(ctx, timeout)
        finally:
            quietly("gesture/waitingFor", bb_remove, ctx, "gesture/waitingFor")
        if gesture is None:
            if ctx.cancelled.is_set():
                return False
            return ctx.fail(f"no gesture from {user} within {timeout:g} s (nobody set the blackboard's {self.INPUT})")
        wm_set(ctx, user, "answer", gesture)
        ctx.raise_event("RemoteAction", {"name": "Gesture", "parameters": [gesture], "subject": user})
        return True

    def _await(self, ctx: RunContext, timeout: float) -> str | None:
        deadline = time.monotonic() + timeout
        with self.watching([self.INPUT]):
            while self._rearm(ctx):
                sensed = self._sensed(ctx)
                if sensed is not None:
                    return sensed
                raw = ctx.bb_get(self.INPUT)
                if raw is not None and str(raw).strip():
                    bb_remove(ctx, self.INPUT)
                    return str(raw).strip()
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._wake.wait(left)
        return None

    def _sensed(self, ctx: RunContext) -> str | None:
        """A gesture a real sensor saw besides the simulated input (none here); one sets ``_wake``."""
        return None


class CommandInput(SimulatedCompetency):
    """A simulated operator console (background).

    Input: BB ``sim/command``, e.g. ``"greet Guest"``; it is consumed (removed). Effect: WM object
    ``Command`` with ``text`` (the whole command), ``object`` (everything after the first word,
    maybe empty), ``count`` (1, 2, ... so a repeated command is still a change), ``<verb> =
    <object>`` (e.g. ``greet = "Guest"``: one fact holding both, for minds that react to a single
    property such as the planner's ``["Command", "greet", "?who"]`` trigger; skipped when the verb
    is not a valid property name or is one of the names above) and ``verb`` (the first word),
    written in that order: ``verb`` comes last, so a mind reacting to it sees the whole command.
    Constructor parameter: fallback re-check interval (``0``: none).
    """

    type = "CommandInput"
    background = True
    INPUT = f"{SIM}/command"
    ENTITY = "Command"
    FIELDS = frozenset({"text", "object", "count", "verb"})

    def __init__(self, interval: str = "0", *, name: str | None = None) -> None:
        super().__init__(interval, name=name)
        self.interval = parse_seconds(interval, "CommandInput: re-check interval")

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        ensure_container(ctx, keys.BLACKBOARD, SIM, BB_CONTAINER)
        previous = ctx.wm_get(self.ENTITY, "count")
        # Go on counting after a restart, so ``count`` never repeats a value a mind has seen.
        count = previous if isinstance(previous, int) and not isinstance(previous, bool) else 0
        with self.watching([self.INPUT]):
            while self._rearm(ctx):
                typed = self._sensed(ctx)
                raw = typed if typed is not None else ctx.bb_get(self.INPUT)
                if raw is None:
                    self._wake.wait(self.interval or None)
                    continue
                text = " ".join(str(raw).split())
                if text:
                    verb, _, obj = text.partition(" ")
                    count += 1
                    writes: list[tuple[str, Any]] = [("text", text), ("object", obj), ("count", count)]
                    if verb not in self.FIELDS and keys.is_name(verb):
                        writes.append((verb, obj))
                    writes.append(("verb", verb))
                    for prop, value in writes:
                        wm_set(ctx, self.ENTITY, prop, value, kind="object")
                # A different command typed meanwhile stays for the next round.
                if typed is None and ctx.bb_get(self.INPUT) == raw:
                    bb_remove(ctx, self.INPUT)
        return True

    def _sensed(self, ctx: RunContext) -> str | None:
        """A command typed on a real console besides the simulated input (none here); one sets ``_wake``."""
        return None
