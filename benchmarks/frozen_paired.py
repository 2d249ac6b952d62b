#!/usr/bin/env python
"""The recorded part of an iteration (psdr_cli/optimisation/frozen_batch.py) against the traced iteration on
the same work: the demo's experiment (``configs/reconstruct_bunny.yaml``) on its initial shape with
Adam's step set to 0 (every iteration does the same work on the same shape), one process, the loop
body as ``psdr optimize`` runs it (iterate, apply; no kernel history, asynchronous launches), blocks
of ``--block`` iterations traced and frozen alternated ``--rounds`` times after a warm-up of each.
Prints and writes the median seconds per iteration of each mode, their ratio, and the reference
loop (10⁷ Python steps) before and after.

    .venv/bin/python benchmarks/frozen_paired.py [--scales 1,2] [--block 5] [--rounds 6] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import drjit as dr  # noqa: E402
from iteration_time import setup  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

from psdr_cli.optimisation import iteration  # noqa: E402
from psdr_cli.optimisation.frozen_batch import FrozenBatch  # noqa: E402
from psdr_cli.support import backend  # noqa: E402


def paired(scale: int, block: int, rounds: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        exp, files, problem, settings, engine, stage = setup(scale, Path(tmp))
        problem.opt.set_learning_rate(0.0)
        loops = {"traced": iteration.Loop(replace(exp.optimize, learning_rate=0.0), engine, 10 ** 6, print),
                 "frozen": iteration.Loop(replace(exp.optimize, learning_rate=0.0), engine, 10 ** 6, print,
                                          frozen=FrozenBatch())}
        times = {"traced": [], "frozen": []}
        guides = iteration.GuideCache()
        it = 0
        with backend.optimization_threads():
            for r in range(rounds + 1):
                for mode, loop in loops.items():
                    for _ in range(block):
                        t0 = time.perf_counter()
                        iteration.iterate(problem, loop, stage, guides, it)
                        problem.apply()
                        dr.sync_thread()
                        if r > 0:  # round 0 warms both modes up
                            times[mode].append(time.perf_counter() - t0)
                        it += 1
        recordings = loops["frozen"].frozen.n_recordings
        problem.release()
    out = {m: {"median_s": statistics.median(t), "mean_s": statistics.fmean(t), "n": len(t)} for m, t in times.items()}
    out["ratio_frozen_to_traced"] = out["frozen"]["median_s"] / out["traced"]["median_s"]
    out["recordings"] = recordings
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scales", default="1,2", help="film scales: 1 = 64², 2 = 128²")
    ap.add_argument("--block", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out = {"drjit": dr.__version__, "reference_before": reference_loop_seconds(), "scales": {}}
    for s in (int(x) for x in args.scales.split(",")):
        res = paired(s, args.block, args.rounds)
        out["scales"][f"{64 * s}x{64 * s}"] = res
        print(f"{64 * s}²: traced median {res['traced']['median_s'] * 1e3:.1f} ms, frozen median "
              f"{res['frozen']['median_s'] * 1e3:.1f} ms per iteration ({res['traced']['n']} each): frozen / traced "
              f"{res['ratio_frozen_to_traced']:.3f}; {res['recordings']} recordings", flush=True)
    out["reference_after"] = reference_loop_seconds()
    print(f"reference loop {out['reference_before']:.2f} / {out['reference_after']:.2f} s")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
