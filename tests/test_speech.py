"""Speech synthesis: espeak-ng's streamed WAV gets true sizes; no engine is a clear error."""

from __future__ import annotations

import struct

import pytest

from cmion_mesh.web import speech


def pcm_wav(samples: int, rate: int = 22050, sizes: int | None = None) -> bytes:
    data = b"\x00\x01" * samples
    fmt = struct.pack("<HHIIHH", 1, 1, rate, rate * 2, 2, 16)
    riff = sizes if sizes is not None else 36 + len(data)
    return (b"RIFF" + struct.pack("<I", riff) + b"WAVE" + b"fmt " + struct.pack("<I", 16) + fmt
            + b"data" + struct.pack("<I", sizes if sizes is not None else len(data)) + data)


def test_a_streamed_header_gets_the_sizes_its_bytes_hold() -> None:
    streamed = pcm_wav(22050, sizes=0x7FFFF000)  # what `espeak-ng --stdout` writes: it cannot know
    fixed = speech.fix_header(streamed)
    assert fixed == pcm_wav(22050)
    assert speech.duration(fixed) == pytest.approx(1.0)


def test_not_a_wav_is_refused() -> None:
    with pytest.raises(speech.SpeechUnavailable, match="not a WAV"):
        speech.duration(b"hello")


def test_no_engine_says_how_to_get_one(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(speech.ENGINE_ENV, "/nonexistent/espeak-ng")
    with pytest.raises(speech.SpeechUnavailable, match="install espeak-ng"):
        speech.synthesize("hello")


@pytest.mark.skipif(speech.engine() is None, reason="no espeak-ng: apt-get install espeak-ng")
def test_espeak_speaks_a_line_of_plausible_length() -> None:
    wav = speech.synthesize("-v Hello, welcome to the building!")  # a leading dash is text, not an option
    assert 0.8 < speech.duration(wav) < 8.0
