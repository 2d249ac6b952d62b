#!/usr/bin/env python
"""Stratified against independent curve draws in the primary term (``primary.stratified``): the
variance of one pass's vertex gradient of Σ w·I (w a fixed weighting of the pixels) over 12 seeds
each, for one view and for a batch of four views traced as one wavefront, on the demo's scene
(``configs/reconstruct_bunny.yaml``, its 64² film, 4 samples per pixel, the target bunny), and
whether the two means agree: |m_s − m_i|² divided by its expectation under equal means,
(tr Σ_s + tr Σ_i) / 12, is about 1 when they do. Then the kernel time of one pass (forward and
backward, Dr.Jit's kernel history with blocking launches) over the loop's batches of four views,
the two draws alternated batch by batch in one process (their ratio is immune to the machine's
drifting speed).

    .venv/bin/python benchmarks/primary_stratified.py [--json docs/benchmarks/primary_stratified.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

import psdr_cli  # noqa: E402
from psdr_cli.estimators import primary, registry  # noqa: E402
from psdr_cli.estimators.boundary_sampling import edge_list  # noqa: E402
from psdr_cli.optimisation.iteration import batch_views  # noqa: E402
from psdr_cli.rendering.estimate import Settings  # noqa: E402
from psdr_cli.scene.build import build_scene  # noqa: E402
from psdr_cli.support import backend  # noqa: E402

CONFIG = REPO / "configs" / "reconstruct_bunny.yaml"
SEEDS = 12
SPP = 4
STRATIFIED = primary.stratified


def independent(u, n_samples, view=None):
    """The draws before stratification: u itself."""
    return u


def vertex_gradient(scene, exp, edges, V0, views, seed: int) -> np.ndarray:
    """∂(Σ_views Σ w·I)/∂V of one primary pass over ``views`` (one view, or a batch)."""
    params = mi.traverse(scene.mi_scene)
    V = mi.Float(V0)
    dr.enable_grad(V)
    params["bunny.vertex_positions"] = V
    params.update()
    term, depth = registry.term("primary"), Settings.from_experiment(exp).max_depth
    if len(views) == 1:
        images = [term.estimate(scene, edges, views[0], SPP, seed, exp.estimator, depth)]
    else:
        images = term.estimate_views(scene, edges, views, SPP, seed, exp.estimator, depth)
    w = dr.sin(dr.arange(mi.Float, dr.width(images[0])) * 0.37)
    dr.backward(sum(dr.sum(w * image) for image in images))
    return np.asarray(dr.grad(V), np.float64)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    exp = psdr_cli.load_experiment(CONFIG)
    backend.activate(exp)
    scene = build_scene(exp)
    V0 = mi.Float(dr.detach(mi.traverse(scene.mi_scene)["bunny.vertex_positions"]))
    edges = edge_list(scene, exp.estimator, False)
    out = {"scene": str(CONFIG.relative_to(REPO)), "spp": SPP, "seeds": SEEDS}
    for views in ([0], [0, 3, 6, 9]):
        stats = {}
        for name, draw in (("independent", independent), ("stratified", STRATIFIED)):
            primary.stratified = draw
            g = np.stack([vertex_gradient(scene, exp, edges, V0, views, 100 + s + 1000 * (draw is STRATIFIED))
                          for s in range(SEEDS)])
            mean = g.mean(0)
            stats[name] = (mean, float(((g - mean) ** 2).sum(1).sum() / (SEEDS - 1)))
        primary.stratified = STRATIFIED
        (m_i, v_i), (m_s, v_s) = stats["independent"], stats["stratified"]
        out[f"{len(views)} view(s)"] = {
            "variance independent": v_i, "variance stratified": v_s, "ratio": v_s / v_i,
            "mean difference / expectation": float(((m_i - m_s) ** 2).sum() / ((v_i + v_s) / SEEDS))}
        print(f"{len(views)} view(s):", out[f"{len(views)} view(s)"], flush=True)
    out["kernel ms per batch pass"] = kernel_times(scene, exp, edges, V0)
    print({k: v for k, v in out["kernel ms per batch pass"].items() if k != "pairs"})
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


def kernel_times(scene, exp, edges, V0, batches: int = 24, warmup: int = 2) -> dict:
    """Kernel execution (ms) of one primary pass over the loop's batch of each iteration, both
    draws per batch in alternating order; the median of the paired ratios."""
    times = {"independent": [], "stratified": []}
    dr.set_flag(dr.JitFlag.LaunchBlocking, True)
    for it in range(batches):
        order = (("independent", independent), ("stratified", STRATIFIED))
        for name, draw in order[:: 1 if it % 2 else -1]:
            primary.stratified = draw
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            vertex_gradient(scene, exp, edges, V0, batch_views(0, it, 12, 4), it)
            history = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            if it >= warmup:
                times[name].append(sum(k.get("execution_time", 0.0) for k in history))  # ms
    primary.stratified = STRATIFIED
    dr.set_flag(dr.JitFlag.LaunchBlocking, False)
    pairs = np.array(times["stratified"]) / np.array(times["independent"])
    return {"median independent": float(np.median(times["independent"])),
            "median stratified": float(np.median(times["stratified"])),
            "median paired ratio": float(np.median(pairs)), "pairs": pairs.round(3).tolist()}


if __name__ == "__main__":
    main()
