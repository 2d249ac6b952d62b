"""A Ctrl-C that lands in a finaliser (psdr_cli/support/interrupts.py): Python drops a
KeyboardInterrupt raised in a weakref callback, as the one a finished thread pool runs (the
geometry worker's, every iteration), and `psdr optimize` then ran on after a Ctrl-C (seen once in
tests/test_faults.py::test_two_optimize_processes_on_one_run under a loaded suite: the run was
still going 120 s after the signal)."""
from __future__ import annotations

import signal
import weakref

import pytest

from psdr_cli.support.interrupts import InterruptLatch


class Thing:
    pass


def drop_an_interrupt():
    """Raise SIGINT inside a weakref callback: its KeyboardInterrupt is dropped ("Exception ignored")."""
    thing = Thing()
    ref = weakref.ref(thing, lambda _: signal.raise_signal(signal.SIGINT))
    del thing
    return ref


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_ctrl_c_dropped_by_a_finaliser_is_raised_again_by_the_latch():
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        drop_an_interrupt()  # without the latch: lost, and we get here
        with InterruptLatch() as latch:
            latch.check()  # nothing yet
            drop_an_interrupt()  # dropped where it landed...
            with pytest.raises(KeyboardInterrupt):
                latch.check()  # ...and raised at the loop's next safe point
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_the_latch_leaves_another_handler_alone():
    def mine(signum, frame):
        pass
    previous = signal.signal(signal.SIGINT, mine)
    try:
        with InterruptLatch() as latch:
            assert signal.getsignal(signal.SIGINT) is mine
            signal.raise_signal(signal.SIGINT)
            latch.check()  # not the latch's signal: no raise
        assert signal.getsignal(signal.SIGINT) is mine
    finally:
        signal.signal(signal.SIGINT, previous)
