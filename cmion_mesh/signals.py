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



class Interrupter:
    """For a foreground command that both runs (Ctrl-C or SIGTERM interrupts it, as
    ``KeyboardInterrupt``, so its ``finally`` blocks run) and then may wait to be stopped.

    Create on the main thread before any other thread: it blocks the signals there (threads
    inherit the mask) and one thread of its own collects them with ``sigwait``, so no other
    thread, nor a handler installed by a library, can swallow one.
    """

    def __init__(self) -> None:
        self._stopper = Stopper()
        # ``interrupt_main`` raises KeyboardInterrupt only where SIGINT has Python's handler: a
        # command started in the background by a shell script inherits SIGINT ignored, and would
        # never be interrupted. The signals themselves are blocked and collected by ``sigwait``
        # (Linux queues a blocked signal even when ignored), so this handler only ever runs for
        # ``interrupt_main``.
        if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        self.stopped = threading.Event()
        self._waiting = False
        self._thread = threading.Thread(target=self._collect, name="signals", daemon=True)
        self._thread.start()

    def _collect(self) -> None:
        import _thread

        self._stopper.wait()
        self.stopped.set()
        if not self._waiting:
            _thread.interrupt_main()  # KeyboardInterrupt on the main thread at its next step

    @property
    def received(self) -> int | None:
        """The signal that stopped us, if one did."""
        return self._stopper.received

    def exit_code(self) -> int:
        """The shell's code for a command a signal stopped: 128 + the signal (130 for SIGINT,
        143 for SIGTERM)."""
        return 128 + (self.received or signal.SIGINT)

    def wait(self) -> None:
        """Until SIGINT or SIGTERM (at once if one came already)."""
        self._waiting = True
        self.stopped.wait()
