"""A Ctrl-C that a long loop never loses.

Python raises KeyboardInterrupt wherever the main thread is when SIGINT arrives; raised inside a
finaliser (a weakref callback, a ``__del__``, such as the one a finished thread pool runs) it is
printed as "Exception ignored" and dropped, and the loop would run on. :class:`InterruptLatch`
replaces Python's default SIGINT handler while a loop runs: the signal still raises
KeyboardInterrupt where it lands, and it is remembered, so that :meth:`InterruptLatch.check` at
the loop's safe points raises it again if it was dropped. Touches only the SIGINT handler of the
main thread, and only when it is Python's default.
"""
from __future__ import annotations

import signal
import threading


class InterruptLatch:
    """Context manager: SIGINT sets :attr:`seen` and raises KeyboardInterrupt; :meth:`check`
    raises it again once seen. Off the main thread, or with a handler other than Python's
    default installed, it changes nothing (and :meth:`check` never raises)."""

    def __init__(self):
        self.seen = False
        self.previous = None

    def __enter__(self) -> "InterruptLatch":
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self.previous = signal.signal(signal.SIGINT, self.interrupted)
        return self

    def interrupted(self, signum, frame):
        """The SIGINT handler: remember, then raise where the signal landed."""
        self.seen = True
        raise KeyboardInterrupt

    def check(self):
        """Raise KeyboardInterrupt if SIGINT came since :meth:`__enter__` (its first raise may have
        been dropped by a finaliser)."""
        if self.seen:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> bool:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
            self.previous = None
        return False
