"""The speed of the machine a benchmark runs on, recorded next to its absolute times."""
from __future__ import annotations

import time


def reference_loop_seconds() -> float:
    """Seconds of a fixed 10⁷-step Python loop: this machine's speed at this moment."""
    t = time.perf_counter()
    s = 0
    for i in range(10_000_000):
        s += i
    return time.perf_counter() - t
