#!/usr/bin/env python
"""Can the loop's Python tracing overlap its kernels without losing bit-reproducibility (issue 38)?

``psdr optimize`` runs Dr.Jit's LLVM backend with one thread (``PSDR_OPTIMIZE_THREADS=1``): a pool
without workers, so every kernel runs on the calling thread before the launch returns and the
tracing of the next kernels waits for it. A pool of two threads (the caller and one worker) makes
launches asynchronous, but the backend then splits every kernel with more SIMD packets than
threads into one work item per thread (drjit-core's launch heuristic, whatever
``jit_llvm_set_block_size`` says), and a scatter-add's floating-point sum then depends on which
thread adds first. Measured here, side by side in one process:

1. whether ``dr.eval`` of a 4·10⁶-lane kernel returns before the kernel has run (1 vs 2 threads);
2. how many distinct results twenty repetitions of the same scatter-add give (16 384 lanes into
   1 117 bins, the shape of the primary term's reverse-mode gather), with 1 thread, 2 threads,
   and 2 threads with the largest work items that do not overflow (``jit_llvm_set_block_size``
   of drjit-core's public C API: 2^24 packets, called through ctypes).

    .venv/bin/python benchmarks/overlap_probe.py [--json docs/benchmarks/overlap_probe.json]
"""
from __future__ import annotations

import argparse
import ctypes
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

from psdr_cli.support import backend  # noqa: E402


def long_kernel():
    x = dr.arange(mi.Float, 4_000_000)
    for _ in range(40):
        x = dr.sin(x) * 1.0001 + 0.5
    return x


def launch_seconds() -> tuple:
    """(seconds until ``dr.eval`` returns, seconds until the kernel is done)."""
    x = long_kernel()
    t0 = time.perf_counter()
    dr.eval(x)
    returned = time.perf_counter() - t0
    dr.sync_thread()
    return returned, time.perf_counter() - t0


def scatter_add(n: int = 16384, bins: int = 1117) -> bytes:
    """Σ cos(i) into bin ⌊(sin(1.7 i)/2 + 1/2)·bins⌋: one kernel with atomic adds."""
    k = mi.UInt32(dr.floor(dr.sin(dr.arange(mi.Float, n) * 1.7) * 0.5 * bins + 0.5 * bins))
    out = dr.zeros(mi.Float, bins)
    dr.scatter_reduce(dr.ReduceOp.Add, out, dr.cos(dr.arange(mi.Float, n)), k)
    dr.eval(out)
    return np.asarray(out).tobytes()


def set_block_size(packets: int | None):
    """drjit-core's ``jit_llvm_set_block_size`` (None: leave it)."""
    if packets is not None:
        lib = ctypes.CDLL(str(Path(dr.__file__).parent / "libdrjit-core.so"))
        setter = lib["_Z23jit_llvm_set_block_sizej"]
        setter.argtypes = [ctypes.c_uint32]
        setter(packets)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    backend.select_variant("llvm_ad_rgb")
    result = {"drjit": dr.__version__, "reference_before": reference_loop_seconds(), "threads": {}}
    for label, threads, block in (("1 thread", 1, None), ("2 threads", 2, None),
                                  ("2 threads, block 2^24 packets", 2, 1 << 24)):
        dr.set_thread_count(threads)
        set_block_size(block)
        long_kernel()
        dr.sync_thread()
        launch_seconds()  # compiled, cached
        returned, done = launch_seconds()
        distinct = len({scatter_add() for _ in range(20)})
        result["threads"][label] = {"eval_returns_s": returned, "kernel_done_s": done,
                                    "distinct_scatter_add_results_of_20": distinct}
        print(f"{label}: dr.eval returns after {returned * 1e3:.1f} ms, kernel done after "
              f"{done * 1e3:.1f} ms; a scatter-add repeated 20 times gave {distinct} distinct result(s)")
    result["reference_after"] = reference_loop_seconds()
    print(f"reference loop (10⁷ steps): {result['reference_before']:.2f} s / {result['reference_after']:.2f} s")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
