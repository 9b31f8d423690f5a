"""Waiting for SIGINT/SIGTERM in long-running commands, reliably.

A signal sent to a process may be delivered to any thread; zenoh's own threads would take it and
the main thread, blocked in a wait, would never see it. So every command that runs until
stopped blocks the signals *before* starting any thread (new threads inherit the mask) and the
main thread collects them with ``sigwait``: no polling, no lost signal.
"""

from __future__ import annotations

import signal
import threading

STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}
_WAKE = signal.SIGUSR1


class Stopper:
    """Create on the main thread before any other thread; ``wait`` until a signal or ``stop``."""

    def __init__(self) -> None:
        self._main = threading.main_thread().ident
        self.received: int | None = None
        signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS | {_WAKE})

    def wait(self, timeout: float | None = None) -> int | None:
        """The signal that stopped us (None after a ``stop()`` or a timeout)."""
        wanted = STOP_SIGNALS | {_WAKE}
        sig: int | None
        if timeout is None:
            sig = signal.sigwait(wanted)
        else:
            info = signal.sigtimedwait(wanted, timeout)
            sig = info.si_signo if info is not None else None
        if sig in STOP_SIGNALS:
            self.received = sig
            return sig
        return None

    def stop(self) -> None:
        """Wake ``wait`` from any thread."""
        if self._main is not None:
            signal.pthread_kill(self._main, _WAKE)


def terminate_as_interrupt() -> None:
    """Make SIGTERM stop a foreground command as Ctrl-C does (``KeyboardInterrupt``), so its
    ``finally`` blocks run: the demo's daemons live in sessions of their own and would outlive it."""

    def interrupt(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)


def wait_for_stop_signal() -> int:
    """Block the main thread until SIGINT or SIGTERM, whichever thread the kernel hands it to.

    For commands that started threads before they wait (so ``Stopper``'s mask comes too late): a
    signal caught by another thread only flags the main thread, which would sleep on; the wakeup
    fd is written whichever thread catches it.
    """
    import socket

    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    reader, writer = socket.socketpair()
    writer.setblocking(False)
    old_fd = signal.set_wakeup_fd(writer.fileno())
    try:
        for sig in STOP_SIGNALS:
            signal.signal(sig, lambda *_: None)  # the wakeup fd tells; nothing to raise
        return reader.recv(1)[0]
    finally:
        signal.set_wakeup_fd(old_fd)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        reader.close()
        writer.close()
