#!/usr/bin/env python
"""Forward-mode passes per term (issue 38, "psdr grad gets the same treatment where it loops"):
wall time, kernel execution, code generation and the rest of ``forward_gradient`` of each term
of ``--config`` (default ``configs/demo.yaml``, view 0, unguided) in ``--passes`` passes, after
two warm-up calls, the third with Dr.Jit's kernel history and blocking launches. ``psdr grad``
with ``estimator.passes``, ``psdr compare``'s reference and the tests' gradient checks
split their samples into passes like this (per-pass images give the standard errors).

    .venv/bin/python benchmarks/grad_passes.py [--passes 16] [--json docs/benchmarks/grad_passes.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

import psdr_cli  # noqa: E402
from psdr_cli.rendering.estimate import forward_gradient, prepare  # noqa: E402


def measured_terms(scene, parameter, edges, settings, terms, passes: int) -> dict:
    """{term: wall, execution, codegen, other (s), operations, passes} of one forward_gradient each."""
    out = {}
    for term in terms:
        dr.sync_thread()
        dr.kernel_history()  # clear
        t = time.perf_counter()
        est = forward_gradient(scene, edges, parameter, 0, term, settings, passes)
        dr.sync_thread()
        wall = time.perf_counter() - t
        history = dr.kernel_history()
        execution = sum(k.get("execution_time", 0.0) for k in history) / 1e3
        codegen = sum(k.get("codegen_time", 0.0) for k in history) / 1e3
        out[term] = {"wall": wall, "execution": execution, "codegen": codegen, "other": wall - execution - codegen,
                     "operations": len(history), "passes": len(est.passes)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "demo.yaml")
    ap.add_argument("--passes", type=int, default=16)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    exp = psdr_cli.load_experiment(args.config)
    scene, parameter, edges, settings = prepare(exp)
    settings = settings.with_estimator(guiding="none")
    terms = list(exp.estimator.terms)
    result = {"config": str(args.config), "passes": args.passes, "threads": dr.thread_count(),
              "drjit": dr.__version__, "reference_before": reference_loop_seconds()}
    for _ in range(2):  # warm-up: kernels compiled or loaded from the cache
        for term in terms:
            forward_gradient(scene, edges, parameter, 0, term, settings, args.passes)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.set_flag(dr.JitFlag.LaunchBlocking, True)
    try:
        result["terms"] = measured_terms(scene, parameter, edges, settings, terms, args.passes)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        dr.set_flag(dr.JitFlag.LaunchBlocking, False)
    result["reference_after"] = reference_loop_seconds()
    for term, r in result["terms"].items():
        print(f"{term:9s} {r['passes']} passes: wall {r['wall']:.3f} s, kernel execution {r['execution']:.3f} s, "
              f"codegen {r['codegen']:.3f} s, other {r['other']:.3f} s, {r['operations']} operations; "
              f"wall / execution {r['wall'] / max(r['execution'], 1e-9):.2f}")
    total = sum(r["wall"] for r in result["terms"].values())
    print(f"all terms: {total:.3f} s; reference loop {result['reference_before']:.3f} / {result['reference_after']:.3f} s")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
