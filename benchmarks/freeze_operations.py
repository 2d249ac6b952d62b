#!/usr/bin/env python
"""What a replayed frozen function launches besides its kernels: Dr.Jit's kernel history of the
fourth call of small ``dr.freeze`` functions (LLVM): one that divides by a ``dr.opaque`` scalar,
one that seeds Mitsuba's independent sampler (as every pass of psdr does,
``estimators.passes.make_sampler``), one with a reverse-mode pass, and a plain one. With the
demo iteration's operation list (``--iteration``: one frozen iteration of
``configs/reconstruct_bunny.yaml`` after four warm-up iterations, grouped by the part that
launched it) it says where the recorded iteration's operations come from
(docs/benchmarks/iteration_time.md, stop 53).

    .venv/bin/python benchmarks/freeze_operations.py [--iteration] [--json FILE]
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")

import iteration_time  # noqa: E402
from psdr_cli.estimators.passes import make_sampler  # noqa: E402
from psdr_cli.optimisation import iteration  # noqa: E402
from psdr_cli.optimisation.frozen_batch import FrozenBatch  # noqa: E402
from psdr_cli.support import backend  # noqa: E402


def operations(history) -> list:
    """(type, size) of each entry of a kernel history."""
    return [(str(e["type"]).split(".")[-1], int(e.get("size", 0))) for e in history]


def replayed(fn, *args) -> list:
    """The operations of the fourth call of ``fn`` (recorded at the first, replayed after)."""
    for _ in range(3):
        dr.eval(fn(*args))
    dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.eval(fn(*args))
    out = operations(dr.kernel_history())
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return out


@dr.freeze
def with_opaque(x):
    return x * 2 + dr.arange(mi.UInt32, 100) // dr.opaque(mi.UInt32, 7)


@dr.freeze
def with_sampler(seed):
    return make_sampler(seed, 1000).next_1d()


@dr.freeze
def with_backward(x, d):
    dr.backward(dr.sum(d * x * x))
    return d


@dr.freeze
def plain(x):
    return x * 2


def probes() -> dict:
    x = dr.arange(mi.Float, 1000)
    dr.enable_grad(x)
    return {"opaque scalar": replayed(with_opaque, mi.UInt32(5)),
            "sampler seeded": replayed(with_sampler, mi.UInt32(5)),
            "reverse pass": replayed(with_backward, x, dr.full(mi.Float, 0.5, 1000)),
            "plain": replayed(plain, dr.arange(mi.Float, 100))}


def iteration_operations() -> dict:
    """One frozen demo iteration's operations per part (see the module docstring)."""
    parts = {}
    with tempfile.TemporaryDirectory() as tmp:
        exp, _, problem, _, engine, stage = iteration_time.setup(1, Path(tmp))
        loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=FrozenBatch())
        guides = iteration.GuideCache()
        with backend.optimization_threads():
            for it in range(4):
                iteration.iterate(problem, loop, stage, guides, it)
                problem.apply()

            def part(name, fn):
                def run(*args, **kwargs):
                    parts.setdefault("between", []).extend(operations(dr.kernel_history()))
                    out = fn(*args, **kwargs)
                    parts.setdefault(name, []).extend(operations(dr.kernel_history()))
                    return out
                return run
            loop.frozen.__class__ = type("Timed", (FrozenBatch,), {"__call__": part("frozen call", FrozenBatch.__call__)})
            for name, recorded in loop.frozen.parts.items():
                recorded.run = part(f"frozen {name}", recorded.run)
            problem.backward_leaves = part("backward through large steps", problem.backward_leaves)
            problem.opt.step = part("Adam step", problem.opt.step)
            dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            iteration.iterate(problem, loop, stage, guides, 4)
            part("scene written (apply)", problem.apply)()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        problem.release()
    return parts


def summary(ops: list) -> dict:
    return dict(collections.Counter(t for t, _ in ops))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iteration", action="store_true", help="also list one frozen demo iteration's operations")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out = {"probes": probes()}
    for name, ops in out["probes"].items():
        print(f"{name}: {ops}")
    if args.iteration:
        parts = iteration_operations()
        out["iteration"] = {name: {"count": len(ops), "types": summary(ops), "operations": ops}
                            for name, ops in parts.items()}
        print(f"one frozen iteration: {sum(len(o) for o in parts.values())} operations")
        for name, ops in parts.items():
            print(f"  {name}: {len(ops)} {summary(ops)}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
