#!/usr/bin/env python
"""How much of ``psdr render`` and ``psdr grad`` is kernel execution (issue 38: "psdr render and
psdr grad get the same treatment where they loop"): wall time, Dr.Jit's kernel execution, code
generation and the rest ("Python": tracing, numpy, file output), and the operations launched, from
Dr.Jit's kernel history, for one call of each command's library function in this process (after
one warm-up call, so that the kernels come from the cache):

- ``render``: :func:`psdr_cli.rendering.render.render_experiment` of ``--render-config`` (default the
  demo's reconstruction), all views at ``--render-spp`` (default its targets' 128);
- ``grad``: :func:`psdr_cli.rendering.estimate.gradient_images` of ``--grad-config`` (default
  ``configs/demo.yaml``, the first example of the README), view 0, every term at its configured
  sample counts (``--grad-spp``: the interior's, as ``psdr grad --spp``);
- ``grad_passes``: the same in ``--grad-passes`` passes per term (default 16; ``psdr grad``
  with ``estimator.passes``, ``psdr compare``'s reference and the tests' gradient
  checks split their samples so, for per-pass images and standard errors).

    .venv/bin/python benchmarks/command_overhead.py [--json docs/benchmarks/command_overhead.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

import psdr_cli  # noqa: E402
from psdr_cli.rendering.estimate import gradient_images  # noqa: E402
from psdr_cli.rendering.render import render_experiment  # noqa: E402


def measured(fn) -> dict:
    """Wall time of one call of ``fn`` as the command runs it (asynchronous launches, the kernel
    history off), then kernel execution, code generation (seconds) and operations of a second
    call with the history on and blocking launches (so that each kernel's time is its own)."""
    t = time.perf_counter()
    fn()
    dr.sync_thread()
    wall = time.perf_counter() - t
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.set_flag(dr.JitFlag.LaunchBlocking, True)
    dr.kernel_history()  # clear
    t = time.perf_counter()
    fn()
    dr.sync_thread()
    wall_blocking = time.perf_counter() - t
    history = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    dr.set_flag(dr.JitFlag.LaunchBlocking, False)
    execution = sum(k.get("execution_time", 0.0) for k in history) / 1e3
    codegen = sum(k.get("codegen_time", 0.0) for k in history) / 1e3
    jit = sum(k["type"] == dr.KernelType.JIT for k in history)
    return {"wall": wall, "wall_blocking": wall_blocking, "execution": execution, "codegen": codegen,
            "python_blocking": wall_blocking - execution - codegen, "operations": len(history),
            "jit_kernels": int(jit), "wall_over_execution": wall / max(execution, 1e-9)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--render-config", type=Path, default=REPO / "configs" / "reconstruct_bunny.yaml")
    ap.add_argument("--grad-config", type=Path, default=REPO / "configs" / "demo.yaml")
    ap.add_argument("--render-spp", type=int, default=128, help="samples per pixel of the render (the demo's targets)")
    ap.add_argument("--grad-spp", type=int, default=None, help="the interior term's samples per pixel (psdr grad --spp)")
    ap.add_argument("--grad-passes", type=int, default=16, help="passes per term of the grad_passes measurement")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    render_exp = psdr_cli.load_experiment(args.render_config)
    grad_exp = psdr_cli.load_experiment(args.grad_config)
    out = {"threads": dr.thread_count(), "render_config": str(args.render_config), "grad_config": str(args.grad_config),
           "drjit": dr.__version__, "reference_before": reference_loop_seconds()}
    with tempfile.TemporaryDirectory() as tmp:
        render = lambda: render_experiment(render_exp, spp=args.render_spp, out=Path(tmp))  # noqa: E731
        grad = lambda: gradient_images(grad_exp, view=0, spp=args.grad_spp)  # noqa: E731
        grad_passes = lambda: gradient_images(grad_exp, view=0, spp=args.grad_spp, min_passes=args.grad_passes)  # noqa: E731
        for name, fn in (("render", render), ("grad", grad), ("grad_passes", grad_passes)):
            fn()  # warm-up: kernels compiled or loaded from the cache
            out[name] = measured(fn)
    out["reference_after"] = reference_loop_seconds()
    out["grad_passes_count"] = args.grad_passes
    for name in ("render", "grad", "grad_passes"):
        r = out[name]
        print(f"{name}: wall {r['wall']:.3f} s; blocking, with the history: wall {r['wall_blocking']:.3f} s, kernel "
              f"execution {r['execution']:.3f} s, codegen {r['codegen']:.3f} s, Python/other {r['python_blocking']:.3f} s, "
              f"{r['operations']} operations ({r['jit_kernels']} JIT kernels); wall / execution "
              f"{r['wall_over_execution']:.2f}")
    print(f"reference loop (10⁷ steps): {out['reference_before']:.3f} s before, {out['reference_after']:.3f} s after")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
