"""Competencies of a body on a web page (``web.body.WebBody``): speech, animation, gestures,
visitors and typed commands. They reach the body through its component half (``web.face.Face``)
and never import its HTTP server: an embodiment that serves no page starts without it.

Each one is the simulated competency of the same type (``spirit.py``) with its world made real:
the same constructor parameters, run parameters, blackboard and world-model writes and events, so
rules and minds cannot tell them apart. When the embodiment has a web body serving its page:

* ``WebSpeechSynthesis`` synthesizes the line on the server (espeak-ng, ``web/speech.py``), shows it on
  the page with its audio and lip movement, and takes as long as the sound does; without a speech
  engine the page shows the text for as long as reading it takes (one warning in the log);
* ``WebAnimation`` plays the animation on the face, at least ``ANIMATION_SECONDS`` of it;
* ``WebGestureDetect`` shows the question with yes/no buttons (keys y/n) and takes the answer;
* ``WebUserDetection`` sees the visitors the page reports (its "I am here" button);
* ``WebCommandInput`` takes commands typed on the page.

The simulated inputs (the blackboard's ``sim`` container) keep working beside the page, and
without a web body each competency is exactly its simulated self: the shipped screen and phone
use these, and the text demo and the tests run them as simulations.
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar

from cmion_mesh.competencies.common import SELF, parse_seconds
from cmion_mesh.competencies.spirit import Animation, CommandInput, GestureDetect, SpeechSynthesis, UserDetection
from cmion_mesh.competency import RunContext
from cmion_mesh.errors import ConfigError
from cmion_mesh.web.face import Face, WebSense, web_body
from cmion_mesh.web.speech import SpeechUnavailable, duration, synthesize

__all__ = ["WebAnimation", "WebCommandInput", "WebGestureDetect", "WebSpeechSynthesis", "WebUserDetection"]

log = logging.getLogger(__name__)

#: Seconds an animation takes on the page (the face needs time to be seen doing it).
ANIMATION_SECONDS: dict[str, float] = {"wave": 1.6, "nod": 1.0, "smile": 1.2, "happy": 1.5, "sad": 1.5, "curious": 1.2, "talk": 0.8}
#: Reading speed used for a line shown without sound (characters per second).
READING_SPEED = 15.0


def _body(competency: Any) -> Face | None:
    sim = competency._sim
    return None if sim is None else web_body(sim)


class WebSpeechSynthesis(SpeechSynthesis):
    """``SpeechSynthesis`` aloud on the page. Constructor parameters: seconds per utterance when
    simulated (``0.05``), the self agent (``Self``), the espeak-ng voice (``en``), words per minute
    (``165``)."""

    _warned: ClassVar[bool] = False

    def __init__(self, step: str = "0.05", agent: str = SELF, voice: str = "en", words_per_minute: str = "165", *,
                 name: str | None = None) -> None:
        super().__init__(step, agent, name=name or "SpeechSynthesis")
        self.constructor_parameters = (step, agent, voice, words_per_minute)
        self.voice = voice
        try:
            self.words_per_minute = max(80, min(450, int(words_per_minute)))
        except ValueError:
            raise ConfigError(f"WebSpeechSynthesis: words per minute {words_per_minute!r} is not a whole number") from None

    def _speak(self, text: str, ctx: RunContext) -> bool:
        body = _body(self)
        if body is None:
            return super()._speak(text, ctx)
        wav: bytes | None
        try:
            wav = synthesize(text, voice=self.voice, words_per_minute=self.words_per_minute)
            seconds = duration(wav)
        except SpeechUnavailable as exc:
            if not WebSpeechSynthesis._warned:
                WebSpeechSynthesis._warned = True
                log.warning("%s: the page shows the text without sound: %s", self.name, exc)
            wav, seconds = None, max(1.0, len(text) / READING_SPEED)
        utterance = body.begin_speech(text, wav, seconds)
        try:
            return ctx.wait(seconds)
        finally:
            body.end_speech(utterance)


class WebAnimation(Animation):
    """``Animation`` on the page's face (constructor parameters as ``Animation``'s)."""

    def __init__(self, step: str = "0.05", *animations: str, name: str | None = None) -> None:
        super().__init__(step, *animations, name=name or "Animation")

    def _play(self, animation: str, ctx: RunContext) -> bool:
        body = _body(self)
        if body is None:
            return super()._play(animation, ctx)
        body.begin_animation(animation)
        try:
            return ctx.wait(max(self.step, ANIMATION_SECONDS.get(animation, 1.0)))
        finally:
            body.end_animation(animation)


class WebGestureDetect(WebSense, GestureDetect):
    """``GestureDetect`` answered on the page: yes/no buttons or keys while the question waits.
    Constructor parameters: the default timeout when simulated (``10``), and when a person
    answers on the page (``120``: people read, hesitate, walk up to the screen); a ``Timeout`` run
    parameter wins over both."""

    sense = "answer"

    def __init__(self, timeout: str = "10", page_timeout: str = "120", *, name: str | None = None) -> None:
        super().__init__(timeout, name=name or "GestureDetect")
        self.constructor_parameters = (timeout, page_timeout)
        self.page_timeout = parse_seconds(page_timeout, "WebGestureDetect: timeout on a page")

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        body = _body(self)
        if body is None:
            return super().run(parameters, ctx)
        if "Timeout" not in parameters:
            parameters = {**parameters, "Timeout": self.page_timeout}
        body.begin_ask(str(parameters.get("PersonID", "")).strip())
        try:
            return super().run(parameters, ctx)
        finally:
            body.end_ask()

    def _sensed(self, ctx: RunContext) -> str | None:
        body = _body(self)
        return None if body is None else body.take_answer()


class WebUserDetection(WebSense, UserDetection):
    """``UserDetection`` that also sees the visitors the page reports."""

    sense = "visitor"

    def __init__(self, interval: str = "0", agent: str = SELF, *, name: str | None = None) -> None:
        super().__init__(interval, agent, name=name or "UserDetection")

    def _sensed(self, ctx: RunContext) -> set[str]:
        body = _body(self)
        return set() if body is None else body.visitors()


class WebCommandInput(WebSense, CommandInput):
    """``CommandInput`` that also takes the commands typed on the page."""

    sense = "command"

    def __init__(self, interval: str = "0", *, name: str | None = None) -> None:
        super().__init__(interval, name=name or "CommandInput")

    def _sensed(self, ctx: RunContext) -> str | None:
        body = _body(self)
        return None if body is None else body.take_command()
