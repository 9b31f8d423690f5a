"""Speech synthesis for bodies that speak aloud: text -> WAV bytes with espeak-ng.

espeak-ng is a packaged engine (Debian: ``apt-get install espeak-ng``), small and offline; it is
run as a process per utterance, with the text on its standard input so that no text is ever read
as an option. ``--stdout`` streams, so it writes "unknown" sizes into the WAV header: they are
set here, because browsers and WAV readers trust them.
"""

from __future__ import annotations

import os
import shutil
import struct

from cmion_mesh.errors import MeshError

#: Longest text synthesized in one utterance (characters): a body says sentences, not books.
MAX_TEXT = 2000
#: Seconds allowed to synthesize one utterance.
TIMEOUT = 20.0
#: Environment variable naming the engine's executable, for an install outside $PATH.
ENGINE_ENV = "CMION_MESH_ESPEAK"


class SpeechUnavailable(MeshError):
    """No speech engine, or it failed on this text: the body shows the text without sound."""


def engine() -> str | None:
    """The espeak-ng (or espeak) executable, or None when neither is installed."""
    configured = os.environ.get(ENGINE_ENV)
    if configured:
        return configured if os.access(configured, os.X_OK) else None
    return shutil.which("espeak-ng") or shutil.which("espeak")


def synthesize(text: str, *, voice: str = "en", words_per_minute: int = 165) -> bytes:
    """The WAV (16-bit PCM) of ``text`` spoken; ``SpeechUnavailable`` saying why when it cannot be."""
    exe = engine()
    if exe is None:
        raise SpeechUnavailable("no speech engine: install espeak-ng (apt-get install espeak-ng) "
                                f"or name its executable in ${ENGINE_ENV}")
    spoken = " ".join(text.split())[:MAX_TEXT]
    if not spoken:
        raise SpeechUnavailable("nothing to say: the text is empty")
    import subprocess  # here: the robot's library holds the speech competency but speaks on no page

    try:
        done = subprocess.run([exe, "--stdout", "-v", voice, "-s", str(words_per_minute)], input=spoken.encode(),
                              capture_output=True, timeout=TIMEOUT, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SpeechUnavailable(f"{exe} failed: {exc}") from None
    if done.returncode != 0 or len(done.stdout) <= 44:
        why = done.stderr.decode(errors="replace").strip() or f"exit status {done.returncode}, {len(done.stdout)} bytes"
        raise SpeechUnavailable(f"{exe} (voice {voice!r}) failed: {why}")
    return fix_header(done.stdout)


def _chunks(wav: bytes) -> tuple[int, int]:
    """Offsets of the ``fmt `` chunk's body and of the ``data`` chunk's header."""
    if wav[:4] != b"RIFF" or wav[8:12] != b"WAVE":
        raise SpeechUnavailable("not a WAV file (no RIFF/WAVE header)")
    offset, fmt = 12, -1
    while offset + 8 <= len(wav):
        tag, size = wav[offset:offset + 4], struct.unpack_from("<I", wav, offset + 4)[0]
        if tag == b"fmt ":
            fmt = offset + 8
        elif tag == b"data":
            if fmt < 0:
                raise SpeechUnavailable("WAV data before its fmt chunk")
            return fmt, offset
        offset += 8 + size + (size & 1)
    raise SpeechUnavailable("WAV without a data chunk")


def fix_header(wav: bytes) -> bytes:
    """``wav`` with its RIFF and data sizes set to what the bytes hold."""
    _, data = _chunks(wav)
    out = bytearray(wav)
    struct.pack_into("<I", out, 4, len(wav) - 8)
    struct.pack_into("<I", out, data + 4, len(wav) - data - 8)
    return bytes(out)


def duration(wav: bytes) -> float:
    """Seconds of sound in a PCM WAV."""
    fmt, data = _chunks(wav)
    _, channels, rate, _, block_align, _ = struct.unpack_from("<HHIIHH", wav, fmt)
    if rate <= 0 or block_align <= 0 or channels <= 0:
        raise SpeechUnavailable(f"WAV with an unusable format (rate {rate}, channels {channels}, block {block_align})")
    size: int = min(struct.unpack_from("<I", wav, data + 4)[0], len(wav) - data - 8)
    return float(size / block_align / rate)
